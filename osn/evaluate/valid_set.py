"""The learned valid set against the dataset's exact valid region (needs ground-truth units)."""

from __future__ import annotations

from typing import Any

import numpy as np

from scenecore.validity import ValidRegion, limiting_bounds, set_accuracy, set_samples

from osn.model.run import TrainedRun
from osn.model.scale_net import VALID_THRESHOLD
from osn.train.labels import read_pool_record
from osn.preprocess.inputs import normalise_scales
from osn.evaluate.units import actual_scales, dataset_box, free_normalised, normalised, true_scales


def valid_set_accuracy(run: TrainedRun, region: ValidRegion, points: int = 200_000, seed: int = 0,
                       names: dict[int, str] | None = None) -> dict[str, Any]:
    """Precision / recall / IoU of the learned valid set (score > VALID_THRESHOLD) against the exact region,
    and which of the region's pair bounds it gets wrong (``limits``).

    Stratified Monte Carlo (:func:`scenecore.validity.set_samples`): ``points`` uniform in the
    scale network's box, as many in the product of the region's intervals and as many in that
    product widened (where a learned set errs), so a region of 1e-6 of the box (8 objects) is
    resolved as well as one of 1e-2. Needs the inputs'
    ground-truth units (oracle or aligned SfM). ``exact_points`` says how many region points
    were drawn; with none, recall and IoU are NaN.

    ``limits`` (:func:`scenecore.validity.limiting_bounds`): per pair bound ``s_i / s_j < B_ij``
    of the region, named ``"i < j"`` by object name, the share of the region the learned set misses
    at that bound (``missed``: cut too tight) and its volume beyond it in units of the region's
    (``excess``: reaches too far); the pairs with the largest shares are what to look at first.
    ``names``: the dataset's object names by id, for the objects the run's inputs leave out.
    Where the run recorded its final label pool, each entry also has ``pool_rays`` (the pool's
    rays of that ordered pair: 0 means nothing in training could set the bound) and
    ``pool_minority`` (``pair_minority`` left them out).

    A scene of one object is its own exact set (1.0); a run whose inputs kept only the anchor of
    several objects learned no scale: NaN, with ``not_measured`` saying why (not a 1.0 that looks
    measured).

    Where the inputs leave objects out (preprocessing dropped them), ``iou_without_dropped`` is
    the IoU of the region with their bounds removed: what a method that learns every other bound
    exactly scores from these inputs, since nothing in them bounds an object they do not hold.
    """
    K = run.inputs.num_objects
    if K == 1 and region.num_objects > 1:  # every object but the anchor dropped: no scale was learned
        nan = float("nan")
        return {"precision": nan, "recall": nan, "iou": nan, "points": 0, "limits": [],
                "not_measured": "preprocessing dropped every object but the anchor; no scale was learned"}
    if K == 1:
        return {"precision": 1.0, "recall": 1.0, "iou": 1.0, "points": 0, "limits": []}
    pts = set_samples(region, dataset_box(run.inputs, run.ranges, region.num_objects), points, seed)
    learned = [run.scores(free_normalised(run.inputs, run.ranges, x)) > VALID_THRESHOLD for x in pts.strata]
    names = {**(names or {}), **{o.id: o.name for o in run.inputs.objects}}

    def name(i: int) -> str:
        return names.get(i, f"object {i}")  # an object the inputs leave out is held at scale 1

    pool = read_pool_record(run.path)
    limits = [{"pair": f"{name(e['i'])} < {name(e['j'])}", **e, **_pool_rays(pool, e["i"], e["j"])}
              for e in limiting_bounds(region, pts, *learned)]
    out = {**set_accuracy(pts, *learned), "points": 3 * points, "limits": limits}
    dropped = sorted(set(range(region.num_objects)) - {o.id for o in run.inputs.objects})
    if dropped:
        bounds = region.ratio_bounds.copy()
        bounds[dropped, :] = bounds[:, dropped] = np.inf
        blind = ValidRegion.from_bounds(bounds, region.anchor)
        out["iou_without_dropped"] = set_accuracy(pts, *(np.asarray(blind.contains(x), dtype=bool) for x in pts.strata))["iou"]
    return out


def _pool_rays(pool: dict[tuple[int, int], tuple[int, bool]] | None, i: int, j: int) -> dict[str, Any]:
    """``pool_rays``: the final label pool's rays that could set bound ``i < j`` (0: nothing in
    the pool bounds the pair), ``pool_minority``: whether ``pair_minority`` left them out; {} for
    a run without the record."""
    if pool is None:
        return {}
    rays, minority = pool.get((i, j), (0, False))
    return {"pool_rays": rays, "pool_minority": minority}


def _exactly_valid(run: TrainedRun, region, actual: np.ndarray) -> np.ndarray:
    """Whether the dataset's region holds the configurations ``actual (n, K)`` (dataset scales of
    the run's objects; dropped objects stay at scale 1)."""
    full = np.ones((len(actual), region.num_objects))
    full[:, [o.id for o in run.inputs.objects]] = actual
    return np.asarray(region.contains(full))


def validity_profile(run: TrainedRun, region, sbar_ref: np.ndarray, k: int, points: int = 400) -> dict[str, np.ndarray]:
    """Learned score and exact validity along object position k's scale, the others at ``sbar_ref (K,)``."""
    lo, hi = run.ranges[k]
    line = np.repeat(sbar_ref[None], points, 0)
    line[:, k] = np.linspace(lo, hi, points)
    s_free = np.delete(normalise_scales(line, run.ranges), run.anchor_pos, axis=1)
    actual = actual_scales(run.inputs, line)
    return {"actual_scale": actual[:, k], "score": run.scores(s_free), "exact": _exactly_valid(run, region, actual)}


def widest_object_profile(run: TrainedRun, region, scales: np.ndarray) -> dict[str, Any] | None:
    """:func:`validity_profile` of the free object with the widest scale range (log ratio), the
    others at the first ground truth ``scales (G, num dataset objects)``; None for the anchor alone."""
    free_pos = [k for k in range(run.inputs.num_objects) if k != run.anchor_pos]
    if not free_pos:
        return None
    k = max(free_pos, key=lambda k: np.log(run.ranges[k, 1] / run.ranges[k, 0]))
    ref = true_scales(run.inputs, np.array([scales[0, o.id] for o in run.inputs.objects]))
    return {"object": run.inputs.objects[k].name, **{a: b.tolist() for a, b in validity_profile(run, region, ref, k).items()}}


def ground_truth_outside_box(run: TrainedRun, scales: np.ndarray) -> dict[str, float]:
    """How many ground-truth configurations ``scales (G, num dataset objects)`` lie outside the
    box the scale network samples (Eq. 1's ranges), and how far (in normalised units, 0 inside).

    Eq. 1 bounds each object's scale by the scene's near/far, a heuristic that does not know the
    benchmark's scale range: such a ground truth can be approached only from the box's edge, which
    caps best-of-N there. Reported so that cap is visible, not hidden in the averages.
    """
    s = normalised(run.inputs, run.ranges, scales)
    free = [k for k in range(run.inputs.num_objects) if k != run.anchor_pos]
    dist = np.maximum(np.maximum(-s[:, free], s[:, free] - 1.0), 0.0).max(axis=1) if free else np.zeros(len(s))
    return {"gt_outside_scale_box": int(np.sum(dist > 0)), "gt_outside_scale_box_max": float(dist.max(initial=0.0))}
