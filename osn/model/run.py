"""A trained run, loaded for inference: fields, scale network, inputs; rendering any view.

``load_run(RUN)`` reads what ``osn train`` wrote (``inputs/``, ``checkpoint.pt`` with the config)
and returns a :class:`TrainedRun`. ``TrainedRun.render_view`` renders a configuration from any
OpenCV camera at a training timestamp, either a training camera or a world-space test camera
placed through :mod:`osn.placement`. All scale vectors are indexed by object *position* in
``inputs.objects``.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from scenecore import dataset as D
from scenecore.cameras import pixel_rays
from osn.model.fields import FIELD_REMOVED_OPTIONS, Field, FieldConfig, make_field, saved_plane_size
from osn.preprocess.inputs import SceneInputs, load_inputs
from osn.model.placement import novel_to_training_camera, object_transforms
from osn.model.scale_net import ScaleNet, check_scores, full_sbar
from osn.model.volume import SKIP_OCCLUDED, ObjectRays, RenderOutput, ShadedSamples, render_by_hits, shade

#: Version of ``checkpoint.pt`` that ``osn train`` writes (2 added the scale phase's replay
#: buffer). The first checkpoints carried no version key and are version 1; both hold the same
#: fields and network, so both are read; any other version is refused with a clear message.
CHECKPOINT_VERSION = 2
READABLE_VERSIONS = (1, 2)


class CheckpointError(ValueError):
    """A run's ``checkpoint.pt`` is unreadable or from another format (message names the file)."""


#: Opacity at or below which a rendered pixel shows no surface (its depth is ``+inf``):
#: ``depth / acc`` of a nearly empty ray is noise (opacity 1e-7 turns a depth of 2 into 0.2).
EMPTY_ACC = 1e-4


