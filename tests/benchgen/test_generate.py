"""benchgen end to end with real Cycles renders of the ``tiny`` preset (a few seconds each)."""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from scenecore import dataset as D
from scenecore.cameras import pixel_rays
from benchgen.cli import main as cli_main
from benchgen.scene.configs import choose_configurations
from benchgen.render.generate import generate, prepare, verify_dataset
from benchgen.render.workers import Task, Worker
from benchgen.scene.plausibility import PlausibilityChecker, room_scale_limits
from benchgen.scene.spec import PRESET_DIR, SpecError, load_preset, load_spec, spec_from_dict
from scenecore.validity import ValidRegion
from benchgen.render.verify import CREASE_FACING_CHANGE, INTERIOR_MIN_FACING, compare_training, interior_mask, summarise

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny(tiny_dataset) -> Path:
    """The session's tiny dataset (tests/conftest.py); read-only here."""
    return tiny_dataset


@pytest.fixture(scope="module")
def worker(tiny) -> Worker:
    spec = load_spec(tiny / "spec.yaml")
    return Worker(spec.to_dict(), spec.source, str(tiny))


def _tree(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def _assert_same_tree(a: Path, b: Path) -> None:
    files = _tree(a)
    assert files == _tree(b)
    _, mismatch, errors = filecmp.cmpfiles(a, b, [str(f) for f in files], shallow=False)
    assert not mismatch and not errors, mismatch[:5]


def test_validator_accepts_output(tiny):
    assert D.validate(tiny) == []
    scene = D.load_scene(tiny)
    assert len(scene.train_frames) == 3 and len(scene.test_frames) == 9 and scene.num_configurations == 3
    assert all((tiny / f"transforms_{s}.json").is_file() for s in ("train", "val", "test"))  # tests/scenecore/test_interop.py


def test_single_timestamp_dataset_is_finished_without_transforms(tmp_path):
    """D-NeRF needs the training video to run from time 0 to 1: with one timestamp generate still
    finishes a valid dataset, leaves the transforms files out and says why."""
    d = load_preset("tiny").to_dict()
    d["rig"].update(times=1, views=3)
    d.update(resolution=[16, 16], configs=2)
    summary = generate(spec_from_dict(d, "tiny-one-time"), tmp_path / "ds", progress=False)
    assert summary.passed and D.validate(tmp_path / "ds") == []
    assert not list((tmp_path / "ds").glob("transforms_*.json"))
    assert any("no transforms_*.json" in line and "exactly 1" in line for line in summary.lines())


def test_every_configuration_reproduces_training_video(tiny, worker):
    ver = D.load_verification(tiny)
    assert ver["passed"] and len(ver["configurations"]) == 3
    scene = D.load_scene(tiny)
    for cfg in D.load_configurations(tiny, scene):
        assert not np.allclose(cfg.scales[1:], 1.0) or cfg.index == 0
        for f in scene.train_frames:
            out = worker.renderer.render(f.camera_to_world, worker.built.poses(f.time_index, cfg.scales))
            rgb, _, ids = D.read_frame(tiny, f.name)
            np.testing.assert_array_equal(out.ids, ids)
            assert np.mean(out.rgb8() != rgb) < 0.005
    # Test views of different configurations are different scenes.
    name = scene.test_frames[0].name
    assert not np.array_equal(D.read_frame(tiny, name, 0)[1], D.read_frame(tiny, name, 1)[1])


def test_bounds_are_tight(tiny, worker):
    """Scaling one object just below its bound keeps every id; just above flips at least one."""
    region = D.load_valid_region(tiny)
    scene = D.load_scene(tiny)
    train = [(f, D.read_frame(tiny, f.name)[2]) for f in scene.train_frames]
    checked = 0
    for k in range(1, scene.num_objects):
        bound = np.min(np.delete(region.ratio_bounds[k], k))
        if not np.isfinite(bound):
            continue
        for factor, expect_same in ((1 - 1e-3, True), (1 + 1e-3, False)):
            s = np.ones(scene.num_objects)
            s[k] = bound * factor
            assert bool(region.contains(s)) == expect_same
            same = all(
                np.array_equal(worker.renderer.render(f.camera_to_world, worker.built.poses(f.time_index, s), 1).ids, ids)
                for f, ids in train
            )
            assert same == expect_same, (k, factor)
        checked += 1
    assert checked >= 1


def test_gnome_house_invariance_on_reduced_rig(tmp_path):
    """Regression: gnome-house (thin pole, tori, crease between parts) keeps its training frames.

    With Cycles' default 1.5 px pixel filter and 8-octave textures, configuration 1 of this rig
    differed by 0.0056 on an interior pixel of the ring toy; pixel-centre rays and band-limited
    textures bring every interior pixel within float noise.
    """
    d = load_preset("gnome-house").to_dict()
    d["rig"].update(views=3, times=3)
    d.update(resolution=[64, 64])
    spec = spec_from_dict(d, "gnome-house-3x3")
    built, limits = prepare(spec)
    w = Worker(spec.to_dict(), spec.source, str(tmp_path))
    train = [f.name for f in built.scene.train_frames]
    region = ValidRegion.from_bounds(w.run(Task("train", train)).bounds, anchor=built.scene.anchor_id)
    configs = choose_configurations(
        region, limits, PlausibilityChecker(built).problem, 4, spec.margin, tuple(spec.scale_range), spec.candidates, spec.seed
    )
    for g, s in enumerate(configs[1:], 1):
        r = w.run(Task("verify", [], g, s.tolist(), configs[0].tolist()))
        verdict = summarise(g, s, r.train_stats, [])
        assert verdict["passed"], verdict["failures"]
        assert verdict["max_interior_diff"] < 5e-5 and verdict["min_interior_fraction"] > 0.7


def test_verdict_fails_blank_renders_and_test_views_that_see_no_rescaled_object():
    """A configuration passes only if its renders show objects and its test views see a
    rescaled object (a NaN camera once rendered every pixel empty and 'passed')."""
    ok = {"max_interior_diff": 0.0, "differing_fraction": 0.0, "ids_identical": True, "interior_fraction": 0.8}
    blank = dict(ok, interior_fraction=0.0)
    assert summarise(1, np.ones(2), [("t0", ok)], [("v1", 100, 99)])["passed"]
    v = summarise(1, np.ones(2), [("t0", ok), ("t1", blank)], [("v1", 100, 99)])
    assert not v["passed"] and "training frame t1: shows no object at all" in v["failures"][0]
    v = summarise(1, np.ones(2), [("t0", ok)], [("v1", 0, 0), ("v2", 0, 0)])
    assert not v["passed"] and "no test view shows an object whose scale differs" in v["failures"][0]
    v = summarise(1, np.ones(2), [("t0", ok)], [("v1", 100, 1)])
    assert not v["passed"] and "test frame v1: only 1.0%" in v["failures"][0]
    assert summarise(0, np.ones(2), [("t0", ok)], [("v1", 0, 0)])["passed"]  # the reference itself


def test_instance_ids_may_flip_on_silhouettes_only():
    """A ray grazing a silhouette may change object by rounding (gnome-house at 1024 px: one
    pixel, max_ids_differing_pixels 1); it counts in the pixel budget. Inside a silhouette a changed id fails."""
    base = np.zeros((8, 8), dtype=np.uint8)
    base[2:6, 2:6] = 1
    rgb = np.zeros((8, 8, 3))
    edge = base.copy()
    edge[2, 2] = 0  # a silhouette corner
    s = compare_training(rgb, base, rgb, edge)
    assert s["ids_identical"] and s["ids_differing_pixels"] == 1 and s["differing_fraction"] == 1 / 64
    inner = base.copy()
    inner[3, 3] = 0  # its 3x3 neighbourhood is all object 1
    assert not compare_training(rgb, base, rgb, inner)["ids_identical"]
    v = summarise(0, np.ones(2), [("t0", compare_training(rgb, base, rgb, inner))], [])
    assert not v["passed"] and any("instance ids differ from the training video inside a silhouette" in f for f in v["failures"])
    v = summarise(0, np.ones(2), [("t0", s), ("t1", compare_training(rgb, base, rgb, base))], [])
    assert v["max_ids_differing_pixels"] == 1  # recorded in verification.json


def test_interior_mask_excludes_borders_silhouettes_and_grazing_hits():
    ids = np.zeros((6, 7), dtype=np.uint8)
    ids[:, 5:] = 1
    facing = np.ones((6, 7), dtype=np.float32)
    facing[2, 2] = INTERIOR_MIN_FACING / 2
    m = interior_mask(ids, facing)
    assert not m[0].any() and not m[-1].any() and not m[:, 0].any() and not m[:, -1].any()
    assert not m[:, 4].any() and not m[2, 2]  # next to object 1; grazing
    assert m[1:5, 1:4].sum() == 11
    assert interior_mask(ids)[2, 2]


def test_crease_hits_get_the_pixel_budget_not_the_interior_limit():
    # A re-render whose pixel (3, 3) hit the other face of a crease (facing 0.3 -> 0.04) and is
    # 0.02 off; a pixel (2, 2) whose facing only rounded differently but whose colour moved.
    ids = np.zeros((6, 6), dtype=np.uint8)
    base_rgb = np.full((6, 6, 3), 0.5)
    base_facing = np.full((6, 6), 0.8, dtype=np.float32)
    base_facing[3, 3] = 0.3
    rgb, facing = base_rgb.copy(), base_facing.copy()
    rgb[3, 3] += 0.02
    facing[3, 3] = 0.04
    stats = compare_training(base_rgb, ids, rgb, ids, base_facing, facing)
    assert stats["max_interior_diff"] == 0.0 and stats["differing_fraction"] == 1 / 36
    facing[2, 2] += CREASE_FACING_CHANGE / 10
    rgb[2, 2] += 0.001
    stats = compare_training(base_rgb, ids, rgb, ids, base_facing, facing)
    assert abs(stats["max_interior_diff"] - 0.001) < 1e-12  # shading moved without a crease: caught
    assert compare_training(base_rgb, ids, rgb, ids, base_facing)["max_interior_diff"] > 0.019


def test_a_pixel_flipping_across_a_texture_edge_gets_the_pixel_budget():
    """A checker edge through a pixel centre: rounding may put the hit on the other square (seen
    on gnome-house at 128 px). Such a flip goes to the budget; any other colour change does not."""
    ids = np.zeros((6, 6), dtype=np.uint8)
    base = np.full((6, 6, 3), 0.2)
    base[:, 3:] = 0.7  # a checker edge between columns 2 and 3
    rgb = base.copy()
    rgb[2, 3] = 0.2 + 1e-6  # pixel (2, 3) flipped to the dark square
    stats = compare_training(base, ids, rgb, ids)
    assert stats["max_interior_diff"] == 0.0 and stats["texture_edge_flips"] == 1
    assert stats["differing_fraction"] == 1 / 36
    rgb[2, 4] = 0.7 - 0.3  # moved, but not to a neighbour's colour: caught
    stats = compare_training(base, ids, rgb, ids)
    assert abs(stats["max_interior_diff"] - 0.3) < 1e-12 and stats["texture_edge_flips"] == 1


def test_demo_preset_is_gnome_house_at_demo_size():
    demo, full = load_preset("gnome-house-demo").to_dict(), load_preset("gnome-house").to_dict()
    assert demo["rig"].pop("test_views") == 30 and full["rig"].pop("test_views") == 0
    for key in ("room", "rig", "objects", "configs", "margin", "scale_range", "seed"):
        assert demo[key] == full[key], key
    assert demo["configs"] == 50 and demo["rig"]["views"] == demo["rig"]["times"] == 15
    assert demo["resolution"] == [64, 64] and demo["samples"] == 1


def test_depth_matches_camera_conventions(tiny):
    """Back-projected room pixels land on the room's walls: intrinsics, pose and planar depth agree."""
    scene = D.load_scene(tiny)
    spec = load_spec(tiny / "spec.yaml")
    sx, sy, sz = spec.room.size
    for f in scene.train_frames:
        _, depth, ids = D.read_frame(tiny, f.name)
        o, d = pixel_rays(scene.intrinsics.matrix(), f.camera_to_world, scene.width, scene.height)
        room = (ids == 0).reshape(-1)
        p = o[room] + depth.reshape(-1)[room, None] * d[room]
        gap = np.min(np.abs(np.stack([p[:, 0] - sx / 2, p[:, 0] + sx / 2, p[:, 1] - sy / 2, p[:, 1] + sy / 2, p[:, 2], p[:, 2] - sz], 1)), 1)
        assert room.sum() > 100 and gap.max() < 1e-3


def test_configurations_are_plausible_and_spread(tiny):
    spec = load_spec(tiny / "spec.yaml")
    built, limits = prepare(spec)
    checker = PlausibilityChecker(built)
    cfgs = np.stack([c.scales for c in D.load_configurations(tiny)])
    assert all(checker.problem(s) is None for s in cfgs)
    assert np.all(cfgs <= limits + 1e-12)
    x = np.log(cfgs)
    assert min(np.linalg.norm(x[i] - x[j]) for i in range(3) for j in range(i)) > 0.3
    assert room_scale_limits(built)[1] == limits[1]
    # The limit is tight: 1% above it a vertex of object 1 leaves the room at some time, 1% below none does.
    lo, hi = built.room_box

    def leaves_room(s1: float) -> bool:
        scales = np.ones(len(limits))
        scales[1] = s1
        for t in range(len(built.scene.timestamps)):
            M = built.poses(t, scales)[1]
            v = built.objects[1].mesh.vertices @ M[:3, :3].T + M[:3, 3]
            if np.any(v < lo - 1e-9) or np.any(v > hi + 1e-9):
                return True
        return False

    assert leaves_room(limits[1] * 1.01) and not leaves_room(limits[1] * 0.99)


def test_deterministic_and_resumable(tiny, tmp_path):
    # Determinism: a second generation is byte-identical.
    again = tmp_path / "again"
    generate(load_preset("tiny"), again, progress=False)
    _assert_same_tree(tiny, again)
    # Resume after losing files mid-run (a killed run leaves whole files only: writes are atomic).
    for p in [D.frame_paths(again, "v00_t01", 2).rgb, D.frame_paths(again, "v00_t00").depth, again / "valid_region.json",
              again / "verification.json", again / ".benchgen" / "verify" / "001.json"]:
        p.unlink()
    shutil.rmtree(again / "configs" / "001" / "depth")
    summary = generate(load_preset("tiny"), again, progress=False)
    assert summary.frames_rendered > 0
    _assert_same_tree(tiny, again)


def test_video_only_writes_the_training_video_and_the_rest_follows(tiny, tmp_path):
    """`--video-only` (SfM's video at another resolution): the training frames, byte for byte
    those of a full generation, and nothing else; generating without it finishes the dataset."""
    out = tmp_path / "video"
    assert cli_main(["generate", "--preset", "tiny", "--out", str(out), "--video-only", "--quiet"]) == 0
    scene = D.load_scene(out)
    train = sorted(p for p in _tree(tiny) if p.parts[0] == "train")
    assert sorted(p for p in _tree(out) if p.parts[0] == "train") == train and len(train) == 3 * len(scene.train_frames)
    _, mismatch, errors = filecmp.cmpfiles(tiny, out, [str(f) for f in train], shallow=False)
    assert not mismatch and not errors
    assert not any((out / n).exists() for n in ("configs", "valid_region.json", "verification.json"))
    assert generate(load_preset("tiny"), out, progress=False, video_only=True).frames_rendered == 0  # resumed: done
    summary = generate(load_preset("tiny"), out, progress=False)
    assert summary.passed
    _assert_same_tree(tiny, out)


def test_without_ground_truth_stops_before_the_test_views_and_the_rest_follows(tiny, tmp_path):
    """`ground_truth=False` (what `osn demo` trains on before its ground truths render): the
    training video, the exact region and the configurations, byte for byte those of a full
    generation, and no test view or verification; a full call finishes the same dataset."""
    out = tmp_path / "partial"
    summary = generate(load_preset("tiny"), out, progress=False, ground_truth=False)
    assert summary.passed and not summary.verification
    files = _tree(out)
    assert {f.parts[0] for f in files} == {"train", "configs", "scene.json", "spec.yaml", "valid_region.json"}
    assert [f for f in files if f.parts[0] == "configs"] == [Path("configs") / f"{g:03d}" / "config.json" for g in range(3)]
    _, mismatch, errors = filecmp.cmpfiles(tiny, out, [str(f) for f in files], shallow=False)
    # scene.json gains the depth range (near / far) once every ground-truth depth exists.
    assert mismatch == ["scene.json"] and not errors
    full = json.loads((tiny / "scene.json").read_text())
    assert {k: v for k, v in full.items() if k not in ("near", "far")} == json.loads((out / "scene.json").read_text())
    summary = generate(load_preset("tiny"), out, progress=False)
    assert summary.passed and summary.verification["passed"]
    _assert_same_tree(tiny, out)


def test_resume_after_killing_parallel_run(tiny, tmp_path):
    out = tmp_path / "killed"
    spec = load_preset("tiny").with_overrides(configs=3)
    cmd = [sys.executable, "-m", "benchgen.cli", "generate", "--preset", "tiny", "--out", str(out), "--workers", "2", "--quiet"]
    # SIGKILL skips every clean-up: the killed workers' scratch directories go to tmp_path.
    env = dict(os.environ, TMPDIR=str(tmp_path))
    proc = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    deadline = time.time() + 60
    while time.time() < deadline and not list((out / "configs").glob("*/rgb/*.png")):
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "verification.json").exists()
    generate(spec, out, workers=1, progress=False)
    _assert_same_tree(tiny, out)


