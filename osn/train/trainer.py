"""One training iteration at a time: the models, their optimisers, the RNG and the three steps.

* stage 1 (:meth:`Trainer.step_stage1`): every object alone on its own masked pixels;
* field phase (:meth:`Trainer.step_fields`): all objects composited at one valid scale vector;
* scale phase (:meth:`Trainer.step_scale`): the scale network on sampled scale vectors labelled
  by the depth orders of :mod:`osn.train.labels`.

:meth:`Trainer.state_dict` holds everything a resume needs (weights, optimisers, every RNG).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import torch
import torch.nn.functional as F

from osn.model.fields import Field, make_field, saved_plane_size
from osn.model.run import CHECKPOINT_VERSION
from osn.model.scale_net import FIELD_STEP_THRESHOLD, ScaleNet, full_sbar, sample_valid
from osn.model.depth_order import in_front_pairs, trimmed_labels
from osn.model.volume import SKIP_OCCLUDED, RenderOutput, render
from osn.preprocess.depth_noise import depth_consistency
from osn.preprocess.inputs import SceneInputs
from osn.train.auto import (anchor_plane_size, checkpoint_anchor_guide_samples, object_resolutions,
                            resolve_anchor_guide_samples, resolve_depth_robust, resolve_w_edge)
from osn.train.config import TrainConfig
from osn.train.labels import build_label_pool, near_positives
from osn.train.losses import disparity_curvature, edge_excess, sparse_depth_loss
from osn.train.planar import planar_depths
from osn.train.schedule import Phase, build_schedule
from osn.train.tensors import SceneTensors

log = logging.getLogger(__name__)

#: Scale vectors drawn per field step to find one scoring above ``FIELD_STEP_THRESHOLD`` (the
#: paper resamples until one passes; a fixed batch keeps the step's cost bounded).
FIELD_STEP_CANDIDATES = 4096
#: Scale vectors labelled valid that a scale phase keeps to sample around (see ``label_replay``).
REPLAY_SIZE = 4096
#: Per object and step, the free pixels of ``w_free``'s term and the silhouette pixels of
#: ``w_edge``'s; per step, the strips of ``w_hidden_smooth``'s. Sampling budgets of a term, not
#: its strength: the weight sets that.
FREE_RAYS = 128
EDGE_RAYS = 64
HIDDEN_STRIPS = 32
#: The paper's loss weights of the sparse depths (Eq. 2 and 9) and of the segmentation (Eq. 10),
#: relative to the squared RGB error's 1 (appendix, Loss Weights); every config held them.
W_DEPTH = 1.0
W_SEG = 0.01
#: How far from an object's mask its free pixels (``w_free``) may lie: pixels showing the anchor or
#: nothing within ``FREE_BAND``; for objects but the anchor, other objects' pixels within
#: ``FREE_BAND_OBJECTS``, for gaps a 64^3 grid cannot resolve (docs/training.md, Free space).
FREE_BAND = 4
FREE_BAND_OBJECTS = 1
#: Pixels per strip of ``w_hidden_smooth``: the shortest odd strip that has a second difference
#: on each side of its centre, so a strip reaching two pixels into an object still holds one
#: visible anchor pixel per triple at the silhouette.
HIDDEN_STRIP_LENGTH = 5


class Trainer:
    """Owns the fields, the scale network, their optimisers and the RNG; one ``step`` per iteration."""

    def __init__(self, inputs: SceneInputs, cfg: TrainConfig, device: torch.device) -> None:
        self.cfg, self.device = cfg, device
        self.st = SceneTensors(inputs, device, resolve_anchor_guide_samples(cfg.anchor_guide_samples, cfg.field, inputs))
        # What `auto` options read of the inputs: whether their depths agree across frames.
        self.depth_consistency = depth_consistency(inputs)
        noisy = self.depth_consistency.noisy
        self.depth_robust = resolve_depth_robust(cfg.depth_robust, noisy)
        self.w_edge = resolve_w_edge(cfg.w_edge, noisy)
        self.source = inputs.source
        K = self.st.K
        if self.st.unposed_pixels:
            log.warning("%d mask pixels belong to objects without a pose in their frame (not registered there); "
                        "no ray is drawn from them", self.st.unposed_pixels)
        torch.manual_seed(cfg.seed)
        self.gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        self.resolutions = object_resolutions(cfg.field, inputs, noisy)  # per object position its grid's schedule
        planes = anchor_plane_size(cfg.field, inputs)
        self.fields = [self._make_object_field(k, self.resolutions[k][0], planes if k == inputs.anchor_pos else 0)
                       for k in range(len(inputs.objects))]
        self.net = ScaleNet(K - 1, seed=cfg.seed).to(device) if K > 1 else None
        self.net_opt = torch.optim.Adam(self.net.parameters(), lr=cfg.scale_lr) if self.net is not None else None
        self.schedule = build_schedule(cfg, K)
        self.total = self.schedule[-1].end if self.schedule else 0
        self.field_total = sum(p.end - p.start for p in self.schedule if p.name != "scale")
        steps = len(self.resolutions[0])  # the same number of steps for every object
        # field iteration -> the upsampling step (index into each object's schedule) it starts
        self.upsample_at = {int(round(self.field_total * 0.4 * i / (steps - 1))): i for i in range(1, steps)}
        self.field_iter = 0
        self.iteration = 0
        self.elapsed = 0.0
        self.fallbacks = 0
        self.cache: dict[str, Any] | None = None  # the scale phase's label pool (labels.build_label_pool)
        self.cache_key: int | None = None  # first iteration of the phase the pool belongs to
        self.noise_floor = 0.0
        self.positives = torch.zeros(0, max(K - 1, 1))
        self.loss_acc: dict[str, list[float]] = {}  # losses since the last metrics line
        # (j, k): j in front of k by the last label pool; the free-space term stops carving j's pixels for k
        self.in_front: frozenset[tuple[int, int]] = frozenset()
        # The pairs (i, j) the last label pool holds rays of (None before the first): it stops
        # carving the pixels of objects it holds no ray of with k (SceneTensors.free_pixels).
        self.constrained: frozenset[tuple[int, int]] | None = None
        self.free = self._free_pixels()
        self.edges = self.st.edge_pairs() if self.w_edge > 0 else None
        self.hidden_strips = self.st.hidden_anchor_strips(HIDDEN_STRIP_LENGTH) if cfg.w_hidden_smooth > 0 else None
        # The anchor's depth targets from its planes (flat pixel indices, depths); None when off.
        self.planar = planar_depths(inputs, cfg.seed) if cfg.w_planar > 0 else None
        self.planar_flat = torch.from_numpy(self.planar.flat).to(device) if self.planar else None
        self.planar_depth = torch.from_numpy(self.planar.depth).to(device) if self.planar else None
        if self.planar is not None:
            log.info("the anchor's planes: %d (points supporting each: %s), depth targets on %d pixels",
                     len(self.planar.planes), [p.points for p in self.planar.planes], len(self.planar.depth))
        self._make_field_opt()

    # ---- optimisers and state ------------------------------------------------------------

    def _make_object_field(self, k: int, resolution: int, planes: int) -> Field:
        """Object position ``k``'s field, on its box, at ``resolution`` with ``planes`` texels."""
        bbox = torch.from_numpy(self.st.inputs.objects[k].bbox).float()
        return make_field(self.cfg.field, bbox, seed=self.cfg.seed + k, resolution=resolution, planes=planes).to(self.device)

    def _make_field_opt(self) -> None:
        groups = [g for f in self.fields for g in f.param_groups()]
        self.field_opt = torch.optim.Adam(groups, betas=(0.9, 0.99))

    def state_dict(self) -> dict[str, Any]:
        """Everything a resume needs: counters, weights, optimisers, replay buffer, RNG states."""
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
            "anchor_guide": self.st.guide,  # resolved: what `auto` gives may change, what trained may not
            "depth_consistency": self.depth_consistency.record(),  # what the other `auto`s read (a record)
            "in_front": sorted(self.in_front),
            "constrained": None if self.constrained is None else sorted(self.constrained),
            "fields": [f.state_dict() for f in self.fields],
            "field_opt": self.field_opt.state_dict(),
            "net": self.net.state_dict() if self.net is not None else None,
            "net_opt": self.net_opt.state_dict() if self.net_opt is not None else None,
            "gen": self.gen.get_state(),
            "torch_rng": torch.get_rng_state(),
            "config": self.cfg.to_dict(),
        }

    def load_state_dict(self, s: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (read onto any device; RNG states go back to the CPU)."""
        self.iteration, self.field_iter, self.elapsed = s["iteration"], s["field_iter"], s["elapsed"]
        self.fallbacks, self.noise_floor = s["fallbacks"], s["noise_floor"]
        # RNG states must be CPU byte tensors and the replay buffer lives on the CPU, whatever
        # device the checkpoint was read onto.
        self.positives = s.get("positives", self.positives).cpu()  # version 1: resumes with an empty buffer
        self.loss_acc = {k: list(v) for k, v in s["loss_acc"].items()}
        for k, (r, sd) in enumerate(zip(s["resolutions"], s["fields"])):
            planes = saved_plane_size(sd)
            if getattr(self.fields[k], "plane_size", 0) != planes:  # trained when `auto` gave another size
                self.fields[k] = self._make_object_field(k, r, planes)
            self.fields[k].set_resolution(r)
            self.fields[k].load_state_dict(sd)
        self._make_field_opt()
        self.field_opt.load_state_dict(s["field_opt"])
        if self.net is not None:
            self.net.load_state_dict(s["net"])
            self.net_opt.load_state_dict(s["net_opt"])
        self.st.guide = checkpoint_anchor_guide_samples(s, self.source)
        constrained = s.get("constrained")
        self._set_pool_pairs(frozenset(tuple(p) for p in s.get("in_front", [])),
                             None if constrained is None else frozenset(tuple(p) for p in constrained))
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
        """The phase global iteration ``it`` belongs to."""
        return next(p for p in self.schedule if p.start <= it < p.end)

    # ---- ray batches ---------------------------------------------------------------------

    def _randint(self, n: int, size: int) -> torch.Tensor:
        return torch.randint(n, (size,), generator=self.gen).to(self.device)

    def _render_alone(self, k: int, flat: torch.Tensor) -> RenderOutput:
        """Object k alone, at its own unit, on training pixels ``flat (R,)`` (stratified samples)."""
        st, cfg = self.st, self.cfg
        one = torch.ones(st.K, device=self.device)
        return render(st.object_rays(self.fields, flat // (st.H * st.W), one, [k]), st.dirs[flat % (st.H * st.W)], cfg.samples, self.gen, skip_occluded=SKIP_OCCLUDED)

    def _free_loss(self, k: int) -> torch.Tensor:
        """Mean squared opacity of object k alone on :data:`FREE_RAYS` of its free pixels (see
        :meth:`SceneTensors.free_pixels`): keeps its field from bleeding past its silhouette,
        which would otherwise read as "k is behind the anchor" to the scale labels."""
        cfg, free = self.cfg, self.free[k]
        if cfg.w_free <= 0 or not len(free):
            return torch.zeros((), device=self.device)
        return self._render_alone(k, free[self._randint(len(free), FREE_RAYS)]).acc.square().mean()

    def _edge_loss(self, k: int) -> torch.Tensor:
        """:func:`edge_excess` of object k alone on :data:`EDGE_RAYS` of its silhouette pixels and their
        inner neighbours (:meth:`SceneTensors.edge_pairs`)."""
        edge, inner = self.edges[k]
        if not len(edge):
            return torch.zeros((), device=self.device)
        i = self._randint(len(edge), EDGE_RAYS)
        out = self._render_alone(k, torch.cat([edge[i], inner[i]]))
        n = len(i)
        return edge_excess(out.depth[:n], out.acc[:n], out.depth[n:], out.acc[n:])

    def _hidden_loss(self) -> torch.Tensor:
        """:func:`disparity_curvature` of the anchor alone on :data:`HIDDEN_STRIPS` strips across
        pixels where objects hide it (:meth:`SceneTensors.hidden_anchor_strips`)."""
        strips = self.hidden_strips
        if strips is None or not len(strips):
            return torch.zeros((), device=self.device)
        strips = strips[self._randint(len(strips), HIDDEN_STRIPS)]
        out = self._render_alone(self.st.anchor, strips.reshape(-1))
        return disparity_curvature(out.depth.reshape(strips.shape), out.acc.reshape(strips.shape))

    # ---- stage 1 -------------------------------------------------------------------------

    def step_stage1(self) -> dict[str, float]:
        """One stage-1 step: each object alone on its masked pixels and sparse depths (Eq. 2)."""
        total, losses = self._alone_loss()
        self.field_opt.zero_grad(set_to_none=True)
        total.backward()
        self.field_opt.step()
        return losses

    def _alone_loss(self) -> tuple[torch.Tensor, dict[str, float]]:
        """The stage-1 objective (each object alone: RGB and sparse depth on its own pixels,
        opacity, free space, TV) and its terms per object."""
        st, cfg = self.st, self.cfg
        losses = {"rgb": 0.0, "depth": 0.0, "opacity": 0.0, "free": 0.0}
        if cfg.w_distortion > 0:
            losses["distortion"] = 0.0
        total = 0.0
        one = torch.ones(1, device=self.device)
        for k in range(st.K):
            pix = st.obj_pixels[k][self._randint(len(st.obj_pixels[k]), cfg.rays_per_object)]
            frames, p = pix // (st.H * st.W), pix % (st.H * st.W)
            n_rgb = len(p)
            if st.has_depth and len(st.obj_sparse[k]):
                sp = st.obj_sparse[k][self._randint(len(st.obj_sparse[k]), cfg.depth_rays)]
                frames = torch.cat([frames, st.sp_frame[sp]])
                p = torch.cat([p, st.sp_pix[sp]])
                d_gt = st.sp_depth[sp]
            else:
                d_gt = torch.zeros(0, device=self.device)
            n_sparse = len(d_gt)
            planar = k == st.anchor and self.planar_depth is not None and len(self.planar_depth) > 0
            if planar:
                pl = self._randint(len(self.planar_depth), cfg.depth_rays)
                frames = torch.cat([frames, self.planar_flat[pl] // (st.H * st.W)])
                p = torch.cat([p, self.planar_flat[pl] % (st.H * st.W)])
            rays = st.object_rays(self.fields, frames, one.expand(st.K), [k])
            out = render(rays, st.dirs[p], cfg.samples, self.gen, skip_occluded=SKIP_OCCLUDED, with_distortion=cfg.w_distortion > 0)
            own = n_rgb + n_sparse  # rays on the object's own pixels; the planar ones may lie behind others
            l_rgb = F.mse_loss(out.rgb[:own], st.images[frames[:own], p[:own]])
            l_depth = sparse_depth_loss(out.depth[n_rgb:own], d_gt, self.depth_robust)
            if planar:
                l_planar = sparse_depth_loss(out.depth[own:], self.planar_depth[pl], self.depth_robust)
                total = total + cfg.w_planar * l_planar
                losses["planar"] = l_planar.item()
            # Every pixel of the object's mask is hit by it: opacity 1. Without this a field can
            # stay semi-transparent and the depth loss (on sum_i w_i t_i, which a transparent
            # ray shortens) then pushes its surfaces behind the true ones.
            l_acc = (1.0 - out.acc).square().mean()
            total = total + l_rgb + W_DEPTH * l_depth + cfg.w_opacity * l_acc
            if cfg.w_distortion > 0:
                # The object's own pixels show one surface: a fog spread along the ray has the right
                # expected depth where sparse depths hold it, and any depth elsewhere (docs/training.md).
                l_dist = out.distortion[:n_rgb].mean()
                total = total + cfg.w_distortion * l_dist
                losses["distortion"] += l_dist.item() / st.K
            if cfg.w_hidden_smooth > 0 and k == st.anchor:
                l_hidden = self._hidden_loss()
                total = total + cfg.w_hidden_smooth * l_hidden
                losses["hidden_smooth"] = l_hidden.item()
            l_free = self._free_loss(k)
            total = total + cfg.w_free * l_free
            if self.w_edge > 0 and k != st.anchor:  # the anchor's edges are against objects, not a silhouette
                l_edge = self._edge_loss(k)
                total = total + self.w_edge * l_edge
                losses["edge"] = losses.get("edge", 0.0) + l_edge.item() / st.K
            losses["free"] += l_free.item() / st.K
            losses["rgb"] += l_rgb.item() / st.K
            losses["depth"] += l_depth.item() / st.K
            losses["opacity"] += l_acc.item() / st.K
        return total, losses

    # ---- stage 2: field phase ------------------------------------------------------------

    def sample_configuration(self) -> tuple[torch.Tensor, float]:
        """One valid scale vector ``(K,)`` for a composite step (anchor = 1; single object = [1])."""
        if self.net is None:
            return torch.ones(1, dtype=torch.float64, device=self.device), 1.0
        # With many objects uniform candidates can all miss the valid set (a small share of the
        # box once several objects are free); then candidates around remembered valid vectors.
        sbar, _, p, fell_back = sample_valid(
            self.net, self.st.ranges, self.st.anchor, self.gen, FIELD_STEP_CANDIDATES, FIELD_STEP_THRESHOLD, warn=False,
            near=self._near_positives if len(self.positives) else None,
        )
        if fell_back and self.fallbacks == 0:
            log.warning("no candidate scored above %.2f (best %.3f): field steps use the best one; "
                        "the count is in metrics.jsonl ('fallbacks')", FIELD_STEP_THRESHOLD, p)
        self.fallbacks += int(fell_back)
        return sbar, p

    def step_fields(self) -> dict[str, float]:
        """One field-phase step: all objects composited at one valid scale vector (Eq. 8-10)."""
        st, cfg = self.st, self.cfg
        sbar, score = self.sample_configuration()
        flat = self._randint(st.T * st.H * st.W, cfg.rays) if st.usable is None else st.usable[self._randint(len(st.usable), cfg.rays)]
        frames, p = flat // (st.H * st.W), flat % (st.H * st.W)
        n_rgb = len(p)
        if st.has_depth:
            sp = self._randint(len(st.sp_depth), cfg.depth_rays)
            frames = torch.cat([frames, st.sp_frame[sp]])
            p = torch.cat([p, st.sp_pix[sp]])
            s_obj = sbar[st.sp_obj[sp]].float()
            d_gt = st.sp_depth[sp]
        else:
            s_obj = d_gt = torch.zeros(0, device=self.device)
        out = render(st.object_rays(self.fields, frames, sbar), st.dirs[p], cfg.samples, self.gen, skip_occluded=SKIP_OCCLUDED)
        l_rgb = F.mse_loss(out.rgb, st.images[frames, p])
        # Eq. 9 compares with sbar_k * d_gt; dividing by sbar_k keeps the loss's weight
        # independent of the sampled scale (same minimiser).
        l_depth = sparse_depth_loss(out.depth[n_rgb:] / s_obj, d_gt, self.depth_robust)  # 0 without depth rays
        lab = st.labels[frames, p]
        seg_ok = lab >= 0
        l_seg = F.nll_loss(out.log_seg[seg_ok], lab[seg_ok]) if st.K > 1 and seg_ok.any() else out.rgb.sum() * 0.0
        loss = l_rgb + W_DEPTH * l_depth + W_SEG * l_seg
        out_losses = {"rgb": l_rgb.item(), "depth": l_depth.item(), "seg": l_seg.item(), "score": score}
        if cfg.w_alone > 0:
            # The stage-1 objective keeps each object's own geometry (its silhouette, opacity,
            # sparse depths) while the composite losses, at sampled configurations, would reshape
            # the contacts to make those configurations look valid (the scale labels drift).
            alone, terms = self._alone_loss()
            loss = loss + cfg.w_alone * alone
            out_losses.update({f"alone_{k}": v for k, v in terms.items()})
        self.field_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.field_opt.step()
        return out_losses

    # ---- stage 2: scale phase ------------------------------------------------------------

    def ensure_cache(self, phase: Phase) -> None:
        """Build the label pool at the start of a scale phase (rebuilt identically on resume);
        its pairs' order then sets which other objects' pixels the free-space term carves."""
        if self.cache_key != phase.start:
            self.cache = build_label_pool(self.st, self.fields, self.cfg, phase.start)
            self.cache_key = phase.start
            pairs = self.cache["constraints"].pairs
            self._set_pool_pairs(in_front_pairs(pairs), frozenset(pairs))

    def _free_pixels(self) -> list[torch.Tensor]:
        """Each object's free pixels under the config and the pairs' order known so far (none
        without the free-space term)."""
        cfg = self.cfg
        if cfg.w_free <= 0:
            return [torch.zeros(0, dtype=torch.long, device=self.device) for _ in range(self.st.K)]
        return self.st.free_pixels(FREE_BAND, FREE_BAND_OBJECTS, self.in_front, self.constrained)

    def _set_pool_pairs(self, in_front: frozenset[tuple[int, int]], constrained: frozenset[tuple[int, int]] | None) -> None:
        """What a label pool says of the pairs: ``(j, k)`` with j in front of k, and every pair
        it holds rays of (None: no pool yet); the free pixels follow them."""
        if (in_front, constrained) != (self.in_front, self.constrained):
            self.in_front, self.constrained = in_front, constrained
            self.free = self._free_pixels()

    def _scale_samples(self) -> torch.Tensor:
        """Normalised free scales ``(scale_samples, K-1)`` for one scale step: uniform in the
        box, plus a share ``label_replay`` jittered around scale vectors labelled valid earlier
        (labels are always recomputed, so this only spends samples where the boundary is, never
        biases a label)."""
        cfg, st = self.cfg, self.st
        n = cfg.scale_samples
        n_near = int(round(n * cfg.label_replay)) if len(self.positives) else 0
        s = torch.rand(n - n_near, st.K - 1, generator=self.gen)
        if n_near:
            s = torch.cat([s, self._near_positives(n_near)])
        return s.to(self.device)

    def _near_positives(self, n: int) -> torch.Tensor:
        return near_positives(self.positives, n, self.gen)

    def _remember(self, s: torch.Tensor) -> None:
        """Keep the last ``REPLAY_SIZE`` scale vectors labelled valid (CPU, checkpointed)."""
        self.positives = torch.cat([self.positives, s.detach().cpu().float()])[-REPLAY_SIZE:]

    def scale_lr_at(self, phase: Phase) -> float:
        """The scale network's learning rate at this iteration: a cosine from ``scale_lr`` at the
        start of every scale phase down to ``scale_lr_final * scale_lr`` at its end: at a constant
        rate the last noisy steps decide where the boundary ends up, and the decay lets the
        boundary settle on the labels (docs/experiments/). A function of the iteration only, so a
        resumed run gets the same rates."""
        cfg = self.cfg
        t = (self.iteration - phase.start) / max(phase.end - phase.start - 1, 1)
        return cfg.scale_lr * (cfg.scale_lr_final + (1.0 - cfg.scale_lr_final) * 0.5 * (1.0 + math.cos(math.pi * t)))

    def label_trim_at(self, phase: Phase) -> float:
        """The share of a pair's rays a valid sample may violate beyond the step's best sample in
        this scale phase: ``final_label_trim`` in the final phase, none in the rounds (a trim there
        was measured not to gain; docs/experiments/)."""
        return self.cfg.final_label_trim if phase.round == self.cfg.rounds + 1 else 0.0

    def step_scale(self, phase: Phase) -> dict[str, float]:
        """One scale-phase step: BCE of the network on sampled scale vectors labelled by the pool."""
        self.ensure_cache(phase)
        st = self.st
        s = self._scale_samples()
        sbar = full_sbar(s, st.ranges, st.anchor)
        cons = self.cache["constraints"]
        # Labels relative to the best sample, per object pair (depth_order.trimmed_labels): learned
        # depths have floaters that make some rays wrong for every scale vector. All samples are
        # scored on the same rays, so "within tolerance of the best" compares like with like.
        # The pool is already restricted to rays some scale in the box explains (contested_rays).
        pv = cons.pair_violations(sbar)
        self.noise_floor = float(pv.sum(1).min()) / max(cons.count, 1)
        labels = trimmed_labels(pv, cons.sizes(), self.label_trim_at(phase))
        self._remember(s[labels > 0])
        loss = F.binary_cross_entropy_with_logits(self.net(s), labels.to(self.device))
        for group in self.net_opt.param_groups:
            group["lr"] = self.scale_lr_at(phase)
        self.net_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.net_opt.step()
        return {"bce": loss.item(), "valid_frac": float(labels.mean()), "contested": float(cons.rays), "noise_floor": self.noise_floor}

    # ---- one iteration -------------------------------------------------------------------

    def step(self) -> dict[str, float]:
        """Run iteration ``self.iteration`` of its phase; returns that step's losses."""
        ph = self.phase(self.iteration)
        if ph.name == "scale":
            out = self.step_scale(ph)
        else:
            if self.field_iter in self.upsample_at:
                for f, res in zip(self.fields, self.resolutions):
                    f.set_resolution(res[self.upsample_at[self.field_iter]])
                self._make_field_opt()  # parameter shapes changed (TensoRF does the same)
            out = self.step_stage1() if ph.name == "stage1" else self.step_fields()
            self.field_iter += 1
        self.iteration += 1
        return out
