"""The SfM consistency check on a real small reconstruction, and on the same reconstruction broken:
frames rotated, depths scrambled, a trajectory mirrored. Nothing here reads ground truth but the
render itself (the check never does)."""

from __future__ import annotations

import copy
import logging

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from scenecore import dataset as D
from osn.evaluate.report import _consistency_lines
from osn.preprocess import video
from osn.preprocess.consistency import ObjectObservations, assess_scene, consistent_core, frame_medians, frame_points
from osn.preprocess.inputs import IGNORE_ID, save_inputs
from osn.preprocess.sfm import ObjectRegistrationError, PreprocessConfig
from tests.osn.preprocess.test_sfm import sfm_scene  # noqa: F401  (the fixture: a render SfM registers)

pytestmark = pytest.mark.slow

BALL, BLOCK, ROOM = 1, 2, 0


@pytest.fixture(scope="module")
def scene(sfm_scene) -> dict:
    """The tiny preset's room, ball and block over 8 frames at 128 px, and its real per-object SfM."""
    root = sfm_scene
    sc = D.load_scene(root)
    images, _, masks = D.read_training_video(root, sc)
    names = {o.id: o.name for o in sc.objects}
    cfg = PreprocessConfig(on_failure="skip")
    results = video.reconstruct_objects(images, masks, sc.intrinsics.matrix(), names, sc.anchor_id, cfg, workers=2)
    assert all(not isinstance(r, Exception) for r in results.values()), results
    return {"images": images, "masks": masks, "K": sc.intrinsics.matrix(), "timestamps": sc.timestamps.copy(),
            "names": names, "anchor": sc.anchor_id, "cfg": cfg, "results": results}


def _rotated(results: dict, oid: int, slots: list[int], degrees: float, axis: str = "x") -> dict:
    """A copy of ``results`` with object ``oid``'s cameras turned by ``degrees`` at ``slots``."""
    out = copy.deepcopy(results)
    R = Rotation.from_euler(axis, degrees, degrees=True).as_matrix()
    for n in slots:
        out[oid].cam_to_obj[n, :3, :3] = out[oid].cam_to_obj[n, :3, :3] @ R
    return out


def _preprocess(scene: dict, results: dict, monkeypatch):
    """``preprocess_video`` on the scene's video, its SfM replaced by ``results``."""
    monkeypatch.setattr(video, "reconstruct_objects", lambda *a, **k: results)
    return video.preprocess_video(scene["images"], scene["masks"], scene["K"], scene["timestamps"], scene["names"],
                                  scene["anchor"], scene["cfg"])


def _assess(scene: dict, results: dict) -> dict:
    obs = [ObjectObservations(k, r.frames, r.cam_to_obj, r.sparse_pix, r.sparse_depth, r.reprojection_error_px)
           for k, r in results.items()]
    return assess_scene(obs, scene["masks"], scene["K"], scene["timestamps"], scene["anchor"], 3, scene["names"])


def test_a_correct_reconstruction_is_not_flagged(scene, monkeypatch):
    verdicts = _assess(scene, scene["results"])
    assert set(verdicts) == {ROOM, BALL, BLOCK}
    for v in verdicts.values():
        rec = v.record()
        assert rec["verdict"] == "consistent" and rec["action"] == "keep" and not rec["message"], rec
        # Far from every threshold: points on their masks, depths agreeing to a fraction of a percent.
        assert rec["mask_miss"] <= 0.02 and rec["depth_disagreement"] < 0.2 * rec["depth_disagreement_threshold"], rec
        assert all(k < 5.0 for k in rec["frame_orientation_kink_deg"].values()), rec
    inputs, report = _preprocess(scene, scene["results"], monkeypatch)
    assert report.dropped == [] and inputs.meta["untrusted_depths"] == []
    for o in inputs.objects:
        # SfM's frames, and those it left the object unposed in, bridged (the block's last three here).
        bridged = inputs.meta["bridged_frames"].get(str(o.id), [])
        assert sorted([*scene["results"][o.id].frames, *bridged]) == list(o.frames)
        assert sum(len(d) for d in o.sparse_depth) > 0
    assert all(r["consistency"]["verdict"] == "consistent" for r in report.objects)
    assert not any("SfM inconsistent" in line for line in video.report_lines(report.objects))


