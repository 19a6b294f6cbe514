"""One writer per output (scenecore/lock.py): real command lines on the same output at once.

For ``benchgen generate``, ``osn train``, ``osn export`` and ``osn demo``: the first process is
started and, once it holds its output's lock, stopped (SIGSTOP, so the second surely runs while
it is mid-way); the second on the same output exits 2 with one line naming the first's pid and
writes nothing; the first, continued, completes with correct outputs. A lock left by a process
killed with ``kill -9`` is taken over by the next run, which completes. ``osn evaluate``,
``benchgen score`` and ``benchgen verify`` are refused the same way while another process holds
their output.

Cost: the tiny preset and the tiny training schedule; the export runs on the training test's
run; the export and the demo are stopped, refused, then killed and finished by the next run
(that the second writes nothing shows the first is unharmed without waiting for it to end).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import pytest
import torch
import yaml

from scenecore.cli import UserError
from scenecore.dataset import load_verification, validate
from scenecore.export_format import read_export
from scenecore.lock import read_holder
from tests.test_robustness import REPO, TINY_TOTAL, TINY_TRAIN, _assert_user_error, _cli, _cli_many, _cmd

DEMO = ["demo", "--preset", "tiny", "--inputs-from", "oracle", "-n", "5", "--max-views", "1", "--workers", "1"]


def _start(log: Path, tool: str, *args: str | Path) -> subprocess.Popen:
    """``python -m TOOL.cli ARGS`` in its own process group, its output in ``log``."""
    with open(log, "w") as f:
        return subprocess.Popen(_cmd(tool, *args), cwd=REPO, start_new_session=True, stdout=f, stderr=subprocess.STDOUT)


def _wait_holding(proc: subprocess.Popen, out: Path, log: Path, also: Callable[[], bool] = lambda: True,
                  timeout: float = 120) -> None:
    """Until ``proc`` holds ``out``'s lock (its record names it) and ``also()``."""
    deadline = time.monotonic() + timeout
    while (read_holder(out) or {}).get("pid") != proc.pid or not also():
        assert proc.poll() is None, f"exited {proc.returncode} without being seen holding {out}:\n{log.read_text()[-2000:]}"
        assert time.monotonic() < deadline, f"{out}: never locked by pid {proc.pid}"
        time.sleep(0.01)


