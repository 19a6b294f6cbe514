"""Evaluation (``osn evaluate``): sampled configurations against every ground truth of a benchgen dataset.

Modules:

* :mod:`~osn.evaluate.bestofn`: :func:`evaluate`, the honest best-of-N evaluation (layered search,
  exact re-rank, metrics, baselines, curves) and its options :class:`EvalConfig`.
* :mod:`~osn.evaluate.ground_truth`: the evaluated test views of every configuration, with
  co-visibility masks (:class:`GroundTruth`).
* :mod:`~osn.evaluate.layered`: the fast approximate search (per-object layers at quantised scales).
* :mod:`~osn.evaluate.exact`: exact renders of one configuration and its image metrics.
* :mod:`~osn.evaluate.valid_set`: the learned valid set against the exact region.
* :mod:`~osn.evaluate.units`: ground-truth unit conversions between a run's scales and a dataset's.
* :mod:`~osn.evaluate.report`: ``report.md``, PNG plots and ``metrics.json``.

Drawing the configurations (``osn sample``) is :mod:`osn.sample`.
"""

from osn.evaluate.bestofn import EvalConfig, EvalResult, evaluate, evaluation_curves, exact_rerank, relative_scale_errors, score_matches
from osn.evaluate.exact import exact_psnr, full_metrics, mean_std, render_sample
from osn.evaluate.ground_truth import GroundTruth, evaluated_views, load_ground_truth
from osn.evaluate.layered import Layer, composite_layers, layered_psnr, masked_mse_matrix, nearest_level, render_layers, scale_levels
from osn.evaluate.report import results_table, summary_lines, write_plots, write_report
from osn.evaluate.units import actual_scales, ground_truth_problem, true_scales
from osn.evaluate.valid_set import ground_truth_outside_box, valid_set_accuracy, validity_profile, widest_object_profile

__all__ = [
    "EvalConfig", "EvalResult", "GroundTruth", "Layer", "actual_scales", "composite_layers", "evaluate", "evaluated_views",
    "evaluation_curves", "exact_psnr", "exact_rerank", "full_metrics", "ground_truth_outside_box", "ground_truth_problem",
    "layered_psnr", "load_ground_truth", "masked_mse_matrix", "mean_std", "nearest_level", "relative_scale_errors",
    "render_layers", "render_sample", "results_table", "scale_levels", "score_matches", "summary_lines", "true_scales",
    "valid_set_accuracy", "validity_profile", "widest_object_profile", "write_plots", "write_report",
]
