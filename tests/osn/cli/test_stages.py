"""Resumable stages (osn demo's engine): skip, resume with the time already spent, refuse changed options,
run background work beside the next stages."""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import pytest

from scenecore.cli import UserError
from osn.cli.stages import BackgroundCommand, Stage, run_stages, stage_error


def test_interrupted_stage_resumes_with_its_time_and_refuses_other_options(tmp_path: Path) -> None:
    calls: list[str] = []

    def slow_then_killed() -> dict:
        calls.append("a")
        time.sleep(0.2)
        raise KeyboardInterrupt

    def quick() -> dict:
        calls.append("b")
        return {"ok": True}

    lines: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        run_stages([Stage("s", "first try", slow_then_killed, {"n": 1})], tmp_path, lines.append)
    started = json.loads((tmp_path / ".done" / "s.started.json").read_text())
    assert started["options"] == {"n": 1} and started["seconds"] >= 0.2
    assert not (tmp_path / ".done" / "s.json").exists()
    assert stage_error(tmp_path, "s") == {"type": "KeyboardInterrupt", "message": ""}

    with pytest.raises(UserError, match=r"stage 's' was run with other options \(n 1 -> 2\)"):
        run_stages([Stage("s", "other n", quick, {"n": 2})], tmp_path, lines.append)
    assert calls == ["a"]  # refused before running anything

    rec = run_stages([Stage("s", "second try", quick, {"n": 1})], tmp_path, lines.append)["s"]
    assert rec["seconds"] >= 0.2 and rec["summary"] == {"ok": True} and "resuming after" in lines[-2]
    again = run_stages([Stage("s", "third", quick, {"n": 1})], tmp_path, lines.append)["s"]
    assert again == rec and calls == ["a", "b"] and "already done" in lines[-1]
    assert json.loads((tmp_path / "stages.json").read_text())["s"]["seconds"] == rec["seconds"]
    assert stage_error(tmp_path, "s") is None and stage_error(tmp_path, "never") is None


def test_a_stage_that_fails_records_which_exception_until_it_succeeds(tmp_path: Path) -> None:
    """The record a caller reads instead of the log: the exception's type and message, gone once
    the stage finishes."""
    from scenecore.errors import EmptyValidSet

    def empty() -> dict:
        raise EmptyValidSet("the scale network accepts none of 10 uniform draws")

    with pytest.raises(EmptyValidSet):
        run_stages([Stage("sample", "draw", empty)], tmp_path)
    assert stage_error(tmp_path, "sample") == {"type": "EmptyValidSet",
                                               "message": "the scale network accepts none of 10 uniform draws"}
    run_stages([Stage("sample", "draw", dict)], tmp_path)
    assert stage_error(tmp_path, "sample") is None


