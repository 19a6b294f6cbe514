"""Joint optimisation of the per-object fields and the object scale network (paper section 3.3).

Schedule (global iteration counter, resumable at any iteration):

1. Stage 1, ``stage1_iters``: every object alone in its own unit, RGB + sparse-depth losses on
   its masked pixels (Eq. 2).
2. ``rounds`` alternation rounds, each a *scale phase* then a *field phase*, and a final scale
   phase. A scale phase renders every object's depth once on all training pixels (the soft
   Z-buffer's per-object depths, Eq. 17), then trains the scale network on ``H`` sampled scale
   vectors per step labelled by the depth order they imply (Eq. 11-13, 18) with BCE-with-logits.
   A field phase composites all objects scaled by one valid scale vector per step (score above
   ``valid_threshold``; the best candidate with a logged warning when none is) with RGB,
   scaled-depth and segmentation losses (weights 1, 1, 0.01; Eq. 8-10).
   The scale phase comes first in a round so field phases never sample from an untrained
   network (in the paper's order the first field phase would); the final scale phase fits the
   network to the final fields.

A single-object scene has no scale phases and no scale network. Objects absent from a frame
are never evaluated on its rays; no depth loss is used when the inputs carry no sparse depth.

Run directory: ``config.yaml``, ``inputs/`` (the per-object inputs used), ``checkpoint.pt``
(atomic, every ``checkpoint_every`` iterations and at the end; has every RNG state, so
``--resume`` reproduces an uninterrupted run bit for bit on the CPU; CUDA's atomic adds make
runs agree only up to rounding), ``metrics.jsonl`` (one JSON line per
evaluation: wall time, iteration, phase, losses, training PSNR and with ground truth the
valid-set precision / recall / IoU and the relative scale-interval error).
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from scenecore import dataset as D
from scenecore.cameras import pixel_rays
from scenecore.cli import UserError

from osn.model.fields import Field, FieldConfig, make_field
from osn.preprocess.inputs import IGNORE_ID, SceneInputs, load_inputs, oracle_inputs, save_inputs
from osn.model.run import CHECKPOINT_VERSION, read_checkpoint
from osn.model.scale_net import ScaleNet, full_sbar, sample_valid
from osn.model.softz import OrderConstraints, order_constraints, trimmed_labels
from osn.model.volume import ObjectRays, render
from benchgen.score.metrics import psnr_from_mse as psnr
from osn.evaluate.units import actual_scales, ground_truth_problem

log = logging.getLogger(__name__)

#: Scale vectors labelled valid that a scale phase keeps to sample around (see ``label_replay``).
REPLAY_SIZE = 4096


@dataclass
class TrainConfig:
    """Everything a training run depends on (stored as ``config.yaml`` in the run).

    Iteration counts are per phase; ``rays`` counts are per step. See the module docstring.
    The defaults are the CPU default (``configs/osn-cpu.yaml``).
    """

    seed: int = 0
    field: FieldConfig = field(default_factory=FieldConfig)
    stage1_iters: int = 400
    rounds: int = 5
    field_iters: int = 100
    scale_iters: int = 150
    final_scale_iters: int = 300
    rays_per_object: int = 384
    rays: int = 1024
    depth_rays: int = 64
    samples: int = 24
    skip_occluded: float = 1e-3
    w_rgb: float = 1.0
    w_depth: float = 1.0
    w_seg: float = 0.01
    w_opacity: float = 1.0
    w_free: float = 1.0
    free_space: str = "anchor"
    free_rays: int = 128
    free_band: int = 4
    scale_width: int = 64
    scale_layers: int = 4
    scale_lr: float = 5e-3
    scale_samples: int = 1024
    label_rays: int = 0
    label_replay: float = 0.5
    label_samples: int = 24
    label_trim: float = 0.01
    label_erode: int = 0
    label_stride: int = 0
    coverage_threshold: float = 0.9
    uncertain_acc: float = 0.05
    valid_threshold: float = 0.95
    candidates: int = 4096
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    eval_every: int = 200
    eval_pixels: int = 4096
    iou_samples: int = 20000
    checkpoint_every: int = 250
    device: str = "auto"

    #: Counts that must be >= 1 (a 0 would divide by zero or render nothing).
    _POSITIVE = ("rays_per_object", "rays", "samples", "scale_width", "scale_layers", "scale_samples",
                 "label_samples", "candidates", "eval_every", "eval_pixels", "iou_samples", "checkpoint_every")
    #: Counts that may be 0 (a phase or a term switched off) but not negative.
    _NON_NEGATIVE = ("rounds", "stage1_iters", "field_iters", "scale_iters", "final_scale_iters", "depth_rays", "free_rays",
                     "free_band", "label_rays", "label_erode", "label_stride")

    def __post_init__(self) -> None:
        def check(name: str, kind: type | tuple[type, ...], ok: Callable[[Any], bool], what: str) -> None:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, kind) or not ok(v):
                raise ValueError(f"training config: {name} must be {what}, got {v!r}")

        for name in self._POSITIVE:
            check(name, int, lambda v: v >= 1, "an integer >= 1")
        for name in self._NON_NEGATIVE:
            check(name, int, lambda v: v >= 0, "an integer >= 0")
        for name in ("label_replay", "label_trim", "coverage_threshold", "uncertain_acc"):
            check(name, (int, float), lambda v: 0.0 <= v <= 1.0, "a number in [0, 1]")
        # Field steps need scores above it: at 1 no candidate ever passes (sigmoid < 1).
        check("valid_threshold", (int, float), lambda v: 0.0 <= v < 1.0, "a number in [0, 1)")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainConfig":
        d = dict(d or {})
        _check_keys(cls, d, "training")
        fd = d.pop("field", {}) or {}
        _check_keys(FieldConfig, fd, "field")
        if "background" in d:
            d["background"] = tuple(float(x) for x in d["background"])
        return cls(field=FieldConfig(**fd), **d)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "TrainConfig":
        try:
            return cls.from_dict(yaml.safe_load(Path(path).read_text()) or {})
        except (ValueError, TypeError, yaml.YAMLError) as e:
            raise ValueError(f"{path}: {e}") from None

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["background"] = list(self.background)
        return d


def _check_keys(cls: type, d: dict[str, Any], what: str) -> None:
    """Reject misspelt config keys instead of silently ignoring them."""
    unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise ValueError(f"unknown {what} config keys: {sorted(unknown)}")


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


def pick_device(name: str = "auto") -> torch.device:
    """CUDA when available (or asked for), else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