@dataclass
class TrainedRun:
    """Everything needed to score and render configurations of a trained model."""

    path: Path
    inputs: SceneInputs
    config: dict
    fields: list[Field]
    net: ScaleNet | None
    device: torch.device
    iteration: int
    train_seconds: float
    anchor_guide_samples: int = 0  # the anchor's guide samples its training used (0: even)

    @property
    def anchor_pos(self) -> int:
        return self.inputs.anchor_pos

    @property
    def ranges(self) -> np.ndarray:
        """``(K, 2)`` Eq. 1 de-normalised scale range per object position."""
        return self.inputs.scale_ranges()

    @property
    def dataset(self) -> str | None:
        p = self.path / "run.json"
        return D.read_json(p).get("dataset") if p.exists() else None

    def sbar(self, s_free: np.ndarray) -> np.ndarray:
        """De-normalised ``(N, K)`` scale vectors from free normalised scales ``(N, K-1)``."""
        t = torch.as_tensor(np.atleast_2d(s_free), dtype=torch.float64)
        return full_sbar(t, torch.from_numpy(self.ranges), self.anchor_pos).numpy()

    @torch.no_grad()
    def scores(self, s_free: np.ndarray, batch: int = 65536) -> np.ndarray:
        """Validity scores (sigmoid) of free normalised scales ``(N, K-1)``; all 1 for one object."""
        s = np.atleast_2d(s_free)
        if self.net is None:
            return np.ones(len(s))
        out = []
        for i in range(0, len(s), batch):
            x = torch.as_tensor(s[i : i + batch], dtype=torch.float32, device=self.device)
            out.append(check_scores(self.net.prob(x), str(self.path / "checkpoint.pt")).double().cpu().numpy())
        return np.concatenate(out) if out else np.zeros(0)

    def _view_rays(self, camera_to_world: np.ndarray | None, time_index: int, sbar: np.ndarray, objects: list[int] | None
                   ) -> tuple[torch.Tensor, dict[int, torch.Tensor]]:
        """Camera-frame ray directions ``(H*W, 3)`` of a view and each posed object's similarity."""
        inp = self.inputs
        M = np.eye(4) if camera_to_world is None else novel_to_training_camera(inp, camera_to_world, time_index)
        T = object_transforms(inp, M, time_index, np.asarray(sbar, dtype=np.float64))
        keep = [k for k in (objects if objects is not None else range(inp.num_objects)) if k in T]
        _, d = pixel_rays(inp.K, np.eye(4), inp.width, inp.height)
        return torch.from_numpy(d).float().to(self.device), {k: torch.from_numpy(T[k]).float().to(self.device) for k in keep}

    def _object_rays(self, k: int, pose: torch.Tensor, R: int) -> ObjectRays:
        wide = torch.tensor([1e-6, 1e9], device=self.device)  # novel views: the box alone bounds t
        return ObjectRays(self.fields[k], pose.expand(R, 4, 4), torch.ones(R, dtype=torch.bool, device=self.device), wide,
                          self.anchor_guide_samples if k == self.anchor_pos else 0)

    @torch.no_grad()
    def shade_anchor(self, camera_to_world: np.ndarray | None, time_index: int, chunk: int = 8192,
                     n_samples: int | None = None) -> list[ShadedSamples]:
        """The anchor's evaluated samples in one view, per ray chunk, for :meth:`render_view`'s
        ``anchor``: its pose does not depend on the configuration (scale 1), so every candidate
        rendered in this view can reuse them. Empty when the anchor is unposed at ``time_index``."""
        sbar = np.ones(self.inputs.num_objects)
        dirs, pose = self._view_rays(camera_to_world, time_index, sbar, [self.anchor_pos])
        if self.anchor_pos not in pose:
            return []
        S = n_samples or int(self.config.get("samples", 32))
        skip = SKIP_OCCLUDED
        return [shade(self._object_rays(self.anchor_pos, pose[self.anchor_pos], len(dc)), dc, S, skip)
                for dc in torch.split(dirs, chunk)]

    @torch.no_grad()
    def render_view(
        self,
        camera_to_world: np.ndarray | None,
        time_index: int,
        sbar: np.ndarray,
        objects: list[int] | None = None,
        chunk: int = 8192,
        n_samples: int | None = None,
        anchor: list[ShadedSamples] | None = None,
    ) -> dict[str, np.ndarray]:
        """Render ``(H, W)`` images of configuration ``sbar (K,)`` at timestamp ``time_index``.

        ``camera_to_world`` is a dataset-world OpenCV camera (test view) or None for the training
        camera of that timestamp. ``objects`` restricts rendering to some object positions (a
        layer). ``anchor``: :meth:`shade_anchor` of the same view, chunk and sample count, used
        instead of querying the anchor's field again (the render is the same). Returns
        ``rgb (H,W,3)``, ``depth (H,W)`` (planar, scene units; ``+inf`` where
        ``acc <= EMPTY_ACC``, as in the dataset format, so depth metrics skip holes instead of
        reading them as surfaces at the camera), ``acc (H,W)`` and ``ids (H,W)`` (object id of the
        largest weight share, 255 where empty).
        """
        inp = self.inputs
        H, W = inp.height, inp.width
        dirs, pose = self._view_rays(camera_to_world, time_index, sbar, objects)
        keep = list(pose)
        if anchor is not None and self.anchor_pos in pose and float(sbar[self.anchor_pos]) != 1.0:
            raise ValueError(f"cached anchor samples are at scale 1, the configuration has {sbar[self.anchor_pos]}")
        cfg = self.config
        S = n_samples or int(cfg.get("samples", 32))
        rgb = torch.zeros(H * W, 3, device=self.device)  # black where nothing is opaque, as in training
        depth = torch.full((H * W,), float("inf"), device=self.device)
        acc = torch.zeros(H * W, device=self.device)
        ids = torch.full((H * W,), 255, dtype=torch.long, device=self.device)
        if keep:
            obj_ids = torch.tensor([inp.objects[k].id for k in keep], device=self.device)
            for c, i in enumerate(range(0, H * W, chunk)):
                dc = dirs[i : i + chunk]
                R = len(dc)
                rays = [anchor[c] if anchor and k == self.anchor_pos else self._object_rays(k, pose[k], R) for k in keep]
                out: RenderOutput = render_by_hits(rays, dc, S, skip_occluded=SKIP_OCCLUDED)
                rgb[i : i + R] = out.rgb
                acc[i : i + R] = out.acc
                depth[i : i + R] = out.normalised_depth(EMPTY_ACC)
                ids[i : i + R] = torch.where(out.acc > 0.5, obj_ids[out.log_seg.argmax(1)], torch.full_like(ids[i : i + R], 255))
        return {
            "rgb": rgb.clamp(0, 1).reshape(H, W, 3).cpu().numpy(),
            "depth": depth.reshape(H, W).cpu().numpy(),
            "acc": acc.reshape(H, W).cpu().numpy(),
            "ids": ids.reshape(H, W).cpu().numpy().astype(np.uint8),
        }


