"""The training configuration (``config.yaml`` of a run), the objects' grid resolutions and the label pool's automatic stride."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from scenecore.cameras import project
from scenecore.config import Rule, choice, from_dict, integer, number, validate

from osn.model.fields import FIELD_ADDED_LATER, FieldConfig
from osn.preprocess.inputs import SceneInputs

#: Counts that must be >= 1 (a 0 would divide by zero or render nothing).
_POSITIVE = ("rays_per_object", "rays", "samples", "edge_rays", "hidden_strips", "scale_width", "scale_layers", "scale_samples",
             "label_samples", "candidates", "eval_every", "eval_pixels", "iou_samples", "checkpoint_every")
#: Counts that may be 0 (a phase or a term switched off) but not negative.
_NON_NEGATIVE = ("rounds", "stage1_iters", "field_iters", "scale_iters", "final_scale_iters", "depth_rays", "free_rays",
                 "free_band", "free_band_objects", "label_rays", "label_erode", "label_stride")
_FRACTIONS = ("label_replay", "label_trim", "pair_minority", "coverage_threshold", "uncertain_acc", "scale_lr_final")

def _auto_or(rule: Rule) -> Rule:
    """``auto`` (resolved per input source by :func:`by_source`) or a value ``rule`` accepts."""
    return Rule(lambda v: v == "auto" or rule.ok(v), f"auto or {rule.what}")


#: Upper bounds of the counts that size a step's tensors: far above any scene's need (the
#: paper's settings included), low enough that a typo is an error, not an allocation of many GB.
MAX_SAMPLES_PER_RAY = 4096
MAX_RAYS = 1 << 20
MAX_POINTS = 1 << 24
_SIZED_BY_RAYS = ("rays_per_object", "rays", "depth_rays", "free_rays", "edge_rays", "label_rays", "hidden_strips")
_SIZED_BY_POINTS = ("scale_samples", "candidates", "eval_pixels", "iou_samples")


def _rgb() -> Rule:
    """Three finite numbers in [0, 1]."""
    unit = number(0.0, 1.0)
    return Rule(lambda v: isinstance(v, (tuple, list)) and len(v) == 3 and all(unit.ok(x) for x in v),
                "three numbers in [0, 1]")


def _device() -> Rule:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N``."""
    return Rule(lambda v: isinstance(v, str) and (v in ("auto", "cpu", "cuda") or
                                                  (v.startswith("cuda:") and v[5:].isdigit())),
                "auto, cpu, cuda or cuda:N")


_RULES: dict[str, Rule] = {
    "seed": integer(0),
    "field": Rule(lambda v: isinstance(v, FieldConfig), "a field mapping"),
    **{name: number(0.0) for name in ("w_rgb", "w_depth", "w_seg", "w_opacity", "w_free")},
    "skip_occluded": number(0.0, 1.0, hi_open=True),
    "scale_lr": number(0.0, lo_open=True, what="a positive learning rate"),
    "background": _rgb(),
    "device": _device(),
    "w_alone": number(0.0),
    "w_distortion": number(0.0),
    "w_before_depth": number(0.0),
    "w_hidden_smooth": _auto_or(number(0.0)),
    # A margin of 1 would empty the surface itself; 0 nothing.
    "before_depth_margin": number(0.0, 1.0, lo_open=True, hi_open=True),
    "w_edge": _auto_or(number(0.0)),
    "anchor_coverage": _auto_or(number(0.0, 1.0)),
    "edge_slope": number(0.0),
    "depth_robust": _auto_or(number(0.0)),
    "final_label_trim": _auto_or(number(0.0, 1.0)),
    "anchor_guide_samples": _auto_or(integer(0)),
    **{name: integer(1) for name in _POSITIVE},
    **{name: integer(1, MAX_RAYS) for name in _SIZED_BY_RAYS if name in _POSITIVE},
    **{name: integer(0, MAX_RAYS) for name in _SIZED_BY_RAYS if name in _NON_NEGATIVE},
    **{name: integer(1, MAX_POINTS) for name in _SIZED_BY_POINTS},
    **{name: integer(1, MAX_SAMPLES_PER_RAY) for name in ("samples", "label_samples")},
    **{name: integer(0) for name in _NON_NEGATIVE},
    **{name: number(0.0, 1.0) for name in _FRACTIONS},
    # Field steps need scores above it: at 1 no candidate ever passes (sigmoid < 1).
    "valid_threshold": number(0.0, 1.0, hi_open=True),
    "free_space": choice("none", "anchor", "objects", "ordered", "all"),
}


