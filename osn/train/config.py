"""The training configuration (``config.yaml`` of a run): its options, their documentation and their checks.

What an ``auto`` option becomes on a scene's inputs is :mod:`osn.train.auto`'s."""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from scenecore.config import Rule, from_dict, integer, number, validate

from osn.model.fields import FieldConfig
from osn.train.run_config import drop_removed_options, upgrade_run_config

log = logging.getLogger(__name__)

#: Counts that must be >= 1 (a 0 would divide by zero or render nothing).
_POSITIVE = ("rays_per_object", "rays", "samples", "scale_samples", "eval_every")
#: Counts that may be 0 (a phase or a term switched off) but not negative.
_NON_NEGATIVE = ("rounds", "stage1_iters", "field_iters", "scale_iters", "final_scale_iters", "depth_rays",
                 "label_stride")
_FRACTIONS = ("label_replay", "pair_minority", "scale_lr_final", "anchor_bias")

def _auto_or(rule: Rule) -> Rule:
    """``auto`` (resolved by a measured property of the inputs) or a value ``rule`` accepts."""
    return Rule(lambda v: v == "auto" or rule.ok(v), f"auto or {rule.what}")


#: Upper bounds of the counts that size a step's tensors: far above any scene's need (the
#: paper's settings included), low enough that a typo is an error, not an allocation of many GB.
MAX_SAMPLES_PER_RAY = 4096
MAX_RAYS = 1 << 20
MAX_POINTS = 1 << 24
_SIZED_BY_RAYS = ("rays_per_object", "rays", "depth_rays")
_SIZED_BY_POINTS = ("scale_samples",)


