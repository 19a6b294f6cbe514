"""Faults of the system rather than of the input: a full disk, SIGTERM or Ctrl-C with worker
processes running, a kill while a report is written, and an ``--out`` that holds the user's files.

A full disk is simulated without root: ``RLIMIT_FSIZE`` in the child process, with SIGXFSZ
ignored, makes every write beyond the limit fail with ``EFBIG`` ("File too large"), an ``OSError``
like ``ENOSPC``; writers that ignore a failed write (OpenVDB, Blender) leave a file cut at the
limit, as a full disk does. Commands that are signalled, killed or limited run as real command
lines in a subprocess; the others in this process.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from scenecore.cli import OS_ERROR_EXIT
from benchgen.cli import main as benchgen
from tests.benchgen.score.test_score import make_pred
from tests.test_robustness import REPO, _assert_user_error, _cmd, _kill_when

SCORE = ["--no-lpips", "--quiet"]


def _file_size_limit(limit: int) -> None:
    """In the child before ``exec``: writes beyond ``limit`` bytes fail with EFBIG, no signal."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


def _run_limited(limit: int, *argv: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run(list(map(str, argv)), cwd=REPO, capture_output=True, text=True, timeout=300,
                          preexec_fn=lambda: _file_size_limit(limit), env={**os.environ, "PYTHONPATH": str(REPO)})


def _assert_os_error(r: subprocess.CompletedProcess, names: str | Path, *phrases: str) -> None:
    """Exit :data:`OS_ERROR_EXIT`, one stderr line naming ``names`` and every phrase, no traceback."""
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == OS_ERROR_EXIT, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    for p in (str(names), *phrases):
        assert p in lines[0], (p, lines[0])


@pytest.fixture(scope="module")
def pred(tiny_dataset: Path, tmp_path_factory) -> Path:
    """Candidates that copy the tiny dataset's three ground truths."""
    return make_pred(tiny_dataset, tmp_path_factory.mktemp("faults") / "pred", {"a": 0, "b": 1, "c": 2})


# --------------------------------------------------------------------------------------------
# A full disk
# --------------------------------------------------------------------------------------------


def test_full_disk_during_score_is_one_line_and_writes_nothing(tiny_dataset: Path, pred: Path, tmp_path: Path) -> None:
    """The report's first plot (tens of KB) meets the limit: one line naming it, exit 3 (not the
    1 of a failed check), no report directory and no temporary left beside it."""
    out = tmp_path / "score"
    r = _run_limited(30_000, *_cmd("benchgen", "score", pred, "--data", tiny_dataset, "--out", out, *SCORE))
    _assert_os_error(r, out / "best_of_n.png", "File too large")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_full_disk_during_generate_is_one_line(tmp_path: Path) -> None:
    """Blender writes its render into a file cut at the limit and carries on: the reader's
    complaint about a missing pass becomes one line naming that file, exit 3."""
    r = _run_limited(20_000, *_cmd("benchgen", "generate", "--preset", "tiny", "--out", tmp_path / "ds", "--quiet"))
    _assert_os_error(r, "frame.exr", "cannot read back Blender's render", "is the disk full?")


_VDB_ON_FULL_DISK = """
import sys
from pathlib import Path
from osn.export.writer import _write_vdb
from tests.osn.export.test_export_addon import make_export_scene
try:
    _write_vdb(Path(sys.argv[1]), make_export_scene().objects[0])
except OSError as e:
    print(e)
"""


def test_vdb_on_full_disk_raises_and_leaves_no_file(tmp_path: Path) -> None:
    """OpenVDB returns normally after writing 32 KB of a 39 KB volume; the writer reads the file
    back, raises ``OSError`` naming it and leaves no file, whole or temporary."""
    vdb = tmp_path / "objects" / "0.vdb"
    vdb.parent.mkdir()
    r = _run_limited(32_768, sys.executable, "-c", _VDB_ON_FULL_DISK, vdb)
    assert r.returncode == 0, r.stderr[-2000:]
    assert str(vdb) in r.stdout and "does not read back" in r.stdout, r.stdout
    assert list(vdb.parent.iterdir()) == []


# --------------------------------------------------------------------------------------------
# SIGTERM / Ctrl-C with workers
# --------------------------------------------------------------------------------------------


def _children(pid: int) -> set[int]:
    """The live processes whose parent is ``pid`` (from /proc)."""
    kids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            kids.add(int(stat.parent.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL], ids=["sigterm", "sigint", "sigkill"])
def test_signal_ends_score_workers(tiny_dataset: Path, pred: Path, tmp_path: Path, sig: int) -> None:
    """``benchgen score --workers 2`` signalled while its two workers exist: the workers (checked
    by pid) are gone when it has exited, with 128 + the signal's number, and no report. After
    SIGKILL, where the command runs no cleanup, the kernel ends them (Linux)."""
    out = tmp_path / "score"

    def default_sigint() -> None:  # a shell's background job inherits SIGINT ignored
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    log = tmp_path / "stderr.txt"  # not a pipe: a worker left behind would hold it open
    with open(log, "w") as err:
        proc = subprocess.Popen(_cmd("benchgen", "score", pred, "--data", tiny_dataset, "--out", out, "--workers", "2", *SCORE),
                                cwd=REPO, start_new_session=True, preexec_fn=default_sigint, stdout=subprocess.DEVNULL, stderr=err)
    workers: set[int] = set()
    try:
        deadline = time.time() + 120
        while proc.poll() is None and time.time() < deadline and len(workers) < 2:
            if len(_children(proc.pid)) >= 2:
                os.kill(proc.pid, signal.SIGSTOP)  # holds the pool as it is while the pids are read
                workers = _children(proc.pid)
                if len(workers) < 2:
                    os.kill(proc.pid, signal.SIGCONT)
            time.sleep(0.005)
        assert len(workers) == 2, "score ended before its workers were seen"
        os.kill(proc.pid, sig)
        os.kill(proc.pid, signal.SIGCONT)
        proc.wait(timeout=60)
        time.sleep(0.2)  # an orphan would be re-parented, not gone
        assert not [w for w in workers if _alive(w)], f"workers {workers} outlived benchgen score"
        assert proc.returncode == (-sig if sig == signal.SIGKILL else 128 + sig), (proc.returncode, log.read_text()[-2000:])
        assert "Traceback" not in log.read_text() and not out.exists()
    finally:
        for pid in (*workers, proc.pid):
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        proc.wait()


# --------------------------------------------------------------------------------------------
# Report directories
# --------------------------------------------------------------------------------------------


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in d.iterdir() if p.is_file()}


