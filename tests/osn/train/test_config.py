"""The training and field configs: every impossible value is one error naming its key."""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from osn.model.fields import FieldConfig
from osn.train import TrainConfig
from osn.train.auto import (
    MIN_OBJECT_RESOLUTION,
    DEPTH_ROBUST_NOISY,
    footprint_resolution,
    label_stride,
    resolve_depth_robust,
)
from tests.osn.train.common import small_config


@pytest.mark.parametrize("bad", [{"eval_every": 0}, {"samples": 0}, {"rounds": -1},
                                 {"w_free": -0.1}, {"scale_lr_final": 1.5}, {"rounds": "five"},
                                 {"label_replay": "high"}, {"label_stride": -1}, {"depth_robust": -1.0},
                                 {"depth_robust": "always"}])
def test_config_rejects_values_that_would_divide_by_zero_or_mean_nothing(bad: dict, tmp_path: Path) -> None:
    (key, value), = bad.items()
    with pytest.raises(ValueError, match=f"{key} must"):
        small_config(**bad)
    path = tmp_path / "c.yaml"
    path.write_text(f"{key}: {value}\n")
    with pytest.raises(ValueError, match=f"^{path}: training config: {key} must"):
        TrainConfig.from_yaml(path)


def test_built_in_defaults_are_the_cpu_config() -> None:
    root = Path(__file__).resolve().parents[3]
    assert TrainConfig() == TrainConfig.from_yaml(root / "configs" / "osn-cpu.yaml")
    with pytest.raises(ValueError, match="unknown training config keys"):
        TrainConfig.from_dict({"stage1_iter": 3})


def test_config_round_trips_and_checks_the_field_section(tmp_path: Path) -> None:
    cfg = small_config(w_free=0.5, device="cpu")
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match=r"unknown field config keys: \['resolutoin'\]"):
        TrainConfig.from_dict({"field": {"resolutoin": 8}})
    path = tmp_path / "c.yaml"
    path.write_text("field:\n  resolution: 1\n")
    with pytest.raises(ValueError, match=f"^{path}: field config: resolution must be an integer in 2..1,024, got 1"):
        TrainConfig.from_yaml(path)


def test_a_run_config_written_before_a_new_term_keeps_it_off(tmp_path: Path) -> None:
    """A run's config.yaml without ``w_distortion`` (written before it existed) resumes and
    compares with the term off; a user's partial config takes the default."""
    d = TrainConfig().to_dict()
    del d["w_distortion"]
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(d))
    assert TrainConfig.from_yaml(path, run_config=True).w_distortion == 0.0
    assert TrainConfig.from_yaml(path).w_distortion == TrainConfig().w_distortion > 0
    assert TrainConfig.from_yaml(path, run_config=True) == dataclasses.replace(TrainConfig(), w_distortion=0.0)


