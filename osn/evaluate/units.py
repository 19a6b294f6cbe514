"""Ground-truth units: the bridge between a method's own scales and a dataset's scales.

Each object's inputs live in their own unknown unit. Only code that measures against ground
truth (the training monitor, evaluation, tests) converts between the method's de-normalised
scales ``sbar`` and the dataset's scales, through each object's ``unit_to_world`` (metres per
unit, known for oracle inputs and for SfM inputs once aligned to the ground truth).
"""

from __future__ import annotations

import numpy as np

from osn.preprocess.inputs import InputsError, SceneInputs, normalise_scales


def _units(inputs: SceneInputs) -> np.ndarray:
    u = [o.unit_to_world for o in inputs.objects]
    if any(x is None for x in u):
        raise InputsError("these inputs carry no ground-truth units (not from the oracle or aligned SfM)")
    return np.array(u, dtype=np.float64)


def true_scales(inputs: SceneInputs, actual_scales: np.ndarray) -> np.ndarray:
    """Actual (dataset) scales ``(..., K)`` -> the inputs' de-normalised scales ``sbar (..., K)``.

    ``sbar_k = s_k * unit_k / unit_anchor``; needs every object's ``unit_to_world``.
    """
    u = _units(inputs)
    return np.asarray(actual_scales) * u / u[inputs.anchor_pos]


def actual_scales(inputs: SceneInputs, sbar: np.ndarray) -> np.ndarray:
    """Inverse of :func:`true_scales`: de-normalised scales ``(..., K)`` to dataset scales."""
    u = _units(inputs)
    return np.asarray(sbar) * u[inputs.anchor_pos] / u


def ground_truth_problem(inputs: SceneInputs, test_views: bool = True) -> str | None:
    """Why ``inputs`` cannot be compared with ground truth (None when they can).

    Every object needs its metres per unit (scales, the valid set) and, with ``test_views``, the
    scene its world-to-anchor similarity (to place test cameras). The oracle has both; SfM has
    them once aligned, unless an alignment failed.
    """
    missing = [f"{o.id} ({o.name})" for o in inputs.objects if o.unit_to_world is None]
    if missing:
        return f"object(s) {', '.join(missing)} have no ground-truth unit (no oracle, or their SfM alignment failed)"
    if test_views and inputs.world_to_anchor is None:
        return "no world-to-anchor alignment, so test cameras cannot be placed"
    return None


def dataset_box(inputs: SceneInputs, ranges: np.ndarray, num_dataset_objects: int) -> np.ndarray:
    """The sampling box of the scale network, ``ranges (K, 2)`` (Eq. 1, the inputs' units), in
    dataset scales ``(num_dataset_objects, 2)``; the anchor and objects the inputs leave out are
    held at 1 (``[1, 1]``)."""
    box = np.ones((num_dataset_objects, 2))
    ids = [o.id for o in inputs.objects]
    box[ids] = actual_scales(inputs, np.asarray(ranges, dtype=np.float64).T).T
    box[ids[inputs.anchor_pos]] = 1.0
    return box


def normalised(inputs: SceneInputs, ranges: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Dataset scales ``(N, num_dataset_objects)`` -> normalised scales ``(N, K)`` of the inputs'
    objects (Eq. 1 inverted in the inputs' units; 0 and 1 are the box's faces)."""
    ids = [o.id for o in inputs.objects]
    sbar = true_scales(inputs, np.asarray(scales, dtype=np.float64)[:, ids])
    return normalise_scales(sbar, np.asarray(ranges, dtype=np.float64))


def free_normalised(inputs: SceneInputs, ranges: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Dataset scales ``(N, num_dataset_objects)`` -> the scale network's input, the free
    normalised scales ``(N, K-1)`` (:func:`normalised` with the anchor dropped)."""
    return np.delete(normalised(inputs, ranges, scales), inputs.anchor_pos, axis=1)