# --------------------------------------------------------------------------------------------
# Tensors of the inputs
# --------------------------------------------------------------------------------------------


class SceneTensors:
    """The inputs as device tensors, indexed by object *position* k (``inputs.objects[k]``)."""

    def __init__(self, inputs: SceneInputs, device: torch.device) -> None:
        self.inputs = inputs
        self.device = device
        T, H, W = inputs.images.shape[:3]
        self.T, self.H, self.W, self.K = T, H, W, inputs.num_objects
        self.images = torch.from_numpy(inputs.images).to(device).float().reshape(T, H * W, 3) / 255.0
        pos_of_id = np.full(256, -1, dtype=np.int64)
        for k, o in enumerate(inputs.objects):
            pos_of_id[o.id] = k
        self.labels = torch.from_numpy(pos_of_id[inputs.masks.reshape(T, H * W)]).to(device)  # -1 = none
        _, d = pixel_rays(inputs.K, np.eye(4), W, H)
        self.dirs = torch.from_numpy(d).float().to(device)  # (HW, 3), camera frame, unit z
        self.anchor = inputs.anchor_pos
        self.poses = torch.eye(4, device=device).repeat(self.K, T, 1, 1)
        self.present = torch.zeros(self.K, T, dtype=torch.bool, device=device)
        self.t_range = torch.zeros(self.K, 2, device=device)  # object-unit planar depth range
        sp_frame, sp_pix, sp_depth, sp_obj = [], [], [], []
        for k, o in enumerate(inputs.objects):
            fr = torch.from_numpy(o.frames).long().to(device)
            self.poses[k, fr] = torch.from_numpy(o.cam_to_obj).float().to(device)
            self.present[k, fr] = True
            self.t_range[k] = torch.tensor([0.5 * o.near, 2.0 * o.far])
            for slot, t in enumerate(o.frames):
                pix, dep = o.sparse_pix[slot], o.sparse_depth[slot]
                if len(dep) == 0:
                    continue
                sp_frame.append(np.full(len(dep), t))
                sp_pix.append(pix[:, 1] * W + pix[:, 0])
                sp_depth.append(dep)
                sp_obj.append(np.full(len(dep), k))
        cat = lambda xs, dt: torch.from_numpy(np.concatenate(xs) if xs else np.zeros(0)).to(device, dt)  # noqa: E731
        self.sp_frame, self.sp_pix = cat(sp_frame, torch.long), cat(sp_pix, torch.long)
        self.sp_depth, self.sp_obj = cat(sp_depth, torch.float32), cat(sp_obj, torch.long)
        # Per object: flat (frame * HW + pixel) indices of its masked pixels and of its sparse depths.
        flat_labels = self.labels.reshape(-1)
        # Pixels of objects that preprocessing dropped carry no supervision at all (None: every pixel).
        ignored = torch.from_numpy(inputs.masks.reshape(-1) == IGNORE_ID).to(device)
        self.usable = torch.nonzero(~ignored)[:, 0] if bool(ignored.any()) else None
        self.obj_pixels = [torch.nonzero(flat_labels == k)[:, 0] for k in range(self.K)]
        self.ignored = ignored
        self.obj_sparse = [torch.nonzero(self.sp_obj == k)[:, 0] for k in range(self.K)]
        self.ranges = torch.from_numpy(inputs.scale_ranges()).to(device, torch.float64)

    def free_pixels(self, mode: str, band: int) -> list[torch.Tensor]:
        """Per object the flat indices of pixels its field must leave empty, within ``band``
        pixels of its mask in frames where it is present.

        ``mode`` "anchor": pixels showing the anchor or nothing (objects are never behind the
        anchor, e.g. a room that contains them); "all": every pixel of another object too
        (the paper's masked images; also carves what other objects hide); "none": no pixels.
        """
        T, H, W = self.T, self.H, self.W
        lab = self.labels.reshape(T, H, W)
        out = []
        for k in range(self.K):
            if mode == "none":
                out.append(torch.zeros(0, dtype=torch.long, device=self.device))
                continue
            near = F.max_pool2d((lab == k).float()[:, None], 2 * band + 1, stride=1, padding=band)[:, 0] > 0
            free = (lab != k) if mode == "all" else (lab == -1) | ((lab == self.anchor) & (k != self.anchor))
            keep = near & free & self.present[k][:, None, None] & ~self.ignored.reshape(T, H, W)
            out.append(torch.nonzero(keep.reshape(-1))[:, 0])
        return out

    @property
    def has_depth(self) -> bool:
        return self.sp_depth.numel() > 0

    def object_rays(self, fields: list[Field], frames: torch.Tensor, sbar: torch.Tensor, objects: list[int] | None = None) -> list[ObjectRays]:
        """Per-object views of rays from training ``frames (R,)`` for configuration ``sbar (K,)``."""
        out = []
        for k in objects if objects is not None else range(self.K):
            s = sbar[k].float()
            P = self.poses[k, frames].clone()
            P[:, :3, :3] = P[:, :3, :3] / s  # cam_to_obj_k @ diag(1/s): scaling about the camera
            out.append(ObjectRays(fields[k], P, self.present[k, frames], self.t_range[k] * s))
        return out