def test_a_run_config_that_names_a_removed_option_still_reads(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A run's config.yaml written while ``anchor_coverage`` existed reads as today's config (the
    option is dropped: the anchor covers as every object does); given as a config (``--config``)
    it reads too, with a warning naming the ignored option."""
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), "anchor_coverage": 0.9, "checkpoint_every": 250}))
    assert TrainConfig.from_yaml(path, run_config=True) == TrainConfig()
    with caplog.at_level(logging.WARNING, logger="osn.train.config"):
        assert TrainConfig.from_yaml(path) == TrainConfig()
    assert f"{path}: anchor_coverage, checkpoint_every no longer an option" in caplog.text
    # One trained with a removed option away from today's behaviour is refused, naming it.
    path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), "w_before_depth": 1.0}))
    with pytest.raises(ValueError, match=r"trained with w_before_depth: 1.0, which this version no longer has"):
        TrainConfig.from_yaml(path, run_config=True)
    with pytest.raises(ValueError, match=rf"^{path}: sets w_before_depth: 1.0, which this version no longer has"):
        TrainConfig.from_yaml(path)
    # A paper value that is a constant now: read at that value, refused at another.
    path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), "coverage_threshold": 0.9, "valid_threshold": 0.95}))
    assert TrainConfig.from_yaml(path, run_config=True) == TrainConfig()
    path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), "coverage_threshold": 0.5}))
    with pytest.raises(ValueError, match=r"trained with coverage_threshold: 0.5, which this version no longer has"):
        TrainConfig.from_yaml(path, run_config=True)
    # The monitor's sample sizes trained nothing: any value reads. The background colour and the
    # field step's candidates read at today's constants only.
    path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), "eval_pixels": 16384, "iou_samples": 100000,
                                    "background": [0.0, 0.0, 0.0], "candidates": 4096}))
    assert TrainConfig.from_yaml(path, run_config=True) == TrainConfig()
    for key, value in (("background", [1.0, 1.0, 1.0]), ("candidates", 64)):
        path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), key: value}))
        with pytest.raises(ValueError, match=rf"trained with {key}: .*, which this version no longer has"):
            TrainConfig.from_yaml(path, run_config=True)
    # A removed field option likewise: read at its neutral value, refused at another.
    d = TrainConfig().to_dict()
    path.write_text(yaml.safe_dump({**d, "field": {**d["field"], "tv_density": 0.0}}))
    assert TrainConfig.from_yaml(path, run_config=True) == TrainConfig()
    path.write_text(yaml.safe_dump({**d, "field": {**d["field"], "tv_density": 0.1}}))
    with pytest.raises(ValueError, match=r"trained with field.tv_density: 0.1, which this version no longer has"):
        TrainConfig.from_yaml(path, run_config=True)
    # One whose options resolved by the inputs' source names what they trained with.
    path.write_text(yaml.safe_dump({**TrainConfig().to_dict(), "w_hidden_smooth": "auto"}))
    with pytest.raises(ValueError, match=r"config.yaml: written before w_hidden_smooth became one number.*0.3 on the oracle"):
        TrainConfig.from_yaml(path, run_config=True)


def test_a_run_config_naming_the_options_that_became_constants_reads_at_their_values(tmp_path: Path) -> None:
    """Sampling budgets, the scale network's and TensoRF's sizes and the free-space choice left
    the config: a run's config.yaml at the values that train as today reads, another is refused."""
    d = TrainConfig().to_dict()
    old = {**d, "hidden_strips": 32, "edge_rays": 64, "edge_slope": 0.02, "free_rays": 128, "scale_width": 64,
           "scale_layers": 4, "free_space": "ordered",
           "field": {**d["field"], "density_components": 16, "appearance_components": 48, "app_dim": 27, "lr_net": 1e-3}}
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(old))
    assert TrainConfig.from_yaml(path, run_config=True) == TrainConfig()
    for key, value in [("edge_rays", 32), ("scale_width", 16), ("free_space", "all")]:
        path.write_text(yaml.safe_dump({**old, key: value}))
        with pytest.raises(ValueError, match=f"trained with {key}: {value!r}"):
            TrainConfig.from_yaml(path, run_config=True)
    path.write_text(yaml.safe_dump({**old, "field": {**old["field"], "app_dim": 12}}))
    with pytest.raises(ValueError, match="field.app_dim: 12"):
        TrainConfig.from_yaml(path, run_config=True)
    # The free-space choices that carve as today: any where the term is off.
    for extra in [{"free_space": "none", "w_free": 0.0}, {"free_space": "all", "w_free": 0.0}]:
        path.write_text(yaml.safe_dump({**old, **extra}))
        assert TrainConfig.from_yaml(path, run_config=True) == dataclasses.replace(TrainConfig(), w_free=0.0)
    path.write_text(yaml.safe_dump({**old, "free_space": "none"}))  # the term on, carving nothing
    with pytest.raises(ValueError, match="free_space: 'none'"):
        TrainConfig.from_yaml(path, run_config=True)
    # `anchor` carved no other object's pixel: the band against objects is a constant of 1 now.
    path.write_text(yaml.safe_dump({**old, "free_space": "anchor", "free_band_objects": 0}))
    with pytest.raises(ValueError, match="free_band_objects: 0"):
        TrainConfig.from_yaml(path, run_config=True)


def test_a_run_config_naming_the_paper_weights_bands_and_field_rates_reads_at_their_values(tmp_path: Path) -> None:
    """The paper's loss weights, the free-space bands, the render shortcut, the checkpoint cadence
    and the field kind's grid rate and colour MLP width left the config: a run's config.yaml at the
    values that train as today reads (the shortcut and the cadence at any value; TensoRF's width at
    any value on a dense field, which has no MLP), another is refused naming the key."""
    d = TrainConfig().to_dict()
    old = {**d, "w_depth": 1.0, "w_seg": 0.01, "free_band": 4, "free_band_objects": 1, "skip_occluded": 1e-4,
           "checkpoint_every": 2000, "field": {**d["field"], "hidden": 64, "lr_grid": 0.2}}
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(old))
    assert TrainConfig.from_yaml(path, run_config=True) == TrainConfig()
    tensorf = {**old, "field": {**old["field"], "kind": "tensorf", "hidden": 128, "lr_grid": 0.02}}
    path.write_text(yaml.safe_dump(tensorf))
    assert TrainConfig.from_yaml(path, run_config=True).field.kind == "tensorf"
    for bad, name in [({**old, "w_seg": 0.5}, "w_seg: 0.5"), ({**old, "free_band": 2}, "free_band: 2"),
                      ({**old, "field": {**old["field"], "lr_grid": 0.1}}, "field.lr_grid: 0.1"),
                      ({**tensorf, "field": {**tensorf["field"], "hidden": 64}}, "field.hidden: 64"),
                      ({**tensorf, "field": {**tensorf["field"], "lr_grid": 0.2}}, "field.lr_grid: 0.2")]:
        path.write_text(yaml.safe_dump(bad))
        with pytest.raises(ValueError, match=f"trained with {name}"):
            TrainConfig.from_yaml(path, run_config=True)


