"""Invariance checks of configurations against the training video (numpy only).

A configuration passes when its re-rendered training frames reproduce the base video (interior
pixels within ``TRAIN_MAX_INTERIOR_DIFF`` in linear RGB, at most ``TRAIN_MAX_DIFFERING_FRACTION``
of all pixels off by more than 1/255 or showing another instance id, instance ids identical
away from silhouettes) and its test views differ from configuration 0's on at least
``TEST_MIN_DIFFERING_FRACTION`` of the pixels where an object whose scale differs from
configuration 0's is seen (so the configurations are really different scenes). Every pixel is
the pixel-centre ray (``benchgen.render``), so identical ids away from silhouettes prove that no
visibility order flipped (a ray grazing a silhouette may flip by rounding); the colour checks
confirm that shading is local. Float
rounding of a rescaled object's hit points is amplified by ``1 / cos`` of the incidence angle, so
silhouettes and grazing hits (outside ``interior_mask``) get the pixel budget, not the 1e-4 limit.
So do crease hits: where two parts of one object intersect, the normal is discontinuous and
rounding picks the face (seen on gnome-house: a ring-toy pixel at the seam of two tori, whose
facing, and through the shading term its colour, changed with the rescale).
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
#: Interior pixels see their surface at least this far from grazing (|cos| of the incidence
#: angle; 0.2 = 78 degrees). Below it, float rounding of the hit point (amplified 5x or more)
#: times the texture gradient can exceed 1e-4 with no change of visibility (seen on a nearly
#: grazing hit on gnome-house's gnome); it removes few pixels.
INTERIOR_MIN_FACING = 0.2
#: A pixel whose ``facing`` changes by more than this between the base frame and a re-render hit
#: a different face of a crease; elsewhere it changes by float rounding only, far below this,
#: while a crease hit changes far above it.
CREASE_FACING_CHANGE = 1e-3
#: A texture discontinuity (a checker edge) between a pixel and a 4-neighbour of the same object
#: is a colour jump above this (linear RGB, max over channels). A pixel centre that lands on such
#: an edge can flip to the other side by float rounding of its hit point (seen on gnome-house: a
#: sofa pixel took its neighbouring square's colour with the same id and facing). A
#: *texture-edge flip* is a pixel whose re-render moved at least halfway to the colour of
#: such a neighbour; it goes to the pixel budget, like a crease hit.
TEXTURE_EDGE_JUMP = 0.1


def interior_mask(ids: np.ndarray, facing: np.ndarray | None = None) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood shows a single object and whose hit is not grazing.

    Border pixels are never interior: their neighbourhood extends beyond the image, where an
    occluding edge may lie just outside the frame.
    """
    H, W = ids.shape
    p = np.pad(ids.astype(np.int32), 1, constant_values=-1)
    same = np.ones((H, W), dtype=bool)
    for dy in range(3):
        for dx in range(3):
            same &= p[dy : dy + H, dx : dx + W] == ids
    if facing is not None:
        same &= facing >= INTERIOR_MIN_FACING
    return same


def compare_training(
    base_rgb: np.ndarray,
    base_ids: np.ndarray,
    rgb: np.ndarray,
    ids: np.ndarray,
    base_facing: np.ndarray | None = None,
    facing: np.ndarray | None = None,
) -> dict[str, Any]:
    """Statistics of a re-rendered training frame against the base frame (linear RGB floats).

    ``base_facing`` (``RenderOutput.facing`` of the base frame) excludes grazing hits from the
    interior pixels; with ``facing`` of the re-render too, crease hits (the facing changed by more
    than ``CREASE_FACING_CHANGE``) are excluded as well. They still count in the pixel budget.
    """
    diff = np.abs(rgb.astype(np.float64) - base_rgb).max(axis=-1)
    interior = interior_mask(base_ids, base_facing)
    if base_facing is not None and facing is not None:
        interior &= np.abs(facing.astype(np.float64) - base_facing) <= CREASE_FACING_CHANGE
    flips = texture_edge_flips(base_rgb, rgb) & interior
    interior &= ~flips
    id_diff = ids != base_ids
    return {
        "max_interior_diff": float(diff[interior].max()) if interior.any() else 0.0,
        "differing_fraction": float(np.mean((diff > TRAIN_PIXEL_TOLERANCE) | id_diff)),
        # Rounding may flip a ray that grazes a silhouette (gnome-house at 1024 px); on an
        # interior pixel a changed id is a changed visibility order, never allowed.
        "ids_identical": not bool(id_diff[interior].any()),
        "ids_differing_pixels": int(id_diff.sum()),
        "interior_fraction": float(interior.mean()),
        "texture_edge_flips": int(flips.sum()),
    }


