"""Fidelity and coverage in ``benchgen score`` (docs/metrics.md "Fidelity", "Coverage and precision").

The spray test renders configurations with benchgen's own Blender renderer on the real ``tiny``
dataset (32 px, 3 training frames, 9 test views, G = 3): a method's valid solutions reproduce the
training video exactly, configurations sprayed over the scale box outside the valid region do not.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from scenecore import dataset as D
from benchgen.cli import main as benchgen
from benchgen.score import coverage as COV
from benchgen.score import fidelity as F
from benchgen.score import metrics as M
from tests.test_robustness import EVAL_ARGS, _cli, train_config, trained  # noqa: F401

#: Candidates of the tiny method (inside the valid region) and of the spray added to them.
VALID, SPRAY = 2, 6


class Configurations:
    """The tiny dataset's scene in Blender: renders any configuration's test and training views."""

    def __init__(self, dataset: Path) -> None:
        from benchgen.render.blender import Renderer
        from benchgen.scene.geometry import build_scene
        from benchgen.scene.spec import load_spec

        self.spec = load_spec(dataset / "spec.yaml")
        self.built = build_scene(self.spec)
        self.renderer = Renderer(self.built, threads=1)
        self.scene = D.load_scene(dataset)
        self.region = D.load_valid_region(dataset, self.scene.num_objects)

    def draw(self, n: int, inside: bool, rng: np.random.Generator) -> list[np.ndarray]:
        """``n`` scale vectors drawn uniformly over the spec's whole scale box (anchor at 1), kept
        when inside the valid region (with the dataset's log margin) or outside it, as asked."""
        lo, hi = self.spec.scale_range
        out: list[np.ndarray] = []
        while len(out) < n:
            s = np.ones(self.scene.num_objects)
            free = np.arange(len(s)) != self.scene.anchor_id
            s[free] = rng.uniform(lo, hi, int(free.sum()))
            if bool(self.region.contains(s[None], self.spec.margin if inside else 0.0)[0]) == inside:
                out.append(s)
        return out

    def write(self, cand: Path, scales: np.ndarray, train: bool = True) -> None:
        """Candidate ``cand`` in the prediction format: every test view, and the training video."""
        for f in self.scene.test_frames:
            out = self.renderer.render(f.camera_to_world, self.built.poses(f.time_index, scales))
            D.write_rgb(cand / "rgb" / f"{f.name}.png", out.rgb8())
            D.write_depth(cand / "depth" / f"{f.name}.exr", out.depth)
            D.write_ids(cand / "ids" / f"{f.name}.png", out.ids)
        if train:
            for f in self.scene.train_frames:
                out = self.renderer.render(f.camera_to_world, self.built.poses(f.time_index, scales))
                D.write_rgb(cand / "train" / "rgb" / f"{f.name}.png", out.rgb8())


def score(pred: Path, dataset: Path, out: Path, *extra: str) -> dict:
    assert benchgen(["score", str(pred), "--data", str(dataset), "--out", str(out), "--quiet", "--no-lpips", *extra]) == 0
    return json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="module")
def spray(tiny_dataset, tmp_path_factory):
    """``(method, spray)`` prediction directories: VALID valid configurations (a method's
    solutions), and the same with SPRAY configurations drawn over the scale box outside the valid
    region added after them."""
    cfg = Configurations(tiny_dataset)
    rng = np.random.default_rng(0)
    valid, sprayed = cfg.draw(VALID, True, rng), cfg.draw(SPRAY, False, rng)
    root = tmp_path_factory.mktemp("spray")
    for name, configs in (("method", valid), ("spray", valid + sprayed)):
        for n, s in enumerate(configs):
            cfg.write(root / name / f"{n:02d}", s)
    return root / "method", root / "spray"


