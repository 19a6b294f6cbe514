"""`osn demo` itself killed (SIGKILL to its whole process group) inside the train and the evaluate
stage, then the same command again: the rerun resumes the killed stage and its ``metrics.json``
equals an uninterrupted demo's, value by value (wall times aside). All stages, at random moments:
``benchmarks/bench_kill_demo.py``."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import pytest
import torch

from tests.osn.cli.conftest import TINY_DEMO, run_tiny_demo

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[3]
# Wall times in metrics.json (osn/evaluate/bestofn.py, osn/evaluate/report.py); everything else must be equal.
TIMING = ("timings.", "train_seconds", "curves.search_seconds_per_view_vs_n.")
ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}
_demo = run_tiny_demo


def _flat(x: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(x, (dict, list)):
        return {prefix[:-1]: x}
    out: dict[str, Any] = {}
    for k, v in (x.items() if isinstance(x, dict) else enumerate(x)):
        out.update(_flat(v, f"{prefix}{k}."))
    return out


def _metrics(work: Path) -> dict[str, Any]:
    m = _flat(json.loads((work / "report" / "metrics.json").read_text()))
    # The command and the provenance's locations name the demo's own --work (digests are of contents).
    m = {k: v.replace(str(work), "WORK") if isinstance(v, str) else v for k, v in m.items()}
    return {k: v for k, v in m.items() if not k.startswith(TIMING)}


def _assert_same_metrics(ref: Path, work: Path) -> None:
    a, b = _metrics(ref), _metrics(work)
    assert len(a) > 1000 and set(a) == set(b), sorted(set(a) ^ set(b))[:10]
    differ = [k for k in a if not (a[k] == b[k] and type(a[k]) is type(b[k])
                                   or isinstance(a[k], float) and math.isnan(a[k]) and math.isnan(b[k]))]
    assert not differ, [(k, a[k], b[k]) for k in differ[:10]]


def _kill_demo_when(work: Path, ready: Callable[[str], bool], timeout: float = 600) -> None:
    """Start the demo on ``work``; SIGKILL its process group once ``ready(stdout so far)`` is true."""
    log = work.parent / "killed.log"
    with open(log, "w") as f:
        proc = subprocess.Popen([sys.executable, *TINY_DEMO, "--work", str(work)], cwd=ROOT, env=ENV, stdout=f,
                                stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + timeout
    try:
        while proc.poll() is None and time.monotonic() < deadline and not ready(log.read_text()):
            time.sleep(0.005)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the demo ended before it could be killed:\n" + log.read_text()[-2000:]


def _files(d: Path) -> set[str]:
    return {str(p.relative_to(d)) for p in d.rglob("*") if p.is_file()}


@pytest.fixture
def reference(tiny_demo: Path) -> Path:
    """An uninterrupted demo."""
    return tiny_demo


def test_demo_killed_in_train_resumes_to_equal_metrics(reference: Path, tmp_path: Path) -> None:
    """Killed right after training's first checkpoint: the rerun skips generate and preprocess,
    resumes training from that checkpoint, and every number equals the uninterrupted demo's."""
    work = tmp_path / "work"
    ckpt = work / "run" / "checkpoint.pt"
    _kill_demo_when(work, lambda out: ckpt.exists())
    assert not (work / ".done" / "train.json").exists(), "train finished before the kill"
    killed_at = torch.load(ckpt, weights_only=True)["iteration"]
    total = json.loads((reference / "run" / "metrics.jsonl").read_text().splitlines()[-1])["iteration"]
    assert 0 < killed_at < total

    r = _demo(work)
    assert r.returncode == 0, r.stderr[-3000:]
    # generate and preprocess; the ground truth, rendering beside training, was killed with the
    # demo (it is in its process group) unless it had finished
    assert "[1/8] generate: already done" in r.stdout and "[2/8] preprocess: already done" in r.stdout
    assert "[4/8] train: train per-object fields" in r.stdout and "(resuming after" in r.stdout
    _assert_same_metrics(reference, work)
    # The training curve too: the same iterations and values, no line twice (wall time aside).
    curve = [[{k: v for k, v in json.loads(ln).items() if k != "wall_time"} for ln in (d / "run" / "metrics.jsonl").read_text().splitlines()]
             for d in (reference, work)]
    assert curve[0] == curve[1]


def test_demo_killed_in_evaluate_resumes_to_equal_metrics(reference: Path, tmp_path: Path) -> None:
    """The reference up to its sample stage (what evaluate, export and addon wrote is removed), then
    the demo killed 0.5 s into evaluate's best-of-N search: no report, and the rerun's metrics.json
    and its report and candidate files equal the uninterrupted demo's."""
    work = tmp_path / "work"
    shutil.copytree(reference, work, symlinks=True)
    for stage in ("evaluate", "export", "addon"):
        for marker in (work / ".done").glob(f"{stage}.*"):
            marker.unlink()
    for d in ("report", "candidates", "export"):
        shutil.rmtree(work / d)
    for f in (*work.glob("*.zip"), work / "stages.json"):
        f.unlink()

    _kill_demo_when(work, lambda out: "\nevaluate: " in out and time.sleep(0.5) is None)
    assert (work / ".done" / "evaluate.started.json").exists()
    assert not (work / ".done" / "evaluate.json").exists() and not (work / "report" / "metrics.json").exists()

    r = _demo(work)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.count("already done") == 5  # generate, preprocess, ground-truth, train, sample
    assert "[6/8] evaluate: best-of-N evaluation" in r.stdout and "(resuming after" in r.stdout
    _assert_same_metrics(reference, work)
    for d in ("report", "candidates"):
        assert _files(reference / d) == _files(work / d), d
