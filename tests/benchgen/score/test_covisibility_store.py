"""Co-visibility masks stored in the dataset (``configs/GGG/covisibility.npz``): written by
``benchgen generate``, read by ``benchgen score`` (older datasets without them still score, with a
note), checked by ``benchgen validate`` and recomputed by ``benchgen verify``; on the real ``tiny``
dataset."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

from scenecore import dataset as D
from benchgen.cli import main as benchgen
from benchgen.score import covisibility as C
from benchgen.score.truth import evaluated_views, load_truth


def copy_dataset(tiny_dataset: Path, to: Path, masks: bool = True) -> Path:
    shutil.copytree(tiny_dataset, to)
    if not masks:
        for g in range(D.load_scene(to).num_configurations):
            D.covisibility_path(to, g).unlink()
    return to


def make_pred(dataset: Path, root: Path) -> Path:
    """Three candidates: symlinks to the dataset's configurations, in reverse order."""
    root.mkdir(parents=True)
    for name, g in (("a", 2), ("b", 1), ("c", 0)):
        (root / name).symlink_to(dataset / "configs" / D.config_dirname(g))
    return root


def score(pred: Path, dataset: Path, out: Path) -> int:
    return benchgen(["score", str(pred), "--data", str(dataset), "--out", str(out), "--quiet", "--no-lpips"])


def test_stored_masks_equal_the_masks_computed_on_the_fly(tiny_dataset):
    scene = D.load_scene(tiny_dataset)
    frames = D.covisibility_frames(scene)
    assert [f.name for f in frames] == [f.name for f in evaluated_views(scene)]
    _, t_depth, t_ids = D.read_training_video(tiny_dataset, scene)
    for c in D.load_configurations(tiny_dataset, scene):
        stored = D.read_covisibility(tiny_dataset, scene, c.index)
        depth, ids = zip(*(D.read_frame(tiny_dataset, f.name, c.index)[1:] for f in frames))
        fresh = C.configuration_masks(scene, c.scales, frames, np.stack(depth), np.stack(ids), t_depth, t_ids)
        assert stored.masks.dtype == bool and np.array_equal(stored.masks, fresh)
        assert (stored.version, stored.rtol) == (C.RULE_VERSION, C.DEPTH_RTOL)
        assert 0.2 < fresh.mean() < 1.0  # masks that mask something, and keep most pixels
    # The scorer's ground truth, with and without the stored masks (a subset of views too).
    for views in (0, 4):
        a, b = load_truth(tiny_dataset, views), load_truth(tiny_dataset, views, stored_masks=False)
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.masked_rgb, b.masked_rgb)
        assert a.masks_note == "" and "computed on the fly for 3 of 3 configurations" in b.masks_note


def test_a_dataset_without_stored_masks_scores_identically_with_a_note(tiny_dataset, tmp_path, capsys):
    new = copy_dataset(tiny_dataset, tmp_path / "new")
    old = copy_dataset(tiny_dataset, tmp_path / "old", masks=False)
    assert benchgen(["validate", str(old)]) == 0  # a dataset from before the masks were stored is valid
    results = {}
    for name, data in (("new", new), ("old", old)):
        capsys.readouterr()
        assert score(make_pred(data, tmp_path / f"pred_{name}"), data, tmp_path / f"out_{name}") == 0
        out = tmp_path / f"out_{name}"
        results[name] = (json.loads((out / "metrics.json").read_text()), np.load(out / "psnr_matrix.npy"),
                         (out / "report.md").read_text(), capsys.readouterr().out)
    (m_new, mat_new, rep_new, out_new), (m_old, mat_old, rep_old, out_old) = results["new"], results["old"]
    assert np.array_equal(mat_new, mat_old)
    assert m_new["per_ground_truth"] == m_old["per_ground_truth"] and m_new["summary"] == m_old["summary"]
    assert m_new["covisible_fraction"] == m_old["covisible_fraction"]
    note = ("co-visibility masks computed on the fly for 3 of 3 configurations: the dataset stores none (written "
            "before 'benchgen generate' stored them; rerunning it with the same options adds them)")
    assert (m_new["covisibility_masks"], m_new["covisibility_note"]) == ("stored", "")
    assert (m_old["covisibility_masks"], m_old["covisibility_note"]) == ("computed", note)
    assert [line for line in rep_old.splitlines() if "co-visibility masks" in line] == [f"Note: {note}."]
    assert "computed on the fly" not in rep_new and "computed on the fly" not in out_new
    assert f"note: {note}" in out_old.splitlines()


def test_rerunning_generate_adds_the_masks_to_an_older_dataset(tiny_dataset, tmp_path):
    from benchgen.render.generate import generate
    from benchgen.scene.spec import load_preset

    old = copy_dataset(tiny_dataset, tmp_path / "old", masks=False)
    summary = generate(load_preset("tiny"), old, progress=False)
    assert summary.frames_rendered == 0 and any("co-visibility masks stored for 3" in n for n in summary.notes)
    for g in range(3):
        assert D.covisibility_path(old, g).read_bytes() == D.covisibility_path(tiny_dataset, g).read_bytes()


def _write_npz(path: Path, **arrays: np.ndarray) -> None:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    path.write_bytes(buf.getvalue())


