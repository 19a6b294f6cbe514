"""Evaluation (``osn evaluate``): sampled configurations against every ground truth of a benchgen dataset.

Modules:

* :mod:`~osn.evaluate.bestofn`: :func:`evaluate`, the honest best-of-N evaluation (layered
  pre-selection, exact scoring of the rendered candidates by ``benchgen.score``, baselines,
  curves) and its options :class:`EvalConfig`.
* :mod:`~osn.evaluate.layered`: the fast approximate search (per-object layers at quantised scales).
* :mod:`~osn.evaluate.exact`: exact renders of configurations as scoring candidates.

The ground truth (evaluated views, co-visibility masks), best of N and every image metric are
the benchmark's own (:mod:`benchgen.score`), so OSN is scored exactly as any other method.
* :mod:`~osn.evaluate.valid_set`: the learned valid set against the exact region.
* :mod:`~osn.evaluate.units`: ground-truth unit conversions between a run's scales and a dataset's.
* :mod:`~osn.evaluate.report`: ``report.md``, PNG plots and ``metrics.json``.

Drawing the configurations (``osn sample``) is :mod:`osn.sample`.
"""

from osn.evaluate.bestofn import EvalConfig, EvalResult, evaluate, evaluation_curves, preselect, relative_scale_errors, single_solutions, write_candidates
from osn.evaluate.exact import RenderedCandidates, render_candidates
from osn.evaluate.layered import Layer, composite_layers, layered_psnr, masked_mse_matrix, masked_targets, nearest_level, render_layers, scale_levels, stack_layers
from osn.evaluate.report import results_table, summary_lines, write_plots, write_report
from osn.evaluate.units import actual_scales, ground_truth_problem, true_scales
from osn.evaluate.valid_set import ground_truth_outside_box, valid_set_accuracy, validity_profile, widest_object_profile

__all__ = [
    "EvalConfig", "EvalResult", "Layer", "RenderedCandidates", "actual_scales", "composite_layers", "evaluate",
    "evaluation_curves", "ground_truth_outside_box", "ground_truth_problem", "layered_psnr", "masked_mse_matrix", "masked_targets",
    "nearest_level", "preselect", "stack_layers", "relative_scale_errors", "render_candidates", "render_layers", "results_table",
    "scale_levels", "single_solutions", "write_candidates", "summary_lines", "true_scales",
    "valid_set_accuracy", "validity_profile", "widest_object_profile", "write_plots", "write_report",
]
