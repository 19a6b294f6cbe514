"""Resumable stages (osn demo's engine): skip, resume with the time already spent, refuse changed options."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

from scenecore.cli import UserError
from osn.cli.stages import Stage, run_stages


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

    with pytest.raises(UserError, match=r"stage 's' was run with other options \(n 1 -> 2\)"):
        run_stages([Stage("s", "other n", quick, {"n": 2})], tmp_path, lines.append)
    assert calls == ["a"]  # refused before running anything

    rec = run_stages([Stage("s", "second try", quick, {"n": 1})], tmp_path, lines.append)["s"]
    assert rec["seconds"] >= 0.2 and rec["summary"] == {"ok": True} and "resuming after" in lines[-2]
    again = run_stages([Stage("s", "third", quick, {"n": 1})], tmp_path, lines.append)["s"]
    assert again == rec and calls == ["a", "b"] and "already done" in lines[-1]
    assert json.loads((tmp_path / "stages.json").read_text())["s"]["seconds"] == rec["seconds"]
