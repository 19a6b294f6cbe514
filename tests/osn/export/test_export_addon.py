"""Export writer + Blender add-on, end to end, headless with the bpy 5.0.1 wheel.

The pytest side writes a small export with analytic grids (a textured wall as the anchor and two
spheres) and builds the add-on zip; one Blender subprocess (this file run as a script, with
``BLENDER_USER_RESOURCES`` pointing at a temporary directory so nothing touches the home
directory) installs and enables the extension, tries malformed exports, imports the real one,
and dumps matrices, scores, voxels and tiny Cycles renders that the tests below check.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[3]
# Sphere configurations (actual scales of anchor, sphere A, sphere B) used by both sides.
CONFIG_A = [1.0, 0.88, 1.0]
CONFIG_B = [1.0, 1.08, 0.95]
CONFIG_INVALID = [1.0, 0.84, 1.16]
RENDER_FRAME = 2  # Blender frame = time index + 1


# --------------------------------------------------------------------------------------------
# The synthetic export (pytest side)
# --------------------------------------------------------------------------------------------


def _diamond_net(m: float, r: float, gain: float = 40.0):
    """A real 2-layer ReLU/sigmoid MLP whose valid set is the L1 ball |s - m|_1 < r (normalised)."""
    from osn.export.writer import ScaleNetwork

    W0 = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    b0 = np.array([-m, m, -m, m])
    return ScaleNetwork(layers=[(W0, b0), (np.full((1, 4), -gain), np.array([gain * r]))])


def _grid_points(bbox: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """``(D, H, W, 3)`` object coordinates of the node-aligned samples (ExportObject convention)."""
    Dn, Hn, Wn = shape
    z, y, x = (np.linspace(bbox[0, a], bbox[1, a], n) for a, n in ((2, Dn), (1, Hn), (0, Wn)))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    return np.stack([xx, yy, zz], axis=-1)


def _rot_z(deg: float, t: np.ndarray) -> np.ndarray:
    a = np.radians(deg)
    M = np.eye(4)
    M[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    M[:3, 3] = t
    return M


def make_export_scene():
    from scenecore.cameras import intrinsics_from_fov, look_at
    from osn.export.writer import ExportObject, ExportScene
    from scenecore import export_format as core

    W, H, T = 40, 30, 4
    ranges = np.array([[0.5, 1.6]] * 2)
    m = float(core.normalise(np.array([1.0, 1.0]), ranges)[0])
    net = _diamond_net(m, 0.15)
    intervals = core.learned_intervals(net.layers, np.vstack([[0.5, 1.6], ranges]), 0, draws=100_000)
    c2s = np.stack([look_at(np.array([0.3 * t - 0.45, -4.0, 0.4]), np.array([0.0, 0.0, 0.3])) for t in range(T)])
    test = np.stack([[look_at(np.array([2.2, -3.3, 1.4 + 0.05 * t]), np.array([0.0, 0.0, 0.3])) for t in range(T)]])
    objects = []
    # Anchor: a slab with an object-space checker texture (it scales with the object).
    wb = np.array([[-3.2, -0.3, -2.4], [3.2, 0.3, 2.4]])
    p = _grid_points(wb, (24, 6, 32))
    dens = np.where(np.abs(p[..., 1]) < 0.2, 60.0, 0.0).astype(np.float32)
    chk = ((np.floor(p[..., 0] * 1.5) + np.floor(p[..., 2] * 1.5)) % 2)[..., None]
    col = (0.25 + 0.5 * chk * np.array([1.0, 0.8, 0.3]) + 0.1 * np.array([0.2, 0.4, 1.0])).astype(np.float32)
    objects.append(ExportObject(0, "wall", True, dens, np.clip(col, 0, 1), wb, (0.5, 1.6), (1.0, 1.0),
                                np.arange(T), np.stack([_rot_z(0.0, [0.0, 2.5, 0.3])] * T)))
    sb = np.array([[-0.5] * 3, [0.5] * 3])
    for k, (centre, tint, spin) in enumerate(((np.array([-0.8, 0.0, 0.3]), np.array([1.0, 0.3, 0.2]), 12.0),
                                              (np.array([0.8, -0.5, 0.2]), np.array([0.2, 0.9, 0.4]), -8.0)), start=1):
        p = _grid_points(sb, (20, 20, 20))
        rad = np.linalg.norm(p, axis=-1)
        dens = (50.0 * np.clip((0.35 - rad) / 0.06, 0.0, 1.0)).astype(np.float32)
        col = np.clip(tint * (0.55 + 0.45 * (p @ np.array([0.6, -0.3, 0.7]))[..., None] / 0.5), 0, 1).astype(np.float32)
        frames = np.arange(T) if k == 1 else np.array([0, 1, 3])  # sphere B is missing at t = 2
        poses = np.stack([_rot_z(spin * t, centre + [0.08 * t, 0.0, 0.0]) for t in frames])
        objects.append(ExportObject(k, f"sphere{k}", False, dens, col, sb, tuple(ranges[k - 1]), tuple(intervals[k]), frames, poses))
    samples = np.array([CONFIG_A, CONFIG_B, [1.0, 0.95, 0.95]])
    return ExportScene(W, H, intrinsics_from_fov(50.0, W, H), np.linspace(0.0, 1.0, T), c2s, objects, test_cameras=test,
                       scale_network=net, samples=samples, source="tests/test_export_addon.py", meta={"name": "test"})


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory):
    from osn.export.writer import write_export

    scene = make_export_scene()
    out = tmp_path_factory.mktemp("export") / "scene"
    t0 = time.perf_counter()
    manifest = write_export(out, scene)
    return scene, manifest, time.perf_counter() - t0


def _drop_vdb_grid(export_dir: Path, rel: str, grid: str) -> None:
    """Rewrite ``rel`` without grid ``grid`` and record its new size and sha256 in the manifest,
    so the export passes ``read_export`` and only Blender's volume check can reject it."""
    from scenecore import export_format as core
    from osn.export.writer import _openvdb

    vdb, path = _openvdb(), export_dir / rel
    grids, _ = vdb.readAll(str(path))
    assert grid in {g.name for g in grids}
    vdb.write(str(path), grids=[g for g in grids if g.name != grid])
    m = json.loads((export_dir / "osn_export.json").read_text())
    (entry,) = (f for f in m["files"] if f["path"] == rel)
    entry["bytes"], entry["sha256"] = path.stat().st_size, core.sha256_file(str(path))
    (export_dir / "osn_export.json").write_text(json.dumps(m))