def test_frames_turned_18_degrees_are_found_and_dropped(scene, monkeypatch, caplog):
    broken = _rotated(scene["results"], BALL, [1, 3], 18.0)
    verdicts = _assess(scene, broken)
    ball = verdicts[BALL].record()
    assert "masks" in ball["reasons"] and ball["bad_frames"] == [1, 3] and ball["action"] == "repair", ball
    assert min(ball["frame_mask_miss"]["1"], ball["frame_mask_miss"]["3"]) > 0.9
    assert max(m for t, m in ball["frame_mask_miss"].items() if t not in ("1", "3")) < 0.1
    # The ball's orientation in the room jumps at the turned frames: the anchor's cameras disagree.
    assert ball["frame_orientation_kink_deg"]["1"] > 15.0
    # No false alarm on the objects left as SfM made them.
    assert verdicts[ROOM].action == "keep" and verdicts[BLOCK].action == "keep"
    with caplog.at_level(logging.WARNING, logger="osn.preprocess.video"):
        inputs, report = _preprocess(scene, broken, monkeypatch)
    assert list(inputs.object(BALL).frames) == list(range(8)) and inputs.meta["bridged_frames"]["1"] == [1, 3]
    assert list(inputs.object(BLOCK).frames) == [*scene["results"][BLOCK].frames, *inputs.meta["bridged_frames"]["2"]]
    (warning,) = [r.getMessage() for r in caplog.records if "SfM inconsistent" in r.getMessage()]
    assert "\n" not in warning and "object 1 (ball)" in warning and "(1, 3)" in warning and "dropped" in warning
    entry = next(r for r in report.objects if r["id"] == BALL)
    assert entry["registered_frames"] == 6 and entry["consistency"]["action"] == "repair"
    assert any(line.strip().startswith("repair: object 1 (ball)") for line in video.report_lines(report.objects))


def test_scrambled_depths_train_without_depths(scene, monkeypatch, tmp_path):
    broken = copy.deepcopy(scene["results"])
    rng = np.random.default_rng(0)
    broken[BLOCK].sparse_depth = [d * rng.uniform(0.8, 1.2, len(d)) for d in broken[BLOCK].sparse_depth]
    verdicts = _assess(scene, broken)
    block = verdicts[BLOCK].record()
    assert block["reasons"] == ["depths"] and block["action"] == "no_depth", block
    assert block["depth_disagreement"] > 0.05 > block["depth_disagreement_threshold"]
    assert verdicts[ROOM].action == "keep" and verdicts[BALL].action == "keep"
    inputs, report = _preprocess(scene, broken, monkeypatch)
    assert inputs.meta["untrusted_depths"] == [BLOCK]
    assert sum(len(d) for d in inputs.object(BLOCK).sparse_depth) == 0  # poses kept, depths not trained on
    assert np.array_equal(inputs.object(BLOCK).frames, scene["results"][BLOCK].frames)
    assert all(sum(len(d) for d in inputs.object(k).sparse_depth) > 0 for k in (ROOM, BALL))
    # The run's report says so, from the inputs the run trained on.
    run = tmp_path / "run"
    save_inputs(run / "inputs", inputs)
    lines = _consistency_lines(run)
    assert len([line for line in lines if line.startswith("- no_depth: object 2 (block)")]) == 1, lines


def test_a_likely_reversed_model_is_named_in_the_warnings_and_the_runs_report(scene, monkeypatch, caplog, tmp_path):
    """A model whose depth-reversed twin fits better (``twin`` from SfM, test_sfm.py builds one) is
    trained as found, and named: a warning, the report's lines, the inputs' meta, the run's report."""
    named = copy.deepcopy(scene["results"])
    named[BALL].twin = {**named[BALL].twin, "fits_better": True, "twin_better_share": 0.8}
    with caplog.at_level(logging.WARNING, logger="osn.preprocess.video"):
        inputs, report = _preprocess(scene, named, monkeypatch)
    assert np.array_equal(inputs.object(BALL).cam_to_obj, _preprocess(scene, scene["results"], monkeypatch)[0].object(BALL).cam_to_obj)
    assert list(inputs.meta["likely_reversed"]) == [str(BALL)]
    assert any("object 1 (ball)" in r.getMessage() and "likely depth-reversed" in r.getMessage() for r in caplog.records)
    assert any("object 1 (ball)" in line and "80%" in line for line in video.report_lines(report.objects))
    run = tmp_path / "run"
    save_inputs(run / "inputs", inputs)
    assert [line for line in _consistency_lines(run) if "likely depth-reversed" in line][0].startswith("- likely depth-reversed: object 1 (ball)")
    assert scene["results"][ROOM].twin["fits_better"] is False  # no false alarm on the real models