def test_spray_raises_unguarded_best_of_n_but_not_the_guarded(tiny_dataset, spray, tmp_path):
    method_dir, spray_dir = spray
    method = score(method_dir, tiny_dataset, tmp_path / "method")
    sprayed = score(spray_dir, tiny_dataset, tmp_path / "spray")
    # Unguarded, the spray wins: some sprayed configuration resembles the ground truths on the test views.
    assert sprayed["summary"]["psnr"]["mean"] > method["summary"]["psnr"]["mean"] + 1.0
    assert any(r["match_index"] >= VALID for r in sprayed["per_ground_truth"])
    # Guarded, it does not: the valid configurations reproduce the training video exactly, the
    # sprayed ones fall far below it on some training frame, so only the method's own candidates count.
    fm, fs = method["fidelity"], sprayed["fidelity"]
    assert fm["checked"] and fs["checked"]
    assert fm["faithful"] == [True] * VALID and fs["faithful"] == [True] * VALID + [False] * SPRAY
    assert fs["faithful_share"] == pytest.approx(VALID / (VALID + SPRAY))
    assert fs["reference_psnr"] == [M.PSNR_MAX] * len(fs["train_frames"])
    assert min(fs["shortfall_db"][VALID:]) > 10 * F.TOLERANCE_DB and fs["shortfall_db"][:VALID] == [0.0] * VALID
    assert fs["summary"] == fm["summary"] == method["summary"]
    assert [r["match"] for r in fs["per_ground_truth"]] == [r["match"] for r in method["per_ground_truth"]]
    # Precision over faithful candidates counts the sprayed ones against the spray; the curves are monotone.
    for m in (method, sprayed):
        for k in ("ground_truths", "candidates", "ground_truths_faithful", "candidates_faithful"):
            assert np.all(np.diff(m["coverage"][k]) <= 0), k
    assert max(sprayed["coverage"]["candidates_faithful"]) <= VALID / (VALID + SPRAY)
    # The report leads with the guarded figure, before the unguarded table.
    report = (tmp_path / "spray" / "report.md").read_text()
    assert report.index("## Method or spray?") < report.index(f"best of {VALID} faithful") < report.index("(unguarded)")
    assert (tmp_path / "spray" / "coverage.png").is_file()