def read_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict:
    """Read an ``osn train`` checkpoint; ``CheckpointError`` naming ``path`` when it is truncated,
    foreign, of another version or lacks the fields and config.

    Runs are shared between people, so a checkpoint is untrusted input: it is unpickled with
    torch's weights-only loader, which rebuilds tensors, numbers, strings and containers and
    refuses any other object (a crafted file cannot run code). Every checkpoint ``osn train``
    writes holds only those types, old versions included.
    """
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:  # weights-only refused an object: never retried unsafely
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: refused: the checkpoint holds objects other than weights and plain data, "
                              f"which could run code when loaded ({first})") from None
    except Exception as e:  # a truncated or foreign file
        raise CheckpointError(f"{path}: not a readable osn checkpoint ({e})") from None
    if not isinstance(ckpt, dict):
        raise CheckpointError(f"{path}: not an osn checkpoint (a pickled {type(ckpt).__name__})")
    version = ckpt.get("version", 1)  # the first checkpoints carried no version
    if version not in READABLE_VERSIONS:
        raise CheckpointError(f"{path}: checkpoint version {version!r}; this toolkit reads versions {', '.join(map(str, READABLE_VERSIONS))}")
    missing = [k for k in ("config", "resolutions", "fields") if k not in ckpt]
    if missing:
        raise CheckpointError(f"{path}: not an osn checkpoint (missing {', '.join(missing)})")
    return ckpt


def load_run(run_dir: str | Path, device: str | torch.device = "cpu") -> TrainedRun:
    """Load an ``osn train`` run directory (its last checkpoint) for inference."""
    run = Path(run_dir)
    ckpt_path = run / "checkpoint.pt"
    if not ckpt_path.is_file():
        raise FileNotFoundError(f"{ckpt_path}: missing (not an osn train run directory, or training has not checkpointed yet)")
    inputs = load_inputs(run / "inputs")
    ckpt = read_checkpoint(ckpt_path)
    if len(ckpt["fields"]) != inputs.num_objects:
        raise CheckpointError(f"{ckpt_path}: {len(ckpt['fields'])} fields but {run / 'inputs'} has {inputs.num_objects} objects")
    dev = torch.device(device)
    cfg = ckpt["config"]
    try:  # a checkpoint of another field kind, size or layout
        fcfg = FieldConfig(**{k: v for k, v in cfg["field"].items() if k not in FIELD_REMOVED_OPTIONS})
        fields = []
        for o, r, sd in zip(inputs.objects, ckpt["resolutions"], ckpt["fields"]):
            f = make_field(fcfg, torch.from_numpy(o.bbox).float(), resolution=r, planes=saved_plane_size(sd))
            f.load_state_dict(sd)
            fields.append(f.to(dev).eval())
        net = None
        if ckpt.get("net") is not None:
            net = ScaleNet(inputs.num_objects - 1)
            net.load_state_dict(ckpt["net"])
            net = net.to(dev).eval()
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{ckpt_path}: does not match this toolkit's fields or scale network ({first})") from None
    from osn.train.auto import checkpoint_anchor_guide_samples  # osn.train imports this module
    return TrainedRun(run, inputs, cfg, fields, net, dev, int(ckpt.get("iteration", 0)), float(ckpt.get("elapsed", 0.0)),
                      checkpoint_anchor_guide_samples(ckpt, inputs.source))