@pytest.fixture(scope="module")
def blender(exported, tmp_path_factory: pytest.TempPathFactory):
    """Run the Blender side once; returns (results dict, work directory)."""
    from osn.export.addon_build import build_addon_zip

    scene, manifest, export_s = exported
    work = tmp_path_factory.mktemp("blender")
    t0 = time.perf_counter()
    zip_path = build_addon_zip(work / "dist")
    zip_s = time.perf_counter() - t0
    # Malformed copies: wrong version, a missing file, a corrupt grid, and (failing only after the
    # wall and sphere 1 are built and keyed) sphere 2's volume without its colour grid.
    src = manifest.parent
    bad = {}
    for kind in ("version", "missing", "corrupt", "no_color"):
        d = work / f"bad_{kind}"
        shutil.copytree(src, d)
        if kind == "version":
            m = json.loads((d / "osn_export.json").read_text())
            m["version"] = 99
            (d / "osn_export.json").write_text(json.dumps(m))
        elif kind == "missing":
            (d / "objects" / "2.ply").unlink()
        elif kind == "no_color":
            _drop_vdb_grid(d, "objects/2.vdb", "color")
        else:
            blob = bytearray((d / "objects" / "1.vdb").read_bytes())
            blob[len(blob) // 2 : len(blob) // 2 + 64] = b"\xff" * 64
            (d / "objects" / "1.vdb").write_bytes(bytes(blob))
        bad[kind] = str(d)
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(work / "user"), PYTHONPATH=str(ROOT))
    args = {"zip": str(zip_path), "export": str(manifest), "bad": bad, "work": str(work)}
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, __file__, json.dumps(args)], env=env, capture_output=True, text=True, timeout=600)
    blender_s = time.perf_counter() - t0
    if r.returncode != 0:
        pytest.fail(f"Blender side failed ({r.returncode}):\n{r.stdout[-4000:]}\n{r.stderr[-4000:]}")
    res = json.loads((work / "results.json").read_text())
    res["timing"].update({"export_s": export_s, "zip_s": zip_s, "blender_subprocess_s": blender_s})
    print("timing:", json.dumps(res["timing"]))
    return res, work


# --------------------------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------------------------