#: Options added after runs were first written, with the value that trained those runs (the
#: term off); :meth:`TrainConfig.from_yaml` fills them in for a run's own ``config.yaml``.
ADDED_LATER: dict[str, Any] = {"anchor_guide_samples": 0, "w_distortion": 0.0, "depth_robust": 0.0, "w_edge": 0.0, "anchor_coverage": 0.9,
                               "w_hidden_smooth": 0.0}


#: ``depth_robust: auto`` on inputs other than the oracle's (SfM, a user's video): the Cauchy
#: scale of the sparse-depth loss in multiples of the batch's median residual (docs/preprocess.md).
DEPTH_ROBUST_SFM = 3.0


def by_source(value: float | str, source: str, oracle: float, other: float) -> float:
    """An option that may be ``auto``: ``oracle`` on the oracle's inputs (exact poses and depths),
    ``other`` on anything else (SfM, a user's video); a number stays itself. The resolvers below
    say, per option, why the two differ."""
    if value == "auto":
        return oracle if source == "oracle" else other
    return float(value)


#: ``w_edge: auto`` on inputs other than the oracle's: the weight of the silhouette-depth term
#: (:func:`osn.train.losses.edge_excess`; docs/training.md, "Losses").
W_EDGE_SFM = 1.0


def resolve_w_edge(value: float | str, source: str) -> float:
    """The silhouette-depth term's weight for inputs from ``source``: ``auto`` is off on the
    oracle's, whose exact silhouettes need no correction (there the term lowers the valid set's
    IoU), and :data:`W_EDGE_SFM` on anything else, where the objects' fields read their silhouettes
    too far and cut the contact bounds tight; the term restores their recall (measurements in
    docs/experiments/)."""
    return by_source(value, source, 0.0, W_EDGE_SFM)


#: ``w_hidden_smooth: auto`` on the oracle's inputs: the weight of the anchor's disparity curvature
#: across the pixels objects hide it on (:func:`osn.train.losses.disparity_curvature`).
W_HIDDEN_SMOOTH_ORACLE = 0.3


def resolve_w_hidden_smooth(value: float | str, source: str) -> float:
    """The hidden-anchor term's weight for inputs from ``source``: ``auto`` is
    :data:`W_HIDDEN_SMOOTH_ORACLE` on the oracle's, where it raises the valid set's IoU and
    narrows its spread over seeds, and off on anything else, where it did not help on SfM's
    inputs (measurements in docs/experiments/)."""
    return by_source(value, source, W_HIDDEN_SMOOTH_ORACLE, 0.0)


#: ``anchor_coverage: auto`` on inputs other than the oracle's, and on the oracle's (the objects' threshold).
ANCHOR_COVERAGE_SFM, ANCHOR_COVERAGE_ORACLE = 0.5, 0.9


def resolve_anchor_coverage(value: float | str, source: str) -> float:
    """The opacity above which the anchor covers a label ray, for inputs from ``source``: ``auto``
    is :data:`ANCHOR_COVERAGE_SFM` on SfM inputs (there the room behind an object's contact stays
    below 0.9 and the pool would lose that object's contact rays) and the objects' 0.9 on the
    oracle's, where 0.5 lowers the valid set's IoU (measurements in docs/experiments/)."""
    return by_source(value, source, ANCHOR_COVERAGE_ORACLE, ANCHOR_COVERAGE_SFM)


#: ``final_label_trim: auto`` on the oracle's inputs and on anything else (see
#: :func:`resolve_final_label_trim`).
FINAL_LABEL_TRIM_ORACLE, FINAL_LABEL_TRIM_SFM = 0.002, 0.003