def texture_edge_flips(base_rgb: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    """``(H, W)`` pixels whose re-render ``rgb`` moved at least halfway from ``base_rgb`` to the
    base colour of a 4-neighbour across a texture discontinuity (jump > ``TEXTURE_EDGE_JUMP``).

    Callers restrict it to interior pixels (3x3 neighbourhood of one object), so the neighbour is
    the same surface. A pixel that merely changed keeps its distance to every neighbour and is
    not a flip.
    """
    base = np.asarray(base_rgb, dtype=np.float64)
    cur = np.asarray(rgb, dtype=np.float64)
    H, W = base.shape[:2]
    pad = np.pad(base, ((1, 1), (1, 1), (0, 0)), mode="edge")
    flip = np.zeros((H, W), dtype=bool)
    for dy, dx in ((0, 1), (2, 1), (1, 0), (1, 2)):
        nb = pad[dy : dy + H, dx : dx + W]
        jump = np.abs(nb - base).max(axis=-1)
        flip |= (jump > TEXTURE_EDGE_JUMP) & (np.abs(cur - nb).max(axis=-1) <= 0.5 * jump)
    return flip


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
        failures.append(f"training frame {bad_ids[0]}: instance ids differ from the training video inside a silhouette")
    blank = [name for name, s in train if s.get("interior_fraction", 1.0) == 0.0]
    if blank:  # every preset's room surrounds the camera: a frame without object pixels is broken
        failures.append(f"training frame {blank[0]}: shows no object at all (blank render)")
    frac = differ / seen if seen else 0.0
    if index != 0 and test and not seen:  # test views were rendered, none shows a rescaled object
        failures.append("no test view shows an object whose scale differs from configuration 000")
    elif index != 0 and seen and frac < TEST_MIN_DIFFERING_FRACTION:
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
        "max_ids_differing_pixels": max(s.get("ids_differing_pixels", 0) for _, s in train),
        "min_interior_fraction": min(s.get("interior_fraction", 1.0) for _, s in train),
        "test_pixels_with_rescaled_objects": seen,
        "test_differing_fraction": frac if index != 0 and seen else None,
        "passed": not failures,
        "failures": failures,
    }


#: Bumped when a verdict rule changes (2: blank renders and test views seeing no rescaled
#: object fail; 3: a silhouette pixel may change its instance id, within the pixel budget), so
#: verdicts cached under the old rules are recomputed.
VERDICT_RULES = 3


def thresholds() -> dict[str, float]:
    """Everything a verdict depends on besides the renders (stored with cached verdicts)."""
    return {
        "verdict_rules": VERDICT_RULES,
        "train_max_interior_diff": TRAIN_MAX_INTERIOR_DIFF,
        "train_max_differing_fraction": TRAIN_MAX_DIFFERING_FRACTION,
        "train_pixel_tolerance": TRAIN_PIXEL_TOLERANCE,
        "interior_min_facing": INTERIOR_MIN_FACING,
        "crease_facing_change": CREASE_FACING_CHANGE,
        "test_min_differing_fraction": TEST_MIN_DIFFERING_FRACTION,
    }
