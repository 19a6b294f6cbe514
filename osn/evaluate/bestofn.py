"""Honest best-of-N evaluation (``osn evaluate``) of sampled configurations against many ground truths.

:func:`evaluate` matches each ground-truth configuration g of a benchgen dataset to the best of
the samples by mean PSNR over g's co-visible test views, and reports PSNR / SSIM / LPIPS /
SSIMAE / PQ / mIoU of the matches (mean and std over the G ground truths, the paper's Table 2),
the same metrics for two single-solution baselines of the same model, the relative scale error,
the learned valid set against the exact region, and curves.

Every reported image metric is an exact score of rendered candidates by the benchmark's own
scorer (:func:`benchgen.score.scorer.score`, the one owner of best of N and of the metrics), the
same code that scores any method's renders with ``benchgen score``. Rendering all N = 1000
samples exactly would dominate the run time, so a pre-selection chooses which samples to render:
the layered search (:mod:`osn.evaluate.layered`) estimates all N x G PSNRs and the ``topk`` best
samples of every ground truth (plus the highest-scoring one) become the candidates. The match is
the best *rendered* candidate; ``benchmarks/bench_bestofn.py`` measures how far that is from
scoring all N exactly.

With ``EvalConfig.true_scales`` the same fields are also rendered at every ground truth's exact
scales and scored as G candidates (the "true scales" row): what best of N would reach if the
samples held every exact configuration. It separates the error the scale search leaves (best of
N below that row) from the error of the fields themselves (that row below the ground truth).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from scenecore import dataset as D
from scenecore.config import flag, integer, validate
from benchgen.score import provenance
from benchgen.score.scorer import ScoreResult, score
from benchgen.score.truth import Truth, load_truth
from osn.evaluate.exact import RenderedCandidates
from osn.evaluate.layered import layered_psnr
from osn.evaluate.units import actual_scales, ground_truth_problem, true_scales
from osn.evaluate.valid_set import ground_truth_outside_box, valid_set_accuracy, widest_object_profile
from osn.model.run import TrainedRun
from osn.preprocess.inputs import InputsError
from osn.sample.configurations import Samples
from osn.train.labels import read_pool_record


#: The table row of the fields rendered at the ground truths' own scales (a reference).
TRUE_SCALES = "true scales"


@dataclass
class EvalConfig:
    """Options of ``osn evaluate``.

    Attributes:
        max_views: evaluate at most this many test views (evenly spread over the test set;
            0 = all). The paper's protocol uses all 210.
        levels: quantised scales per object for the layered search (at least 2), at quantiles
            of the samples' scales (:func:`osn.evaluate.layered.scale_levels`).
        topk: candidates per ground truth rendered exactly before the match is decided.
        lpips: compute LPIPS (needs the weights installed by ``make setup``).
        valid_points: Monte-Carlo points of the valid-set accuracy, as many again in the exact
            region's interval box and in that box widened (stratified;
            :func:`osn.evaluate.valid_set.valid_set_accuracy`).
        seed: seed of Monte-Carlo points.
        true_scales: also score the fields at every ground truth's exact scales (what best of N
            approaches with these fields; G more candidates rendered).
    """

    max_views: int = 30
    levels: int = 64
    topk: int = 2
    lpips: bool = True
    valid_points: int = 200_000
    seed: int = 0
    true_scales: bool = True

    def __post_init__(self) -> None:
        validate(self, "evaluate", {
            "max_views": integer(0),
            "levels": integer(2),
            "topk": integer(1),
            "lpips": flag(),
            "valid_points": integer(1000),
            "seed": integer(0),
            "true_scales": flag(),
        })


@dataclass
class EvalResult:
    """Everything ``report.md`` and ``metrics.json`` show (:mod:`osn.evaluate.report`)."""

    table: dict[str, dict[str, list[float]]]
    per_gt: list[dict[str, Any]]
    valid_set: dict[str, Any]
    scale_error: list[float]
    curves: dict[str, Any]
    timings: dict[str, float]
    extra: dict[str, Any] = field(default_factory=dict)
    #: Files written beside ``metrics.json`` (name -> bytes): the per-file digests of
    #: :mod:`benchgen.score.provenance` (``extra["provenance"]`` records their digests).
    files: dict[str, bytes] = field(default_factory=dict, repr=False)


def relative_scale_errors(actual: np.ndarray, true: np.ndarray, ids: list[int], anchor_id: int) -> list[float]:
    """Per ground truth ``g``: the mean over non-anchor objects of ``|actual - true| / true``
    (empty when the anchor is the only object).

    ``actual (G, K)`` holds the matched samples' scales for the run's objects ``ids`` (dataset
    units, anchor 1); ``true (G, num_objects)`` the ground truths' scales indexed by object id.
    """
    free = [k for k, i in enumerate(ids) if i != anchor_id]
    if not free:  # the anchor alone: no scale is free, so there is no error to report
        return []
    t = true[:, [ids[k] for k in free]]
    return [float(v) for v in np.mean(np.abs(actual[:, free] - t) / t, axis=1)]


def sample_name(n: int) -> str:
    """The candidate name of sample ``n`` (its index in ``samples.npz``)."""
    return f"sample_{n:05d}"


def preselect(approx_mean: np.ndarray, scores: np.ndarray, topk: int) -> np.ndarray:
    """Samples to render exactly: the ``topk`` best of every ground truth by the estimate
    ``approx_mean (N, G)``, plus the highest-scoring sample; sorted indices ``(C,)``."""
    top = np.argsort(-np.nan_to_num(approx_mean, nan=-np.inf), axis=0, kind="stable")[:topk].reshape(-1)
    return np.unique(np.concatenate([top, [int(np.argmax(scores))]]))


def _table_row(res: ScoreResult) -> dict[str, list[float]]:
    """A scorer summary as the report's ``metric -> [mean, std]``."""
    return {k: [v["mean"], v["std"]] for k, v in res.summary.items()}