# --------------------------------------------------------------------------------------------
# Trainer
# --------------------------------------------------------------------------------------------


@dataclass
class Phase:
    name: str  # "stage1", "scale", "fields"
    start: int
    end: int
    round: int


def build_schedule(cfg: TrainConfig, num_objects: int) -> list[Phase]:
    """Phases in order; a single object has no scale phases."""
    phases: list[Phase] = []
    it = 0

    def add(name: str, n: int, r: int) -> None:
        nonlocal it
        if n > 0:
            phases.append(Phase(name, it, it + n, r))
            it += n

    add("stage1", cfg.stage1_iters, 0)
    for r in range(1, cfg.rounds + 1):
        if num_objects > 1:
            add("scale", cfg.scale_iters, r)
        add("fields", cfg.field_iters, r)
    if num_objects > 1:
        add("scale", cfg.final_scale_iters, cfg.rounds + 1)
    return phases


class Trainer:
    """Owns the fields, the scale network, their optimisers and the RNG; one ``step`` per iteration."""

    def __init__(self, inputs: SceneInputs, cfg: TrainConfig, device: torch.device) -> None:
        self.cfg, self.device = cfg, device
        self.st = SceneTensors(inputs, device)
        K = self.st.K
        torch.manual_seed(cfg.seed)
        self.gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        self.fields = [make_field(cfg.field, torch.from_numpy(o.bbox).float(), seed=cfg.seed + k).to(device) for k, o in enumerate(inputs.objects)]
        self.net = ScaleNet(K - 1, cfg.scale_width, cfg.scale_layers, seed=cfg.seed).to(device) if K > 1 else None
        self.net_opt = torch.optim.Adam(self.net.parameters(), lr=cfg.scale_lr) if self.net is not None else None
        self.schedule = build_schedule(cfg, K)
        self.total = self.schedule[-1].end if self.schedule else 0
        self.field_total = sum(p.end - p.start for p in self.schedule if p.name != "scale")
        res = cfg.field.resolutions()
        self.upsample_at = {int(round(self.field_total * 0.4 * (i + 1) / (len(res) - 1))): r for i, r in enumerate(res[1:])} if len(res) > 1 else {}
        self.field_iter = 0
        self.iteration = 0
        self.elapsed = 0.0
        self.fallbacks = 0
        self.cache: dict[str, torch.Tensor] | None = None
        self.cache_key: int | None = None
        self.noise_floor = 0.0
        self.positives = torch.zeros(0, max(K - 1, 1))
        self.loss_acc: dict[str, list[float]] = {}  # losses since the last metrics line
        self.bg = torch.tensor(cfg.background, device=device)
        if cfg.free_space not in ("none", "anchor", "all"):
            raise ValueError(f"free_space must be none, anchor or all, got {cfg.free_space!r}")
        self.free = self.st.free_pixels(cfg.free_space, cfg.free_band)
        self._make_field_opt()

    # ---- optimisers and state ------------------------------------------------------------

    def _make_field_opt(self) -> None:
        groups = [g for f in self.fields for g in f.param_groups(self.cfg.field.lr_grid, self.cfg.field.lr_net)]
        self.field_opt = torch.optim.Adam(groups, betas=(0.9, 0.99))

    def state_dict(self) -> dict[str, Any]:
        return {
            "version": CHECKPOINT_VERSION,
            "iteration": self.iteration,
            "field_iter": self.field_iter,
            "elapsed": self.elapsed,
            "fallbacks": self.fallbacks,
            "noise_floor": self.noise_floor,
            "positives": self.positives,
            "loss_acc": self.loss_acc,
            "resolutions": [f.resolution for f in self.fields],
            "fields": [f.state_dict() for f in self.fields],
            "field_opt": self.field_opt.state_dict(),
            "net": self.net.state_dict() if self.net is not None else None,
            "net_opt": self.net_opt.state_dict() if self.net_opt is not None else None,
            "gen": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "config": self.cfg.to_dict(),
        }

    def load_state_dict(self, s: dict[str, Any]) -> None:
        self.iteration, self.field_iter, self.elapsed = s["iteration"], s["field_iter"], s["elapsed"]
        self.fallbacks, self.noise_floor = s["fallbacks"], s["noise_floor"]
        # RNG states must be CPU byte tensors and the replay buffer lives on the CPU, whatever
        # device the checkpoint was read onto.
        self.positives = s.get("positives", self.positives).cpu()  # version 1: resumes with an empty buffer
        self.loss_acc = {k: list(v) for k, v in s["loss_acc"].items()}
        for f, r, sd in zip(self.fields, s["resolutions"], s["fields"]):
            f.set_resolution(r)
            f.load_state_dict(sd)
        self._make_field_opt()
        self.field_opt.load_state_dict(s["field_opt"])
        if self.net is not None:
            self.net.load_state_dict(s["net"])
            self.net_opt.load_state_dict(s["net_opt"])
        self.gen.set_state(s["gen"].cpu())
        torch.set_rng_state(s["torch_rng"].cpu())

    def non_finite_parameters(self) -> list[str]:
        """Which models hold a NaN or infinite weight (``field <id>``, ``scale network``)."""
        bad = [f"field {o.id}" for o, f in zip(self.st.inputs.objects, self.fields)
               if not all(bool(torch.isfinite(p).all()) for p in f.parameters())]
        if self.net is not None and not all(bool(torch.isfinite(p).all()) for p in self.net.parameters()):
            bad.append("scale network")
        return bad

    def phase(self, it: int) -> Phase:
        return next(p for p in self.schedule if p.start <= it < p.end)

    # ---- ray batches ---------------------------------------------------------------------

    def _randint(self, n: int, size: int) -> torch.Tensor:
        return torch.randint(n, (size,), generator=self.gen).to(self.device)

    def _depth_loss(self, out_depth: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return F.mse_loss(out_depth, target) if target.numel() else out_depth.sum() * 0.0

    def _free_loss(self, k: int) -> torch.Tensor:
        """Mean squared opacity of object k alone on ``free_rays`` of its free pixels (see
        :meth:`SceneTensors.free_pixels`): keeps its field from bleeding past its silhouette,
        which would otherwise read as "k is behind the anchor" to the scale labels."""
        st, cfg, free = self.st, self.cfg, self.free[k]
        if cfg.w_free <= 0 or not len(free):
            return torch.zeros((), device=self.device)
        fp = free[self._randint(len(free), cfg.free_rays)]
        one = torch.ones(st.K, device=self.device)
        out = render(st.object_rays(self.fields, fp // (st.H * st.W), one, [k]), st.dirs[fp % (st.H * st.W)], self.cfg.samples, self.gen, self.bg, cfg.skip_occluded)
        return out.acc.square().mean()

    def _tv(self, k: int) -> torch.Tensor | float:
        w = self.cfg.field.tv_density
        return w * self.fields[k].density_tv() if w > 0 else 0.0

    # ---- stage 1 -------------------------------------------------------------------------

    def step_stage1(self) -> dict[str, float]:
        st, cfg = self.st, self.cfg
        losses = {"rgb": 0.0, "depth": 0.0, "opacity": 0.0, "free": 0.0}
        total = 0.0
        one = torch.ones(1, device=self.device)
        for k in range(st.K):
            pix = st.obj_pixels[k][self._randint(len(st.obj_pixels[k]), cfg.rays_per_object)]
            frames, p = pix // (st.H * st.W), pix % (st.H * st.W)
            n_rgb = len(p)
            if st.has_depth and cfg.w_depth > 0 and len(st.obj_sparse[k]):
                sp = st.obj_sparse[k][self._randint(len(st.obj_sparse[k]), cfg.depth_rays)]
                frames = torch.cat([frames, st.sp_frame[sp]])
                p = torch.cat([p, st.sp_pix[sp]])
                d_gt = st.sp_depth[sp]
            else:
                d_gt = torch.zeros(0, device=self.device)
            rays = st.object_rays(self.fields, frames, one.expand(st.K), [k])
            out = render(rays, st.dirs[p], cfg.samples, self.gen, self.bg, cfg.skip_occluded)
            l_rgb = F.mse_loss(out.rgb, st.images[frames, p])
            l_depth = self._depth_loss(out.depth[n_rgb:], d_gt)
            # Every pixel of the object's mask is hit by it: opacity 1. Without this a field can
            # stay semi-transparent and the depth loss (on sum_i w_i t_i, which a transparent
            # ray shortens) then pushes its surfaces behind the true ones (the room by ~6-10%).
            l_acc = (1.0 - out.acc).square().mean()
            total = total + cfg.w_rgb * l_rgb + cfg.w_depth * l_depth + cfg.w_opacity * l_acc + self._tv(k)
            l_free = self._free_loss(k)
            total = total + cfg.w_free * l_free
            losses["free"] += l_free.item() / st.K
            losses["rgb"] += l_rgb.item() / st.K
            losses["depth"] += l_depth.item() / st.K
            losses["opacity"] += l_acc.item() / st.K
        self.field_opt.zero_grad(set_to_none=True)
        total.backward()
        self.field_opt.step()
        return losses

    # ---- stage 2: field phase ------------------------------------------------------------

    def sample_configuration(self) -> tuple[torch.Tensor, float]:
        """One valid scale vector ``(K,)`` for a composite step (anchor = 1; single object = [1])."""
        if self.net is None:
            return torch.ones(1, dtype=torch.float64, device=self.device), 1.0
        # With many objects uniform candidates can all miss the valid set (gnome-house's is 1.4%
        # of the box with 3 free objects); then candidates around remembered valid vectors.
        sbar, _, p, fell_back = sample_valid(
            self.net, self.st.ranges, self.st.anchor, self.gen, self.cfg.candidates, self.cfg.valid_threshold, warn=False,
            near=self._near_positives if len(self.positives) else None,
        )
        if fell_back and self.fallbacks == 0:
            log.warning("no candidate scored above %.2f (best %.3f): field steps use the best one; "
                        "the count is in metrics.jsonl ('fallbacks')", self.cfg.valid_threshold, p)
        self.fallbacks += int(fell_back)
        return sbar, p

    def step_fields(self) -> dict[str, float]:
        st, cfg = self.st, self.cfg
        sbar, score = self.sample_configuration()
        flat = self._randint(st.T * st.H * st.W, cfg.rays) if st.usable is None else st.usable[self._randint(len(st.usable), cfg.rays)]
        frames, p = flat // (st.H * st.W), flat % (st.H * st.W)
        n_rgb = len(p)
        if st.has_depth and cfg.w_depth > 0:
            sp = self._randint(len(st.sp_depth), cfg.depth_rays)
            frames = torch.cat([frames, st.sp_frame[sp]])
            p = torch.cat([p, st.sp_pix[sp]])
            s_obj = sbar[st.sp_obj[sp]].float()
            d_gt = st.sp_depth[sp]
        else:
            s_obj = d_gt = torch.zeros(0, device=self.device)
        out = render(st.object_rays(self.fields, frames, sbar), st.dirs[p], cfg.samples, self.gen, self.bg, cfg.skip_occluded)
        l_rgb = F.mse_loss(out.rgb, st.images[frames, p])
        # Eq. 9 compares with sbar_k * d_gt; dividing by sbar_k keeps the loss's weight
        # independent of the sampled scale (same minimiser).
        l_depth = self._depth_loss(out.depth[n_rgb:] / s_obj, d_gt) if len(d_gt) else out.depth.sum() * 0.0
        lab = st.labels[frames, p]
        seg_ok = lab >= 0
        l_seg = F.nll_loss(out.log_seg[seg_ok], lab[seg_ok]) if st.K > 1 and seg_ok.any() else out.rgb.sum() * 0.0
        loss = cfg.w_rgb * l_rgb + cfg.w_depth * l_depth + cfg.w_seg * l_seg + sum(self._tv(k) for k in range(st.K))
        self.field_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.field_opt.step()
        return {"rgb": l_rgb.item(), "depth": l_depth.item(), "seg": l_seg.item(), "score": score}

    # ---- stage 2: scale phase ------------------------------------------------------------

    def _label_pixels(self) -> torch.Tensor:
        """Flat (frame * HW + pixel) indices of the label pool candidates: every
        ``label_stride``-th pixel per axis, labelled, away from mask boundaries by ``label_erode``
        (independent coverage is unreliable on silhouettes)."""
        st, cfg = self.st, self.cfg
        lab = st.labels.reshape(st.T, st.H, st.W)
        keep = lab >= 0
        e = cfg.label_erode
        if e > 0:
            padded = F.pad(lab[:, None].float(), (e, e, e, e), mode="replicate")
            mx = F.max_pool2d(padded, 2 * e + 1, stride=1)[:, 0]
            mn = -F.max_pool2d(-padded, 2 * e + 1, stride=1)[:, 0]
            keep &= (mx == lab) & (mn == lab)
        stride = label_stride(cfg.label_stride, st.H, st.W)
        grid = torch.zeros(st.H, st.W, dtype=torch.bool, device=self.device)
        grid[::stride, ::stride] = True
        return torch.nonzero((keep & grid).reshape(-1))[:, 0]

    @torch.no_grad()
    def render_alone_depths(self, flat: torch.Tensor, chunk: int = 8192) -> dict[str, torch.Tensor]:
        """Every object's independent planar depth (own unit), opacity ``acc`` and coverage on
        training pixels ``flat`` (the soft Z-buffer's per-object depths, rendered once per scale
        phase), and ``uncertain``: some object's ``acc`` is in ``(uncertain_acc, coverage_threshold]``."""
        st, cfg = self.st, self.cfg
        HW = st.H * st.W
        depth = torch.zeros(len(flat), st.K, device=self.device)
        covered = torch.zeros(len(flat), st.K, dtype=torch.bool, device=self.device)
        # Some object is semi-transparent on the ray (acc between uncertain_acc and the coverage
        # threshold): whether it "covers" is a coin flip of the threshold, so the ray is dropped.
        uncertain = torch.zeros(len(flat), dtype=torch.bool, device=self.device)
        acc = torch.zeros(len(flat), st.K, device=self.device)
        one = torch.ones(st.K, device=self.device)
        frames_all, pix_all = flat // HW, flat % HW
        for k in range(st.K):
            idx = torch.nonzero(st.present[k, frames_all])[:, 0]  # absent frames cost nothing
            for a in range(0, len(idx), chunk):
                i = idx[a : a + chunk]
                out = render(st.object_rays(self.fields, frames_all[i], one, [k]), st.dirs[pix_all[i]], cfg.label_samples, None, None, cfg.skip_occluded)
                depth[i, k] = out.normalised_depth()
                acc[i, k] = out.acc
                covered[i, k] = out.acc > cfg.coverage_threshold
                uncertain[i] |= (out.acc > cfg.uncertain_acc) & (out.acc <= cfg.coverage_threshold)
        return {"depth": depth, "covered": covered, "uncertain": uncertain, "acc": acc}

    def _contested(self, flat: torch.Tensor, depth: torch.Tensor, covered: torch.Tensor) -> torch.Tensor:
        """Mask of rays that can inform the scale network: the labelled object covers the ray,
        another object does too, and *some* scale vector in the sampling box explains the
        label (``lo_L d_L < hi_j d_j`` for every other covering j). Rays no sampled scale can
        explain (geometry noise) would only make every sample look equally wrong."""
        st = self.st
        gt = st.labels.reshape(-1)[flat]
        gt_cov = covered.gather(1, gt[:, None])[:, 0]
        lo = st.ranges[:, 0].clone()
        hi = st.ranges[:, 1].clone()
        lo[st.anchor] = hi[st.anchor] = 1.0
        best_l = (lo[gt] * depth.gather(1, gt[:, None])[:, 0].double())[:, None]
        others = torch.where(covered, hi[None] * depth.double(), torch.full_like(depth, float("inf"), dtype=torch.float64))
        others.scatter_(1, gt[:, None], float("inf"))
        satisfiable = (best_l < others).all(1)
        return gt_cov & (covered.sum(1) >= 2) & satisfiable

    def ensure_cache(self, phase: Phase) -> None:
        """Render the per-object depths at the start of a scale phase (recomputed identically on resume)."""
        if self.cache_key != phase.start:
            flat = self._label_pixels()
            c = self.render_alone_depths(flat)
            keep = self._contested(flat, c["depth"], c["covered"]) & ~c["uncertain"]
            self.cache = {"flat": flat[keep], "depth": c["depth"][keep], "covered": c["covered"][keep]}
            self.cache["gt"] = self.st.labels.reshape(-1)[self.cache["flat"]]
            self.cache["constraints"] = order_constraints(self.cache["depth"], self.cache["covered"], self.cache["gt"])
            self.cache_key = phase.start
            if not len(self.cache["flat"]):
                # No ray constrains any depth order (fields still transparent, or every ray dropped
                # as semi-transparent): every sample is labelled valid, which says nothing.
                log.warning(
                    "scale phase at iteration %d: no contested ray among %d labelled pixels (%d semi-transparent); "
                    "the network learns no depth order (fields not opaque yet? see uncertain_acc)",
                    phase.start, len(flat), int(c["uncertain"].sum()),
                )

    def _constraints(self) -> OrderConstraints:
        """The scale phase's depth-order constraints: every contested pool ray, or a random
        ``label_rays`` of them per step when that is set (> 0)."""
        c, n = self.cache, len(self.cache["flat"])
        if self.cfg.label_rays <= 0 or self.cfg.label_rays >= n:
            return c["constraints"]
        r = self._randint(n, self.cfg.label_rays)
        return order_constraints(c["depth"][r], c["covered"][r], c["gt"][r])

    def _scale_samples(self) -> torch.Tensor:
        """Normalised free scales for one scale step: uniform in the box, plus a share
        ``label_replay`` jittered around scale vectors labelled valid earlier (labels are always
        recomputed, so this only spends samples where the boundary is, never biases a label)."""
        cfg, st = self.cfg, self.st
        n = cfg.scale_samples
        n_near = int(round(n * cfg.label_replay)) if len(self.positives) else 0
        s = torch.rand(n - n_near, st.K - 1, generator=self.gen)
        if n_near:
            s = torch.cat([s, self._near_positives(n_near)])
        return s.to(self.device)

    def _near_positives(self, n: int) -> torch.Tensor:
        """``n`` normalised scale vectors (CPU) jittered around remembered valid ones, at three
        spreads (0.01, 0.03, 0.1 of the box) so both the boundary and the interior are reached."""
        pick = self.positives[torch.randint(len(self.positives), (n,), generator=self.gen)]
        sigma = torch.tensor([0.01, 0.03, 0.1])[torch.randint(3, (n, 1), generator=self.gen)]
        return (pick + sigma * torch.randn(n, self.st.K - 1, generator=self.gen)).clamp(0.0, 1.0 - 1e-6)

    def _remember(self, s: torch.Tensor) -> None:
        """Keep the last ``REPLAY_SIZE`` scale vectors labelled valid (CPU, checkpointed)."""
        self.positives = torch.cat([self.positives, s.detach().cpu().float()])[-REPLAY_SIZE:]

    def step_scale(self, phase: Phase) -> dict[str, float]:
        self.ensure_cache(phase)
        cfg, st = self.cfg, self.st
        s = self._scale_samples()
        sbar = full_sbar(s, st.ranges, st.anchor)
        cons = self._constraints()
        # Labels relative to the best sample, per object pair (softz.trimmed_labels): learned
        # depths have floaters that make some rays wrong for every scale vector. All samples are
        # scored on the same rays, so "within tolerance of the best" compares like with like.
        # The pool is already restricted to rays some scale in the box explains (_contested).
        pv = cons.pair_violations(sbar)
        self.noise_floor = float(pv.sum(1).min()) / max(cons.count, 1)
        labels = trimmed_labels(pv, cons.sizes(), cfg.label_trim)
        self._remember(s[labels > 0])
        loss = F.binary_cross_entropy_with_logits(self.net(s), labels.to(self.device))
        self.net_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.net_opt.step()
        return {"bce": loss.item(), "valid_frac": float(labels.mean()), "contested": float(cons.rays), "noise_floor": self.noise_floor}

    # ---- one iteration -------------------------------------------------------------------

    def step(self) -> dict[str, float]:
        ph = self.phase(self.iteration)
        if ph.name == "scale":
            out = self.step_scale(ph)
        else:
            if self.field_iter in self.upsample_at:
                for f in self.fields:
                    f.set_resolution(self.upsample_at[self.field_iter])
                self._make_field_opt()  # parameter shapes changed (TensoRF does the same)
            out = self.step_stage1() if ph.name == "stage1" else self.step_fields()
            self.field_iter += 1
        self.iteration += 1
        return out


# --------------------------------------------------------------------------------------------
# Evaluation against the training video and the exact region
# --------------------------------------------------------------------------------------------


class Evaluator:
    """Training-view PSNR on a fixed pixel subset and, with ground truth, valid-set accuracy."""

    def __init__(self, trainer: Trainer, dataset_root: str | Path | None) -> None:
        self.tr = trainer
        st, cfg = trainer.st, trainer.cfg
        g = torch.Generator().manual_seed(12345)
        # Pixels of dropped objects (IGNORE_ID) are never trained on, so they are not scored.
        pool = st.usable if st.usable is not None else torch.arange(st.T * st.H * st.W, device=st.device)
        n = min(cfg.eval_pixels, len(pool))
        self.flat = pool[torch.randperm(len(pool), generator=g)[:n].to(st.device)]
        self.region = None
        has_region = dataset_root is not None and (Path(dataset_root) / "valid_region.json").exists()
        # Scales need only the units; test cameras (world_to_anchor) are evaluation's concern.
        problem = ground_truth_problem(st.inputs, test_views=False) if has_region else None
        if problem:
            log.warning("valid-set accuracy is not measured during training: %s", problem)
        if trainer.net is not None and has_region and not problem:
            self.region = D.load_valid_region(dataset_root)
            self.s_mc = torch.rand(cfg.iou_samples, st.K - 1, generator=g, dtype=torch.float64)
            sbar = full_sbar(self.s_mc, st.ranges.cpu(), st.anchor).numpy()
            self.actual_mc = actual_scales(st.inputs, sbar)
            full = np.ones((len(sbar), self.region.num_objects))
            full[:, [o.id for o in st.inputs.objects]] = self.actual_mc
            self.exact = np.asarray(self.region.contains(full))

    @torch.no_grad()
    def best_configuration(self) -> torch.Tensor:
        tr = self.tr
        if tr.net is None:
            return torch.ones(1, dtype=torch.float64, device=tr.device)
        g = torch.Generator().manual_seed(54321)
        s = torch.rand(4096, tr.st.K - 1, generator=g).to(tr.device)
        return full_sbar(s[tr.net(s).argmax()][None], tr.st.ranges, tr.st.anchor)[0]

    @torch.no_grad()
    def __call__(self) -> dict[str, float]:
        tr, st, cfg = self.tr, self.tr.st, self.tr.cfg
        frames, p = self.flat // (st.H * st.W), self.flat % (st.H * st.W)
        sbar = self.best_configuration()
        out = render(st.object_rays(tr.fields, frames, sbar), st.dirs[p], cfg.samples, None, tr.bg, cfg.skip_occluded)
        m: dict[str, float] = {"psnr": psnr(float(F.mse_loss(out.rgb, st.images[frames, p])))}
        if st.K > 1:
            lab = st.labels[frames, p]
            ok = lab >= 0
            m["seg_acc"] = float((out.log_seg[ok].argmax(1) == lab[ok]).float().mean())
            m["sbar_best"] = [float(x) for x in sbar.cpu()]
        if self.region is not None:
            learned = (tr.net(self.s_mc.float().to(tr.device)) > 0).cpu().numpy()
            inter = float(np.sum(learned & self.exact))
            m["precision"] = inter / max(float(learned.sum()), 1.0)
            m["recall"] = inter / max(float(self.exact.sum()), 1.0)
            m["iou"] = inter / max(float(np.sum(learned | self.exact)), 1.0)
            m["scale_rel_err"] = self._interval_error(learned)
        return m

    def _interval_error(self, learned: np.ndarray) -> float:
        """Mean relative error of the learned per-object scale intervals (actual scales, within
        the sampled box) against the exact region's intervals; 1.0 when either set is empty."""
        if not learned.any() or not self.exact.any():
            return 1.0
        errs = []
        for k in range(self.tr.st.K):
            if k == self.tr.st.anchor:
                continue
            a, e = self.actual_mc[learned, k], self.actual_mc[self.exact, k]
            errs += [abs(a.min() - e.min()) / e.min(), abs(a.max() - e.max()) / e.max()]
        return float(np.mean(errs))


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


def _save_checkpoint(path: Path, trainer: Trainer) -> None:
    buf = io.BytesIO()
    torch.save(trainer.state_dict(), buf)
    D.atomic_write_bytes(path, buf.getvalue())


class TrainingDiverged(UserError):
    """A loss or a weight became NaN or infinite; the message names the run, iteration, phase
    and what diverged. Checked before every checkpoint, so the last one written stays finite."""

    @classmethod
    def at(cls, out: Path, iteration: int, phase: Phase, what: str) -> "TrainingDiverged":
        return cls(f"{out}: training diverged at iteration {iteration} ({phase.name} phase): {what}; "
                   "the last checkpoint is kept (lower field.lr_grid / scale_lr, or check the inputs)")


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """The records of a run's ``metrics.jsonl`` (empty if absent). A line cut by a kill
    mid-write, or anything else that is not a record with an ``iteration``, is skipped."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    for ln in path.read_text().splitlines():
        try:
            rec = json.loads(ln)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and isinstance(rec.get("iteration"), int):
            out.append(rec)
    return out


def _truncate_metrics(path: Path, iteration: int) -> None:
    """Drop metric lines written after the checkpoint being resumed (they will be rewritten)."""
    if not path.exists():
        return
    lines = [json.dumps(rec) for rec in read_metrics(path) if rec["iteration"] <= iteration]
    D.atomic_write_bytes(path, ("\n".join(lines) + "\n" if lines else "").encode())


def train(
    dataset: str | Path | None,
    out: str | Path,
    cfg: TrainConfig | None = None,
    resume: bool = False,
    inputs: SceneInputs | None = None,
    max_iterations: int | None = None,
    progress: bool = True,
) -> Path:
    """Train OSN on ``dataset`` (oracle inputs unless ``inputs`` is given) into run directory ``out``.

    ``max_iterations`` stops early after that global iteration (with a checkpoint), as an
    interruption would; ``resume`` continues from ``out/checkpoint.pt``. Returns ``out``.
    """
    from tqdm import tqdm

    out = Path(out)
    ckpt = out / "checkpoint.pt"
    if resume:
        if not ckpt.exists():
            raise FileNotFoundError(f"{ckpt}: nothing to resume")
        cfg = TrainConfig.from_yaml(out / "config.yaml")
        inputs = load_inputs(out / "inputs")
    else:
        if ckpt.exists():
            raise FileExistsError(f"{out} already holds a run; pass --resume to continue it or choose another --out")
        # A run killed before its first checkpoint may have left metric lines; a fresh start
        # rewrites them, so they must not stay in front of the new curve.
        (out / "metrics.jsonl").unlink(missing_ok=True)
        cfg = cfg or TrainConfig()
        inputs = inputs if inputs is not None else oracle_inputs(dataset)
        out.mkdir(parents=True, exist_ok=True)
        save_inputs(out / "inputs", inputs)
        D.atomic_write_bytes(out / "config.yaml", yaml.safe_dump(cfg.to_dict(), sort_keys=False).encode())
        D.atomic_write_json(out / "run.json", {"dataset": str(dataset) if dataset else None})
    device = pick_device(cfg.device)
    trainer = Trainer(inputs, cfg, device)
    metrics_path = out / "metrics.jsonl"
    if resume:
        # Read onto the CPU: load_state_dict moves weights and optimiser state to the device
        # itself, and the RNG states it restores must stay on the CPU (a CUDA resume crashed).
        trainer.load_state_dict(read_checkpoint(ckpt, "cpu"))
        _truncate_metrics(metrics_path, trainer.iteration)
    ds = D.read_json(out / "run.json").get("dataset")
    evaluator = Evaluator(trainer, ds)
    stop = min(trainer.total, max_iterations) if max_iterations is not None else trainer.total
    bar = tqdm(total=trainer.total, initial=trainer.iteration, desc="osn train", disable=not progress, dynamic_ncols=True)
    t_start = time.perf_counter() - trainer.elapsed
    acc = trainer.loss_acc
    while trainer.iteration < stop:
        ph = trainer.phase(trainer.iteration)
        losses = trainer.step()
        bad = sorted(k for k, v in losses.items() if not math.isfinite(v))
        if bad:  # stop before a NaN reaches a checkpoint; the last good one stays resumable
            raise TrainingDiverged.at(out, trainer.iteration, ph, f"loss {', '.join(bad)} is {losses[bad[0]]}")
        for key, v in losses.items():
            acc.setdefault(key, []).append(v)
        it = trainer.iteration
        trainer.elapsed = time.perf_counter() - t_start
        phase_end = it == ph.end
        if it % cfg.eval_every == 0 or phase_end or it == trainer.total:
            rec = {"iteration": it, "wall_time": round(trainer.elapsed, 3), "phase": ph.name, "round": ph.round}
            rec.update({key: float(np.mean(v)) for key, v in acc.items()})
            if "rgb" in acc:
                rec["train_batch_psnr"] = psnr(rec["rgb"])
            rec.update(evaluator())
            rec["fallbacks"] = trainer.fallbacks
            acc.clear()
            with metrics_path.open("a") as fh:
                fh.write(json.dumps(rec) + "\n")
            bar.set_postfix(phase=ph.name, psnr=f"{rec['psnr']:.2f}", iou=f"{rec.get('iou', float('nan')):.3f}")
        if it % cfg.checkpoint_every == 0 or it == stop:
            bad_params = trainer.non_finite_parameters()
            if bad_params:  # an update can blow the weights up while the step's loss was finite
                raise TrainingDiverged.at(out, it, ph, f"non-finite weights in {', '.join(bad_params)}")
            _save_checkpoint(ckpt, trainer)
        bar.update(1)
    bar.close()
    if trainer.fallbacks:
        log.warning("%d field steps used a fallback scale vector (no candidate above %.2f)", trainer.fallbacks, cfg.valid_threshold)
    return out


def add_train_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``osn train DATASET --out RUN [--config FILE] [--resume]``."""
    from scenecore.cli import subcommand

    def _cmd(args: argparse.Namespace) -> int:
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        if args.resume and (args.config or args.inputs):
            # A resumed run keeps the config and inputs it started with (saved in --out).
            raise UserError(f"{args.out}: --resume continues with the run's own config.yaml and inputs; drop --config/--inputs")
        cfg = TrainConfig.from_yaml(args.config) if args.config else None
        inputs = load_inputs(args.inputs) if args.inputs else None
        run = train(args.dataset, args.out, cfg, resume=args.resume, inputs=inputs, max_iterations=args.max_iterations)
        records = read_metrics(Path(run) / "metrics.jsonl")
        if records:
            rec = records[-1]
            summary = {k: rec[k] for k in ("iteration", "wall_time", "psnr", "iou", "precision", "recall", "scale_rel_err") if k in rec}
            print(json.dumps(summary))
        return 0

    p = subcommand(sub, "train", _cmd, "train per-object fields and the object scale network on a dataset")
    p.set_defaults(resume_hint="run the same command with --resume to continue")
    p.add_argument("dataset", help="benchgen dataset directory (oracle per-object inputs are derived from it)")
    p.add_argument("--out", required=True, help="run directory (checkpoint, metrics.jsonl, config, inputs)")
    p.add_argument("--config", help="YAML training config; omitted keys take the CPU defaults (configs/osn-cpu.yaml)")
    p.add_argument("--inputs", help="per-object inputs directory from `osn preprocess` (or `osn oracle`); "
                   "default: oracle inputs derived from the dataset's ground truth")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint, with the config and inputs it started with")
    p.add_argument("--max-iterations", type=int, default=None, help="stop after this global iteration (resumable)")