def resolve_final_label_trim(value: float | str, source: str) -> float:
    """The share of a pair's rays a valid sample may violate in the final scale phase, for inputs
    from ``source``: ``auto`` is :data:`FINAL_LABEL_TRIM_ORACLE` on the oracle's exact contacts
    (a looser trim accepts samples past the region's bounds) and :data:`FINAL_LABEL_TRIM_SFM` on
    anything else, where a few contact rays of each pair are off and the oracle's trim cuts into
    the region, while the rounds' looser trim lets the final fields' labels reach past the
    objects' bounds against the room (measurements in docs/experiments/)."""
    return by_source(value, source, FINAL_LABEL_TRIM_ORACLE, FINAL_LABEL_TRIM_SFM)


#: ``anchor_guide_samples: auto``: the guide pass's density samples along each of the anchor's
#: rays (:func:`osn.model.volume.guided_positions`) where its grid under-resolves what it sees.
ANCHOR_GUIDE_SAMPLES = 64


def resolve_anchor_guide_samples(value: int | str, fcfg: FieldConfig, inputs: SceneInputs) -> int:
    """The anchor's guide samples (0: even samples): ``auto`` is :data:`ANCHOR_GUIDE_SAMPLES`
    unless the anchor's box spans no more pixels than its grid has voxels (:func:`anchor_pixels`;
    without sparse depths it is on). Where the room's grid is coarser than the pixels that see
    it, even samples miss its surfaces and the guide finds them, for best of N and the valid set
    alike, on SfM's inputs and the oracle's; where the grid already has a voxel per pixel (the
    tiny test scene) the guide only costs recall (measurements in docs/experiments/)."""
    if value != "auto":
        return int(value)
    n = anchor_pixels(inputs)
    return 0 if n is not None and n <= fcfg.resolution else ANCHOR_GUIDE_SAMPLES


def checkpoint_anchor_guide_samples(ckpt: dict[str, Any], source: str) -> int:
    """The anchor's guide samples a checkpoint's training used (its ``anchor_guide``). A checkpoint
    without that key does not say: its config's ``auto`` meant :data:`ANCHOR_GUIDE_SAMPLES` on SfM
    inputs and 0 on the oracle's, and a config without ``anchor_guide_samples`` trained without
    the guide (0)."""
    if "anchor_guide" in ckpt:
        return int(ckpt["anchor_guide"])
    return int(by_source(ckpt["config"].get("anchor_guide_samples", 0), source, 0, ANCHOR_GUIDE_SAMPLES))


def resolve_depth_robust(value: float | str, source: str) -> float:
    """The sparse-depth loss's robustness for inputs from ``source``: ``auto`` is the squared
    error on the oracle's exact depths (a robust loss there lowers the valid set's IoU) and
    :data:`DEPTH_ROBUST_SFM` on anything else, whose depths hold SfM's phantom points."""
    return by_source(value, source, 0.0, DEPTH_ROBUST_SFM)


