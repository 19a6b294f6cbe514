"""Shared fixtures. ``tiny_dataset``: the real ``tiny`` benchgen preset (room + 2 objects, 32x32,
3 frames), rendered once per test session (a few seconds with Cycles)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    from benchgen.render.generate import generate
    from benchgen.scene.spec import load_preset

    root = tmp_path_factory.mktemp("tiny_dataset") / "ds"
    summary = generate(load_preset("tiny"), root, progress=False)
    assert summary.passed, summary.lines()
    return root
