"""Names read from files never lead a read or a write outside their directory.

A frame name in ``scene.json`` becomes part of every frame path (dataset reads, candidate writes
of ``osn evaluate --candidates``), and the files of ``osn_export.json`` are opened by the export
reader (``osn``, the Blender add-on). An absolute name, a ``..`` or a symbolic link out of the
export is refused with one line naming the file and the value, before anything is written.

Cost: the synthetic dataset for the dataset cases, the tiny training run of
``tests/test_robustness.py`` for ``osn evaluate``, one small export, one ``bpy`` subprocess.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scenecore import dataset as D
from scenecore import export_format as core
from scenecore.paths import join_inside, name_problem
from tests.synthetic import synthetic_images, write_synthetic_dataset
from tests.test_robustness import EVAL_ARGS, REPO, _assert_user_error, _cli, _cli_many, train_config, trained  # noqa: F401

#: Frame names that would read outside the dataset: a parent directory and an absolute path.
ESCAPING = ["../x", "/etc/passwd"]


def _tree(root: Path, skip: Path | None = None) -> dict[str, tuple[int, int]]:
    """Every file under ``root`` (not under ``skip``) with its size and modification time."""
    out = {}
    for p in root.rglob("*"):
        if p.is_file() and not (skip and p.is_relative_to(skip)):
            st = p.stat()
            out[p.relative_to(root).as_posix()] = (st.st_size, st.st_mtime_ns)
    return out


def _rename_frame(root: Path, old: str, new: str) -> Path:
    """Give frame ``old`` the name ``new`` in ``root/scene.json`` (its files stay where they are)."""
    path = root / "scene.json"
    m = json.loads(path.read_text())
    (f,) = (f for f in m["frames"] if f["name"] == old)
    f["name"] = new
    path.write_text(json.dumps(m))
    return path


# --------------------------------------------------------------------------------------------
# The helper
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("rel", ["../x", "/etc/passwd", "a/../../b", "a\\..\\b", "C:x", "", ".", "a//b", "a\x00b"])
def test_join_inside_refuses_names_that_leave_the_base(tmp_path: Path, rel: str) -> None:
    with pytest.raises(ValueError) as e:
        join_inside(tmp_path, rel, "name", source="list.json")
    msg = str(e.value)
    assert msg.startswith("list.json: name ") and repr(rel) in msg and "\n" not in msg, msg


@pytest.mark.parametrize("rel", ["v00_t00", "a/b", "v00.t00", "..x"])
def test_join_inside_keeps_plain_relative_names(tmp_path: Path, rel: str) -> None:
    assert name_problem(rel) is None
    assert join_inside(tmp_path, rel, "name", resolve=True) == tmp_path / rel


# --------------------------------------------------------------------------------------------
# Datasets: read side and the library's write side
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("paths") / "synthetic"
    write_synthetic_dataset(root)
    return root


def _bad_copy(synthetic: Path, base: Path, name: str) -> tuple[Path, Path]:
    """A copy of the synthetic dataset whose first training frame is called ``name``."""
    root = base / "ds"
    shutil.copytree(synthetic, root)
    return root, _rename_frame(root, D.load_scene(root).train_frames[0].name, name)


@pytest.mark.parametrize("name", ESCAPING)
def test_escaping_frame_name_is_a_dataset_error_naming_scene_json(synthetic: Path, tmp_path: Path, name: str) -> None:
    root, manifest = _bad_copy(synthetic, tmp_path, name)
    with pytest.raises(D.DatasetError) as e:
        D.load_scene(root)
    msg = str(e.value)
    assert msg.startswith(f"{manifest}: frame 0 name {name!r}") and "\n" not in msg, msg


@pytest.mark.parametrize("name", ESCAPING)
def test_benchgen_validate_reports_an_escaping_frame_name_on_one_line(synthetic: Path, tmp_path: Path, name: str) -> None:
    root, manifest = _bad_copy(synthetic, tmp_path, name)
    r = _cli("benchgen", "validate", root)
    assert r.returncode == 1, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 1 and str(manifest) in lines[0] and repr(name) in lines[0], r.stdout


def test_osn_oracle_refuses_escaping_frame_names_on_one_line(synthetic: Path, tmp_path: Path) -> None:
    jobs = []
    for i, name in enumerate(ESCAPING):
        root, manifest = _bad_copy(synthetic, tmp_path / str(i), name)
        jobs.append((name, manifest, tmp_path / str(i) / "inputs"))
    for (name, manifest, out), r in zip(jobs, _cli_many([("osn", "oracle", m.parent, "--out", o) for _, m, o in jobs])):
        _assert_user_error(r, manifest, repr(name))
        assert not out.exists()


def test_frame_files_outside_the_dataset_are_neither_read_nor_written(synthetic: Path, tmp_path: Path) -> None:
    """The library's own entry points (``frame_paths``, ``read_frame``, ``write_frame``) refuse a
    name that bypassed the manifest check, before touching a file."""
    root = tmp_path / "ds"
    shutil.copytree(synthetic, root)
    name = "../../../outside/v"  # from train/rgb/ to the dataset's parent directory
    before = _tree(tmp_path)
    scene = D.load_scene(root)
    for call in (lambda: D.frame_paths(root, name), lambda: D.read_frame(root, name),
                 lambda: D.write_frame(root, name, *synthetic_images(scene, 0)),
                 lambda: D.write_frame(root, name, *synthetic_images(scene, 0), config=0)):
        with pytest.raises(D.DatasetError, match=r"frame name '\.\./\.\./\.\./outside/v' contains '\.\.'"):
            call()
    assert _tree(tmp_path) == before and not (tmp_path / "outside").exists()


# --------------------------------------------------------------------------------------------
# osn evaluate --candidates: nothing is written outside the candidates directory
# --------------------------------------------------------------------------------------------


def test_evaluate_with_escaping_frame_name_writes_nothing(trained: Path, tiny_dataset: Path, tmp_path: Path) -> None:
    """The first evaluated test view is renamed to lead from ``configs/GGG/rgb/`` out of the
    dataset, where its files are planted (one PNG serves as colour and ids), so that every read
    succeeds: the rename alone is what must be refused, with no file written anywhere."""
    from benchgen.score.truth import evaluated_views

    root = tmp_path / "ds"
    shutil.copytree(tiny_dataset, root)
    scene = D.load_scene(root)
    first = evaluated_views(scene, 2)[0].name
    name = "../../../../escaped/v"  # read: tmp/escaped/v.*; write: DIR/CAND/rgb/ + 4 parents
    manifest = _rename_frame(root, first, name)
    (tmp_path / "escaped").mkdir()
    src = D.frame_paths(root, first, 0)
    shutil.copy(src.ids, tmp_path / "escaped" / "v.png")
    shutil.copy(src.depth, tmp_path / "escaped" / "v.exr")
    cands = tmp_path / "a" / "candidates"  # CAND/rgb/ + 4 parents = tmp_path
    before = _tree(tmp_path)
    run_before = _tree(trained)
    r = _cli("osn", "evaluate", trained, "--data", root, *EVAL_ARGS, "--no-true-scales", "--candidates", cands,
             "--out", tmp_path / "report")
    _assert_user_error(r, manifest, repr(name))
    assert _tree(tmp_path) == before and _tree(trained) == run_before
    assert not cands.exists() and not (tmp_path / "report").exists()


def test_candidate_writer_refuses_paths_leaving_its_directory(trained: Path, tiny_dataset: Path, tmp_path: Path) -> None:
    """The write side checks on its own: a truth whose view name bypassed the manifest check
    makes ``RenderedCandidates.write`` raise before it renders or writes anything."""
    from benchgen.score.predictions import PredictionError
    from benchgen.score.truth import load_truth
    from osn.evaluate.exact import RenderedCandidates
    from osn.model.run import load_run

    run = load_run(trained)
    good = load_truth(tiny_dataset, 1, workers=1)
    frame = dataclasses.replace(good.frames[0], name="../../../../escaped")
    truth = dataclasses.replace(good, frames=[frame])
    cands = tmp_path / "a" / "candidates"  # CAND/rgb/ + 4 parents = tmp_path
    sbar = {"one": np.ones(run.inputs.num_objects)}
    source = RenderedCandidates(run, truth, sbar)
    with pytest.raises(PredictionError) as e:
        source.write(cands, {"name": "test"})
    msg = str(e.value)
    assert msg.startswith(f"{cands}: candidate file 'one/rgb/../../../../escaped.png' contains '..'"), msg
    assert _tree(tmp_path) == {} and not source.rendered
    # The view's own name writes where it always did.
    RenderedCandidates(run, good, sbar).write(cands, {"name": "test"})
    name = good.frames[0].name
    train = [f"one/train/rgb/{f.name}.png" for f in good.scene.train_frames]  # its renders of the training video
    assert sorted(_tree(tmp_path)) == sorted(f"a/candidates/{p}" for p in
                                             ("method.json", f"one/rgb/{name}.png", f"one/depth/{name}.exr", f"one/ids/{name}.png", *train))


# --------------------------------------------------------------------------------------------
# Exports: symbolic links out of the export, absolute and '..' file names
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    from osn.export.writer import write_export
    from tests.osn.export.test_export_addon import make_export_scene

    out = tmp_path_factory.mktemp("paths_export") / "scene"
    write_export(out, make_export_scene())
    return out


def _link_out(export: Path, tmp_path: Path, rel: str) -> tuple[Path, Path]:
    """A copy of the export whose ``rel`` (file or folder) is a symbolic link to an identical copy
    outside it: same bytes, same sha256, so only where it leads is wrong."""
    d = tmp_path / "export"
    shutil.copytree(export, d)
    outside = tmp_path / "outside" / Path(rel).name
    outside.parent.mkdir()
    shutil.move(d / rel, outside)
    os.symlink(outside, d / rel)
    return d, d / rel


@pytest.mark.parametrize("rel", ["arrays.npz", "scale_net.npz", "objects/1.vdb", "objects/2.ply", "objects"])
def test_export_files_linking_outside_are_refused(exported: Path, tmp_path: Path, rel: str) -> None:
    d, link = _link_out(exported, tmp_path, rel)
    with pytest.raises(core.ExportFormatError) as e:
        core.read_export(str(d))
    msg = str(e.value)
    assert "\n" not in msg and "symbolic link leads outside" in msg, msg
    assert msg.startswith(str(link)), msg  # the link itself, or the file under the linked folder


def test_export_link_inside_the_export_still_loads(exported: Path, tmp_path: Path) -> None:
    d = tmp_path / "export"
    shutil.copytree(exported, d)
    (d / "objects" / "1.ply").rename(d / "mesh-1.ply")
    os.symlink("../mesh-1.ply", d / "objects" / "1.ply")
    data = core.read_export(str(d))
    assert data.objects[1].mesh is not None


@pytest.mark.parametrize("bad", ["/etc/passwd", "../scene/arrays.npz", "objects/../../x"])
def test_export_file_names_leaving_the_export_are_refused(exported: Path, tmp_path: Path, bad: str) -> None:
    d = tmp_path / "export"
    shutil.copytree(exported, d)
    m = json.loads((d / "osn_export.json").read_text())
    m["files"][0]["path"] = bad
    (d / "osn_export.json").write_text(json.dumps(m))
    with pytest.raises(core.ExportFormatError) as e:
        core.read_export(str(d))
    msg = str(e.value)
    assert msg.startswith(f"{d / 'osn_export.json'}: files[0].path {bad!r}") and "\n" not in msg, msg


_ADDON_IMPORT = """
import json, sys
import bpy
from blender_addon import scene_build
counts = lambda: {a: len(getattr(bpy.data, a)) for a in ("objects", "meshes", "volumes", "collections")}
before = counts()
try:
    scene_build.import_export(bpy.context, sys.argv[1])
    msg = None
except scene_build.core.ExportFormatError as e:
    msg = str(e)
print(json.dumps({"message": msg, "same": counts() == before}))
"""


def test_addon_import_refuses_an_export_linking_outside(exported: Path, tmp_path: Path) -> None:
    """The add-on's importer reads through the same reader: refused, nothing built in Blender."""
    pytest.importorskip("bpy")
    d, link = _link_out(exported, tmp_path, "objects/1.vdb")
    r = subprocess.run([sys.executable, "-c", _ADDON_IMPORT, str(d / "osn_export.json")], cwd=REPO,
                       env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["same"] and res["message"] and res["message"].startswith(str(link)), res
    assert "symbolic link leads outside" in res["message"]