def _break(data: Path, case: str) -> Path:
    """Break configuration 001's mask file in one way; returns its path."""
    path = D.covisibility_path(data, 1)
    scene = D.load_scene(data)
    with np.load(path) as z:
        good = {k: z[k] for k in z.files}
    if case == "not a zip":
        path.write_bytes(b"this is not an npz file")
    elif case == "truncated":
        path.write_bytes(path.read_bytes()[:-40])
    elif case == "wrong size":  # masks of a 16x16 image: 32 bytes per view instead of 128
        _write_npz(path, **{**good, "masks": good["masks"][:, :32]})
    elif case == "missing view":
        _write_npz(path, **{**good, "masks": good["masks"][:-1], "views": good["views"][:-1]})
    elif case == "views out of order":
        _write_npz(path, **{**good, "views": good["views"][::-1].copy()})
    elif case == "huge declared shape":  # a small file whose masks header declares 128 GiB
        header = io.BytesIO()
        np.lib.format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": (1 << 30, 128)})
        _write_npz(path, **{k: v for k, v in good.items() if k != "masks"})
        with zipfile.ZipFile(path, "a") as zf:
            zf.writestr("masks.npy", header.getvalue() + bytes(64))
    elif case == "extra member":
        _write_npz(path, **good, extra=np.zeros(3))
    elif case == "a directory":
        path.unlink()
        path.mkdir()
    assert len(scene.test_frames) == len(good["views"])
    return path


CASES = ["not a zip", "truncated", "wrong size", "missing view", "views out of order", "huge declared shape",
         "extra member", "a directory"]


@pytest.mark.parametrize("case", CASES)
def test_a_corrupt_or_wrong_size_mask_file_is_one_line(tiny_dataset, tmp_path, capsys, case):
    data = copy_dataset(tiny_dataset, tmp_path / "data")
    path = _break(data, case)
    capsys.readouterr()
    assert score(make_pred(data, tmp_path / "pred"), data, tmp_path / "out") == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("benchgen: error: ") and str(path) in err[0], err
    assert not (tmp_path / "out").exists()  # nothing half-written
    # validate names the same file (and nothing else).
    assert benchgen(["validate", str(data)]) == 1
    problems = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert len(problems) == 1 and str(path) in problems[0], problems


def test_validate_wants_masks_for_every_configuration_or_none(tiny_dataset, tmp_path, capsys):
    data = copy_dataset(tiny_dataset, tmp_path / "data")
    D.covisibility_path(data, 2).unlink()
    capsys.readouterr()
    assert benchgen(["validate", str(data)]) == 1
    problems = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert len(problems) == 1 and str(D.covisibility_path(data, 2)) in problems[0] and "missing" in problems[0]


def test_verify_catches_a_tampered_mask(tiny_dataset, tmp_path, capsys):
    data = copy_dataset(tiny_dataset, tmp_path / "data")
    scene = D.load_scene(data)
    stored = D.read_covisibility(data, scene, 2)
    masks = stored.masks.copy()
    masks[3, 10, 12] ^= True  # one pixel of one view: still a well-formed file
    D.write_covisibility(data, 2, scene, masks, stored.version, stored.rtol)
    assert benchgen(["validate", str(data)]) == 0
    capsys.readouterr()
    assert benchgen(["verify", str(data), "--quiet"]) == 1
    out = capsys.readouterr().out
    view = D.covisibility_frames(scene)[3].name
    failed = [line for line in out.splitlines() if "FAILED" in line]
    assert len(failed) == 1 and "configuration 002" in failed[0] and f"view {view}" in failed[0], out
    assert "in 1 pixel(s)" in failed[0]
    v = D.load_verification(data)
    assert not v["passed"] and [c["covisibility"] for c in v["configurations"]] == ["match", "match", "differs"]
    assert [c["passed"] for c in v["configurations"]] == [True, True, False]
    # Put back: verify passes again and records every configuration's masks as matching.
    D.write_covisibility(data, 2, scene, stored.masks, stored.version, stored.rtol)
    assert benchgen(["verify", str(data), "--quiet"]) == 0
    assert D.load_verification(data)["covisibility_masks"] == "match"


def test_exact_float32_products_equal_the_float64_errors_bit_for_bit(tiny_dataset):
    """8-bit candidates are scored in float32 blocks (bestofn._sse_8bit): the same squared errors as
    the float64 products, bit for bit, at extreme values and at sizes that leave partial blocks."""
    import torch

    from benchgen.score import bestofn

    rng = np.random.default_rng(0)
    for P, G in ((33001, 3), (1000, 5)):  # more pixels than one block of squares; 3P not a multiple of 256
        mask = rng.random((G, P)) < 0.8
        mask[0] = True
        y8 = (np.where(rng.random((G, 3 * P)) < 0.5, 255, rng.integers(0, 256, (G, 3 * P))) * np.repeat(mask, 3, 1)).astype(np.uint8)
        x8 = rng.integers(0, 256, (4, 3 * P)).astype(np.uint8)
        x8[0], x8[1] = 255, 0
        y2 = np.einsum("gp,gp->g", y8, y8, dtype=np.float64)
        x = torch.from_numpy(x8.astype(np.float64) * 257)
        sq = x.square().reshape(4, -1, 3).sum(-1)
        expected = sq @ torch.from_numpy(mask).double().T - 2 * 257 * (x @ torch.from_numpy(y8).double().T) + 257**2 * torch.from_numpy(y2)
        assert torch.equal(bestofn._sse_8bit(x8, y8, mask, y2), expected)
    # On the dataset: the PSNR of the whole pass is the same either way.
    truth = load_truth(tiny_dataset)
    rgbs = [np.clip(truth.views(g)[0].astype(int) + rng.integers(-30, 31, truth.views(g)[0].shape), 0, 255).astype(np.uint8)
            for g in range(3)]
    try:
        bestofn.EXACT_FLOAT32 = False
        slow = bestofn.view_psnr(rgbs, truth)
    finally:
        bestofn.EXACT_FLOAT32 = True
    assert np.array_equal(bestofn.view_psnr(rgbs, truth), slow, equal_nan=True)