@dataclass
class TrainConfig:
    """Everything a training run depends on (stored as ``config.yaml`` in the run).

    Iteration counts are per phase; ``rays`` counts are per step. See :mod:`osn.train.loop`.
    The defaults are the CPU default (``configs/osn-cpu.yaml``).
    """

    seed: int = 0
    field: FieldConfig = field(default_factory=FieldConfig)
    stage1_iters: int = 400
    rounds: int = 5
    field_iters: int = 100
    scale_iters: int = 150
    final_scale_iters: int = 2000
    rays_per_object: int = 384
    rays: int = 1024
    depth_rays: int = 64
    samples: int = 48
    anchor_guide_samples: int | str = "auto"  # resolved by resolve_anchor_guide_samples
    skip_occluded: float = 1e-3
    w_rgb: float = 1.0
    w_depth: float = 1.0
    depth_robust: float | str = "auto"  # resolved by resolve_depth_robust
    w_seg: float = 0.01
    w_opacity: float = 1.0
    w_free: float = 1.0
    w_distortion: float = 0.03
    w_before_depth: float = 0.0
    before_depth_margin: float = 0.95
    w_hidden_smooth: float | str = "auto"  # resolved by resolve_w_hidden_smooth
    hidden_strips: int = 32
    w_alone: float = 1.0
    w_edge: float | str = "auto"  # resolved by resolve_w_edge
    edge_rays: int = 64
    edge_slope: float = 0.02
    free_space: str = "ordered"
    free_rays: int = 128
    free_band: int = 4
    free_band_objects: int = 1
    scale_width: int = 64
    scale_layers: int = 4
    scale_lr: float = 5e-3
    scale_lr_final: float = 0.1
    scale_samples: int = 1024
    label_rays: int = 0
    label_replay: float = 0.5
    label_samples: int = 24
    label_trim: float = 0.01
    final_label_trim: float | str = "auto"  # resolved by resolve_final_label_trim
    pair_minority: float = 0.2
    label_erode: int = 0
    label_stride: int = 0
    coverage_threshold: float = 0.9
    anchor_coverage: float | str = "auto"  # resolved by resolve_anchor_coverage
    uncertain_acc: float = 0.9
    valid_threshold: float = 0.95
    candidates: int = 4096
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    eval_every: int = 200
    eval_pixels: int = 4096
    iou_samples: int = 20000
    checkpoint_every: int = 250
    device: str = "auto"

    def __post_init__(self) -> None:
        validate(self, "training", _RULES)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "TrainConfig":
        """From plain data (parsed YAML); misspelt keys, here or under ``field``, are errors."""
        d = dict(d or {})
        if "background" in d:
            d["background"] = tuple(float(x) for x in d["background"])
        return from_dict(cls, d, "training", nested={"field": (FieldConfig, "field")})

    @classmethod
    def from_yaml(cls, path: str | Path, run_config: bool = False) -> "TrainConfig":
        """Read a YAML config; every error is a ``ValueError`` prefixed with ``path``.

        Omitted keys take the defaults, except with ``run_config`` (a run's own ``config.yaml``,
        which lists every key it trained with): there a key it lacks was added after it was
        written and takes the value it trained with (:data:`ADDED_LATER`), so resuming or
        comparing an older run does not silently switch a new term on.
        """
        try:
            d = yaml.safe_load(Path(path).read_text()) or {}
            if run_config and isinstance(d, dict):
                d = {**ADDED_LATER, **d}
                if isinstance(d.get("field"), dict):
                    d["field"] = {**FIELD_ADDED_LATER, **d["field"]}
            return cls.from_dict(d)
        except (ValueError, TypeError, yaml.YAMLError) as e:
            raise ValueError(f"{path}: {e}") from None

    def to_dict(self) -> dict[str, Any]:
        """Plain data for ``config.yaml`` (round-trips through :meth:`from_dict`)."""
        d = dataclasses.asdict(self)
        d["background"] = list(self.background)
        return d


#: ``field.object_resolution: auto`` keeps at least this many voxels per axis (an object a few
#: pixels wide still gets a grid that trilinear interpolation can shape).
MIN_OBJECT_RESOLUTION = 16


