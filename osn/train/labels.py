"""The scale phase's label pool: which training pixels can say anything about the object scales.

At the start of a scale phase every object's depth is rendered alone, in its own unit, on a
strided grid of labelled training pixels (the soft Z-buffer's per-object depths, Eq. 17). The
rays kept are those where the labelled object and another one both cover the ray opaquely and
some scale vector in the sampling box explains the label; they become per-pair depth-order
constraints (:func:`osn.model.depth_order.order_constraints`) that label every sampled scale vector
of the phase's steps.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import torch
import torch.nn.functional as F

from scenecore import dataset as D
from scenecore.cameras import project_pixels
from scenecore.errors import DatasetError
from osn.model.fields import Field
from osn.model.depth_order import order_constraints
from osn.model.volume import SKIP_OCCLUDED, render_by_hits
from osn.train.auto import label_stride
from osn.train.config import TrainConfig
from osn.train.tensors import SceneTensors

log = logging.getLogger(__name__)

#: Samples per ray of the label pool's renders, each object alone (the paper's M points of Eq. 17);
#: every config used this value (docs/training.md, "What is not an option").
LABEL_SAMPLES = 24
#: An object covers a label-pool ray when its opacity alone exceeds this (the objects whose depths
#: the soft Z-buffer orders on a ray, Eq. 16-18; the paper names no threshold).
COVERAGE_THRESHOLD = 0.9
#: The anchor's own sparse depths within this many pixels of an object's mask, in the same frame,
#: are beside the object (:func:`anchor_bias`).
BIAS_BAND = 2
#: Fewer of the anchor's depths beside and behind an object than this: no bias is measured for it (0).
BIAS_MIN_DEPTHS = 10


def label_pixels(st: SceneTensors, cfg: TrainConfig) -> torch.Tensor:
    """Flat ``(P,)`` (frame * HW + pixel) indices of the label pool candidates: every
    ``label_stride``-th labelled pixel per axis, silhouettes included."""
    keep = st.labels.reshape(st.T, st.H, st.W) >= 0
    stride = label_stride(cfg.label_stride, st.H, st.W)
    grid = torch.zeros(st.H, st.W, dtype=torch.bool, device=st.device)
    grid[::stride, ::stride] = True
    return torch.nonzero((keep & grid).reshape(-1))[:, 0]


@torch.no_grad()
def render_alone_depths(st: SceneTensors, fields: list[Field], flat: torch.Tensor, cfg: TrainConfig,
                        chunk: int = 8192, objects: list[int] | None = None) -> dict[str, torch.Tensor]:
    """Every object (or those at positions ``objects``) rendered alone on training pixels ``flat (P,)``.

    Returns ``depth (P, K)`` (independent planar depth in the object's own unit), ``acc (P, K)``
    (opacity) and ``covered (P, K)`` (``acc >`` :data:`COVERAGE_THRESHOLD`). A ray an object covers
    semi-transparently stays in the pool: a thin part is semi-transparent wherever it is, and
    dropping every ray it touches lost the bounds it sets (factory's robot arm; docs/training.md).
    """
    HW = st.H * st.W
    depth = torch.full((len(flat), st.K), float("inf"), device=st.device)  # no surface where absent
    covered = torch.zeros(len(flat), st.K, dtype=torch.bool, device=st.device)
    acc = torch.zeros(len(flat), st.K, device=st.device)
    one = torch.ones(st.K, device=st.device)
    frames_all, pix_all = flat // HW, flat % HW
    for k in range(st.K) if objects is None else objects:
        idx = torch.nonzero(st.present[k, frames_all])[:, 0]  # absent frames cost nothing
        for a in range(0, len(idx), chunk):
            i = idx[a : a + chunk]
            # Only the rays that cross the object's box are rendered (the same values: one object alone).
            out = render_by_hits(st.object_rays(fields, frames_all[i], one, [k]), st.dirs[pix_all[i]], LABEL_SAMPLES, None, SKIP_OCCLUDED)
            depth[i, k] = out.normalised_depth()
            acc[i, k] = out.acc
            covered[i, k] = out.acc > COVERAGE_THRESHOLD
    return {"depth": depth, "covered": covered, "acc": acc}


def _anchor_points_near_objects(st: SceneTensors) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The anchor's own sparse depths where objects' contact bounds are read: ``flat (N,)`` pixels
    (frame * HW + pixel), planar depths ``(N,)`` float64 and the object position ``(N,)`` each
    belongs to. *Beside* an object: the anchor's depths within :data:`BIAS_BAND` pixels of the
    object's mask in the same frame. *Behind* it: the anchor's points of every other frame, through
    its poses, projected into a frame where they fall on the object's mask (the anchor is never in
    front of an object, so there the object hides them)."""
    a, HW = st.anchor, st.H * st.W
    sel = torch.nonzero(st.sp_obj == a)[:, 0]
    lab = st.labels.reshape(st.T, st.H, st.W)
    flat = st.sp_frame[sel] * HW + st.sp_pix[sel]
    depth = st.sp_depth[sel].double()
    out_flat, out_depth, out_obj = [], [], []
    for k in range(st.K):
        if k == a:
            continue
        near = F.max_pool2d((lab == k).float()[:, None], 2 * BIAS_BAND + 1, stride=1, padding=BIAS_BAND)
        m = near.reshape(-1)[flat] > 0
        out_flat.append(flat[m]), out_depth.append(depth[m]), out_obj.append(torch.full((int(m.sum()),), k, device=st.device))
    # Behind: every anchor point in the anchor's frame, then in each other frame's camera.
    poses = st.poses[a].double()  # (T, 4, 4) camera-to-anchor
    frames = st.sp_frame[sel]
    cam = depth[:, None] * st.dirs[st.sp_pix[sel]].double()  # camera frame: dirs have z = 1
    pts = torch.einsum("nij,nj->ni", poses[frames, :3, :3], cam) + poses[frames, :3, 3]
    pts_np, frames_np, poses_np = pts.cpu().numpy(), frames.cpu().numpy(), poses.cpu().numpy()
    for g in torch.nonzero(st.present[a])[:, 0].tolist():
        _, z, pix, inside = project_pixels(pts_np[frames_np != g], st.inputs.K, poses_np[g], st.W, st.H)
        uv = torch.from_numpy(pix[inside]).to(st.device)
        zf = torch.from_numpy(z[inside]).to(st.device)
        covering = lab[g, uv[:, 1], uv[:, 0]]
        hidden = (covering >= 0) & (covering != a)
        out_flat.append(g * HW + uv[hidden, 1] * st.W + uv[hidden, 0])
        out_depth.append(zf[hidden]), out_obj.append(covering[hidden].long())
    cat = torch.cat
    return cat(out_flat), cat(out_depth), cat(out_obj)


@torch.no_grad()
def anchor_bias(st: SceneTensors, fields: list[Field], cfg: TrainConfig) -> torch.Tensor:
    """Per object position, how far the anchor's rendered depth sits from the anchor's own sparse
    depths where that object's contact bounds are read, beside and behind it
    (:func:`_anchor_points_near_objects`): the median of ``log(rendered / sparse)``. ``(K,)``
    float64; 0 for the anchor itself and for an object with fewer than :data:`BIAS_MIN_DEPTHS`
    such depths.

    An object's bounds against the anchor are read at its contacts, on a surface of the anchor
    the object hides or borders. A field fitted to depths a few per cent off (SfM's) renders that
    surface nearer or farther than its own depths say there (docs/training.md, the label rule);
    on exact depths the figure is the field's own error.
    """
    out = torch.zeros(st.K, dtype=torch.float64, device=st.device)
    if st.K < 2 or not bool((st.sp_obj == st.anchor).any()):
        return out
    flat, depth, obj = _anchor_points_near_objects(st)
    if not len(flat):
        return out
    rendered = render_alone_depths(st, fields, flat, cfg, objects=[st.anchor])["depth"][:, st.anchor].double()
    r = torch.log(rendered) - torch.log(depth)
    for k in range(st.K):
        m = (obj == k) & torch.isfinite(r)
        if k != st.anchor and int(m.sum()) >= BIAS_MIN_DEPTHS:
            out[k] = r[m].median()
    return out


def contested_rays(st: SceneTensors, flat: torch.Tensor, depth: torch.Tensor, covered: torch.Tensor) -> torch.Tensor:
    """Mask ``(P,)`` of the rays ``flat (P,)`` (depths and coverage ``(P, K)``) that can inform
    the scale network: the labelled object covers the ray, another object does too, and *some*
    scale vector in the sampling box explains the label (``lo_L d_L < hi_j d_j`` for every
    other covering j). Rays no sampled scale can explain (geometry noise) would only make every
    sample look equally wrong."""
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


def build_label_pool(st: SceneTensors, fields: list[Field], cfg: TrainConfig, iteration: int) -> dict:
    """The contested rays of the current fields: ``flat (P,)``, ``depth (P, K)``,
    ``covered (P, K)``, ``gt (P,)`` and their ``constraints`` (:class:`OrderConstraints`), and
    ``anchor_bias (K,)``, the log correction applied to the anchor's depth on each object's rays
    (``cfg.anchor_bias`` times :func:`anchor_bias`; zeros, unmeasured, where the option is 0).

    Deterministic given the fields, so a resumed scale phase rebuilds the same pool.
    ``iteration`` (the phase's first) only goes into the warning when no ray is contested.
    """
    flat = label_pixels(st, cfg)
    c = render_alone_depths(st, fields, flat, cfg)
    # On each object's rays the anchor's depth is moved by (a share of) its measured bias beside
    # and behind that object, so a contact bound is read against the surface its depths say.
    bias = torch.zeros(st.K, dtype=torch.float64, device=st.device)
    if cfg.anchor_bias > 0:
        bias = cfg.anchor_bias * anchor_bias(st, fields, cfg)
    gt_all = st.labels.reshape(-1)[flat]
    c["depth"][:, st.anchor] *= torch.exp(-bias[gt_all]).to(c["depth"].dtype)
    keep = contested_rays(st, flat, c["depth"], c["covered"])
    pool = {"flat": flat[keep], "depth": c["depth"][keep], "covered": c["covered"][keep], "anchor_bias": bias}
    pool["gt"] = st.labels.reshape(-1)[pool["flat"]]
    pool["constraints"] = order_constraints(pool["depth"], pool["covered"], pool["gt"], cfg.pair_minority)
    if not len(pool["flat"]):
        # No ray constrains any depth order (fields still transparent): every sample is
        # labelled valid, which says nothing.
        log.warning(
            "scale phase at iteration %d: no contested ray among %d labelled pixels; the network learns "
            "no depth order (fields not yet opaque on two objects at once)", iteration, len(flat),
        )
    return pool


#: The final scale phase's label pool, per ordered pair, in the run directory (:func:`pool_record`).
POOL_FILE = "label_pool.json"
#: Bound on its size when read: three integers per ordered pair of a few hundred objects.
MAX_POOL_BYTES = 8 << 20


def pool_record(pool: dict, ids: list[int]) -> dict:
    """What the final label pool holds per ordered pair, by dataset object id (``ids``: per
    object position): ``pairs``, ``[i, j, rays]`` with ``i`` labelled and ``j`` covering the ray
    too ("``i`` in front of ``j``", as the exact region's bound ``s_i / s_j < B_ij``), and
    ``minority``, the pairs ``pair_minority`` left out, with their rays. Read by the evaluation,
    which names for each exact bound the rays that could set it (none: nothing in the pool bounds
    that pair)."""
    c = pool["constraints"]
    return {"pairs": [[ids[i], ids[j], len(t)] for (i, j), t in zip(c.pairs, c.thresholds)],
            "minority": [[ids[i], ids[j], n] for (i, j), n in c.dropped.items()]}


def read_pool_record(run_dir: Path) -> dict[tuple[int, int], tuple[int, bool]] | None:
    """``(i, j) -> (rays, left out as a minority)`` of a run's :data:`POOL_FILE` (dataset ids);
    None where the run has none (trained before it was written, or a single object). A shared
    run is untrusted input: the file is read up to a bound, and anything but lists of three
    non-negative integers is ``DatasetError`` naming it."""
    path = Path(run_dir) / POOL_FILE
    if not path.exists():
        return None
    try:
        rec = json.loads(D.read_regular(path, MAX_POOL_BYTES))
        out = {}
        for key, minority in (("pairs", False), ("minority", True)):
            for i, j, n in rec[key]:
                if not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in (i, j, n)):
                    raise ValueError(f"{[i, j, n]} is not three non-negative integers")
                out[(i, j)] = (n, minority)
    except (ValueError, TypeError, KeyError) as e:  # JSONDecodeError is a ValueError
        raise DatasetError(f"{path}: not a label pool record ({e})") from None
    return out


def near_positives(positives: torch.Tensor, n: int, gen: torch.Generator) -> torch.Tensor:
    """``n`` normalised scale vectors ``(n, K-1)`` (CPU) jittered around remembered valid ones
    ``positives (M, K-1)``, at three spreads (0.01, 0.03, 0.1 of the box) so both the boundary
    and the interior are reached."""
    pick = positives[torch.randint(len(positives), (n,), generator=gen)]
    sigma = torch.tensor([0.01, 0.03, 0.1])[torch.randint(3, (n, 1), generator=gen)]
    return (pick + sigma * torch.randn(n, positives.shape[1], generator=gen)).clamp(0.0, 1.0 - 1e-6)
