"""Invariance checks of configurations against the training video (numpy only).

A configuration passes when its re-rendered training frames reproduce the base video (interior
pixels within ``TRAIN_MAX_INTERIOR_DIFF`` in linear RGB, at most ``TRAIN_MAX_DIFFERING_FRACTION``
of all pixels off by more than 1/255, instance ids identical) and its test views differ from
configuration 0's on at least ``TEST_MIN_DIFFERING_FRACTION`` of the pixels where an object whose
scale differs from configuration 0's is seen (so the configurations are really different scenes).
Silhouette pixels mix objects and differ by float noise on grazing hits, hence the pixel budget.
"""

from __future__ import annotations

from typing import Any

import numpy as np

TRAIN_MAX_INTERIOR_DIFF = 1e-4
TRAIN_MAX_DIFFERING_FRACTION = 0.005
TRAIN_PIXEL_TOLERANCE = 1.0 / 255.0
TEST_MIN_DIFFERING_FRACTION = 0.98
#: Relative depth change that counts as "different" in a test view.
TEST_DEPTH_TOLERANCE = 1e-5


def interior_mask(ids: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood (clamped at the border) shows a single object."""
    p = np.pad(ids, 1, mode="edge")
    H, W = ids.shape
    same = np.ones((H, W), dtype=bool)
    for dy in range(3):
        for dx in range(3):
            same &= p[dy : dy + H, dx : dx + W] == ids
    return same


def compare_training(base_rgb: np.ndarray, base_ids: np.ndarray, rgb: np.ndarray, ids: np.ndarray) -> dict[str, Any]:
    """Statistics of a re-rendered training frame against the base frame (linear RGB floats)."""
    diff = np.abs(rgb.astype(np.float64) - base_rgb).max(axis=-1)
    interior = interior_mask(base_ids)
    return {
        "max_interior_diff": float(diff[interior].max()) if interior.any() else 0.0,
        "differing_fraction": float(np.mean(diff > TRAIN_PIXEL_TOLERANCE)),
        "ids_identical": bool(np.array_equal(ids, base_ids)),
    }


def test_difference(
    ref: tuple[np.ndarray, np.ndarray, np.ndarray], cur: tuple[np.ndarray, np.ndarray, np.ndarray], scaled: np.ndarray
) -> tuple[int, int]:
    """``(seen, differing)`` pixel counts of a test view against configuration 0's.

    ``scaled`` is a boolean per object id: its scale differs from configuration 0's. A pixel is
    *seen* when such an object is visible in either view; it *differs* when ids, depth
    (relative ``TEST_DEPTH_TOLERANCE``) or RGB differ.
    """
    (rgb0, d0, id0), (rgb1, d1, id1) = ref, cur
    lut = np.zeros(256, dtype=bool)
    lut[: len(scaled)] = scaled
    seen = lut[id0] | lut[id1]
    with np.errstate(invalid="ignore"):
        depth_diff = ~(np.abs(d1 - d0) <= TEST_DEPTH_TOLERANCE * np.abs(d0))
    differ = (id0 != id1) | depth_diff | np.any(rgb0 != rgb1, axis=-1)
    return int(seen.sum()), int((seen & differ).sum())


def summarise(index: int, scales: np.ndarray, train: list[tuple[str, dict[str, Any]]], test: list[tuple[str, int, int]]) -> dict[str, Any]:
    """Per-configuration verdict from per-frame training statistics and test-view counts."""
    worst = max(train, key=lambda x: x[1]["max_interior_diff"])
    worst_frac = max(train, key=lambda x: x[1]["differing_fraction"])
    bad_ids = [name for name, s in train if not s["ids_identical"]]
    seen = sum(s for _, s, _ in test)
    differ = sum(d for _, _, d in test)
    failures = []
    if worst[1]["max_interior_diff"] > TRAIN_MAX_INTERIOR_DIFF:
        failures.append(f"training frame {worst[0]}: interior pixels differ by {worst[1]['max_interior_diff']:.3g} > {TRAIN_MAX_INTERIOR_DIFF}")
    if worst_frac[1]["differing_fraction"] > TRAIN_MAX_DIFFERING_FRACTION:
        failures.append(
            f"training frame {worst_frac[0]}: {100 * worst_frac[1]['differing_fraction']:.2f}% of pixels differ by more than 1/255"
        )
    if bad_ids:
        failures.append(f"training frame {bad_ids[0]}: instance ids differ from the training video")
    frac = differ / seen if seen else 1.0
    if frac < TEST_MIN_DIFFERING_FRACTION:
        worst_test = min((t for t in test if t[1]), key=lambda t: t[2] / t[1])
        failures.append(
            f"test frame {worst_test[0]}: only {100 * frac:.1f}% of pixels showing a rescaled object differ from configuration 000"
        )
    return {
        "index": index,
        "scales": np.asarray(scales).tolist(),
        "max_interior_diff": worst[1]["max_interior_diff"],
        "worst_frame": worst[0],
        "max_differing_fraction": worst_frac[1]["differing_fraction"],
        "ids_identical": not bad_ids,
        "test_pixels_with_rescaled_objects": seen,
        "test_differing_fraction": frac if index != 0 else None,
        "passed": not failures,
        "failures": failures,
    }


def thresholds() -> dict[str, float]:
    return {
        "train_max_interior_diff": TRAIN_MAX_INTERIOR_DIFF,
        "train_max_differing_fraction": TRAIN_MAX_DIFFERING_FRACTION,
        "train_pixel_tolerance": TRAIN_PIXEL_TOLERANCE,
        "test_min_differing_fraction": TEST_MIN_DIFFERING_FRACTION,
    }
