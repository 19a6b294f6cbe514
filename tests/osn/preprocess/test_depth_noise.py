"""Exact or noisy inputs, measured (osn.preprocess.depth_noise): the rule behind three ``auto`` options."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from osn.preprocess.depth_noise import NOISY_SHARE, depth_consistency
from osn.preprocess.freespace import MARGIN, contradicted_share, occlusion_tests
from osn.preprocess.oracle import oracle_inputs
from tests.osn.train.common import with_phantoms


def test_exact_depths_do_not_contradict_and_phantoms_do(tiny_dataset: Path) -> None:
    """The tiny scene's exact inputs contradict themselves nowhere; 5% of the room's depths at half
    their value (SfM's phantoms) make the inputs noisy whatever their source label says, and only
    the room's share moves."""
    exact = oracle_inputs(tiny_dataset)
    c = depth_consistency(exact)
    assert c.shares == (0.0,) * exact.num_objects and not c.noisy
    relabelled = depth_consistency(dataclasses.replace(exact, source="colmap"))
    assert relabelled == c  # the label is not read
    noisy = depth_consistency(with_phantoms(exact, 0.05))
    a = exact.anchor_pos
    assert noisy.noisy and noisy.worst == noisy.shares[a] > 3 * NOISY_SHARE
    assert all(s == 0.0 for k, s in enumerate(noisy.shares) if k != a)
    assert noisy.record()["noisy"] is True and noisy.record()["threshold"] == NOISY_SHARE


def test_the_share_does_not_depend_on_the_objects_unit_and_needs_two_frames(tiny_dataset: Path) -> None:
    """An object's unit is unknown (SfM's is arbitrary): scaling its depths and camera centres
    together leaves the share as it is. One frame cannot test itself (0, no division by zero)."""
    o = with_phantoms(oracle_inputs(tiny_dataset), 0.05).objects[0]
    inputs = oracle_inputs(tiny_dataset)
    K, W, H = inputs.K, inputs.width, inputs.height

    def share(poses: np.ndarray, pix: list[np.ndarray], depths: list[np.ndarray]) -> float:
        return contradicted_share(occlusion_tests(poses, pix, depths, K, W, H, MARGIN))

    base = share(o.cam_to_obj, o.sparse_pix, o.sparse_depth)
    for unit in (1e-4, 1e4):
        poses = o.cam_to_obj.copy()
        poses[:, :3, 3] *= unit
        assert np.isclose(share(poses, o.sparse_pix, [d * unit for d in o.sparse_depth]), base)
    assert base > 0
    assert share(o.cam_to_obj[:1], o.sparse_pix[:1], o.sparse_depth[:1]) == 0.0
    assert share(o.cam_to_obj, [p[:0] for p in o.sparse_pix], [d[:0] for d in o.sparse_depth]) == 0.0