def test_a_mirrored_trajectory_drops_the_object(scene, monkeypatch, caplog):
    broken = copy.deepcopy(scene["results"])
    flip = np.diag([1.0, 1.0, -1.0, 1.0])  # the ball's cameras reflected through its first frame's image plane
    broken[BALL].cam_to_obj = flip @ broken[BALL].cam_to_obj @ flip
    with caplog.at_level(logging.WARNING, logger="osn.preprocess.video"):
        inputs, report = _preprocess(scene, broken, monkeypatch)
    assert report.dropped == [BALL] and BALL not in [o.id for o in inputs.objects]
    assert not np.any(inputs.masks == BALL) and np.any(inputs.masks == IGNORE_ID)
    entry = next(r for r in report.objects if r["id"] == BALL)
    assert entry["consistency"]["action"] == "drop" and "training without it" in entry["error"]
    assert any("object 1 (ball)" in r.getMessage() and "not used" in r.getMessage() for r in caplog.records)
    assert all(next(r for r in report.objects if r["id"] == k)["consistency"]["action"] == "keep" for k in (ROOM, BLOCK))


def _spun(results: dict, oid: int, K: np.ndarray, degrees: tuple[float, float], seed: int = 0) -> dict:
    """A copy of ``results`` with object ``oid``'s model turned about the centre of its points by a
    random rotation of ``degrees`` (low, high) per frame. For a ball every frame's points stay on
    its surface, so its silhouettes and depths keep agreeing; its orientation in the room does not."""
    out = copy.deepcopy(results)
    r = out[oid]
    centre = np.median(np.concatenate(frame_points(r.cam_to_obj, r.sparse_pix, r.sparse_depth, K)), axis=0)
    rng = np.random.default_rng(seed)
    for n in range(len(r.frames)):
        axis = rng.normal(size=3)
        turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(*degrees))).as_matrix()
        Q = np.eye(4)
        Q[:3, :3], Q[:3, 3] = turn, centre - turn @ centre
        r.cam_to_obj[n] = Q @ r.cam_to_obj[n]
    return out


def test_a_model_spinning_against_the_anchor_is_named(scene, monkeypatch, caplog, tmp_path):
    """The ball's model turned about its centre by 4-8 degrees per frame: wrong as a whole (a round
    object's spin), yet its points stay on its masks and its depths agree; its orientation against
    the room's cameras jumps in every frame, which names it. A spin leaves a ball's shape right, so
    it trains as found, named in the warning and the run's report."""
    broken = _spun(scene["results"], BALL, scene["K"], (4.0, 8.0))
    ball = _assess(scene, broken)[BALL].record()
    assert ball["reasons"] == ["orientation"] and ball["action"] == "keep", ball
    assert ball["mask_miss"] < ball["mask_miss_threshold"] and ball["depth_disagreement"] < ball["depth_disagreement_threshold"]
    good = _assess(scene, scene["results"])[BALL].record()  # the ball as SfM made it
    assert ball["orientation_kink_deg"] > ball["orientation_kink_threshold_deg"] > 2 * good["orientation_kink_deg"], (ball, good)
    assert good["reasons"] == [] and good["action"] == "keep"
    with caplog.at_level(logging.WARNING, logger="osn.preprocess.video"):
        inputs, report = _preprocess(scene, broken, monkeypatch)
    assert report.dropped == [] and set(broken[BALL].frames) <= set(inputs.object(BALL).frames)
    (warning,) = [r.getMessage() for r in caplog.records if "SfM inconsistent" in r.getMessage()]
    assert "\n" not in warning and "object 1 (ball)" in warning and "orientation" in warning and "trained as found" in warning
    assert any(line.strip().startswith("keep: object 1 (ball)") for line in video.report_lines(report.objects))
    run = tmp_path / "run"
    save_inputs(run / "inputs", inputs)
    assert [line for line in _consistency_lines(run) if line.startswith("- keep: object 1 (ball)")], _consistency_lines(run)


def test_an_anchor_contradicted_in_most_frames_stops(scene, monkeypatch):
    broken = _rotated(scene["results"], ROOM, [0, 2, 4, 6], 18.0, "y")
    with pytest.raises(ObjectRegistrationError, match=r"object 0 \(room\).*anchor cannot be dropped"):
        _preprocess(scene, broken, monkeypatch)


def test_frame_medians_skip_untested_pairs():
    pairs = np.array([[np.nan, 0.1, np.nan], [0.3, np.nan, 0.9], [np.nan, 0.5, np.nan]])
    assert np.allclose(frame_medians(pairs), [0.2, 0.45, 0.7])
    assert np.isnan(frame_medians(np.full((2, 2), np.nan))).all()


def test_consistent_core_peels_the_frames_that_disagree_with_the_rest():
    pairs = np.full((6, 6), 0.01)
    pairs[[1, 4], :] = pairs[:, [1, 4]] = 0.3  # two frames disagree with every other
    np.fill_diagonal(pairs, np.nan)
    assert list(np.flatnonzero(~consistent_core(pairs, 0.05))) == [1, 4]
    assert consistent_core(pairs, 0.5).all()
    assert consistent_core(np.where(np.isnan(pairs), np.nan, 0.3), 0.05).sum() == 2  # no core: all disagree