BAD_SPECS = [
    (lambda d: d["objects"][0]["parts"][0].update(type="pyramid"), "objects[0] (ball).parts[0].type: unknown object type 'pyramid'"),
    (lambda d: d["objects"][0].pop("parts") and d["objects"][0].update(mesh="nowhere.obj"), "objects[0] (ball).mesh: mesh file"),
    (lambda d: d["objects"][0]["motion"].append({"t": 0.5, "location": [0, 0, 1]}), "keyframe times must strictly increase"),
    (lambda d: d["objects"][1]["motion"][0].update(location=[-0.5, 0.2, 0.6]), "intersect at time index 0"),
    (lambda d: d["objects"][0]["motion"][0].update(location=[-0.8, -1.09, 1.3]), "inside object 'ball'"),
    (lambda d: d["objects"][0]["motion"][0].update(location=[0.0, 0.0, 2.4]), "'ball' pokes out of the room"),
    (lambda d: d.update(margin=3.0), "no room for a log margin of 3.0"),
    (lambda d: d.update(colour=1), "colour: unknown field"),
    (lambda d: d["rig"].update(height=float("nan")), "rig.height: must be a finite number, got nan"),
    (lambda d: d.update(margin=float("inf")), "margin: must be a finite number"),
    (lambda d: d["rig"].update(views=1), "rig.views: needs at least 2 camera positions"),
    (lambda d: d["rig"].update(views=4, times=2, arc=[0, 180], radius=1.9), "test camera of frame v03_t00 is outside the room"),
]