def single_solutions(samples: Samples) -> dict[str, np.ndarray]:
    """The two baselines that commit to one solution of the same model: the highest-scoring
    sample and the centre of the learned ranges (the middle of each object's span over the
    valid samples), as ``name -> sbar (K,)``."""
    centre = 0.5 * (samples.sbar.min(0) + samples.sbar.max(0))
    return {"highest score": samples.sbar[int(np.argmax(samples.score))], "centre of learned ranges": centre}


def evaluate(
    run: TrainedRun, dataset_root: str | Path, samples: Samples, cfg: EvalConfig, echo: Callable[[str], None] = print,
    candidates_dir: str | Path | None = None, unverified: bool = False,
) -> EvalResult:
    """Best-of-N evaluation of ``samples`` of ``run`` against every configuration of the dataset.

    With ``candidates_dir``, the rendered candidates are also written there as prediction
    directories (``preselected/``, ``highest-score/``, ``centre-of-ranges/``) that
    ``benchgen score`` scores the same way (8-bit colour, as any method's PNGs).
    A dataset whose ``verification.json`` is missing or failed is refused (``DatasetError``)
    unless ``unverified``; ``extra["provenance"]`` records it with the digests of the files read.
    """
    problem = ground_truth_problem(run.inputs)
    if problem:  # checked before any rendering: every metric below needs it
        raise InputsError(f"{dataset_root}: cannot evaluate against ground truth: {problem}")
    verified = provenance.verification(dataset_root, D.load_scene(dataset_root), unverified)
    read_pool_record(run.path)  # a malformed record of the run's label pool stops here, before the search
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    # Configurations read and masked in forked processes, one per core torch would use (numpy only).
    truth = load_truth(dataset_root, cfg.max_views, workers=max(1, min(torch.get_num_threads(), os.cpu_count() or 1)))
    region = D.load_valid_region(dataset_root, truth.scene.num_objects)
    G, V = truth.num_configurations, truth.num_views
    timings["ground_truth_s"] = time.perf_counter() - t0
    echo(f"evaluate: {len(samples.sbar)} samples x {G} ground truths x {V} views")

    t0 = time.perf_counter()
    approx_mean = np.nanmean(layered_psnr(run, samples, truth, cfg.levels, echo=echo), axis=2)  # (N, G)
    timings["layered_search_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    cand = preselect(approx_mean, samples.score, cfg.topk)
    rendered = {"preselected": RenderedCandidates(run, truth, {sample_name(int(n)): samples.sbar[n] for n in cand})}
    res = score(truth, rendered["preselected"], cfg.lpips, progress=True)
    match = cand[[r["match_index"] for r in res.per_ground_truth]]
    timings["exact_scoring_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    table = {f"best of {len(samples.sbar)}": _table_row(res)}
    by_object = {f"best of {len(samples.sbar)}": res.by_object}
    for name, (cands, res_single) in _single_solution_scores(run, samples, truth, cfg.lpips).items():
        rendered[name] = cands
        table[name], by_object[name] = _table_row(res_single), res_single.by_object
    timings["baselines_s"] = time.perf_counter() - t0
    true_extra: dict[str, Any] = {}
    if cfg.true_scales:
        t0 = time.perf_counter()
        if candidates_dir is None:
            rendered.clear()  # renders are kept only to be written: free them before G more
        rendered[TRUE_SCALES], res_true = true_scales_candidates(run, truth, cfg.lpips)
        table[TRUE_SCALES], by_object[TRUE_SCALES] = _table_row(res_true), res_true.by_object
        true_extra = _true_scales_extra(res_true)
        timings["true_scales_s"] = time.perf_counter() - t0
    if candidates_dir is not None:
        write_candidates(rendered, Path(candidates_dir), len(samples.sbar))
    t0 = time.perf_counter()
    sets = [CANDIDATE_DIRS[k] for k in rendered] if candidates_dir is not None else ()
    prov = provenance.collect(dataset_root, truth.scene, [f.name for f in truth.frames], cfg.max_views,
                              res.info["metrics"], verified, candidates_dir if sets else None, sets, region=True)
    timings["digests_s"] = time.perf_counter() - t0
    per_gt = [{**{k: v for k, v in r.items() if k not in ("match", "match_index", "configuration")},
               "sample": int(n), "approx_psnr": float(approx_mean[n, g])} for g, (r, n) in enumerate(zip(res.per_ground_truth, match))]

    # Relative scale error of the matched samples (non-anchor objects, dataset scales); the units
    # it needs were checked above (ground_truth_problem).
    actual = actual_scales(run.inputs, samples.sbar[match])
    scale_err = relative_scale_errors(actual, truth.scales, [o.id for o in run.inputs.objects], truth.scene.anchor_id)
    valid = valid_set_accuracy(run, region, cfg.valid_points, cfg.seed, {o.id: o.name for o in truth.scene.objects})
    curves = evaluation_curves(run, samples, truth, res.matrix, cand, cfg.levels)
    curves["validity_profile"] = widest_object_profile(run, region, truth.scales)
    extra = {**_run_extra(run, samples, truth, approx_mean, cand, match), **true_extra,
             "error_by_object": by_object, "provenance": prov.record}
    return EvalResult(table, per_gt, valid, scale_err, curves, timings, extra, prov.files)


def _single_solution_scores(run: TrainedRun, samples: Samples, truth: Truth,
                            with_lpips: bool) -> dict[str, tuple[RenderedCandidates, ScoreResult]]:
    """Each baseline of :func:`single_solutions` rendered and scored as the only candidate
    against all G ground truths."""
    out = {}
    for name, sbar in single_solutions(samples).items():
        cands = RenderedCandidates(run, truth, {name.replace(" ", "-"): sbar})
        out[name] = (cands, score(truth, cands, with_lpips))
    return out


def _true_scales_extra(res_true: ScoreResult) -> dict[str, Any]:
    """The "true scales" row's per-ground-truth PSNR, how often each ground truth's own render is
    its best match, and by how much it beats the others' on average (``true_scales_own_margin_db``:
    per ground truth its own PSNR minus the mean over the other ground truths' scales, averaged;
    None with one ground truth). Two ground truths a few percent apart in one object's scale can
    swap places in the first; a wrong unit or object order takes the second to zero or below."""
    own = [r["match_index"] == g for g, r in enumerate(res_true.per_ground_truth)]
    m = res_true.matrix  # (G, G): candidate c (ground truth c's scales) against ground truth g
    G = m.shape[1]
    margin = None
    if G > 1:
        seen = np.isfinite(m) & ~np.eye(G, dtype=bool)  # NaN: no co-visible view
        count = seen.sum(0)
        others = np.where(seen, m, 0.0).sum(0) / np.maximum(count, 1)
        gaps = np.where(count > 0, np.diag(m) - others, np.nan)
        margin = float(gaps[np.isfinite(gaps)].mean()) if np.isfinite(gaps).any() else None
    return {"true_scales_psnr": [r["psnr"] for r in res_true.per_ground_truth], "true_scales_own_match": float(np.mean(own)),
            "true_scales_own_margin_db": margin}


def _run_extra(run: TrainedRun, samples: Samples, truth: Truth, approx_mean: np.ndarray, cand: np.ndarray,
               match: np.ndarray) -> dict[str, Any]:
    """What the report says of the evaluation itself: its sizes, how far the layered estimate's
    matches ``approx_mean (N, G)`` agree with the exact ones ``match (G,)`` among the rendered
    ``cand (C,)``, the sampler's fallbacks, and what the run could not place."""
    approx_match = np.nanargmax(np.nan_to_num(approx_mean, nan=-np.inf), axis=0)
    return {
        "num_samples": int(len(samples.sbar)),
        "num_gt": truth.num_configurations,
        "num_views": truth.num_views,
        "views": [f.name for f in truth.frames],
        "covisible_fraction": float(truth.mask.mean()),
        "candidates_rendered_exactly": int(len(cand)),
        "approx_match_agrees": float(np.mean(approx_match == match)),
        "sample_fallbacks": samples.fell_back,
        "samples_by_hit_and_run": samples.chained,
        **ground_truth_outside_box(run, truth.scales),
        **unposed_object_pixels(run, truth),
    }


def true_scales_candidates(run: TrainedRun, truth: Truth, with_lpips: bool) -> tuple[RenderedCandidates, ScoreResult]:
    """The run's fields rendered at each of the G ground truths' exact scales, scored as G
    candidates against every ground truth (best of G): what best of N reaches when the samples
    hold every exact configuration. Reads the ground truth, so it is a reference, not a method.
    Each ground truth is usually matched to its own scales (``extra["true_scales_own_match"]``)."""
    ids = [o.id for o in run.inputs.objects]
    sbar = true_scales(run.inputs, truth.scales[:, ids])
    source = RenderedCandidates(run, truth, {f"true_scales_{g:03d}": sbar[g] for g in range(len(sbar))})
    return source, score(truth, source, with_lpips)


def unposed_object_pixels(run: TrainedRun, truth: Truth) -> dict[str, Any]:
    """Co-visible test pixels (configuration 0's ground truth) that show an object the run has no
    pose for at that view's timestamp: it left the training view then (or preprocessing did not
    register it), so the run renders nothing for it there and those pixels count as errors.

    Returns the share of co-visible pixels, and per such object the timestamps it is unposed at.
    """
    posed = {o.id: set(int(t) for t in o.frames) for o in run.inputs.objects}
    _, _, ids = truth.views(0)
    mask = truth.masks(0)
    hit = np.zeros_like(mask)
    unposed: dict[str, list[int]] = {}
    for v, f in enumerate(truth.frames):
        missing = [oid for oid in range(len(truth.scene.objects)) if f.time_index not in posed.get(oid, set())]
        hit[v] = np.isin(ids[v], missing) & mask[v]
        for oid in missing:
            if np.any(ids[v] == oid):
                unposed.setdefault(truth.scene.objects[oid].name, []).append(f.time_index)
    return {
        "unposed_object_fraction": float(hit.sum() / max(int(mask.sum()), 1)),
        "unposed_objects": {k: sorted(set(v)) for k, v in unposed.items()},
    }


#: Prediction directory of each rendered candidate set under ``--candidates DIR``.
CANDIDATE_DIRS = {"preselected": "preselected", "highest score": "highest-score",
                  "centre of learned ranges": "centre-of-ranges", TRUE_SCALES: "true-scales"}


def write_candidates(rendered: dict[str, RenderedCandidates], out: Path, n: int) -> None:
    """The rendered candidates as prediction directories under ``out`` (docs/predictions.md)."""
    notes = {
        "preselected": f"OSN: the samples of {n} that the layered estimate pre-selected (top-k per ground truth "
                       "and the highest-scoring sample), rendered exactly",
        "highest score": f"OSN: the highest-scoring of {n} samples (one solution)",
        "centre of learned ranges": f"OSN: the centre of the learned scale ranges of {n} samples (one solution)",
        TRUE_SCALES: "OSN's fields rendered at every ground truth's exact scales (reads the ground truth: a reference, not a method)",
    }
    for key, source in rendered.items():
        source.write(out / CANDIDATE_DIRS[key], {"name": f"OSN {key}", "notes": notes[key]})


def evaluation_curves(
    run: TrainedRun, samples: Samples, truth: Truth, exact: np.ndarray, cand: np.ndarray, levels: int
) -> dict[str, Any]:
    """Best PSNR against N and against the number of ground truths (paper appendix), and the
    layered search's seconds per view against N (measured here).

    ``exact (C, G)`` holds the exact mean PSNRs of the rendered candidates ``cand (C,)`` (sample
    indices): the best of the first n samples is taken over the rendered ones among them, an
    exact score of a rendered candidate and a lower bound of the best of all first n samples.
    """
    N, G = len(samples.sbar), exact.shape[1]
    Ns = [n for n in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000) if n <= N]
    if N not in Ns:
        Ns.append(N)
    best_vs_n = []
    for n in Ns:
        inside = cand < n
        best_vs_n.append(float(np.nanmean(np.nanmax(exact[inside], axis=0))) if inside.any() else float("nan"))
    Gs = list(range(1, G + 1))
    overall_vs_g = [float(np.nanmean(np.nanmax(exact[:, :m], axis=1))) for m in Gs]
    timing_vs_n = {}
    one = truth.first_views(1)
    for n in [x for x in (10, 100, 1000) if x <= N]:
        ta = time.perf_counter()
        sub = Samples(samples.s_free[:n], samples.sbar[:n], samples.score[:n], samples.threshold, samples.seed)
        layered_psnr(run, sub, one, levels)
        timing_vs_n[n] = time.perf_counter() - ta
    return {
        "best_psnr_vs_n": {"n": Ns, "psnr": best_vs_n, "basis": "exact PSNR of the pre-selected rendered candidates"},
        "overall_psnr_vs_num_gt": {"num_gt": Gs, "psnr": overall_vs_g},
        "search_seconds_per_view_vs_n": {str(k): v for k, v in timing_vs_n.items()},
    }
