"""Robustness of the numerics: no silent NaN, degenerate scenes, extremes (docs/robustness.md).

Each test here names the hole it closes (without the fix it guards, it fails);
`test_doc_table_names_real_tests` (tests/test_robustness.py) checks that every one of them is
listed in docs/robustness.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from scenecore.validity import ValidRegion, accumulate_ratio_bounds

from osn.model.fields import FieldConfig, make_field
from osn.model.scale_net import NonFiniteScores, ScaleNet, sample_valid
from osn.model.volume import ObjectRays, RenderOutput, render, transmittance_weights
from osn.preprocess.inputs import InputsError, check_inputs
from osn.preprocess.oracle import oracle_inputs
from osn.train import Trainer, TrainingDiverged, train
from osn.train.tensors import SceneTensors
from tests.osn.train.common import small_config

# --------------------------------------------------------------------------------------------
# The exact region: NaN depths, float32 overflow, no objects
# --------------------------------------------------------------------------------------------


def test_nan_depth_is_an_error_naming_the_frame() -> None:
    """A NaN in the visible object's depth made the pair's minimum NaN and the bound was dropped
    silently (the region became unbounded); now it is an error naming the frame and object."""
    visible = np.zeros((2, 2), np.int64)
    depths = np.stack([np.full((2, 2), 1.0), np.full((2, 2), 2.0)])
    depths[0, 1, 1] = np.nan
    with pytest.raises(ValueError, match=r"frame v00_t03: the depth of object 0 rendered alone is NaN at 1 pixels"):
        accumulate_ratio_bounds(np.full((2, 2), np.inf), visible, depths, where="frame v00_t03")
    depths[0, 1, 1] = np.inf  # visible, yet its own render misses the pixel: contradictory input
    with pytest.raises(ValueError, match="object 0 is visible at 1 pixels where its own depth is not finite"):
        accumulate_ratio_bounds(np.full((2, 2), np.inf), visible, depths, where="frame v00_t03")


def test_ratio_bounds_are_float64_for_float32_depths() -> None:
    """float32 depths 1e-30 (in front) and 1e30 (behind): the ratio 1e60 overflowed float32 to inf,
    which reads as "unconstrained"; it is taken in float64 now."""
    visible = np.zeros((1, 1), np.int64)
    depths = np.array([[[1e-30]], [[1e30]]], dtype=np.float32)
    B = accumulate_ratio_bounds(np.full((2, 2), np.inf), visible, depths)
    assert np.isfinite(B[0, 1]) and B[0, 1] == pytest.approx(float(np.float32(1e30)) / float(np.float32(1e-30)), rel=1e-12)
    region = ValidRegion.from_bounds(B)
    assert region.intervals[1, 0] == pytest.approx(1 / B[0, 1], rel=1e-12)


def test_region_needs_an_object_and_a_real_anchor() -> None:
    """K = 0 raised IndexError from deep inside; an anchor outside the objects likewise."""
    with pytest.raises(ValueError, match="needs at least one object"):
        ValidRegion.from_bounds(np.zeros((0, 0)))
    with pytest.raises(ValueError, match="anchor 3 is not one of the 2 objects"):
        ValidRegion.from_bounds(np.full((2, 2), np.inf), anchor=3)
    with pytest.raises(ValueError, match="square matrix"):
        ValidRegion.from_bounds(np.ones(3))


@settings(max_examples=40, deadline=None)
@given(data=st.data(), K=st.integers(1, 16))
def test_region_is_exact_for_depths_1e_6_to_1e6_and_scales_1e_4_to_1e4(data, K: int) -> None:
    """K objects (1..16) over 64 pixels, each covering a random subset at float32 depths 1e-6..1e6
    m; the visible one is the nearest. The region from these depths is exact: a scale vector
    (1e-4..1e4, anchor 1) is valid iff the nearest *scaled* object is the visible one on every
    pixel, and the unscaled scene is valid."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    P = 64
    d = np.exp(rng.uniform(np.log(1e-6), np.log(1e6), (K, P))).astype(np.float32)
    covers = rng.random((K, P)) < 0.6
    covers[rng.integers(0, K, P), np.arange(P)] = True  # every pixel shows some object
    alone = np.where(covers, d, np.float32(np.inf))
    visible = np.argmin(alone, axis=0)
    region = ValidRegion.from_bounds(accumulate_ratio_bounds(np.full((K, K), np.inf), visible[None], alone[:, None]))
    assert region.contains(np.ones(K)) and not np.any(np.isnan(region.intervals))
    d64 = alone.astype(np.float64)
    for _ in range(20):
        s = np.exp(rng.uniform(np.log(1e-4), np.log(1e4), K))
        s[0] = 1.0
        scaled = s[:, None] * d64
        nearest = np.argmin(scaled, axis=0)
        # Skip draws that land on a tie (probability ~0; the region's inequalities are strict).
        top2 = np.sort(scaled, axis=0)[:2] if K > 1 else None
        if top2 is not None and np.any(np.isclose(top2[0], top2[1], rtol=1e-9)):
            continue
        assert bool(region.contains(s)) == bool(np.all(nearest == visible)), s


