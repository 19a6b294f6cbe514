"""The ground truth of a scoring: evaluated test views, co-visibility masks, masked colours.

Shared by ``benchgen score`` and ``osn evaluate`` so that their numbers are comparable: the same
evenly spread subset of test views (:func:`evaluated_views`) and the same co-visibility masks
(:func:`configuration_masks`, from ground-truth depth and ids as in docs/metrics.md).

Only what the candidate pass needs stays in memory: per view, every configuration's colour with
masked-out pixels zeroed (uint8) and the masks. Depth, ids and unmasked colour of a configuration
are read again from the dataset when its matched candidate gets its full metrics.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from scenecore import dataset as D
from benchgen.score import covisibility as C
from benchgen.score import covisibility_store as store
from benchgen.score import metrics as M
from benchgen.score.parallel import ordered_map
from benchgen.score.pngread import PngError, decode_ids, decode_rgb, max_png_bytes


def evaluated_views(scene: D.Scene, max_views: int = 0) -> list[D.Frame]:
    """Test frames in (time, view) order; with ``max_views`` > 0 at most that many, evenly spread."""
    test = sorted(scene.test_frames, key=lambda f: (f.time_index, f.view))
    if max_views and len(test) > max_views:
        test = [test[i] for i in np.linspace(0, len(test) - 1, max_views).round().astype(int)]
    return test


configuration_masks = C.configuration_masks  # its home is covisibility.py; kept here for callers


#: Ground-truth views :meth:`Truth.views` keeps in memory once read, when every configuration's
#: fit in this many bytes: the scorer reads each configuration's views once per scored candidate
#: set (``osn evaluate`` scores four), and those re-reads are a noticeable part of an evaluation.
VIEWS_CACHE_BYTES = 256 * 2**20
#: LPIPS features :meth:`Truth.lpips_features` keeps, when every configuration's fit in this many
#: bytes (the demo's, counted from the feature shapes: 50 x 3.8 MB); larger images compute them again.
LPIPS_CACHE_BYTES = 512 * 2**20


@dataclass
class Truth:
    """The evaluated views of every ground-truth configuration.

    ``masked_rgb`` ``(V, G, H*W*3)`` uint8: colour with masked-out pixels zeroed, view-major so
    that one view of all G configurations is contiguous; ``mask`` ``(V, G, H*W)`` bool
    (True = co-visible, evaluated); ``scales`` ``(G, K)``.
    """

    root: Path
    scene: D.Scene
    frames: list[D.Frame]
    scales: np.ndarray
    masked_rgb: np.ndarray
    mask: np.ndarray
    _views: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False, compare=False)
    _lpips: dict[int, list] = field(default_factory=dict, repr=False, compare=False)
    #: One line when some co-visibility masks were computed here rather than read from the
    #: dataset (``configs/GGG/covisibility.npz``, :mod:`covisibility_store`); "" when all were read.
    masks_note: str = field(default="", compare=False)

    @property
    def num_configurations(self) -> int:
        return self.mask.shape[1]

    @property
    def num_views(self) -> int:
        return len(self.frames)

    def views(self, g: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Configuration g's ``rgb (V, H, W, 3)`` uint8, ``depth (V, H, W)``, ``ids (V, H, W)`` from
        disk (:func:`read_frame`), kept (read-only) for the next call when all configurations fit
        :data:`VIEWS_CACHE_BYTES`."""
        if g in self._views:
            return self._views[g]
        rgb, depth, ids = (np.stack(x) for x in zip(*(read_frame(self.root, f.name, g, self.scene) for f in self.frames)))
        if self.num_configurations * (rgb.nbytes + depth.nbytes + ids.nbytes) <= VIEWS_CACHE_BYTES:
            for a in (rgb, depth, ids):
                a.setflags(write=False)
            self._views[g] = (rgb, depth, ids)
        return rgb, depth, ids

    def lpips_features(self, g: int, rgb: np.ndarray | None = None) -> list[list[torch.Tensor]]:
        """:func:`metrics.lpips_features` of configuration g's colour (:func:`metrics.from_rgb8`),
        kept for the next candidate set when every configuration's fit :data:`LPIPS_CACHE_BYTES`.
        ``rgb``: that colour, when the caller has read it (:meth:`views`), so it is not read again."""
        if g in self._lpips:
            return self._lpips[g]
        feats = M.lpips_features(M.from_rgb8(self.views(g)[0] if rgb is None else rgb))
        size = sum(t.numel() * t.element_size() for batch in feats for t in batch)
        if self.num_configurations * size <= LPIPS_CACHE_BYTES:
            self._lpips[g] = feats
        return feats

    def first_views(self, v: int) -> "Truth":
        """The same ground truths restricted to the first ``v`` evaluated views (no copy)."""
        return Truth(self.root, self.scene, self.frames[:v], self.scales, self.masked_rgb[:v], self.mask[:v],
                     masks_note=self.masks_note)

    def masks(self, g: int) -> np.ndarray:
        """Configuration g's masks ``(V, H, W)`` bool."""
        return self.mask[:, g].reshape(self.num_views, self.scene.height, self.scene.width)


# Set before forking workers (:func:`parallel.ordered_map`), so that they inherit it unpickled.
_JOB: dict[str, Any] = {}


def _training_depth_ids() -> tuple[np.ndarray, np.ndarray]:
    """The training video's depth and ids, read once per process when a mask is computed."""
    if "train" not in _JOB:
        _JOB["train"] = D.read_training_video(_JOB["root"], _JOB["scene"])[1:]
    return _JOB["train"]