def test_a_run_config_written_before_object_resolution_keeps_the_objects_at_resolution(tmp_path: Path) -> None:
    d = TrainConfig().to_dict()
    del d["field"]["object_resolution"]
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(d))
    assert TrainConfig.from_yaml(path, run_config=True).field.object_resolution == 0
    assert TrainConfig.from_yaml(path).field.object_resolution == "auto" == FieldConfig().object_resolution


@pytest.mark.parametrize("bad", [{"resolution": 1}, {"initial_resolution": 0}, {"kind": "mlp"}, {"resolution": 64.5},
                                 {"upsample_steps": 1.5}, {"upsample_steps": True},
                                 {"object_resolution": -1}, {"object_resolution": "half"}, {"object_resolution": 2.5}])
def test_field_config_rejects_impossible_values(bad: dict) -> None:
    (key, _), = bad.items()
    with pytest.raises(ValueError, match=f"field config: {key} must"):
        FieldConfig(**bad)


def _looking_at_box(distance: float, n: int = 3) -> np.ndarray:
    """``(n, 4, 4)`` camera-to-object poses: the camera ``distance`` in front of the origin on -z
    (OpenCV: looking along +z), slightly turned frame to frame."""
    out = []
    for a in np.linspace(-0.02, 0.02, n):
        c, s = np.cos(a), np.sin(a)
        R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = R @ np.array([0.0, 0.0, -distance])
        out.append(T)
    return np.stack(out)


@pytest.mark.parametrize("unit", [1.0, 1e-3, 1e4])
def test_footprint_resolution_is_the_boxes_extent_in_pixels(unit: float) -> None:
    """A unit box 10 units away under a focal length f spans about f / 9.5 pixels (its near face),
    whatever the unit; clamped to [MIN_OBJECT_RESOLUTION, cap]; a camera inside the box gives cap."""
    box = np.array([[-0.5] * 3, [0.5] * 3]) * unit

    def K(f: float) -> np.ndarray:
        return np.array([[f, 0.0, 32.0], [0.0, f, 32.0], [0.0, 0.0, 1.0]])

    poses = _looking_at_box(10.0 * unit)
    r = footprint_resolution(box, poses, K(380.0), 64)
    assert abs(r - 40) <= 1, r  # 380 / 9.5 = 40 pixels facing the camera; the turn adds a little
    assert footprint_resolution(box, poses, K(9500.0), 64) == 64  # capped
    assert footprint_resolution(box, poses, K(19.0), 64) == MIN_OBJECT_RESOLUTION  # 2 px: at least 16
    assert footprint_resolution(box, poses, K(19.0), 8) == 8  # never above the cap
    inside = _looking_at_box(0.0)
    assert footprint_resolution(box, inside, K(380.0), 64) == 64
    broken = poses.copy()
    broken[0, 0, 3] = np.nan  # a frame without a usable pose is skipped, not a NaN resolution
    assert abs(footprint_resolution(box, broken, K(380.0), 64) - 40) <= 1


def test_auto_label_stride_keeps_the_pool_size_of_a_128_pixel_frame() -> None:
    assert [label_stride(0, s, s) for s in (32, 64, 128, 129, 256, 512)] == [1, 1, 1, 2, 2, 4]
    assert label_stride(0, 300, 512) == 4 and label_stride(3, 512, 512) == 3


def test_auto_depth_robustness_is_off_for_exact_depths_only() -> None:
    """``depth_robust: auto``: the squared error on depths that agree across frames, the robust
    loss on noisy ones (:mod:`osn.preprocess.depth_noise`); a number is taken as it is."""
    assert TrainConfig().depth_robust == "auto"
    assert resolve_depth_robust("auto", noisy=False) == 0.0
    assert resolve_depth_robust("auto", noisy=True) == DEPTH_ROBUST_NOISY > 0
    assert resolve_depth_robust(0, noisy=True) == 0.0 and resolve_depth_robust(2.5, noisy=False) == 2.5


def test_options_that_resolved_by_the_inputs_source_are_plain_numbers() -> None:
    """``final_label_trim`` and ``w_hidden_smooth`` no longer resolve by the inputs' source: ``auto``
    (which did) is refused, as are words and out-of-range numbers."""
    assert TrainConfig().final_label_trim == 0.002 and TrainConfig().w_hidden_smooth == 0.3
    for key, bad in (("final_label_trim", "auto"), ("final_label_trim", "loose"), ("final_label_trim", 1.5),
                     ("w_hidden_smooth", "auto"), ("w_hidden_smooth", -0.1)):
        with pytest.raises(ValueError, match=key):
            TrainConfig(**{key: bad})