# --------------------------------------------------------------------------------------------
# Rendering: NaN density, empty rays, no objects
# --------------------------------------------------------------------------------------------


def test_nan_optical_thickness_stays_nan() -> None:
    """`nan_to_num` read a NaN density as empty space, hiding a diverged field; it stays NaN now
    (+inf is still an opaque sample)."""
    w, _ = transmittance_weights(torch.tensor([[0.5, float("nan"), 1.0], [0.5, float("inf"), 1.0]]))
    assert torch.isnan(w[0, 1:]).all() and torch.isfinite(w[0, 0])
    assert torch.isfinite(w[1]).all() and w[1].sum() == pytest.approx(1.0)


def test_nan_density_stops_training_instead_of_reading_as_empty_space(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    """Only the density channel of a field turns NaN (colour stays finite): before, the object
    silently rendered as empty space and training went on with a finite loss."""
    real = Trainer.step_stage1

    def poisoned(self: Trainer) -> dict[str, float]:
        if self.iteration == 5:
            with torch.no_grad():
                self.fields[1].grid[:, 0] = float("nan")
        return real(self)

    monkeypatch.setattr(Trainer, "step_stage1", poisoned)
    with pytest.raises(TrainingDiverged, match=r"training diverged at iteration 6 \(stage1 phase\): loss .* is nan"):
        train(tmp_path / "r", small_config(), inputs=oracle_inputs(tiny_dataset), progress=False)


def test_depth_of_an_empty_ray_is_infinite_not_the_camera() -> None:
    """`normalised_depth` returned 0 (a surface at the camera centre, in front of everything)
    where nothing was hit; now +inf, and a NaN opacity stays NaN."""
    out = RenderOutput(rgb=torch.zeros(3, 3), depth=torch.tensor([2.0, 0.0, 1.0]), acc=torch.tensor([0.5, 0.0, float("nan")]),
                       log_seg=torch.zeros(3, 1))
    depth = out.normalised_depth()
    assert depth[0] == 4.0 and depth[1] == float("inf") and torch.isnan(depth[2])


def test_render_of_no_objects_is_the_background() -> None:
    """`render([])` failed in `torch.cat` of nothing; a frame where every object is absent is the
    background: opacity 0, depth 0 (sum of no weights), an empty segmentation."""
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = render([], torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.2, 1.0]]), 8, background=bg)
    assert torch.equal(out.rgb, bg.expand(2, 3)) and torch.equal(out.acc, torch.zeros(2))
    assert out.log_seg.shape == (2, 0) and torch.equal(out.depth, torch.zeros(2))


def test_render_of_an_object_absent_from_every_ray_is_the_background() -> None:
    """One object with no pose on any ray: background, no NaN in any output."""
    field = make_field(FieldConfig(kind="dense", resolution=8, initial_resolution=8), torch.tensor([[-1.0, -1, 1], [1, 1, 3]]))
    R = 4
    obj = ObjectRays(field, torch.eye(4).expand(R, 4, 4), torch.zeros(R, dtype=torch.bool), torch.tensor([0.1, 10.0]))
    out = render([obj], torch.tensor([[0.0, 0.0, 1.0]]).expand(R, 3), 8, background=torch.ones(3))
    assert torch.equal(out.rgb, torch.ones(R, 3)) and torch.equal(out.acc, torch.zeros(R))
    assert torch.isfinite(out.log_seg).all() and torch.isinf(out.normalised_depth()).all()


# --------------------------------------------------------------------------------------------
# Scale network: NaN scores
# --------------------------------------------------------------------------------------------