def test_export_round_trip_and_atomicity(exported, tmp_path: Path) -> None:
    from scenecore import export_format as core
    from osn.export.writer import write_export

    scene, manifest, _ = exported
    data = core.read_export(str(manifest))
    assert [o.name for o in data.objects] == ["wall", "sphere1", "sphere2"]
    assert data.anchor_index == 0 and data.test_cameras.shape == (1, 4, 4, 4)
    for src, got in zip(scene.objects, data.objects):
        np.testing.assert_array_equal(got.object_to_scene, src.object_to_scene)
        assert got.mesh is not None and len(got.mesh["faces"]) > 50
        # Mesh vertices lie on the object's surface: spheres of radius ~0.35 - 0.03.
        if not src.is_anchor:
            r = np.linalg.norm(got.mesh["vertices"], axis=1)
            assert 0.27 < r.min() and r.max() < 0.36
    # Every file is named in the manifest, and nothing else is in the directory.
    listed = {f["path"] for f in data.manifest["files"]} | {"osn_export.json"}
    on_disk = {p.relative_to(manifest.parent).as_posix() for p in manifest.parent.rglob("*") if p.is_file()}
    assert listed == on_disk
    # A failing export leaves the previous export untouched and no temporary directory behind.
    broken = make_export_scene()
    broken.objects[1].colour = broken.objects[1].colour[..., :2]
    target = tmp_path / "out"
    write_export(target, make_export_scene())
    before = (target / "osn_export.json").read_bytes()
    with pytest.raises(core.ExportFormatError):
        write_export(target, broken)
    assert (target / "osn_export.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    with pytest.raises(core.ExportFormatError, match="not an OSN export"):
        write_export(tmp_path / "other", make_export_scene())


def test_export_grids_read_back_with_openvdb(exported) -> None:
    """The VDB holds the density transposed to [x, y, z] with the node-aligned transform."""
    from osn.export.writer import _openvdb

    scene, manifest, _ = exported
    vdb = _openvdb()
    o = scene.objects[1]
    grid = {g.name: g for g in vdb.readAll(str(manifest.parent / "objects" / "1.vdb"))[0]}["density"]
    back = np.zeros(o.density.shape[::-1], np.float32)
    grid.copyToArray(back)
    np.testing.assert_array_equal(back.transpose(2, 1, 0), o.density)
    i, j, k = 3, 7, 11  # voxel [d=k, h=j, w=i] sits at bbox_min + (i, j, k) * voxel
    np.testing.assert_allclose(grid.transform.indexToWorld((i, j, k)), o.bbox[0] + np.array([i, j, k]) * o.voxel_size(), atol=1e-6)


def _torch_scores(layers, s_norm: np.ndarray) -> np.ndarray:
    """Reference scale network: torch ``nn.Linear`` layers, ReLU between, sigmoid at the end."""
    import torch

    lin = [torch.nn.Linear(W.shape[1], W.shape[0]).double() for W, _ in layers]
    x = torch.from_numpy(np.atleast_2d(s_norm))
    with torch.no_grad():
        for i, (m, (W, b)) in enumerate(zip(lin, layers)):
            m.weight.copy_(torch.from_numpy(W))
            m.bias.copy_(torch.from_numpy(b))
            x = m(x)
            x = torch.relu(x) if i < len(lin) - 1 else torch.sigmoid(x)
    return x[:, 0].numpy()


def _torch_validity(scene, sbar: list[float]) -> float:
    """Validity computed independently of the add-on: torch layers on Eq. 1-normalised scales."""
    from osn.preprocess.inputs import normalise_scales

    ranges = np.array([o.scale_range for o in scene.objects])[1:]
    return float(_torch_scores(scene.scale_network.layers, normalise_scales(np.asarray(sbar[1:]), ranges))[0])


def test_scale_net_numpy_matches_torch(exported) -> None:
    from scenecore.export_format import scale_net_numpy

    scene, _, _ = exported
    s = np.random.default_rng(0).random((257, 2))
    ref = _torch_scores(scene.scale_network.layers, s)
    assert 0.01 < (ref >= 0.5).mean() < 0.99  # both valid and invalid draws are compared
    np.testing.assert_allclose(scale_net_numpy(scene.scale_network.layers, s), ref, rtol=1e-12, atol=1e-15)


def test_malformed_exports_leave_scene_untouched(blender) -> None:
    from scenecore import export_format as core

    res, work = blender
    # "no_color" passes read_export (right checksums): it fails in Blender's volume check on the
    # last object, after the others were built and keyed, so it exercises the rollback of every
    # datablock kind, the keyframe actions included.
    core.read_export(str(work / "bad_no_color"))
    for kind, expect in (("version", "version 99"), ("missing", "2.ply: missing file"), ("corrupt", "1.vdb: corrupt file"),
                         ("no_color", "2.vdb: volume lacks grids")):
        r = res["bad"][kind]
        assert r["raised"], kind
        assert expect in r["message"], r["message"]
        assert r["counts_after"] == r["counts_before"], kind


def _mutate(m: dict, keys: tuple, value) -> None:
    for k in keys[:-1]:
        m = m[k]
    m[keys[-1]] = value


# (manifest keys, bad value, what the one-line message must name)
MALFORMED_FIELDS = [
    (("objects", 1, "bbox"), [0.0, 0.0, 0.0, 1.0, 1.0], "object 1: bbox"),
    (("objects", 1, "scale_range"), [1], "object 1: scale_range"),
    (("objects", 0, "id"), "a", "object 0: id"),
    (("camera", "K"), [1.0, 2.0, 3.0], "camera.K"),
    (("files", 0, "path"), 7, "files[0].path"),
    (("timestamps",), 3, "'timestamps'"),
    (("objects", 2, "grid_shape"), ["x", 20, 20], "object 2: grid_shape"),
    (("objects", 1, "valid_interval"), None, "object 1: valid_interval"),
    (("objects", 1, "is_anchor"), "no", "object 1: is_anchor"),
    (("objects", 1, "volume"), ["objects/1.vdb"], "volume"),
    (("objects",), {"0": {}}, "'objects' must be a list"),
    (("camera", "width"), "40", "camera.width"),
    (("camera",), "cam", "'camera' must be a JSON object"),
    (("files", 1, "bytes"), "12", "files[1].bytes"),
    (("files",), "arrays.npz", "'files' must be a list"),
    (("scale_network", "threshold"), "high", "scale_network: threshold"),
    (("scale_network", "layers"), "2", "scale_network: layers"),
    (("objects", 2, "id"), 1, "object 2: id 1 is used by another object"),
]


@pytest.mark.parametrize("keys,value,names", MALFORMED_FIELDS, ids=[".".join(map(str, k)) for k, _, _ in MALFORMED_FIELDS])
def test_malformed_manifest_fields_are_one_line_format_errors(exported, tmp_path: Path, keys, value, names) -> None:
    """A wrong type or shape in any manifest field is an ExportFormatError naming the file and the
    field (the import operator reports those; anything else reaches the artist as a traceback)."""
    from scenecore import export_format as core

    _, manifest, _ = exported
    d = tmp_path / "export"
    shutil.copytree(manifest.parent, d)
    m = json.loads((d / "osn_export.json").read_text())
    _mutate(m, keys, value)
    (d / "osn_export.json").write_text(json.dumps(m))
    with pytest.raises(core.ExportFormatError) as e:
        core.read_export(str(d))
    msg = str(e.value)
    assert msg.startswith(f"{d / 'osn_export.json'}: ") and "\n" not in msg, msg
    assert names in msg, msg


def test_import_menu_opens_file_browser_unless_this_call_names_the_manifest() -> None:
    """``names_manifest(filepath, set_in_call)`` decides ``invoke``: ``set_in_call`` is Blender's
    ``is_property_set("filepath")``, false for a path carried over from the last run (a "ghost"
    value). The real operator's wiring is checked inside Blender (``res["invoke"]``)."""
    from scenecore import export_format as core

    for filepath, set_in_call, expect in (
        ("/exports/a/osn_export.json", False, "browser"),  # File > Import after an import: remembered path
        ("/exports/a/osn_export.json", True, "import"),  # dropped on the viewport, or a script
        ("/exports/a/notes.json", True, "browser"),  # another dropped JSON: let the artist pick
        ("", False, "browser"),
    ):
        outcome = "import" if core.names_manifest(filepath, set_in_call) else "browser"
        assert [outcome] == [expect], (filepath, set_in_call)


def test_scale_network_arrays_are_checked_like_every_other_array(exported, tmp_path: Path) -> None:
    """A NaN bias once passed and made every validity score NaN; a missing or mis-shaped layer
    names its array."""
    from scenecore import export_format as core

    _, manifest, _ = exported
    m = json.loads(manifest.read_text())
    rel = m["scale_network"]["file"]
    for what, change, message in (
        ("nan bias", lambda z: z.update(b0=np.full_like(z["b0"], np.nan)), "array 'b0' has non-finite values"),
        ("no layer 1", lambda z: z.pop("W1"), "missing array 'W1'"),
        ("wrong width", lambda z: z.update(W0=np.zeros((z["W0"].shape[0], 5))), "array 'W0' has shape"),
        ("strings", lambda z: z.update(b0=np.array(["1.5"] * len(z["b0"]))), "array 'b0' has dtype"),
    ):
        d = tmp_path / what.replace(" ", "_")
        shutil.copytree(manifest.parent, d)
        with np.load(d / rel) as f:
            z = {k: f[k] for k in f.files}
        change(z)
        np.savez(d / rel, **z)
        mm = json.loads((d / "osn_export.json").read_text())
        (entry,) = (f for f in mm["files"] if f["path"] == rel)
        entry["bytes"], entry["sha256"] = (d / rel).stat().st_size, core.sha256_file(str(d / rel))
        (d / "osn_export.json").write_text(json.dumps(mm))
        with pytest.raises(core.ExportFormatError) as e:
            core.read_export(str(d))
        assert message in str(e.value) and "scale_network" in str(e.value), (what, str(e.value))


def test_addon_manifest_declares_file_access(blender) -> None:
    """The add-on reads export files from disk, so the extension declares the "files" permission
    (Blender shows it at install); Blender's own validator accepted the manifest when the
    ``blender`` fixture built the zip (``build_addon_zip`` runs blender_ext validate + build)."""
    import tomllib

    m = tomllib.loads((ROOT / "blender_addon" / "blender_manifest.toml").read_text())
    assert m["permissions"]["files"].strip()
    assert set(m["permissions"]) == {"files"}
    _, work = blender
    assert list((work / "dist").glob("*.zip"))


def test_import_builds_objects_cameras_and_loads_volumes(blender, exported) -> None:
    res, _ = blender
    assert res["enabled"]
    # The real operator's invoke inside Blender: a call naming the manifest imports at once,
    # one without a path opens the browser. (Scripted calls never reuse remembered properties,
    # so the remembered-path case is covered by the stand-in operator test above, not here.)
    assert res["invoke"] == {"set": ["import"], "unset": ["browser"]}
    assert res["osn_objects"] == ["wall", "sphere1", "sphere2"]
    assert sorted(res["children"]["sphere1"]) == ["MESH", "VOLUME"]
    assert res["cameras"] == ["OSN test camera 0", "OSN training camera"]
    for name, v in res["volumes"].items():
        assert v["loaded"] and {"density", "color"} <= set(v["grids"]), name
    # Blender's own volume-to-mesh of sphere 1's density at the export's mesh level is a sphere
    # of radius ~0.32 in object coordinates.
    lo, hi = np.array(res["volume_to_mesh"]["min"]), np.array(res["volume_to_mesh"]["max"])
    assert res["volume_to_mesh"]["vertices"] > 50
    np.testing.assert_allclose(hi, -lo, atol=0.03)
    assert np.all((hi > 0.27) & (hi < 0.36)), hi


def test_trajectories_equal_exported_poses(blender, exported) -> None:
    from scenecore.cameras import opengl_from_opencv, scale_about

    res, _ = blender
    scene, _, _ = exported
    for rec in res["trajectory"]:
        t = rec["frame"] - 1
        c = scene.camera_to_scene[t][:3, 3]
        present = [o.name for o in scene.objects if t in o.frames]
        assert sorted(rec["objects"]) == sorted(present)  # sphere2 has no pose at frame 3
        for k, o in enumerate(scene.objects):
            if o.name not in present:
                continue
            slot = int(np.nonzero(o.frames == t)[0][0])
            expect = scale_about(c, rec["scales"][k]) @ o.object_to_scene[slot]
            np.testing.assert_allclose(np.array(rec["objects"][o.name]), expect, atol=2e-5)
            np.testing.assert_allclose(np.array(rec["volumes"][o.name]), expect, atol=2e-5)
        np.testing.assert_allclose(np.array(rec["camera"]), opengl_from_opencv(scene.camera_to_scene[t]), atol=2e-5)
        np.testing.assert_allclose(np.array(rec["test_camera"]), opengl_from_opencv(scene.test_cameras[0, t]), atol=2e-5)


def test_objects_are_hidden_at_frames_without_a_pose(blender, exported) -> None:
    """An object that left the view at some frames is hidden there, not held at its last pose;
    meshes are a viewport preview, kept out of renders ([hide_render, hide_viewport]) until
    ``render_meshes`` lets them in, hidden where their object has no pose."""
    res, _ = blender
    scene, _, _ = exported
    for frame, hidden in res["hidden"].items():
        t = int(frame) - 1
        for o in scene.objects:
            parts = [n for n in hidden if n.startswith(f"{o.name} ")]
            assert parts, o.name
            for n in parts:
                absent = t not in o.frames
                assert hidden[n] == ([True, absent] if n.endswith(" mesh") else [absent, absent]), (n, frame)
                if n.endswith(" mesh"):
                    assert res["hidden_meshes_rendered"][frame][n] == [absent, absent], (n, frame)
    assert any(any(v[0] for v in h.values()) for h in res["hidden"].values())  # the case is exercised


def test_slider_limits_and_handler_rekey(blender, exported) -> None:
    res, _ = blender
    scene, _, _ = exported
    for o in scene.objects[1:]:
        lim = res["slider_limits"][o.name]
        assert lim == pytest.approx(list(o.valid_interval))
    assert res["handler_rekeyed"], "moving a slider did not re-key the trajectory"


def test_validity_score_equals_osn(blender, exported) -> None:
    res, _ = blender
    scene, _, _ = exported
    for sbar, score in res["validity"]:
        assert score == pytest.approx(_torch_validity(scene, sbar), abs=1e-9)
    scores = dict((tuple(s), v) for s, v in res["validity"])
    assert scores[tuple(CONFIG_A)] > 0.5 and scores[tuple(CONFIG_B)] > 0.5 and scores[tuple(CONFIG_INVALID)] < 0.5


def test_sampled_configurations_are_valid(blender, exported) -> None:
    res, _ = blender
    scene, _, _ = exported
    sampled = np.array(res["sampled"])
    assert len(sampled) == 5 and len(np.unique(sampled.round(9), axis=0)) == 5
    for s in sampled:
        assert _torch_validity(scene, list(s)) >= 0.5
        for k, o in enumerate(scene.objects):
            assert o.valid_interval[0] <= s[k] <= o.valid_interval[1]
    assert res["sampled_reproducible"]
    np.testing.assert_allclose(res["applied_sample"], scene.samples[1])


def test_training_view_invariant_novel_view_changes(blender) -> None:
    """The defining property: two valid configurations give the same training image, not the same novel image."""
    res, work = blender
    img = {k: np.load(work / f"{k}.npy") for k in ("train_A", "train_B", "novel_A", "novel_B")}
    assert img["train_A"].shape == (30, 40, 4) and img["train_A"][..., :3].max() > 0.1
    d_train = np.abs(img["train_A"] - img["train_B"]).max()
    d_novel = np.abs(img["novel_A"] - img["novel_B"]).max()
    print(f"max |diff| training camera {d_train:.2e}, novel camera {d_novel:.2e}")
    assert d_train < 1e-4
    assert d_novel > 0.05
    # The volume material is scale-compensated too: the training view barely changes.
    v = {k: np.load(work / f"{k}.npy") for k in ("vol_train_A", "vol_train_B")}
    assert v["vol_train_A"][..., :3].max() > 0.1
    assert np.abs(v["vol_train_A"] - v["vol_train_B"]).mean() < 0.01


def test_osn_export_command_on_a_run_directory(tmp_path: Path) -> None:
    """``osn export RUN`` on a run directory in ``osn train``'s layout (inputs/, checkpoint.pt).

    The run is built from the oracle inputs of the synthetic dataset with untrained fields of the
    real field classes and a real ``ScaleNet``, so poses, grids and the network folding are the
    run-loading code's, whatever the training learned.
    """
    import torch

    from scenecore.cameras import invert_pose, scale_about
    from osn.cli import main
    from osn.model.fields import FieldConfig, make_field
    from osn.preprocess.inputs import save_inputs
    from osn.preprocess.oracle import oracle_inputs
    from osn.model.scale_net import ScaleNet
    from tests.synthetic import write_synthetic_dataset

    from scenecore import export_format as core

    write_synthetic_dataset(tmp_path / "data")
    inputs = oracle_inputs(tmp_path / "data")
    run = tmp_path / "run"
    save_inputs(run / "inputs", inputs)
    fcfg = FieldConfig(kind="dense", resolution=12, initial_resolution=12)
    fields = [make_field(fcfg, torch.from_numpy(o.bbox).float(), seed=k) for k, o in enumerate(inputs.objects)]
    axis = torch.linspace(-1, 1, 12)
    blob = 12.0 - 40.0 * (axis[:, None, None] ** 2 + axis[None, :, None] ** 2 + axis[None, None, :] ** 2)
    with torch.no_grad():  # a blob in every box so the mesh is not empty
        for f in fields:
            f.grid.data[:, 0] = blob.reshape(-1)  # symmetric, so the voxel order does not matter
    net = ScaleNet(len(inputs.objects) - 1, seed=3)
    with torch.no_grad():
        net.mlp[-1].bias.fill_(4.0)  # accept most of the domain, as a trained network on an easy scene
    cfg = {"field": vars(fcfg)}
    torch.save({"config": cfg, "resolutions": [12] * len(fields), "fields": [f.state_dict() for f in fields],
                "net": net.state_dict(), "iteration": 7}, run / "checkpoint.pt")
    (run / "run.json").write_text(json.dumps({"dataset": str(tmp_path / "data")}))  # as `osn train` writes; not read
    assert main(["export", str(run), "--out", str(tmp_path / "export"), "--data", str(tmp_path / "data"),
                 "-n", "6", "--seed", "1"]) == 0

    data = core.read_export(str(tmp_path / "export"))
    assert len(data.objects) == len(inputs.objects) and data.samples.shape == (6, len(inputs.objects))
    assert data.test_cameras is not None and data.test_cameras.shape[1:] == (len(inputs.timestamps), 4, 4)
    # The folded network scores exactly as ScaleNet does on normalised scales.
    s = np.random.default_rng(0).random((50, len(inputs.objects) - 1))
    with torch.no_grad():
        ref = net.prob(torch.from_numpy(s).float()).double().numpy()
    sbar = np.ones((len(s), len(inputs.objects)))
    sbar[:, data.free_indices] = core.denormalise(s, data.scale_ranges[data.free_indices])
    np.testing.assert_allclose(data.validity(sbar), ref, atol=1e-6)
    assert np.all(data.validity(data.samples) >= 0.6)
    # Poses follow osn.inputs: a camera point x at frame t sits in object k at cam_to_obj_k[t] @ (x / sbar_k).
    x = np.array([0.1, -0.2, 1.3, 1.0])
    for i, o in enumerate(inputs.objects):
        for slot, t in enumerate(o.frames):
            sbar = 1.3 if o.id != inputs.anchor else 1.0
            obj_to_scene = scale_about(data.camera_to_scene[t][:3, 3], sbar) @ data.objects[i].object_to_scene[slot]
            p_obj = invert_pose(obj_to_scene) @ data.camera_to_scene[t] @ x
            np.testing.assert_allclose(p_obj[:3], (o.cam_to_obj[slot] @ np.r_[x[:3] / sbar, 1.0])[:3], atol=1e-9)

    # With `osn sample` output in the run, a plain export carries exactly those (evaluated)
    # configurations; an explicit --samples still draws that many new ones.
    from osn.sample.configurations import Samples

    sbar = np.ones((3, len(inputs.objects)))
    sbar[:, data.free_indices] = 1.1
    Samples(np.zeros((3, len(inputs.objects) - 1)), sbar, np.ones(3), 0.5, 0).save(run / "samples.npz")
    assert main(["export", str(run), "--out", str(tmp_path / "e2")]) == 0
    np.testing.assert_allclose(core.read_export(str(tmp_path / "e2")).samples, sbar)
    # Test cameras come only from the dataset named by --data (a dataset that is not there is an error).
    assert core.read_export(str(tmp_path / "e2")).test_cameras is None
    assert main(["export", str(run), "--out", str(tmp_path / "e5"), "--data", str(tmp_path / "nowhere")]) == 2
    assert not (tmp_path / "e5").exists()
    assert main(["export", str(run), "--out", str(tmp_path / "e3"), "-n", "4"]) == 0
    assert core.read_export(str(tmp_path / "e3")).samples.shape == (4, len(inputs.objects))
    assert main(["export", str(run), "--out", str(tmp_path / "e4"), "-n", "-1"]) == 2
    assert not (tmp_path / "e4").exists()


# --------------------------------------------------------------------------------------------
# Blender side (run as a script in a subprocess)
# --------------------------------------------------------------------------------------------


def _blender_main(args: dict) -> None:
    t_start = time.perf_counter()
    import bpy

    timing = {"bpy_import_s": time.perf_counter() - t_start}
    work = Path(args["work"])
    t0 = time.perf_counter()
    bpy.ops.extensions.package_install_files(filepath=args["zip"], repo="user_default", enable_on_install=True)
    timing["install_s"] = time.perf_counter() - t0
    addon = sys.modules.get("bl_ext.user_default.osn_import")
    sb = addon.scene_build
    res: dict = {"enabled": addon is not None and hasattr(bpy.ops.import_scene, "osn"), "timing": timing, "bad": {}}

    def counts() -> dict:
        return {a: len(getattr(bpy.data, a)) for a in ("objects", "meshes", "volumes", "materials", "cameras", "actions", "collections")}

    for kind, d in args["bad"].items():
        before = counts()
        try:
            bpy.ops.import_scene.osn(filepath=str(Path(d) / "osn_export.json"))
            raised, msg = False, ""
        except RuntimeError as e:
            raised, msg = True, str(e)
        res["bad"][kind] = {"raised": raised, "message": msg, "counts_before": before, "counts_after": counts()}

    t0 = time.perf_counter()
    bpy.ops.import_scene.osn(filepath=args["export"])
    timing["import_s"] = time.perf_counter() - t0
    scene = bpy.context.scene
    coll = scene.osn_collection
    objs = sb.osn_objects(coll)
    res["osn_objects"] = [o.name for o in objs]
    res["children"] = {o.name: [c.type for c in o.children] for o in objs}
    res["cameras"] = sorted(o.name for o in coll.objects if o.type == "CAMERA")
    res["volumes"] = {o.name: {"loaded": o.data.grids.is_loaded, "grids": [g.name for g in o.data.grids]}
                      for o in coll.objects if o.type == "VOLUME"}
    res["slider_limits"] = {o.name: [o.id_properties_ui(sb.P_SCALE).as_dict()[k] for k in ("min", "max")] for o in objs if sb.P_SCALE in o}

    # Blender's volume-to-mesh on sphere 1's volume at the export's mesh level.
    vobj = bpy.data.objects["sphere1 volume"]
    level = json.loads(coll[sb.P_MANIFEST])["objects"][1]["mesh_level"]
    probe = bpy.data.objects.new("probe", bpy.data.meshes.new("probe"))
    scene.collection.objects.link(probe)
    mod = probe.modifiers.new("v2m", "VOLUME_TO_MESH")
    mod.object, mod.threshold, mod.resolution_mode = vobj, level, "GRID"
    ev = probe.evaluated_get(bpy.context.evaluated_depsgraph_get()).to_mesh()
    co = np.zeros(3 * len(ev.vertices))
    ev.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    # The modifier outputs in the probe's space = world; bring it back to sphere 1's object space.
    inv = np.linalg.inv(np.array(vobj.matrix_world)) @ np.array(probe.matrix_world)
    co = co @ inv[:3, :3].T + inv[:3, 3]
    res["volume_to_mesh"] = {"vertices": len(co), "min": co.min(0).tolist(), "max": co.max(0).tolist()}
    bpy.data.objects.remove(probe)

    # Trajectories at chosen frames and configurations (only objects with a pose at that frame).
    res["trajectory"] = []
    for frame, cfg in ((1, CONFIG_A), (4, CONFIG_B), (2, CONFIG_B)):
        sb.set_scales(coll, np.array(cfg))
        scene.frame_set(frame)
        names = [o.name for o in objs if (frame - 1) in list(o[sb.P_FRAMES])]
        res["trajectory"].append({
            "frame": frame, "scales": cfg,
            "objects": {n: [list(r) for r in bpy.data.objects[n].matrix_world] for n in names},
            "volumes": {n: [list(r) for r in bpy.data.objects[f"{n} volume"].matrix_world] for n in names},
            "camera": [list(r) for r in bpy.data.objects["OSN training camera"].matrix_world],
            "test_camera": [list(r) for r in bpy.data.objects["OSN test camera 0"].matrix_world],
        })

    # Which parts are shown at each frame (sphere2 has no pose at t = 2, Blender frame 3).
    res["hidden"] = {}
    for frame in range(1, 5):
        scene.frame_set(frame)
        res["hidden"][frame] = {o.name: [o.hide_render, o.hide_viewport] for o in coll.objects if o.type in ("VOLUME", "MESH")}
    sb.render_meshes(coll)
    res["hidden_meshes_rendered"] = {}
    for frame in range(1, 5):
        scene.frame_set(frame)
        res["hidden_meshes_rendered"][frame] = {o.name: [o.hide_render, o.hide_viewport] for o in coll.objects if o.type == "MESH"}
    sb.render_meshes(coll, on=False)

    res["validity"] = []
    for cfg in (CONFIG_A, CONFIG_B, CONFIG_INVALID, [1.0, 0.9, 1.1]):
        sb.set_scales(coll, np.array(cfg))
        res["validity"].append([list(sb.current_scales(coll)), sb.validity(coll)])

    # Moving a slider through the property alone: the depsgraph handler re-keys.
    s1 = bpy.data.objects["sphere1"]
    s1[sb.P_SCALE] = 0.93
    s1.update_tag()
    bpy.context.view_layer.update()
    res["handler_rekeyed"] = abs(float(s1[sb.P_KEYED]) - 0.93) < 1e-12

    scene.osn_seed = 7
    first = len(sb.export_data(coll).samples)
    for _ in range(5):
        bpy.ops.osn.sample_configuration()
    sampled = sb.export_data(coll).samples[first:]
    res["sampled"] = sampled.tolist()
    res["sampled_reproducible"] = bool(np.allclose(sb.export_data(coll).sample(1, 7)[0], sampled[0]))
    bpy.ops.osn.apply_configuration(index=1)
    res["applied_sample"] = list(sb.current_scales(coll))

    # Tiny Cycles renders at a frame where every object is present.
    r = scene.render
    r.engine = "CYCLES"
    scene.cycles.device, scene.cycles.samples, scene.cycles.use_adaptive_sampling = "CPU", 4, False
    scene.cycles.use_denoising, scene.cycles.seed = False, 0
    scene.cycles.volume_step_rate = 2.0
    scene.view_settings.view_transform, r.dither_intensity = "Standard", 0.0
    r.image_settings.file_format, r.image_settings.color_depth = "OPEN_EXR", "32"
    world = bpy.data.worlds.new("black")
    world.color = (0.0, 0.0, 0.0)
    scene.world = world
    scene.frame_set(RENDER_FRAME)

    def render(name: str, camera: str, cfg: list[float], volumes: bool) -> None:
        sb.set_scales(coll, np.array(cfg))
        for o in coll.objects:
            if o.type in {"MESH", "VOLUME"}:
                # Volume renders show the spheres only: a dense wall volume costs a minute. The
                # import keys hide_render where an object has no pose; those keys would override
                # a manual setting at render time, so they go first.
                fcurves = sb._fcurve_collection(o, create=False)
                keyed = fcurves.find("hide_render") if fcurves is not None else None
                if keyed is not None:
                    fcurves.remove(keyed)
                o.hide_render = (o.type == "VOLUME") != volumes or (volumes and o.parent.name == "wall")
        scene.camera = bpy.data.objects[camera]
        path = str(work / f"{name}.exr")
        r.filepath = path
        t = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        timing[f"render_{name}_s"] = time.perf_counter() - t
        img = bpy.data.images.load(path)
        px = np.zeros(img.size[0] * img.size[1] * 4, np.float32)
        img.pixels.foreach_get(px)
        np.save(work / f"{name}.npy", px.reshape(img.size[1], img.size[0], 4)[::-1])
        bpy.data.images.remove(img)

    for cfg_name, cfg in (("A", CONFIG_A), ("B", CONFIG_B)):
        render(f"train_{cfg_name}", "OSN training camera", cfg, volumes=False)
        render(f"novel_{cfg_name}", "OSN test camera 0", cfg, volumes=False)
        render(f"vol_train_{cfg_name}", "OSN training camera", cfg, volumes=True)
    # invoke on a real operator instance: background Blender has no event, so INVOKE_DEFAULT runs
    # execute; from there call the operator's invoke with the file browser and the import stubbed.
    ui = addon.ui
    cls, helper = ui.OSN_OT_import, ui.ImportHelper
    real_execute, real_browser = cls.execute, helper.invoke
    res["invoke"] = {}

    def probe(op, context):
        outcome: list[str] = []
        cls.execute = lambda _op, _c: outcome.append("import") or {"CANCELLED"}
        helper.invoke = lambda _op, _c, _e: outcome.append("browser") or {"CANCELLED"}
        try:
            cls.invoke(op, context, None)
        finally:
            cls.execute, helper.invoke = probe, real_browser
        res["invoke"]["set" if op.properties.is_property_set("filepath") else "unset"] = outcome
        return {"CANCELLED"}

    cls.execute = probe
    try:
        bpy.ops.import_scene.osn("INVOKE_DEFAULT", filepath=args["export"])
        bpy.ops.import_scene.osn("INVOKE_DEFAULT")
    finally:
        cls.execute = real_execute
    timing["blender_total_s"] = time.perf_counter() - t_start
    (work / "results.json").write_text(json.dumps(res))


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    _blender_main(json.loads(sys.argv[1]))