def _device() -> Rule:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N``."""
    return Rule(lambda v: isinstance(v, str) and (v in ("auto", "cpu", "cuda") or
                                                  (v.startswith("cuda:") and v[5:].isdigit())),
                "auto, cpu, cuda or cuda:N")


_RULES: dict[str, Rule] = {
    "seed": integer(0),
    "field": Rule(lambda v: isinstance(v, FieldConfig), "a field mapping"),
    **{name: number(0.0) for name in ("w_opacity", "w_free")},
    "scale_lr": number(0.0, lo_open=True, what="a positive learning rate"),
    "device": _device(),
    "w_alone": number(0.0),
    "w_distortion": number(0.0),
    "w_hidden_smooth": number(0.0),
    "w_planar": number(0.0),
    "w_edge": _auto_or(number(0.0)),
    "depth_robust": _auto_or(number(0.0)),
    "final_label_trim": number(0.0, 1.0),
    "anchor_guide_samples": _auto_or(integer(0)),
    **{name: integer(1) for name in _POSITIVE},
    **{name: integer(1, MAX_RAYS) for name in _SIZED_BY_RAYS if name in _POSITIVE},
    **{name: integer(0, MAX_RAYS) for name in _SIZED_BY_RAYS if name in _NON_NEGATIVE},
    **{name: integer(1, MAX_POINTS) for name in _SIZED_BY_POINTS},
    "samples": integer(1, MAX_SAMPLES_PER_RAY),
    **{name: integer(0) for name in _NON_NEGATIVE},
    **{name: number(0.0, 1.0) for name in _FRACTIONS},
}


@dataclass
class TrainConfig:
    """Everything a training run depends on (stored as ``config.yaml`` in the run).

    Iteration counts are per phase; ``rays`` counts are per step. See :mod:`osn.train.loop`.
    The defaults are the CPU default (``configs/osn-cpu.yaml``). The paper's loss weights are
    constants: RGB 1, sparse depth :data:`osn.train.trainer.W_DEPTH`, segmentation
    :data:`osn.train.trainer.W_SEG` (the additions' weights are options). Each option's docstring begins
    with its category (``paper (...)``, ``addition (...)`` or ``infrastructure``) and names its
    neutral value; docs/training.md's Options table is generated from them
    (``scripts/docs_generate.py``).
    """

    seed: int = 0
    """infrastructure: Seed of the fields' initialisation, the rays each step draws and the scale
    samples; an integer >= 0. Neutral: none (each seed is one draw of the same training)."""
    field: FieldConfig = field(default_factory=FieldConfig)
    """paper (Sec. 3.1; appendix "Details of Networks"): The per-object radiance fields, each in its
    object's own unit: their kind and size (the ``field.*`` options). Neutral: none."""
    stage1_iters: int = 400
    """paper (Sec. 3.3, Stage 1; appendix "Details of the Joint Optimization", Training Schedule):
    Iterations of stage 1, every object trained alone on its own pixels and sparse depths (Eq. 2,
    plus this project's stage-1 terms). Unit: iterations. Neutral: 0 skips stage 1."""
    rounds: int = 5
    """paper (Sec. 3.3, Stage 2: R rounds of alternation): Rounds of a scale phase followed by a
    field phase. Unit: rounds. Neutral: 0 (no alternation: stage 1, then the final scale phase)."""
    field_iters: int = 100
    """paper (Sec. 3.3, Stage 2; appendix "Details of the Joint Optimization", Training Schedule):
    Iterations of each round's field phase: all objects composited at one valid scale vector per
    step (Eq. 8-10). Unit: iterations per round. Neutral: 0 (no field phases)."""
    scale_iters: int = 150
    """paper (Sec. 3.3, Stage 2; appendix "Details of the Joint Optimization", Training Schedule):
    Iterations of each round's scale phase: the scale network trained on depth-order labels
    (Eq. 13-15). Unit: iterations per round. Neutral: 0 (no scale phase in the rounds)."""
    final_scale_iters: int = 2000
    """addition (experiments/2026-11-25-final-scale-phase.md): Iterations of a last scale phase
    after the last field phase, on the final fields' label pool trimmed by ``final_label_trim``,
    long enough for the network to fit its labels. Unit: iterations. Neutral: 0 (training ends
    with the last field phase, as the paper's schedule does)."""
    rays_per_object: int = 384
    """paper (Sec. 3.3, Eq. 2): Pixels of an object's mask drawn for it per stage-1 step (and per
    ``w_alone`` term of a field step). Unit: rays per object and step. Neutral: none (at least 1)."""
    rays: int = 1024
    """paper (Sec. 3.3, Eq. 8-10): Training pixels drawn per field step, rendered as the
    composite of every object. Unit: rays per step. Neutral: none (at least 1)."""
    depth_rays: int = 64
    """paper (Sec. 3.3, Eq. 2 and Eq. 9): Sparse depths drawn per object in a stage-1 step, and
    over all objects per field step. Unit: rays per step. Neutral: 0 (no sparse-depth rays: the
    depth loss sees nothing)."""
    samples: int = 48
    """paper (Sec. 3.3, the M points sampled along each ray): Stratified samples per object and
    ray, in training and in every render of the run (``osn evaluate`` renders with this count).
    Unit: samples per object and ray. Neutral: none (at least 1)."""
    anchor_guide_samples: int | str = "auto"
    """addition (experiments/2026-11-27-anchor-guide-samples.md,
    experiments/2026-11-28-one-rule-room-options.md): A gradient-free pass of this many density
    samples along each of the anchor's rays places its ``samples`` at the quantiles of the weights
    it finds (``osn.model.volume.guided_positions``). ``auto`` (:func:`resolve_anchor_guide_samples`):
    :data:`ANCHOR_GUIDE_SAMPLES` where the anchor's box spans more pixels than its grid has voxels
    or it has no sparse depth, else 0. Unit: density samples per anchor ray. Neutral: 0 (even
    stratified samples)."""
    depth_robust: float | str = "auto"
    """addition (experiments/2026-11-26-sfm-phantom-depths-robust-depth-loss.md): The sparse-depth
    loss's form: 0 the squared error, ``k > 0`` a Cauchy loss at ``k`` times the batch's median
    residual, against SfM's phantom depths. ``auto`` (:func:`resolve_depth_robust`): 0 on exact
    inputs, :data:`DEPTH_ROBUST_NOISY` on noisy ones (:mod:`osn.preprocess.depth_noise`). Unit:
    multiples of the median
    residual. Neutral: 0 (the paper's squared error)."""
    w_opacity: float = 1.0
    """addition (experiments/2026-11-24-measurements-two-cores.md): Weight of the stage-1 term that
    pulls an object's opacity to 1 on every pixel of its mask, so a semi-transparent field cannot
    shorten its depths. Unit: loss weight. Neutral: 0 (term off)."""
    w_free: float = 1.0
    """addition (experiments/2026-11-24-measurements-two-cores.md,
    experiments/2026-11-28-free-space-ordered.md): Weight of the stage-1 free-space term, the
    squared opacity of an object alone on :data:`osn.train.trainer.FREE_RAYS` of its free pixels
    per step, so objects do not bleed past their silhouettes. An object's free pixels
    (``osn.train.tensors.SceneTensors.free_pixels``) show the anchor or nothing within
    :data:`osn.train.trainer.FREE_BAND` pixels of its mask, or, for objects but the anchor,
    another object within :data:`osn.train.trainer.FREE_BAND_OBJECTS`, except objects the last
    label pool put in front of it or, holding rays of both, holds none of the pair. Unit: loss
    weight. Neutral: 0 (term off)."""
    w_distortion: float = 0.03
    """addition (experiments/2026-11-26-seed-spread-distortion.md): Weight of mip-NeRF 360's
    distortion loss on an object's own pixels in stage 1 (how spread the weights are along the
    ray), so a pixel shows one surface instead of a fog. Unit: loss weight (the loss is
    unit-free). Neutral: 0 (term off)."""
    w_hidden_smooth: float = 0.3
    """addition (experiments/2026-11-28-hidden-anchor-smoothness.md,
    experiments/2026-11-29-lost-recall-from-sfm-inputs.md): Weight of the anchor's disparity
    curvature on :data:`osn.train.trainer.HIDDEN_STRIPS` strips per step across pixels that
    objects hide it on (``osn.train.losses.disparity_curvature``): zero on any plane, so a floor
    continues behind what stands on it. Unit: loss weight. Neutral: 0 (term off)."""
    w_planar: float = 1.0
    """addition (experiments/2026-12-01-anchor-planes.md): Weight of the anchor's depth targets from the
    planes its sparse depths of every frame support (``osn.train.planar``), on every pixel whose
    ray meets one inside its points' hull, in the anchor's stage-1 objective (so in every field step
    through ``w_alone``): a floor SfM found few points on is held where its plane is, also behind
    the objects standing on it. Unit: loss weight (as the sparse depths' 1). Neutral: 0 (no targets)."""
    w_alone: float = 1.0
    """addition (experiments/2026-11-24-what-limited-valid-set-iou.md,
    experiments/2026-11-25-valid-set-scene-suite.md): Weight of every object's stage-1 objective
    added to each field step, so the composite at sampled configurations cannot reshape an
    object's contacts to fit the labels. Unit: loss weight. Neutral: 0 (field steps as the
    paper's Eq. 8-10 alone)."""
    w_edge: float | str = "auto"
    """addition (experiments/2026-11-26-silhouette-depth.md): Weight of the silhouette-depth term
    (``osn.train.losses.edge_excess``, objects but the anchor, on :data:`osn.train.trainer.EDGE_RAYS`
    silhouette pixels per object and step): an edge pixel's log depth may exceed its inner
    neighbour's by at most :data:`osn.train.losses.EDGE_SLOPE`, the excess squared. ``auto``
    (:func:`resolve_w_edge`): 0 on exact inputs, :data:`W_EDGE_NOISY` on noisy ones
    (:mod:`osn.preprocess.depth_noise`). Unit: loss weight. Neutral: 0 (term off)."""
    scale_lr: float = 5e-3
    """paper (appendix "Details of the Joint Optimization", Training Schedule: Adam): The scale
    network's Adam learning rate at the start of every scale phase (the paper's is 0.001). Unit:
    learning rate. Neutral: none (must be positive)."""
    scale_lr_final: float = 0.1
    """addition (experiments/2026-11-24-what-limited-valid-set-iou.md,
    experiments/2026-11-25-valid-set-scene-suite.md): The fraction of ``scale_lr`` the rate
    decays to by a cosine within every scale phase. Unit: fraction of ``scale_lr``, in [0, 1].
    Neutral: 1 (a constant rate, as the paper's)."""
    scale_samples: int = 1024
    """paper (Sec. 3.3, Eq. 11: the H sampled scale combinations): Normalised scale vectors drawn
    and labelled per scale step. Unit: scale vectors per step. Neutral: none (at least 1)."""
    label_replay: float = 0.5
    """addition (experiments/2026-11-29-option-count-final-phase-single-options.md): The share of
    each scale step's samples drawn jittered around scale vectors labelled valid earlier instead of
    uniformly. Labels are always recomputed, but a sample's label is relative to the step's best
    sample (:func:`osn.model.depth_order.trimmed_labels`): without valid samples in the step the
    best is itself far from valid and the learned set comes out many times too large or empty.
    Unit: fraction of ``scale_samples``, in [0, 1]. Neutral: 0 (uniform samples, as the paper's)."""
    final_label_trim: float = 0.002
    """addition (experiments/2026-11-25-final-scale-phase.md,
    experiments/2026-11-29-lost-recall-from-sfm-inputs.md,
    experiments/2026-11-30-single-options-development-split.md): In the final scale phase a sample
    is labelled valid when on every object pair it violates at most the step's best sample's count
    plus this share of the pair's rays, against noise in the final fields' depths (the rounds'
    phases allow no more than the best sample's). Unit: fraction of a pair's rays, in [0, 1].
    Neutral: 0 (no more violations than the best sample's)."""
    pair_minority: float = 0.2
    """addition (experiments/2026-11-25-valid-set-scene-suite.md,
    experiments/2026-11-29-paper-constants-and-pair-minority.md): An object pair with fewer label
    rays than this times its opposite pair's is left out of the labels: those few rays are a field
    filling a gap it cannot resolve. Unit: ratio of ray counts, in [0, 1]. Neutral: 0 (every pair
    kept)."""
    anchor_bias: float = 1.0
    """addition (experiments/2026-11-30-anchor-bias-contact-bounds.md): The label pool reads the
    anchor's depth on each object's rays moved by this share of the anchor's measured bias beside
    and behind that object (:func:`osn.train.labels.anchor_bias`: its rendered depth against its
    own sparse depths within :data:`osn.train.labels.BIAS_BAND` pixels of the object's mask, and
    against its points of other frames that the object hides), so a contact bound is read against
    the surface the anchor's depths say, not one its field pulled nearer. Unit: fraction of the
    measured bias, in [0, 1]. Neutral: 0 (the anchor's depth as rendered)."""
    label_stride: int = 0
    """addition (not measured): The label pool takes every ``label_stride``-th labelled pixel per
    axis; 0 picks the stride that keeps about :data:`AUTO_LABEL_SIDE` pixels along the longer
    image side (:func:`osn.train.auto.label_stride`), which bounds the pool's render cost. Unit:
    pixels. Neutral: 1 (every pixel)."""
    eval_every: int = 200
    """infrastructure: Iterations between two lines of ``metrics.jsonl`` and two checkpoints (a
    line is also written at every phase end, a checkpoint at the end), so a resumed run repeats
    fewer than this many iterations. Unit: iterations. Neutral: none (at least 1)."""
    device: str = "auto"
    """infrastructure: Where training runs: ``auto`` (CUDA when present, else the CPU), ``cpu``,
    ``cuda`` or ``cuda:N``. Unit: a device name. Neutral: none."""

    def __post_init__(self) -> None:
        validate(self, "training", _RULES)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "TrainConfig":
        """From plain data (parsed YAML); misspelt keys, here or under ``field``, are errors."""
        d = dict(d or {})
        return from_dict(cls, d, "training", nested={"field": (FieldConfig, "field")})

    @classmethod
    def from_yaml(cls, path: str | Path, run_config: bool = False) -> "TrainConfig":
        """Read a YAML config; every error is a ``ValueError`` prefixed with ``path``.

        Omitted keys take the defaults, except with ``run_config`` (a run's own ``config.yaml``,
        which lists every key it trained with), read through :func:`osn.train.run_config.upgrade_run_config`.
        Options this version no longer has are ignored, with a warning, where they hold the value
        that trains as today (an older run's ``config.yaml`` given as a config), and refused otherwise.
        """
        try:
            d = yaml.safe_load(Path(path).read_text()) or {}
            if run_config and isinstance(d, dict):
                d = upgrade_run_config(d)
            elif isinstance(d, dict):
                d, dropped = drop_removed_options(d, "sets")
                if dropped:
                    log.warning("%s: %s no longer an option (trains as today at the value given); ignored",
                                path, ", ".join(dropped))
            return cls.from_dict(d)
        except (ValueError, TypeError, yaml.YAMLError) as e:
            raise ValueError(f"{path}: {e}") from None

    def to_dict(self) -> dict[str, Any]:
        """Plain data for ``config.yaml`` (round-trips through :meth:`from_dict`)."""
        return dataclasses.asdict(self)