def test_nan_scale_scores_are_an_error_not_a_sample(tiny_dataset: Path, tmp_path: Path, monkeypatch) -> None:
    """`argmax` takes NaN as the largest score, so a diverged scale network gave an arbitrary
    "best" sample; now sampling raises, and inside training it is a `TrainingDiverged` line."""
    net = ScaleNet(2)
    with torch.no_grad():
        net.mlp[-1].bias.fill_(float("nan"))
    ranges = torch.tensor([[1.0, 1.0], [0.5, 2.0], [0.5, 2.0]], dtype=torch.float64)
    with pytest.raises(NonFiniteScores, match="scores 256 of 256 candidates NaN"):
        sample_valid(net, ranges, 0, torch.Generator().manual_seed(0))

    real = Trainer.step_scale

    def poisoned(self: Trainer, phase) -> dict[str, float]:
        losses = real(self, phase)
        with torch.no_grad():
            self.net.mlp[-1].bias.fill_(float("nan"))
        return losses

    monkeypatch.setattr(Trainer, "step_scale", poisoned)
    with pytest.raises(TrainingDiverged, match=r"training diverged at iteration \d+ \(\w+ phase\)"):
        train(tmp_path / "r", small_config(), inputs=oracle_inputs(tiny_dataset), progress=False)

    # `osn sample`'s scorer on the run's (finite) last checkpoint, then with NaN weights: named.
    from osn.model.run import load_run

    run = load_run(tmp_path / "r")
    assert np.isfinite(run.scores(np.full((4, 2), 0.5))).all()
    with torch.no_grad():
        run.net.mlp[-1].bias.fill_(float("nan"))
    with pytest.raises(NonFiniteScores, match=r"r/checkpoint.pt: the scale network scores 4 of 4 candidates NaN"):
        run.scores(np.full((4, 2), 0.5))


# --------------------------------------------------------------------------------------------
# Inputs: objects without mask pixels, rays in frames without a pose, an object in one frame
# --------------------------------------------------------------------------------------------


def test_object_without_mask_pixels_in_its_frames_is_named(tiny_dataset: Path) -> None:
    """An object whose registered frames hold none of its mask pixels: `randint(0, 0)` deep in
    stage 1 before; now `check_inputs` names it in one line."""
    inputs = oracle_inputs(tiny_dataset)
    o = inputs.objects[1]
    inputs.masks[inputs.masks == o.id] = 0  # its pixels now show the room
    with pytest.raises(InputsError, match=rf"x: object {o.id} \({o.name}\) covers no mask pixel in the 3 frame\(s\) where it has a pose"):
        check_inputs(inputs, "x")


def _keep_frames(inputs, k: int, frames: list[int]) -> None:
    """Object at position k keeps its pose (and sparse depths) in ``frames`` only."""
    o = inputs.objects[k]
    sel = [i for i, f in enumerate(o.frames) if f in frames]
    o.frames, o.cam_to_obj = o.frames[sel], o.cam_to_obj[sel]
    o.sparse_pix = [o.sparse_pix[i] for i in sel]
    o.sparse_depth = [o.sparse_depth[i] for i in sel]
    o.sparse_weight = [o.sparse_weight[i] for i in sel]


def test_object_posed_in_one_frame_only_draws_rays_there_and_trains(tiny_dataset: Path, tmp_path: Path) -> None:
    """SfM registered object 1 in frame 1 only, while its mask shows it in all three frames: rays
    of frames 0 and 2 must not be drawn for it (no pose, so no gradient, only a constant error
    and, in composite steps, a label no rendered object can match): they are left out, counted,
    and a short training on the object seen in one frame ends finite."""
    inputs = oracle_inputs(tiny_dataset)
    _keep_frames(inputs, 1, [1])
    check_inputs(inputs, "x")
    st_ = SceneTensors(inputs, torch.device("cpu"))
    HW = st_.H * st_.W
    frames_of_pixels = torch.unique(st_.obj_pixels[1] // HW)
    assert frames_of_pixels.tolist() == [1]
    unposed = (torch.from_numpy(inputs.masks).reshape(-1) == inputs.objects[1].id) & (torch.arange(st_.T).repeat_interleave(HW) != 1)
    assert st_.unposed_pixels == int(unposed.sum()) > 0
    assert st_.usable is not None and not torch.isin(torch.nonzero(unposed)[:, 0], st_.usable).any()
    run = train(tmp_path / "r", small_config(), inputs=inputs, progress=False)
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert all(torch.isfinite(v).all() for sd in state["fields"] for v in sd.values())