@pytest.mark.parametrize("mutate,message", BAD_SPECS)
def test_bad_specs_are_rejected_before_rendering(tmp_path, capsys, mutate, message):
    d = yaml.safe_load((PRESET_DIR / "tiny.yaml").read_text())
    mutate(d)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    out = tmp_path / "out"
    assert cli_main(["generate", "--spec", str(path), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and str(path) in err and len(err.strip().splitlines()) == 1
    assert not (out / "configs").exists()


def test_output_and_input_problems_are_one_line(tmp_path, capsys):
    """--out naming a file, a dataset whose spec.yaml is not YAML, a mesh trimesh cannot read:
    each is one line naming the file, exit 2, nothing rendered."""
    not_dir = tmp_path / "file"
    not_dir.write_text("x")
    assert cli_main(["generate", "--preset", "tiny", "--out", str(not_dir), "--quiet"]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    ds = tmp_path / "ds"
    ds.mkdir()
    (ds / "spec.yaml").write_text("rig: [unclosed")
    assert cli_main(["verify", str(ds)]) == 2
    err = capsys.readouterr().err
    assert f"{ds / 'spec.yaml'}: not valid YAML" in err and len(err.strip().splitlines()) == 1
    d = yaml.safe_load((PRESET_DIR / "tiny.yaml").read_text())
    mesh = tmp_path / "thing.xyz123"
    mesh.write_text("not a mesh")
    d["objects"][0].pop("parts")
    d["objects"][0]["mesh"] = str(mesh)
    spec = tmp_path / "mesh.yaml"
    spec.write_text(yaml.safe_dump(d))
    assert cli_main(["generate", "--spec", str(spec), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{mesh}: cannot load the mesh" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "configs").exists()


def test_spec_round_trip_and_overrides():
    spec = load_preset("tiny")
    again = spec_from_dict(spec.to_dict(), "x")
    assert again.to_dict() == spec.to_dict()
    assert spec.with_overrides(resolution=64, configs=7).resolution == [64, 64]
    with pytest.raises(SpecError, match="resolution"):
        spec.with_overrides(resolution=2)


def test_verify_detects_a_broken_configuration(tiny, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(tiny, broken)
    region = D.load_valid_region(broken)
    scales = np.ones(region.num_objects)
    scales[1] = region.intervals[1, 1] * 1.5  # far outside: some training id must change
    D.write_configuration(broken, D.Configuration(2, scales))
    assert cli_main(["verify", str(broken), "--quiet"]) == 1
    out, err = capsys.readouterr()
    assert "FAILED configuration 002" in out and "training frame v" in out
    # stderr: one line naming the dataset and the first failure (what a script running it shows)
    err = err.strip().splitlines()
    assert len(err) == 1 and f"{broken}: verification failed: 1 of 3 configurations (configuration 002: training frame v" in err[0], err
    assert verify_dataset(tiny, progress=False).passed


def test_ray_executor_matches_local(tiny, tmp_path):
    """Same shards on a local Ray instance give the same files (skipped when Ray is absent)."""
    ray = pytest.importorskip("ray")
    out = tmp_path / "ray"
    try:
        summary = generate(load_preset("tiny"), out, workers=2, executor="ray", progress=False)
    finally:
        ray.shutdown()
    assert summary.passed
    _assert_same_tree(tiny, out)


def test_a_render_does_not_depend_on_what_was_rendered_before():
    """Persistent Cycles data and skipped unchanged matrices must not leak history into a render:
    a frame (full and each object alone) is bit-identical from a fresh renderer and from one that
    rendered other times, scales and hidden objects first. Sharding and resuming rely on it."""
    from benchgen.render.blender import Renderer
    from benchgen.scene.geometry import build_scene

    built = build_scene(load_preset("tiny"))
    frames = built.scene.frames
    target, scales = frames[-1], np.array([1.0, 0.8, 0.9])

    def views(r: Renderer) -> list:
        poses = built.poses(target.time_index, scales)
        return [r.render(target.camera_to_world, poses, only=k) for k in (None, 0, 1, 2)]

    fresh = views(Renderer(built, threads=1))
    used = Renderer(built, threads=1)
    for f, s in [(frames[0], [1.0, 1.0, 1.0]), (frames[5], [1.0, 0.7, 1.1]), (target, [1.0, 0.8, 0.9])]:
        used.render(f.camera_to_world, built.poses(f.time_index, np.array(s)), only=1)
    for a, b in zip(fresh, views(used)):
        assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.ids, b.ids)
        assert np.array_equal(a.depth, b.depth)
    with pytest.raises(ValueError, match="2 poses for 3 objects"):
        used.render(target.camera_to_world, built.poses(0)[:2])
