"""A held-out run whose sampler found nothing: a result read from its records, not a crash."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_heldout import finished_figures, tables  # noqa: E402
from osn.cli.stages import Stage, run_stages  # noqa: E402
from scenecore.scale_space import learned_intervals  # noqa: E402

def _trained_then(work: Path, stage: str, run) -> None:
    """A demo work directory whose training finished and whose stage ``stage`` ran ``run``
    through the stage runner ``osn demo`` uses."""
    (work / ".done").mkdir(parents=True)
    (work / "run").mkdir()
    (work / ".done" / "train.json").write_text(json.dumps({"seconds": 71.2, "summary": {"psnr": 25.6, "iou": 0.0}}))
    (work / "run" / "metrics.jsonl").write_text(
        json.dumps({"iteration": 700, "iou": 0.2, "precision": 0.5, "recall": 0.1}) + "\n"
        + json.dumps({"iteration": 1400, "iou": 0.01, "precision": 0.9, "recall": 0.005}) + "\n"
        + json.dumps({"iteration": 1400, "psnr": 25.6}) + "\n")
    with pytest.raises(Exception):
        run_stages([Stage(stage, "a stage", run)], work, echo=lambda line: None)


def _accepting_nothing() -> dict:
    """The learned intervals' search (the sampler's and the export's) on a scale network whose
    logit is -1e9 everywhere."""
    layers = [(np.eye(2), np.zeros(2)), (np.ones((1, 2)), np.array([-1e9]))]
    learned_intervals(layers, np.array([[1.0, 1.0], [0.5, 2.0], [0.5, 2.0]]), 0, draws=500)
    return {}


@pytest.mark.parametrize("stage", ["sample", "export"])
def test_a_run_whose_learned_set_holds_nothing_reports_the_monitors_last_figures(tmp_path: Path, stage: str) -> None:
    _trained_then(tmp_path / "random-1000" / "paper-colmap", stage, _accepting_nothing)
    r = finished_figures(tmp_path, 1000, "paper", "colmap")
    assert (r["iou"], r["precision"], r["recall"]) == (0.01, 0.9, 0.005)  # the last record with valid-set figures
    assert r["best_minus_highest_db"] is None and r["train_seconds"] == 71.2
    assert r["note"].startswith("no valid configuration (valid-set figures from the training monitor): "
                                "the scale network accepts none")
    row = tables([{**r, "config": "paper"}])["heldout_pooled"]["rows"][0]
    assert row[:4] == ["paper", "colmap", "1", "0.010"] and row[6] == "- (0 of 1)"  # no best of N to average


def test_a_run_that_failed_otherwise_is_not_read_as_finished(tmp_path: Path) -> None:
    def missing() -> dict:
        raise FileNotFoundError("spec.yaml: missing file")

    _trained_then(tmp_path / "random-1000" / "paper-colmap", "sample", missing)
    assert finished_figures(tmp_path, 1000, "paper", "colmap") is None


def test_the_short_table_keeps_the_set_the_renders_and_the_time() -> None:
    run = {"seed": 1000, "source": "colmap", "iou": 0.5, "precision": 0.6, "recall": 0.7, "best_minus_highest_db": 2.0,
           "scale_error": 0.2, "train_psnr": 28.0, "train_seconds": 150.0, "config": "defaults"}
    t = tables([run, {**run, "seed": 1001, "iou": 0.3}])
    assert t["heldout_short"]["columns"] == ["config", "inputs", "seeds", "IoU", "best of N - highest score (dB)",
                                             "training time (s)", "worst seed's IoU"]
    assert t["heldout_short"]["rows"] == [["defaults", "colmap", "2", "0.400 ± 0.141", "+2.00 ± 0.00", "150 ± 0", "0.300"]]
