"""Provenance of a score (``benchgen score`` and ``osn evaluate``): the digests of every file read,
``benchgen score --check``, and the refusal of an unverified dataset, on the real ``tiny`` dataset."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

import benchgen
from scenecore import dataset as D
from benchgen.cli import main as benchgen_main
from benchgen.score import digests as G
from benchgen.score import provenance as P
from benchgen.score.lpips import default_weights_path
from benchgen.score.truth import evaluated_views

REPO = Path(__file__).resolve().parents[3]


def make_pred(dataset: Path, root: Path, names: dict[str, int]) -> Path:
    """A prediction directory whose candidate ``name`` is a copy of ``configs/GGG``, with a method.json."""
    root.mkdir(parents=True)
    for name, g in names.items():
        shutil.copytree(dataset / "configs" / D.config_dirname(g), root / name)
    (root / "method.json").write_text(json.dumps({"name": "copies"}))
    return root


def score(pred: Path, dataset: Path, out: Path, *extra: str) -> int:
    return benchgen_main(["score", str(pred), "--data", str(dataset), "--out", str(out), "--quiet", *extra])


def check(metrics: Path, *extra: str) -> int:
    return benchgen_main(["score", "--check", str(metrics), *extra])


def one_pixel(path: Path) -> None:
    """Change one pixel of a PNG by one grey level (the file is re-encoded)."""
    a = np.array(Image.open(path))
    a[3, 4, 0] ^= 1
    Image.fromarray(a).save(path)


def _digests(pred: Path, dataset: Path, views: list[str], workers: int = 1) -> tuple[dict, dict]:
    """Records of the prediction and the ground-truth file sets (the scene read from the tiny
    dataset's copy's original: a byte flipped in scene.json must not change which files are read)."""
    scene = D.load_scene(dataset.parent / "scene-kept") if (dataset.parent / "scene-kept").exists() else D.load_scene(dataset)
    gt = G.hash_groups(dataset, P.ground_truth_groups(dataset, scene, views, True), G.DATASET_LISTING, workers).record()
    pr = G.hash_groups(pred, P.prediction_groups(pred), G.PREDICTIONS_LISTING, workers).record()
    return pr, gt


def test_digests_are_stable_and_change_with_any_byte_of_any_file(tiny_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    (tmp_path / "scene-kept").mkdir()
    shutil.copy(data / "scene.json", tmp_path / "scene-kept")
    pred = make_pred(data, tmp_path / "pred", {"a": 0, "b": 1})
    views = [f.name for f in evaluated_views(D.load_scene(data), 4)]
    pr, gt = _digests(pred, data, views)
    assert (pr, gt) == _digests(pred, data, views) == _digests(pred, data, views, workers=2)
    # Paths are relative to the candidate: a copy of configs/GGG has that configuration's digest
    # over all its test views.
    all_views = [f.name for f in evaluated_views(D.load_scene(data))]
    assert _digests(pred, data, all_views)[1]["groups"]["configs/000"] == pr["groups"]["a"]
    assert set(pr["groups"]) == {"method.json", "a", "b"} and pr["files"] == 1 + 2 * len(list((pred / "a").rglob("*.*")))
    assert set(gt["groups"]) == {"scene.json", "verification.json", "valid_region.json", "train", "configs/000",
                                 "configs/001", "configs/002"}
    # One file's digest is hashlib's over its bytes.
    files = G.hash_groups(pred, {"b": None}, "x").files
    assert files["b/rgb/v00_t01.png"] == hashlib.sha256((pred / "b/rgb/v00_t01.png").read_bytes()).hexdigest()

    rng = np.random.default_rng(0)
    scene = D.load_scene(data)
    for root, which in ((pred, 0), (data, 1)):
        rec = (pr, gt)[which]
        groups = P.ground_truth_groups(data, scene, views, True) if which else P.prediction_groups(pred)
        listed = G.hash_groups(root, groups, "x").files
        assert len(listed) == rec["files"]
        for rel in listed:  # one byte of each file flipped, at a random place
            path = root / rel
            raw = path.read_bytes()
            k = int(rng.integers(len(raw)))
            path.write_bytes(raw[:k] + bytes([raw[k] ^ 0x01]) + raw[k + 1:])
            now = _digests(pred, data, views)[which]
            path.write_bytes(raw)
            assert now["sha256"] != rec["sha256"], rel
            changed = [g for g in rec["groups"] if now["groups"][g] != rec["groups"][g]]
            assert len(changed) == 1 and (rel == changed[0] or rel.startswith(changed[0] + "/")), (rel, changed)
    assert _digests(pred, data, views) == (pr, gt)
    # A renamed file changes its candidate's digest as well.
    (pred / "b/rgb/v00_t01.png").rename(pred / "b/rgb/v00_t01x.png")
    assert _digests(pred, data, views)[0]["groups"]["b"] != pr["groups"]["b"]


def test_a_fifo_among_the_predictions_is_refused_in_one_line(tiny_dataset, tmp_path, capsys):
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"a": 0})
    os.mkfifo(pred / "a" / "notes.fifo")
    assert score(pred, tiny_dataset, tmp_path / "out", "--no-lpips") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(pred / "a" / "notes.fifo") in err[0] and "not a regular file" in err[0], err
    assert not (tmp_path / "out").exists()


def test_metrics_json_records_digests_protocol_scorer_and_per_view_metrics(tiny_dataset, tmp_path):
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"a": 0, "b": 2})
    noisy = pred / "b" / "rgb"
    rng = np.random.default_rng(1)
    for p in sorted(noisy.iterdir()):  # b is no longer an exact copy: finite per-view PSNRs
        a = np.array(Image.open(p))
        a[..., :3] = np.clip(a[..., :3].astype(int) + rng.integers(-9, 10, a[..., :3].shape), 0, 255)
        Image.fromarray(a).save(p)
    out = tmp_path / "out"
    assert score(pred, tiny_dataset, out, "--max-views", "4") == 0
    m = json.loads((out / "metrics.json").read_text())
    prov = m["provenance"]
    listing = G.parse_listing((out / "predictions.sha256").read_bytes(), out)
    assert prov["predictions"]["sha256"] == G.set_digest(listing) == hashlib.sha256(
        (out / "predictions.sha256").read_bytes()).hexdigest()
    for rel, h in listing.items():
        assert hashlib.sha256((pred / rel).read_bytes()).hexdigest() == h
    assert set(prov["predictions"]["groups"]) == {"a", "b", "method.json"}
    # The ground truth: the files the score read, the four evaluated views and no other.
    gt = G.parse_listing((out / "dataset.sha256").read_bytes(), out)
    views = m["views"]
    assert len(views) == 4 and prov["protocol"]["views"] == views and prov["protocol"]["max_views"] == 4
    expect = {"scene.json", "verification.json"} | {
        p.relative_to(tiny_dataset).as_posix() for f in D.load_scene(tiny_dataset).train_frames
        for p in D.frame_paths(tiny_dataset, f.name).all()}
    for g in range(3):
        masks = tiny_dataset / "configs" / f"{g:03d}" / "covisibility.npz"  # stored masks, when generated with them
        expect |= {f"configs/{g:03d}/config.json"} | ({masks.relative_to(tiny_dataset).as_posix()} if masks.exists() else set()) | {
            p.relative_to(tiny_dataset).as_posix() for v in views for p in D.frame_paths(tiny_dataset, v, g).all()}
    assert set(gt) == expect and prov["ground_truth"]["sha256"] == G.set_digest(gt)
    assert prov["verification"] == {"verified": True, "problem": None, "scored_unverified": False}
    proto = prov["protocol"]
    assert proto["name"] == P.PROTOCOL_NAME and proto["version"] == P.PROTOCOL_VERSION and proto["mask"]["depth_rtol"] > 0
    assert proto["metrics"]["ssim"]["sigma"] == 1.5 and proto["metrics"]["ssim"]["k2"] == 0.03
    assert proto["metrics"]["lpips"]["weights_sha256"] == hashlib.sha256(default_weights_path().read_bytes()).hexdigest()
    assert set(proto["metrics"]) == set(m["summary"])
    assert prov["scorer"]["version"] == benchgen.__version__ and "git" in prov["scorer"]
    # Per-view raw metrics of every match, whose means are the reported ones.
    for r in m["per_ground_truth"]:
        assert set(r["per_view"]) == set(m["summary"])
        for k, values in r["per_view"].items():
            assert len(values) == 4
            assert np.mean(values) == pytest.approx(r[k], rel=1e-12, abs=1e-12), k
    assert max(m["per_ground_truth"][2]["per_view"]["psnr"]) < 60  # b's noisy views
    report = (out / "report.md").read_text()
    assert "## Provenance" in report and prov["predictions"]["sha256"] in report and "Unverified" not in report


def test_check_passes_on_an_untouched_result_and_names_the_changed_file(tiny_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    pred = make_pred(data, tmp_path / "pred", {"a": 0, "b": 1})
    out = tmp_path / "out"
    assert score(pred, data, out, "--no-lpips") == 0
    capsys.readouterr()
    metrics = out / "metrics.json"
    assert check(metrics) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == f"{metrics}: every recorded digest matches the files"

    view = json.loads(metrics.read_text())["views"][5]
    for changed in (pred / "b" / "rgb" / f"{view}.png", data / "configs" / "002" / "rgb" / f"{view}.png"):
        raw = changed.read_bytes()
        one_pixel(changed)
        assert check(metrics) == 1
        io = capsys.readouterr()
        lines = [ln for ln in io.out.splitlines() if not ln.startswith("note:")]
        assert len(lines) == 1 and lines[0].startswith(f"{changed}: contents differ"), io.out
        assert "1 difference" in io.err
        changed.write_bytes(raw)
        assert check(metrics) == 0
        capsys.readouterr()

    # A candidate added, a file removed: one line each.
    shutil.copytree(pred / "a", pred / "c")
    (pred / "a" / "ids" / f"{view}.png").unlink()
    assert check(metrics) == 1
    lines = [ln for ln in capsys.readouterr().out.splitlines() if not ln.startswith("note:")]
    assert sorted(lines) == sorted([f"{pred / 'c'}: not in the scored predictions (added since)",
                                    f"{pred / 'a' / 'ids' / view}.png: missing (scored, sha256 "
                                    + G.parse_listing((out / 'predictions.sha256').read_bytes(), out)[
                                        f"a/ids/{view}.png"][:12] + "...)"]), lines
    shutil.rmtree(pred / "c")
    shutil.copy(data / "configs" / "000" / "ids" / f"{view}.png", pred / "a" / "ids" / f"{view}.png")

    # The listings: gone, the groups are still checked (a note); edited, a difference.
    listing = out / "predictions.sha256"
    raw = listing.read_bytes()
    listing.unlink()
    assert check(metrics) == 0 and "note: " in capsys.readouterr().out
    one_pixel(pred / "b" / "rgb" / f"{view}.png")
    assert check(metrics) == 1
    assert f"{pred / 'b'}: contents differ from the scored predictions" in capsys.readouterr().out
    shutil.copy(data / "configs" / "001" / "rgb" / f"{view}.png", pred / "b" / "rgb" / f"{view}.png")
    listing.write_bytes(raw.replace(b"  a/", b"  A/", 1))
    assert check(metrics) == 1
    assert f"{listing}: does not match metrics.json's digest" in capsys.readouterr().out
    listing.write_bytes(raw)
    assert check(metrics) == 0
    capsys.readouterr()

    # Moved elsewhere: PRED and --data say where the files are now.
    shutil.move(pred, tmp_path / "moved-pred")
    shutil.move(data, tmp_path / "moved-data")
    assert check(metrics) == 1
    capsys.readouterr()
    assert check(metrics, str(tmp_path / "moved-pred"), "--data", str(tmp_path / "moved-data")) == 0


@pytest.mark.parametrize("case", ["missing", "failed", "other configurations"])
def test_unverified_dataset_is_refused_in_one_line_and_scored_only_when_forced(tiny_dataset, tmp_path, capsys, case):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    ver = data / "verification.json"
    if case == "missing":
        ver.unlink()
    elif case == "failed":
        v = json.loads(ver.read_text())
        v["passed"], v["configurations"][1]["passed"] = False, False
        v["configurations"][1]["failures"] = ["training frame v00_t01: interior pixels differ by 0.01 > 0.0001"]
        ver.write_text(json.dumps(v))
    else:  # configuration 002 rescaled after verification
        cfg = data / "configs" / "002" / "config.json"
        c = json.loads(cfg.read_text())
        c["scales"] = [s * 1.01 for s in c["scales"]]
        cfg.write_text(json.dumps(c))
    pred = make_pred(tiny_dataset, tmp_path / "pred", {"a": 0})
    out = tmp_path / "out"
    assert score(pred, data, out, "--no-lpips") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(ver) in err[0] and "--unverified" in err[0], err
    assert {"missing": "missing", "failed": "configuration 001: training frame v00_t01",
            "other configurations": "configuration 002's verified scales differ"}[case] in err[0]
    assert not out.exists()

    assert score(pred, data, out, "--no-lpips", "--unverified") == 0
    m = json.loads((out / "metrics.json").read_text())
    v = m["provenance"]["verification"]
    assert v["verified"] is False and v["scored_unverified"] is True and str(ver) in v["problem"]
    assert "--unverified" in m["command"]
    report = (out / "report.md").read_text()
    assert "**Unverified dataset, scored with `--unverified`:**" in report and "NOT verified" in report


def _cli(tool: str, *args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", f"{tool}.cli", *map(str, args)], cwd=REPO, capture_output=True,
                          text=True, timeout=600)


def test_osn_evaluate_records_the_same_provenance_and_refuses_unverified_data(tiny_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    (data / "verification.json").unlink()
    r = _cli("osn", "evaluate", tmp_path / "no-run", "--data", data, "--out", tmp_path / "refused")
    err = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(err) == 1 and str(data / "verification.json") in err[0], r.stderr
    assert not (tmp_path / "refused").exists()

    from tests.test_robustness import TINY_TRAIN

    cfg = tmp_path / "tiny-train.yaml"
    cfg.write_text(yaml.safe_dump(TINY_TRAIN))
    run = tmp_path / "run"
    for args in (("train", "--data", tiny_dataset, "--out", run, "--config", cfg), ("sample", run, "-n", "12")):
        r = _cli("osn", *args)
        assert r.returncode == 0, r.stderr[-2000:]
    report, cands = tmp_path / "report", tmp_path / "cands"
    r = _cli("osn", "evaluate", run, "--data", data, "--out", report, "--candidates", cands, "--unverified",
             "--no-lpips", "--max-views", "2", "--levels", "4", "--topk", "1", "--no-true-scales")
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((report / "metrics.json").read_text())
    prov = m["extra"]["provenance"]
    assert prov["verification"]["scored_unverified"] and "Unverified dataset" in (report / "report.md").read_text()
    assert "valid_region.json" in prov["ground_truth"]["groups"]  # osn evaluate reads the region
    assert prov["predictions"]["sets"] == ["preselected", "highest-score", "centre-of-ranges"]
    assert prov["protocol"]["views"] == m["extra"]["views"]
    assert all(len(row["per_view"]["psnr"]) == 2 for row in m["per_gt"])
    r = _cli("benchgen", "score", "--check", report / "metrics.json")
    assert r.returncode == 0, r.stdout + r.stderr
    one_pixel(cands / "highest-score" / "highest-score" / "rgb" / f"{m['extra']['views'][0]}.png")
    r = _cli("benchgen", "score", "--check", report / "metrics.json")
    assert r.returncode == 1 and f"{cands / 'highest-score' / 'highest-score' / 'rgb'}" in r.stdout, r.stdout


def test_file_digest_equals_sha256_at_every_size_and_refuses_a_file_that_changed(tmp_path, monkeypatch):
    """The digest is the file's SHA-256 at sizes around the read piece; a file that grew or shrank
    between being opened and read (simulated by the size recorded at opening) is one error naming
    it, for the digest and for the scorer's reader alike."""
    from scenecore.dataset import images

    rng = np.random.default_rng(0)
    for n in (0, 1, G.CHUNK - 1, G.CHUNK, G.CHUNK + 1, 2 * G.CHUNK + 7):
        f = tmp_path / f"f{n}"
        data = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
        f.write_bytes(data)
        assert G.file_sha256(f) == G.file_sha256(str(f)) == hashlib.sha256(data).hexdigest()
        if n:
            assert D.read_regular(f, n) == data
    real = images._open_regular
    for delta in (-1, 1):  # recorded one byte short: the file grew; one byte over: it shrank
        monkeypatch.setattr(images, "_open_regular", lambda p, d=delta: (lambda fh, size: (fh, size + d))(*real(p)))
        for n in (1, G.CHUNK + 1):
            f = tmp_path / f"f{n}"
            with pytest.raises(D.DatasetError, match=f"{f}: changed size while being read"):
                G.file_sha256(f)
            with pytest.raises(D.DatasetError, match=f"{f}: changed size while being read"):
                D.read_regular(f, 10 * n)