def footprint_resolution(bbox: np.ndarray, cam_to_obj: np.ndarray, K: np.ndarray, cap: int) -> int:
    """Voxels per axis at which one voxel is about one pixel of the training frames: the median,
    over the frames that see the whole box in front of the camera, of the box's projected extent
    (the longer side of its eight corners' image bounding box, in pixels), rounded and clamped to
    ``[MIN_OBJECT_RESOLUTION, cap]``; ``cap`` when no frame sees the box whole (a camera inside it).

    ``bbox (2, 3)`` min / max corner in object units, ``cam_to_obj (F, 4, 4)`` OpenCV camera-to-object
    poses, ``K (3, 3)`` intrinsics.
    """
    lo, hi = np.asarray(bbox, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    extents = []
    for pose in np.asarray(cam_to_obj, dtype=np.float64):
        uv, depth = project(corners, K, pose)
        if np.all(depth > 0) and np.all(np.isfinite(uv)):
            extents.append(float(np.ptp(uv, axis=0).max()))
    if not extents:
        return int(cap)
    return int(np.clip(round(float(np.median(extents))), min(MIN_OBJECT_RESOLUTION, cap), cap))


def object_resolutions(fcfg: FieldConfig, inputs: SceneInputs) -> list[list[int]]:
    """Per object position its fields' resolution schedule (:meth:`FieldConfig.resolutions`): the
    anchor's ends at ``field.resolution``, every other object's at ``field.object_resolution``
    (0: ``resolution``; never above it). ``auto``: :func:`footprint_resolution` on SfM inputs (or
    a user's video), where a small object's voxels at ``resolution`` are a fraction of a pixel
    and coarser ones, a voxel per pixel, render its test pixels and best of N better;
    ``resolution`` on the oracle's, whose exact contacts lose recall on coarser grids
    (measurements in docs/experiments/)."""
    out = []
    for k, o in enumerate(inputs.objects):
        final = fcfg.resolution
        r = fcfg.object_resolution
        if k != inputs.anchor_pos and r == "auto" and inputs.source != "oracle":
            final = footprint_resolution(o.bbox, o.cam_to_obj, inputs.K, fcfg.resolution)
        elif k != inputs.anchor_pos and r not in ("auto", 0):
            final = min(int(r), fcfg.resolution)
        out.append(fcfg.resolutions(final))
    return out


#: ``field.anchor_planes: auto`` keeps the anchor's colour planes within these sizes (texels per side).
MIN_ANCHOR_PLANES, MAX_ANCHOR_PLANES = 16, 1024


def anchor_pixels(inputs: SceneInputs) -> float | None:
    """How many pixels the anchor's box spans: the longest side of its box over the pixel
    footprint at the median of its sparse depths (depth / focal length; both in the anchor's unit,
    so the figure does not depend on it). None when the anchor has no sparse depth."""
    a = inputs.objects[inputs.anchor_pos]
    depths = np.concatenate([np.asarray(d, dtype=np.float64).reshape(-1) for d in a.sparse_depth] + [np.zeros(0)])
    depths = depths[np.isfinite(depths) & (depths > 0)]
    if not len(depths):
        return None
    footprint = float(np.median(depths)) / float(inputs.K[0, 0])
    return float(np.max(np.asarray(a.bbox[1]) - np.asarray(a.bbox[0]))) / footprint


def anchor_plane_size(fcfg: FieldConfig, inputs: SceneInputs) -> int:
    """Texels per side of the anchor's colour planes (0: none; dense fields only). ``auto``: about
    one texel per pixel where the anchor's surfaces are (:func:`anchor_pixels`), within
    [:data:`MIN_ANCHOR_PLANES`, :data:`MAX_ANCHOR_PLANES`]; 0 where that is no more than the
    anchor's grid resolution (the grid holds as much) or the anchor has no sparse depth. The
    planes give the room's colour the detail its grid cannot hold where the room spans more pixels
    than the grid has voxels; below that they only add parameters to fit (measurements in
    docs/experiments/)."""
    if fcfg.kind != "dense" or fcfg.anchor_planes == 0:
        return 0
    if fcfg.anchor_planes != "auto":
        return int(fcfg.anchor_planes)
    n = anchor_pixels(inputs)
    if n is None or n <= fcfg.resolution:
        return 0
    return int(np.clip(round(n), MIN_ANCHOR_PLANES, MAX_ANCHOR_PLANES))


#: ``label_stride: 0`` keeps about this many pool pixels per frame side: the per-object depth
#: renders of a scale phase cost ~ T * (side / stride)^2 rays per object, 16x more at 512 px
#: than at 128 px for no better labels (a bound is set by a few contact rays either way).
AUTO_LABEL_SIDE = 128


def label_stride(configured: int, height: int, width: int) -> int:
    """The label pool's pixel stride: ``configured`` when > 0, else one that keeps about
    ``AUTO_LABEL_SIDE`` pixels along the longer image side (1 up to 128 px, 4 at 512 px)."""
    if configured > 0:
        return configured
    return max(1, -(-max(height, width) // AUTO_LABEL_SIDE))
