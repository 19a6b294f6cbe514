"""The ablation's verdict columns: a family's paired difference against the default's own spread."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_ablation import ablation_tables, beyond_spread, default_spread  # noqa: E402


def _run(config: str, seed: int, train_seed: int, iou: float, best_psnr: float = 20.0) -> dict:
    return {"config": config, "seed": seed, "train_seed": train_seed, "iou": iou, "precision": 1.0, "recall": iou,
            "best_psnr": best_psnr, "train_seconds": 100.0, "seconds": 1.0, "source": "colmap"}


def test_a_difference_counts_only_beyond_the_defaults_spread_on_its_scene():
    runs = [_run("default", 0, 0, 0.70), _run("default", 0, 1, 0.60), _run("default", 0, 2, 0.66),  # spread 0.10
            _run("default", 1, 0, 0.80, 21.0), _run("default", 1, 1, 0.79, 20.5),                   # spread 0.01 (0.5 dB)
            _run("default", 2, 0, 0.50),                                                             # one seed: none
            _run("free-space", 0, 0, 0.65, 19.0), _run("free-space", 1, 0, 0.70, 20.0),
            _run("final-scale-phase", 0, 0, 0.85), _run("final-scale-phase", 1, 0, 0.795, 21.2)]
    spread = default_spread(runs)  # keyed by bench_heldout.scene_key: (0, seed)
    assert spread == pytest.approx({(0, 0): 0.10, (0, 1): 0.01})
    # scene 0: -0.05 inside 0.10; scene 1: -0.10 beyond 0.01
    assert beyond_spread({(0, 0): -0.05, (0, 1): -0.10}, spread) == "lower 1, higher 0 of 2"
    assert beyond_spread({(0, 0): 0.15, (0, 1): -0.005}, spread) == "lower 0, higher 1 of 2"
    assert beyond_spread({(0, 2): -0.5}, spread) == "-"  # no spread measured on that scene
    tables = ablation_tables(runs, ["default", "free-space", "final-scale-phase"])
    rows = {r[0]: r for r in tables["departures"]["rows"]}
    # The default's row averages the seeds the families share (0), not its extra spread seeds.
    assert rows["default"][2] == "0.700 / 0.800 / 0.500"
    assert rows["without free-space"][4] == "-0.075 ± 0.035" and rows["without free-space"][5] == "lower 1, higher 0 of 2"
    assert rows["without final-scale-phase"][5] == "lower 0, higher 1 of 2"
    # Best of N's PSNR paired the same way: -1 dB on both scenes; scene 0's default spread is 0 dB,
    # scene 1's 0.5 dB, so both count.
    assert rows["without free-space"][7] == "-1.00 ± 0.00 (lower 2, higher 0 of 2)"
    assert rows["without final-scale-phase"][7] == "+0.10 ± 0.14 (lower 0, higher 0 of 2)"  # +0.2 dB: inside 0.5
    assert rows["default's spread"][2] == "0.100 / 0.010 / -"
    # Two training seeds: a scene's IoU is their mean, its verdict the mean of its paired differences.
    runs2 = [*runs, _run("free-space", 0, 1, 0.50, 19.0), _run("free-space", 1, 1, 0.79, 20.5)]
    rows2 = {r[0]: r for r in ablation_tables(runs2, ["default", "free-space"])["departures"]["rows"]}
    assert rows2["default"][2] == "0.650 / 0.795 / 0.500"  # seeds 0 and 1 (scene 2: seed 0 alone)
    assert rows2["without free-space"][2] == "0.575 / 0.745"
    # scene 0: (-0.05 - 0.10) / 2 inside its spread 0.10; scene 1: (-0.10 + 0) / 2 beyond 0.01
    assert rows2["without free-space"][5] == "lower 1, higher 0 of 2"
    assert tables["departures_short"]["columns"][-2:] == ["scenes beyond the default's spread", "best of N PSNR - default's (dB; scenes beyond its spread)"]


def test_finished_only_starts_no_run_and_lists_what_is_missing(tmp_path: Path) -> None:
    """A queue stopped early: ``--finished-only`` trains nothing and names the runs it lacks."""
    import json
    import subprocess

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "ablation.json"
    proc = subprocess.run([sys.executable, str(root / "benchmarks" / "bench_ablation.py"), "--root", str(tmp_path / "abl"),
                           "--base", "cur", "--seed-list", "0", "--families", "free-space", "--finished-only",
                           "--out", str(out)], capture_output=True, text=True, cwd=root, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "not run (2, --finished-only): default scene 0 training seed 0; free-space scene 0 training seed 0" in proc.stdout
    assert not (tmp_path / "abl" / "random-0").exists()  # no run started from the (absent) base
    assert json.loads(out.read_text())["data"]["not_run"] == ["default scene 0 training seed 0",
                                                                "free-space scene 0 training seed 0"]


def test_finished_only_keeps_the_finished_runs_and_names_the_rest(tmp_path: Path) -> None:
    """A queue stopped part-way: the run whose training finished is kept (its evaluation resumes from
    the SfM base run's inputs); the one that did not is named, not started."""
    from bench_ablation import plan_runs

    from tests.test_bench_seed_work import _base

    _base(tmp_path, "cur-colmap", {"sfm_resolution": 768})
    done = tmp_path / "random-0" / "abl-default-s0-colmap" / ".done"
    done.mkdir(parents=True)
    (done / "train.json").write_text("{}")
    jobs, not_run = plan_runs(tmp_path, "cur", "colmap", ["default", "free-space"], [0], [], [0], finished_only=True)
    assert [(name, t, seed, label, extra) for name, t, seed, _, label, extra in jobs] == [
        ("default", 0, 0, "abl-default-s0", ["--sfm-resolution", "768"])]
    assert not_run == ["free-space scene 0 training seed 0"]
    assert not (tmp_path / "random-0" / "abl-free-space-s0-colmap").exists()
    assert (tmp_path / "random-0" / "abl-default-s0-colmap" / ".done" / "train.json").read_text() == "{}"  # kept as it was
    # Without --finished-only both run; the free-space run starts from the base's inputs.
    jobs, not_run = plan_runs(tmp_path, "cur", "colmap", ["default", "free-space"], [0], [], [0], finished_only=False)
    assert [j[0] for j in jobs] == ["default", "free-space"] and not_run == []
    assert (tmp_path / "random-0" / "abl-free-space-s0-colmap" / "sfm" / "inputs.npz").read_bytes() == b"sfm"
    assert "w_free: 0.0" in (tmp_path / "ablation-configs" / "free-space-s0.yaml").read_text()