def _signal(proc: subprocess.Popen, sig: int) -> None:
    """Signal ``proc``'s process group while ``proc`` has not been reaped (its pid is still ours)."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)


def _kill(proc: subprocess.Popen) -> None:
    """``kill -9`` of the process and its children; its lock file stays behind, stale."""
    _signal(proc, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL


def _finish(proc: subprocess.Popen, log: Path, timeout: float = 300) -> None:
    """Continue a stopped process; it must complete with exit 0."""
    _signal(proc, signal.SIGCONT)
    assert proc.wait(timeout) == 0, log.read_text()[-3000:]


def _refused(r: subprocess.CompletedProcess, out: Path, holder: subprocess.Popen, command: str) -> None:
    """Exit 2, one line: ``OUT: in use by pid PID (... COMMAND ...) on HOST; wait for it or stop it``."""
    _assert_user_error(r, out, f"in use by pid {holder.pid} (", command, "; wait for it or stop it")


def _no_locks(*dirs: Path) -> None:
    left = [p for d in dirs for p in d.rglob(".*.lock")]
    assert not left, left


# --------------------------------------------------------------------------------------------
# benchgen generate
# --------------------------------------------------------------------------------------------


def _assert_dataset(out: Path) -> None:
    assert validate(out) == [] and load_verification(out)["passed"]
    assert not [p for p in out.rglob(".*") if p.is_file()], "temporary files left"


def test_second_generate_on_the_same_out_is_refused_and_the_first_completes(tmp_path: Path) -> None:
    """Before, the second's clean-up of a killed run's temporary files deleted the first's live
    ones and the first died."""
    out, log = tmp_path / "ds", tmp_path / "first.log"
    first = _start(log, "benchgen", "generate", "--preset", "tiny", "--out", out, "--quiet")
    try:
        _wait_holding(first, out, log)
        _signal(first, signal.SIGSTOP)
        r = _cli("benchgen", "generate", "--preset", "tiny", "--out", out, "--quiet")
        _refused(r, out, first, "benchgen.cli generate")
        _finish(first, log)
    finally:
        _signal(first, signal.SIGKILL)
    _assert_dataset(out)
    _no_locks(tmp_path)


def test_generate_killed_holding_the_lock_is_taken_over(tmp_path: Path) -> None:
    out, log = tmp_path / "ds", tmp_path / "killed.log"
    first = _start(log, "benchgen", "generate", "--preset", "tiny", "--out", out, "--quiet")
    _wait_holding(first, out, log)
    _kill(first)
    assert read_holder(out)["pid"] == first.pid  # its lock file, stale
    r = _cli("benchgen", "generate", "--preset", "tiny", "--out", out, "--quiet")
    assert r.returncode == 0, r.stderr[-2000:]
    _assert_dataset(out)
    _no_locks(tmp_path)


def test_generate_killed_writing_its_first_file_resumes(tmp_path: Path) -> None:
    """A run killed while writing spec.yaml leaves only that write's temporary file: the next run
    takes the directory for its own (before, it was "not empty and holds no benchgen dataset")."""
    from benchgen.render.generate import _check_output, _remove_stale_temp_files

    out = tmp_path / "ds"
    out.mkdir()
    (out / ".spec.yaml.k2j4x9_a.tmp").write_text("name: ti")
    _check_output(out, "name: tiny\n")
    assert _remove_stale_temp_files(out) == 1 and not any(out.iterdir())
    (out / "notes.txt").write_text("a user's file")
    with pytest.raises(UserError, match="is not empty and holds no benchgen dataset"):
        _check_output(out, "name: tiny\n")


# --------------------------------------------------------------------------------------------
# osn train (new runs and --resume), then osn export of its run
# --------------------------------------------------------------------------------------------


def _assert_run(run: Path, cfg: dict) -> None:
    """One uninterrupted run of ``cfg``: its config, every metric line once, in order, to the end."""
    assert yaml.safe_load((run / "config.yaml").read_text())["stage1_iters"] == cfg["stage1_iters"]
    its = [json.loads(ln)["iteration"] for ln in (run / "metrics.jsonl").read_text().splitlines()]
    assert its == sorted(set(its)) and its[-1] == TINY_TOTAL, its
    assert torch.load(run / "checkpoint.pt", weights_only=True)["iteration"] == TINY_TOTAL


@pytest.fixture(scope="module")
def configs(tmp_path_factory) -> tuple[Path, Path]:
    """The tiny training config, and another one a second writer would have mixed in."""
    d = tmp_path_factory.mktemp("lock_cfg")
    (d / "tiny.yaml").write_text(yaml.safe_dump(TINY_TRAIN))
    (d / "other.yaml").write_text(yaml.safe_dump({**TINY_TRAIN, "stage1_iters": 3}))
    return d / "tiny.yaml", d / "other.yaml"


@pytest.fixture(scope="module")
def train_race(tiny_dataset: Path, configs: tuple[Path, Path], tmp_path_factory):
    """A training run stopped while it holds its lock; a new run and a ``--resume`` on the same
    ``--out`` meanwhile; then the first continued to its end."""
    d = tmp_path_factory.mktemp("lock_train")
    run, log = d / "run", d / "first.log"
    first = _start(log, "osn", "train", "--data", tiny_dataset, "--out", run, "--config", configs[0])
    try:
        _wait_holding(first, run, log)
        _signal(first, signal.SIGSTOP)
        second = _cli_many([("osn", "train", "--data", tiny_dataset, "--out", run, "--config", configs[1]),
                            ("osn", "train", "--data", tiny_dataset, "--out", run, "--resume")])
        _finish(first, log)
    finally:
        _signal(first, signal.SIGKILL)
    return run, first, second


def test_second_train_on_the_same_out_is_refused_and_the_first_completes(train_race) -> None:
    """Before, both exited 0 with their metric lines interleaved in one metrics.jsonl, and
    config.yaml and checkpoint.pt could come from different runs."""
    run, first, (new, resume) = train_race
    _refused(new, run, first, "osn.cli train")
    _refused(resume, run, first, "osn.cli train")
    _assert_run(run, TINY_TRAIN)
    _no_locks(run.parent)


def test_train_killed_holding_the_lock_is_taken_over(tiny_dataset: Path, configs: tuple[Path, Path], tmp_path: Path) -> None:
    """The next run takes the dead one's lock: ``--resume`` when it left a checkpoint, else a new run."""
    run, log = tmp_path / "run", tmp_path / "killed.log"
    first = _start(log, "osn", "train", "--data", tiny_dataset, "--out", run, "--config", configs[0])
    _wait_holding(first, run, log)
    _kill(first)
    assert read_holder(run)["pid"] == first.pid
    again = ["--resume"] if (run / "checkpoint.pt").exists() else ["--config", configs[0]]
    r = _cli("osn", "train", "--data", tiny_dataset, "--out", run, *again)
    assert r.returncode == 0, r.stderr[-2000:]
    _assert_run(run, TINY_TRAIN)
    _no_locks(tmp_path)


def _assert_export(out: Path, samples: int) -> None:
    e = read_export(str(out))  # every file present with its recorded checksum
    assert e.samples is not None and len(e.samples) == samples
    assert not list(out.parent.glob(f".{out.name}.*.partial")) and not list(out.parent.glob(f".{out.name}.old-*"))