#: Read the ground truth's PNGs through :mod:`pngread` (Pillow directly) rather than through the
#: dataset's reader (imageio, whose format detection costs more than decoding a small PNG); False:
#: the dataset's reader (``benchmarks/bench_score_protocol.py`` times both). The same arrays.
DIRECT_PNG = True


def _png(path: Path, scene: D.Scene, decode: Callable[[bytes], np.ndarray],
         dataset_reader: Callable[[Path], np.ndarray]) -> np.ndarray:
    """A ground-truth PNG decoded by ``decode`` (:mod:`pngread`), as ``dataset_reader`` returns it.
    A file the direct path does not take as the dataset writes it (16-bit, grey colour, another
    format) goes to ``dataset_reader``, so what it accepts and the errors it gives stay its own."""
    if DIRECT_PNG:
        with contextlib.suppress(PngError):
            a = decode(D.read_regular(path, max_png_bytes(scene.height, scene.width)))
            if a.dtype == np.uint8:
                return a
    return dataset_reader(path)


def _read_rgb(root: Path, scene: D.Scene, name: str, g: int) -> np.ndarray:
    path = D.frame_paths(root, name, g).rgb
    rgb = _png(path, scene, decode_rgb, D.read_rgb)
    if p := D.size_problem(path, rgb.shape[:2], scene):
        raise D.DatasetError(p)
    return rgb


def read_frame(root: Path, name: str, g: int, scene: D.Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`scenecore.dataset.read_frame` with ``scene`` (the same arrays, checks and errors),
    its PNGs decoded as :func:`_png` does."""
    if not DIRECT_PNG:
        return D.read_frame(root, name, g, scene=scene)
    p = D.frame_paths(root, name, g)
    rgb, depth, ids = _png(p.rgb, scene, decode_rgb, D.read_rgb), D.read_depth(p.depth), _png(p.ids, scene, decode_ids, D.read_ids)
    for problem in (D.size_problem(p.rgb, rgb.shape[:2], scene), D.size_problem(p.depth, depth.shape, scene),
                    D.size_problem(p.ids, ids.shape, scene) or D.ids_problem(p.ids, ids, scene.num_objects)):
        if problem:
            raise D.DatasetError(problem)
    return rgb, depth, ids


def _load_configuration(g: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Configuration g: masked colour ``(V, H*W*3)`` uint8, masks ``(V, H*W)`` and where the masks
    came from (``stored``, else why they were computed: ``absent``, another rule, ``not used``).
    Stored masks spare reading the views' depth and ids."""
    root, scene, frames, scales = _JOB["root"], _JOB["scene"], _JOB["frames"], _JOB["scales"]
    mask, source = store.stored(root, scene, g, frames) if _JOB["use_stored"] else (None, "not used")
    if mask is not None:
        rgb = [_read_rgb(root, scene, f.name, g) for f in frames]
    else:
        rgb, depth, ids = zip(*(read_frame(root, f.name, g, scene) for f in frames))
        mask = configuration_masks(scene, scales[g], frames, np.stack(depth), np.stack(ids), *_training_depth_ids())
    V = len(frames)
    return (np.stack(rgb) * mask[..., None]).reshape(V, -1), mask.reshape(V, -1), source


def masks_note(sources: list[str]) -> str:
    """One line saying which configurations' masks were computed rather than read ("" when none)."""
    computed = [s for s in sources if s != "stored"]
    if not computed:
        return ""
    why = {"absent": "the dataset stores none (written before 'benchgen generate' stored them; rerunning it with the "
                     "same options adds them)", "not used": "stored masks were not used"}
    reasons = sorted({why.get(s, f"stored under another rule: {s}") for s in computed})
    return (f"co-visibility masks computed on the fly for {len(computed)} of {len(sources)} configurations: "
            + "; ".join(reasons))


def load_truth(root: str | Path, max_views: int = 0, workers: int = 1, progress: bool = False,
               stored_masks: bool = True) -> Truth:
    """Read every configuration's evaluated views and their co-visibility masks.

    The masks are read from the dataset (``configs/GGG/covisibility.npz``, written by ``benchgen
    generate``) where it stores them under the current rule, else computed (``stored_masks=False``:
    always computed); :attr:`Truth.masks_note` says when any were computed. Both give the same
    masks (``benchgen verify`` checks it). ``workers`` > 1 reads and masks configurations in that
    many processes (same result; at most a few configurations' arrays are in flight besides the result).
    """
    from tqdm import tqdm

    root = Path(root)
    scene = D.load_scene(root)
    frames = evaluated_views(scene, max_views)
    if not frames:
        raise D.DatasetError(f"{root / 'scene.json'}: the dataset has no test frames")
    configs = D.load_configurations(root, scene)
    if not configs:
        raise D.DatasetError(f"{root / 'scene.json'}: the dataset has no ground-truth configurations")
    scales = np.stack([c.scales for c in configs])
    _JOB.update(root=root, scene=scene, frames=frames, scales=scales, use_stored=stored_masks)
    G, V, P = len(configs), len(frames), scene.height * scene.width
    masked_rgb, mask = np.empty((V, G, P * 3), np.uint8), np.empty((V, G, P), bool)
    sources: list[str] = []
    try:
        with tqdm(total=G, desc="ground truth", unit="config", disable=not progress, dynamic_ncols=True) as bar:
            for g, (rgb_g, mask_g, source) in enumerate(ordered_map(_load_configuration, [(g,) for g in range(G)], workers)):
                masked_rgb[:, g], mask[:, g] = rgb_g, mask_g
                sources.append(source)
                bar.update()
    finally:
        _JOB.clear()
    return Truth(root, scene, frames, scales, masked_rgb, mask, masks_note=masks_note(sources))