def test_kill_during_report_write_keeps_the_old_report_whole(tiny_dataset: Path, tmp_path: Path) -> None:
    """A scoring killed once its new ``psnr_matrix.npy`` exists leaves the previous report's
    files, all of them and only them; the rerun replaces them together."""
    out = tmp_path / "score"
    two = make_pred(tiny_dataset, tmp_path / "two", {"a": 0, "b": 1})
    three = make_pred(tiny_dataset, tmp_path / "three", {"a": 0, "b": 1, "c": 2})
    assert benchgen(["score", str(two), "--data", str(tiny_dataset), "--out", str(out), *SCORE]) == 0
    before = _files(out)
    proc = subprocess.Popen(_cmd("benchgen", "score", three, "--data", tiny_dataset, "--out", out, *SCORE), cwd=REPO,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    new_matrix = lambda: ((out / "psnr_matrix.npy").read_bytes() != before["psnr_matrix.npy"]  # noqa: E731
                          or any(tmp_path.glob(".score.*.partial/psnr_matrix.npy")))
    assert _kill_when(proc, new_matrix), "score ended before its report was written"
    assert _files(out) == before
    assert benchgen(["score", str(three), "--data", str(tiny_dataset), "--out", str(out), *SCORE]) == 0
    after = _files(out)
    assert after["psnr_matrix.npy"] != before["psnr_matrix.npy"] and after["report.md"] != before["report.md"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["score", "three", "two"], "temporaries left"


def test_out_dir_holding_user_files_is_refused(tiny_dataset: Path, pred: Path, tmp_path: Path, capsys) -> None:
    """``--out`` a folder with the user's own ``report.md``: one line naming it, exit 2, the file
    untouched (``benchgen score``, and ``osn evaluate`` before it reads anything)."""
    from osn.cli import main as osn

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "report.md").write_text("my notes\n")
    calls = [(benchgen, ["score", str(pred), "--data", str(tiny_dataset), *SCORE], "is not a benchgen score report"),
             (osn, ["evaluate", str(tmp_path / "no-run"), "--data", str(tiny_dataset)], "is not an osn evaluation report")]
    for tool, argv, phrase in calls:
        rc = tool([*argv, "--out", str(mine)])
        r = subprocess.CompletedProcess(argv, rc, "", capsys.readouterr().err)
        _assert_user_error(r, mine, phrase, "choose another --out")
    assert _files(mine) == {"report.md": b"my notes\n"}


def test_out_dir_of_an_earlier_report_is_replaced(tiny_dataset: Path, pred: Path, tmp_path: Path) -> None:
    """A report directory of ours is replaced, also one written before reports carried a marker
    (its files are all report files and its ``metrics.json`` says ``benchgen-score``); an empty
    directory is used."""
    from benchgen.score.report import MARKER

    out = tmp_path / "score"
    out.mkdir()
    argv = ["score", str(pred), "--data", str(tiny_dataset), "--out", str(out), *SCORE]
    assert benchgen(argv) == 0 and (out / MARKER).is_file()
    (out / MARKER).unlink()
    (out / "report.md").write_text("stale")
    assert benchgen(argv) == 0 and (out / MARKER).is_file() and (out / "report.md").read_text() != "stale"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowed exception is the case
def test_a_signal_swallowed_where_python_ignores_exceptions_still_stops_the_command(sig: int, capsys) -> None:
    """Python ignores an exception raised in a finaliser (or a logging lock's release): a Ctrl-C or
    SIGTERM landing there must still end the command with 128 + its number, not exit 0."""
    import argparse

    from scenecore.cli import run_cli

    class Finalised:
        def __del__(self) -> None:
            os.kill(os.getpid(), sig)  # the handler raises here, where Python only prints it

    def command(_args: argparse.Namespace) -> int:
        Finalised()
        return 0

    parser = argparse.ArgumentParser(prog="t")
    parser.set_defaults(func=command)
    previous = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        assert run_cli(parser, [], "t") == 128 + sig
    finally:
        signal.signal(signal.SIGINT, previous)
    assert ("interrupted" if sig == signal.SIGINT else "terminated") in capsys.readouterr().err