def _snapshot(d: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``d`` (hidden ones included) with its size and modification time."""
    return {str(p.relative_to(d)): (p.stat().st_size, p.stat().st_mtime_ns) for p in d.rglob("*")}


def _refused_while_stopped_then_kill(first: subprocess.Popen, out: Path, log: Path, second: tuple, command: str,
                                     tree: Path, also: Callable[[], bool] = lambda: True) -> None:
    """Stop ``first`` once it holds ``out``'s lock (and ``also()``); the ``second`` command line is
    refused and changes nothing under ``tree``; then ``kill -9`` ``first``, its lock left stale."""
    try:
        _wait_holding(first, out, log, also, timeout=300)
        _signal(first, signal.SIGSTOP)
        before = _snapshot(tree)
        _refused(_cli(*second), out, first, command)
        assert _snapshot(tree) == before
    finally:
        _signal(first, signal.SIGKILL)
        first.wait()
    assert first.returncode == -signal.SIGKILL and read_holder(out)["pid"] == first.pid


def test_second_export_to_the_same_out_is_refused_and_a_killed_export_is_taken_over(train_race, tmp_path: Path) -> None:
    """The first export, stopped while it holds its lock: a second one to the same ``--out`` is
    refused and touches nothing beside it. Before, an export's clean-up of a killed export's
    temporary directories could delete another export's live one. The first is then killed
    (its lock left stale) and the next export takes the lock over and completes."""
    run = train_race[0]
    out, log = tmp_path / "export", tmp_path / "first.log"
    first = _start(log, "osn", "export", run, "--out", out, "-n", "5")
    _refused_while_stopped_then_kill(first, out, log, ("osn", "export", run, "--out", out, "-n", "7"),
                                     "osn.cli export", tmp_path)
    r = _cli("osn", "export", run, "--out", out, "-n", "7")
    assert r.returncode == 0, r.stderr[-2000:]
    _assert_export(out, 7)
    _no_locks(tmp_path)


def test_evaluate_score_and_verify_are_refused_while_their_output_is_in_use(train_race, tiny_dataset: Path,
                                                                           tmp_path: Path) -> None:
    """``osn evaluate --out``, ``benchgen score --out`` and ``benchgen verify DATASET`` (which
    rewrites its verification.json) while another process holds that output."""
    report, score = tmp_path / "report", tmp_path / "score"
    holder_code = ("import sys, contextlib\nfrom scenecore.lock import output_lock\n"
                   "with contextlib.ExitStack() as s:\n    [s.enter_context(output_lock(p)) for p in sys.argv[1:]]\n"
                   "    print('held', flush=True); sys.stdin.read()")
    holder = subprocess.Popen([sys.executable, "-c", holder_code, report, score, tiny_dataset], cwd=REPO,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "held\n"
        ev, sc, ve = _cli_many([("osn", "evaluate", train_race[0], "--data", tiny_dataset, "--out", report, "--no-lpips"),
                                ("benchgen", "score", tmp_path, "--data", tiny_dataset, "--out", score),
                                ("benchgen", "verify", tiny_dataset, "--quiet")])
    finally:
        holder.communicate("")
    for r, out in ((ev, report), (sc, score), (ve, tiny_dataset)):
        _refused(r, out, holder, "python")
    assert not report.exists() and not score.exists()


# --------------------------------------------------------------------------------------------
# osn demo: the whole work directory; its own background `benchgen generate` is not refused
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_second_demo_on_the_same_work_is_refused_and_a_killed_demo_is_taken_over(configs: tuple[Path, Path],
                                                                                 tmp_path: Path) -> None:
    """The first demo, stopped once training has written a checkpoint: a second demo on the same
    ``--work`` is refused and touches nothing. Before, it took the first's live stages for killed ones and ran them
    all again beside it. The first is then killed with its background child (the locks it held
    are left stale) and the next demo takes them over, resumes, and completes: report, export and
    add-on, its own background ``benchgen generate`` (which locks the dataset it writes) included."""
    work, log = tmp_path / "work", tmp_path / "first.log"
    demo = [*DEMO, "--config", configs[0], "--work", work]
    first = _start(log, "osn", *demo)
    _refused_while_stopped_then_kill(first, work, log, ("osn", *demo), "osn.cli demo", tmp_path,
                                     also=lambda: (work / "run" / "checkpoint.pt").exists())
    r = _cli("osn", *demo, timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "[1/8] generate: already done" in r.stdout
    assert (work / "report" / "metrics.json").exists() and load_verification(work / "dataset")["passed"]
    read_export(str(work / "export"))
    _no_locks(tmp_path)
