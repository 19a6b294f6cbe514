"""Published files honour the umask (tempfile alone would make every file 0600 and directory 0700)."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

import numpy as np
import pytest

from scenecore import atomic
from scenecore import dataset as D


@pytest.fixture()
def set_umask():
    """Set the process umask for one test; the previous one is restored afterwards."""
    old = os.umask(0o022)
    os.umask(old)
    yield os.umask
    os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask, file_mode, dir_mode", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700), (0o002, 0o664, 0o775)])
def test_written_files_and_published_directories_follow_the_umask(tmp_path, set_umask, mask, file_mode, dir_mode):
    set_umask(mask)
    assert atomic.current_umask() == mask
    D.atomic_write_json(tmp_path / "a.json", {"a": 1})
    D.write_rgb(tmp_path / "rgb" / "f.png", np.zeros((4, 5, 3), np.uint8))
    D.write_depth(tmp_path / "depth" / "f.exr", np.ones((4, 5), np.float32))
    for p in ("a.json", "rgb/f.png", "depth/f.exr"):
        assert _mode(tmp_path / p) == file_mode, p
    published = Path(tempfile.mkdtemp(dir=tmp_path))
    assert _mode(published) == 0o700  # what tempfile gives
    atomic.publish_mode(published)
    assert _mode(published) == dir_mode
    assert _mode(tmp_path / "rgb") == dir_mode  # made by mkdir, which honours the umask itself


def test_umask_is_read_without_proc(set_umask, monkeypatch):
    """Without /proc the umask is read by setting and restoring it; it is left unchanged."""
    set_umask(0o027)

    def no_proc(*a, **k):
        raise OSError("no /proc")

    monkeypatch.setattr(atomic, "open", no_proc, raising=False)
    assert atomic.current_umask() == 0o027
    monkeypatch.undo()
    assert atomic.current_umask() == 0o027


def test_overwrite_takes_the_current_umask(tmp_path, set_umask):
    target = tmp_path / "x.json"
    set_umask(0o077)
    D.atomic_write_json(target, {"a": 1})
    set_umask(0o022)
    D.atomic_write_json(target, {"a": 2})
    assert _mode(target) == 0o644