def test_without_training_renders_fidelity_is_not_checked(tiny_dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    for g in range(3):  # the dataset's own configurations: test views only
        (pred / f"c{g}").mkdir(parents=True)
        for kind in ("rgb", "depth", "ids"):
            (pred / f"c{g}" / kind).symlink_to(tiny_dataset / "configs" / D.config_dirname(g) / kind)
    m = score(pred, tiny_dataset, tmp_path / "out")
    assert m["fidelity"] == {"checked": False, "note": F.NOT_CHECKED}
    assert "fidelity was not checked" in (tmp_path / "out" / "report.md").read_text()
    assert "fidelity was not checked" in capsys.readouterr().out
    # With the training video as their training renders, they are all faithful (120 dB on every frame).
    for g in range(3):
        (pred / f"c{g}" / "train").mkdir()
        (pred / f"c{g}" / "train" / "rgb").symlink_to(tiny_dataset / "train" / "rgb")
    m = score(pred, tiny_dataset, tmp_path / "out")
    assert m["fidelity"]["checked"] and m["fidelity"]["faithful"] == [True] * 3
    assert m["fidelity"]["summary"] == m["summary"]


def test_training_renders_in_some_candidates_only_or_incomplete_are_one_line_errors(tiny_dataset, tmp_path, capsys):
    scene = D.load_scene(tiny_dataset)
    pred = tmp_path / "pred"
    for g in range(2):
        (pred / f"c{g}").mkdir(parents=True)
        for kind in ("rgb", "depth", "ids"):
            (pred / f"c{g}" / kind).symlink_to(tiny_dataset / "configs" / D.config_dirname(g) / kind)
    (pred / "c1" / "train" / "rgb").mkdir(parents=True)
    out = tmp_path / "out"
    args = ["score", str(pred), "--data", str(tiny_dataset), "--out", str(out), "--quiet", "--no-lpips"]
    assert benchgen(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{pred / 'c0' / 'train'}: missing, but {pred / 'c1' / 'train'} exists" in err[0], err
    (pred / "c0" / "train" / "rgb").mkdir(parents=True)
    first = sorted(scene.train_frames, key=lambda f: f.time_index)[0].name
    assert benchgen(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{pred / 'c0' / 'train' / 'rgb' / (first + '.png')}: missing view" in err[0], err
    assert not out.exists()


def test_coverage_and_precision_on_a_hand_built_matrix():
    # 3 candidates x 3 ground truths; the last ground truth has nothing to compare (all views masked).
    matrix = np.array([[20.0, 25.0, np.nan], [30.0, 10.0, np.nan], [15.0, 15.0, np.nan]])
    levels = np.array([10.0, 15.0, 20.0, 25.0, 30.0, 31.0])
    c = COV.curves(matrix, np.array([True, False, True]), levels)
    # Ground truths' best: 30 and 25; candidates' best: 25, 30, 15.
    assert c["ground_truths"] == [1.0, 1.0, 1.0, 1.0, 0.5, 0.0]
    assert c["candidates"] == pytest.approx([1.0, 1.0, 2 / 3, 2 / 3, 1 / 3, 0.0])
    # Faithful candidates 0 and 2 only: ground truths' best 20 and 25; precision over all three.
    assert c["ground_truths_faithful"] == [1.0, 1.0, 1.0, 0.5, 0.0, 0.0]
    assert c["candidates_faithful"] == pytest.approx([2 / 3, 2 / 3, 1 / 3, 1 / 3, 0.0, 0.0])
    full = COV.curves(matrix)
    assert "ground_truths_faithful" not in full and full["levels"] == COV.LEVELS.tolist()
    for k in ("ground_truths", "candidates"):
        assert np.all(np.diff(full[k]) <= 0) and full[k][0] == 1.0 and full[k][-1] == 0.0


def test_faithful_rule_tolerance_and_flat_floor():
    flat = np.array([12.0, 12.0])
    p = np.array([[30.0, 28.0], [29.5, 27.2], [30.0, 26.5], [11.0, 11.0]])
    rule = F.faithful(p, flat, tolerance_db=1.0)
    assert rule["reference"].tolist() == [30.0, 28.0]
    assert rule["shortfall"].tolist() == pytest.approx([0.0, 0.8, 1.5, 19.0])
    assert rule["faithful"].tolist() == [True, True, False, False]
    # Every candidate equally bad, below a flat colour: none explains the video.
    assert not F.faithful(np.full((3, 2), 11.0), flat)["faithful"].any()
    video = np.zeros((1, 4, 4, 3), np.uint8)
    video[0, :2] = 255
    assert F.flat_psnr(video)[0] == pytest.approx(-10 * np.log10(0.25))  # half black, half white: MSE 1/4
    assert F.frame_psnr(video, video)[0] == M.PSNR_MAX


def test_osn_evaluate_candidates_carry_training_renders(trained, tiny_dataset, tmp_path):
    """``osn evaluate --candidates`` writes every candidate's render of the training video, from
    the run's own training cameras, so that ``benchgen score`` checks its fidelity."""
    cands = tmp_path / "candidates"
    r = _cli("osn", "evaluate", trained, "--data", tiny_dataset, *EVAL_ARGS, "--no-true-scales", "--candidates", cands,
             "--out", tmp_path / "report")
    assert r.returncode == 0, r.stderr[-3000:]
    scene = D.load_scene(tiny_dataset)
    train = sorted(f.name + ".png" for f in scene.train_frames)
    for pred in ("preselected", "highest-score", "centre-of-ranges"):
        for cand in (p for p in (cands / pred).iterdir() if p.is_dir()):
            assert sorted(x.name for x in (cand / "train" / "rgb").iterdir()) == train, cand
    m = score(cands / "preselected", tiny_dataset, tmp_path / "score", "--max-views", "2")  # as evaluated
    f = m["fidelity"]
    assert f["checked"] and f["train_frames"] == [x.removesuffix(".png") for x in train]
    assert len(f["faithful"]) == m["num_candidates"] and f["num_faithful"] == sum(f["faithful"])
    assert len(f["reference_psnr"]) == len(train) and all(np.isfinite(f["reference_psnr"]))
