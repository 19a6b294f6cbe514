"""``tiny_demo``: one uninterrupted ``osn demo`` on the ``tiny`` preset (oracle inputs, a short
schedule), shared by the tests that read a finished demo and those that kill one and compare."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
TINY_DEMO = ["-m", "osn.cli", "demo", "--preset", "tiny", "--inputs-from", "oracle", "--field-iterations", "150", "-n", "60",
             "--max-views", "3", "--workers", "1"]


def run_tiny_demo(work: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    """``osn demo`` with :data:`TINY_DEMO`'s options on ``work``, output captured."""
    return subprocess.run([sys.executable, *TINY_DEMO, "--work", str(work)], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"})


@pytest.fixture(scope="session")
def tiny_demo(tmp_path_factory) -> Path:
    """The work directory of a finished demo. Tests read it or copy it; a rerun on it must find
    every stage done (it changes nothing)."""
    work = tmp_path_factory.mktemp("tiny_demo") / "work"
    r = run_tiny_demo(work)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "best of 60" in r.stdout and "report:" in r.stdout
    return work
