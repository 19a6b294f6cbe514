"""A benchmark run started from a base run's inputs: what it links, and the arguments its records need."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_heldout import seed_work  # noqa: E402


def _base(root: Path, name: str, preprocess_options: dict) -> Path:
    scene = root / "random-0"
    (scene / "dataset").mkdir(parents=True, exist_ok=True)
    base = scene / name
    (base / ".done").mkdir(parents=True)
    for stage in ("generate", "preprocess", "ground-truth"):
        (base / ".done" / f"{stage}.json").write_text(json.dumps({"seconds": 1.0}))
    (base / ".done" / "preprocess.started.json").write_text(json.dumps({"options": preprocess_options}))
    for d in ("sfm", "oracle"):
        (base / d).mkdir()
        (base / d / "inputs.npz").write_bytes(d.encode())
    (base / ".done" / "train.json").write_text("{}")  # downstream: never copied
    return base


def test_an_oracle_run_starts_from_the_sfm_base_with_its_sfm_video_size(tmp_path: Path) -> None:
    base = _base(tmp_path, "cur-colmap", {"sfm_resolution": 768, "training_frames": "benchmark"})
    extra = seed_work(tmp_path, 0, "cur", "abl-default-s0", "oracle", prefer_sfm=True)
    # Without it, osn demo would see other preprocess options (no SfM video) and refuse to resume.
    assert extra == ["--sfm-resolution", "768"]
    run = tmp_path / "random-0" / "abl-default-s0-oracle"
    assert sorted(p.name for p in (run / ".done").iterdir()) == ["generate.json", "ground-truth.json", "preprocess.json",
                                                                  "preprocess.started.json"]
    assert (run / "oracle" / "inputs.npz").read_bytes() == b"oracle"
    assert (run / "oracle" / "inputs.npz").stat().st_ino == (base / "oracle" / "inputs.npz").stat().st_ino  # linked
    assert (run / "dataset").resolve() == (tmp_path / "random-0" / "dataset").resolve()
    # Started once: a second call keeps what the run has done since.
    (run / ".done" / "train.started.json").write_text("{}")
    assert seed_work(tmp_path, 0, "cur", "abl-default-s0", "oracle", prefer_sfm=True) == extra
    assert (run / ".done" / "train.started.json").is_file()


def test_a_base_on_the_benchmarks_own_frames_needs_no_arguments_and_a_missing_base_stops(tmp_path: Path) -> None:
    _base(tmp_path, "cur-oracle", {"drop_occluding": "training"})
    assert seed_work(tmp_path, 0, "cur", "next", "oracle") == []
    # No SfM base run to prefer: the run starts from its own source's.
    assert seed_work(tmp_path, 0, "cur", "next2", "oracle", prefer_sfm=True) == []
    assert (tmp_path / "random-0" / "next2-oracle" / "oracle" / "inputs.npz").read_bytes() == b"oracle"
    with pytest.raises(SystemExit, match="cur-colmap: no finished inputs"):
        seed_work(tmp_path, 0, "cur", "next3", "colmap", prefer_sfm=True)