def _python(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def test_a_train_stage_recorded_with_options_since_removed_is_done_where_they_held_todays_values(tmp_path: Path) -> None:
    """A demo work directory whose train stage recorded options that are constants now (at their
    value) stays done; one that trained with another value is refused, naming the option."""
    from osn.cli.demo import _flat, recorded_train_options
    from osn.train import TrainConfig

    today = {"inputs": "oracle", **{f"train.{k}": v for k, v in _flat(TrainConfig().to_dict()).items()}}
    old = {**today, "train.free_space": "ordered", "train.edge_rays": 64, "train.field.lr_net": 0.001}
    calls: list[str] = []

    def train() -> dict:
        calls.append("train")
        return {}

    run_stages([Stage("train", "older version", train, old)], tmp_path, lambda _: None)
    lines: list[str] = []
    run_stages([Stage("train", "today", train, today, recorded=recorded_train_options)], tmp_path, lines.append)
    assert calls == ["train"] and "already done" in lines[-1]
    with pytest.raises(UserError, match=r"stage 'train' was run with other options \(train.edge_rays 64 -> None, "):
        run_stages([Stage("train", "no reading", train, today)], tmp_path, lines.append)

    other = tmp_path / "other"
    run_stages([Stage("train", "older version", train, {**old, "train.edge_rays": 32})], other, lambda _: None)
    with pytest.raises(UserError, match=r"stage 'train' was run by an older version \(trained with edge_rays: 32"):
        run_stages([Stage("train", "today", train, today, recorded=recorded_train_options)], other, lines.append)


def test_background_stage_runs_beside_the_next_and_is_waited_for_where_needed(tmp_path: Path) -> None:
    """A real child process: the stage after it runs while it sleeps, the stage that needs it
    starts only once it has written its file, its time is its own, and it runs at the lowest
    CPU priority. A rerun skips it like any finished stage."""
    flag = tmp_path / "flag"
    job = BackgroundCommand(_python(f"import os, time, pathlib; print('niceness', os.nice(0)); time.sleep(0.5); "
                                    f"pathlib.Path({str(flag)!r}).write_text('x')"), tmp_path / "bg.log",
                            lambda: {"wrote": flag.exists()})
    seen: dict[str, bool] = {}

    def beside() -> dict:
        seen["beside"] = flag.exists()
        return {}

    def after() -> dict:  # idles past the job's end: its recorded time must not include this
        deadline = time.monotonic() + 60
        while not flag.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        seen["flag_at"] = time.perf_counter() - t0
        time.sleep(1.0)
        return {}

    lines: list[str] = []
    t0 = time.perf_counter()
    stages = [Stage("bg", "sleep, then write", job.start, background=True), Stage("beside", "b", beside),
              Stage("idle", "i", after), Stage("needing", "n", lambda: seen.update(needing=flag.exists()), needs=("bg",))]
    rec = run_stages(stages, tmp_path / "w", lines.append)
    flag_at = seen.pop("flag_at")
    assert seen == {"beside": False, "needing": True}
    assert list(rec) == ["bg", "beside", "idle", "needing"]
    assert rec["bg"]["background"] and rec["bg"]["summary"] == {"wrote": True}
    # Its own end, not when "needing" waited for it (1 s after the flag): a child at the lowest
    # priority on a loaded machine may take a good part of that second to exit after writing.
    assert 0.5 <= rec["bg"]["seconds"] < flag_at + 1.0
    assert rec["bg"]["waited"] < 0.1  # it had ended during "idle"
    assert any("bg: done in" in ln and "in the background" in ln for ln in lines)
    if shutil.which("nice"):
        assert "niceness 19" in (tmp_path / "bg.log").read_text()
    again = run_stages([Stage("bg", "x", lambda: pytest.fail("rerun"), background=True),
                        Stage("needing", "n", lambda: {}, needs=("bg",))], tmp_path / "w", lines.append)
    assert again["bg"] == rec["bg"]


def test_background_failure_and_foreground_errors(tmp_path: Path) -> None:
    """A failing command stops the job with its log's last line and stays resumable; an error
    in a foreground stage stops a background command still running (it never writes its file)."""
    bad = BackgroundCommand(_python("import sys; print('first'); print('what went wrong'); sys.exit(3)"), tmp_path / "bad.log")
    stages = [Stage("bg", "fails", bad.start, background=True), Stage("needing", "n", dict, needs=("bg",))]
    with pytest.raises(UserError, match=r"bad\.log: .* failed \(exit 3\): what went wrong"):
        run_stages(stages, tmp_path / "a")
    assert (tmp_path / "a" / ".done" / "bg.started.json").exists() and not (tmp_path / "a" / ".done" / "bg.json").exists()

    flag = tmp_path / "flag"
    ready = tmp_path / "ready"
    # It ignores SIGINT, as a command started from a non-interactive shell's background job does.
    slow = BackgroundCommand(_python(f"import signal, time, pathlib; signal.signal(signal.SIGINT, signal.SIG_IGN); "
                                     f"pathlib.Path({str(ready)!r}).write_text('x'); time.sleep(3); "
                                     f"pathlib.Path({str(flag)!r}).write_text('x')"), tmp_path / "slow.log")

    def broken() -> dict:
        deadline = time.monotonic() + 60
        while not ready.exists() and time.monotonic() < deadline:  # the command ignores SIGINT by now
            time.sleep(0.01)
        raise RuntimeError("foreground failed")

    with pytest.raises(RuntimeError, match="foreground failed"):
        run_stages([Stage("bg", "slow", slow.start, background=True), Stage("broken", "b", broken)], tmp_path / "b")
    assert not slow.running() and slow.ended is not None
    time.sleep(3.5)
    assert not flag.exists()

    with pytest.raises(ValueError, match=r"stage 'x' needs \['bg'\], which are not earlier background stages"):
        run_stages([Stage("x", "x", dict, needs=("bg",)), Stage("bg", "later", slow.start, background=True)], tmp_path / "c")
