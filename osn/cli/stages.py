"""Resumable multi-stage jobs: each stage runs once, records its time, and is skipped on re-runs.

A stage is done when its marker ``.done/<name>.json`` exists; the marker is written atomically
after the stage's own outputs, so a killed job re-runs only the stage it was in (which is itself
resumable). ``stages.json`` collects every stage's wall time, summed over the invocations that
worked on it (a ``kill -9`` loses the killed invocation's share: only a normal end, an
exception or Ctrl-C records it), so error can be put next to time.

Each stage names the options its outputs depend on. They are recorded when the stage starts; a
later call with different values stops with one line instead of skipping (or resuming) the
stage with outputs made under the old ones.

A background stage (``background=True``) starts its work and lets the next stages run beside it;
it is waited for before the first stage that ``needs`` it (or at the end), and stopped if the job
stops first. Its recorded time is its own wall time, which overlaps the stages beside it.
"""

from __future__ import annotations

import json
import shlex
import shutil
import signal
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Protocol

from scenecore.dataset import atomic_write_json
from scenecore.cli import UserError
from scenecore.lock import output_lock


class Job(Protocol):
    """What a background stage's ``run()`` returns: work already under way. ``ended``: the
    ``time.perf_counter()`` at which it ended (None while it runs), so its time is its own,
    not the moment a later stage waited for it."""

    ended: float | None

    def wait(self) -> dict[str, Any]:
        """Block until the work is done; its JSON-able summary (raises if it failed)."""

    def stop(self) -> None:
        """End the work now (the job stops before it); safe to call when it has ended."""


@dataclass
class Stage:
    """A named step; ``run()`` returns a JSON-able summary stored with its time, or, for a
    ``background`` stage, starts the work and returns its :class:`Job`. ``needs``: background
    stages that must be done before this one starts. ``recorded``: how options an older version
    recorded read today (``ValueError`` where they cannot), so a renamed or removed option that
    held the value that works as today does not refuse a finished stage."""

    name: str
    description: str
    run: Callable[[], Any]
    options: dict[str, Any] = field(default_factory=dict)
    background: bool = False
    needs: tuple[str, ...] = ()
    recorded: Callable[[dict[str, Any]], dict[str, Any]] | None = None


@dataclass
class _Running:
    """A background stage under way: its job, position, options and clock."""

    job: Job
    index: int
    options: dict[str, Any]
    spent: float
    t0: float


def run_stages(stages: list[Stage], workdir: str | Path, echo: Callable[[str], None] = print) -> dict[str, dict]:
    """Run ``stages`` in order under ``workdir``, skipping those already done; return their records.

    Raises:
        UserError: a stage was started or finished with other values of its options.
        OutputInUse: another process runs stages in ``workdir`` (:mod:`scenecore.lock`).
        ValueError: a stage needs a stage that is not an earlier background stage of ``stages``.
    """
    # The whole work directory: a second job on it would take this one's live stages for killed
    # ones and run them again beside it. Stages' outputs take their own locks (``osn demo``'s
    # background ``benchgen generate`` locks the dataset it writes, not the work directory).
    with output_lock(workdir):
        return _run_stages_locked(stages, Path(workdir), echo)


def _run_stages_locked(stages: list[Stage], work: Path, echo: Callable[[str], None]) -> dict[str, dict]:
    done_dir = work / ".done"
    done_dir.mkdir(parents=True, exist_ok=True)
    records: dict[str, dict] = {}
    n = len(stages)
    for i, st in enumerate(stages):
        bad = [d for d in st.needs if d not in {s.name for s in stages[:i] if s.background}]
        if bad:
            raise ValueError(f"stage {st.name!r} needs {bad}, which are not earlier background stages")
    running: dict[str, _Running] = {}

    def record_started(name: str, r: _Running) -> None:
        _record_started(done_dir, name, r.options, r.spent + time.perf_counter() - r.t0)

    def finish(name: str) -> None:
        r = running.pop(name)
        t_wait = time.perf_counter()
        try:
            summary = r.job.wait() or {}
        except BaseException:  # failed, or interrupted while waiting
            r.job.stop()
            record_started(name, r)
            raise
        now = time.perf_counter()
        end = min(now, r.job.ended if r.job.ended is not None else now)
        rec = {"seconds": r.spent + end - r.t0, "summary": summary, "options": r.options, "background": True,
               "waited": now - t_wait}
        atomic_write_json(done_dir / f"{name}.json", rec)
        records[name] = rec
        echo(f"[{r.index}/{n}] {name}: done in {rec['seconds']:.1f} s in the background (waited {rec['waited']:.1f} s)")

    try:
        for i, st in enumerate(stages, 1):
            for dep in st.needs:
                if dep in running:
                    finish(dep)
            _run_one(st, i, n, done_dir, records, running, echo)
        for name in list(running):
            finish(name)
    finally:  # an error or an interrupt in the foreground ends the background work too
        for name, r in running.items():
            r.job.stop()
            record_started(name, r)
    records = {st.name: records[st.name] for st in stages}  # in stage order, not in order of completion
    atomic_write_json(work / "stages.json", records)
    return records


def _record_started(done_dir: Path, name: str, options: dict[str, Any], seconds: float,
                    error: BaseException | None = None) -> None:
    """A started stage's record (``.started.json``): its options, the time spent on it so far,
    which a resumed run adds its own to, and, where it stopped on an exception, which one
    (``error``: ``type`` and ``message``), so a caller tells an outcome of the method (a sampler
    that found no valid configuration) from a crash without reading a log."""
    rec: dict[str, Any] = {"options": options, "seconds": seconds}
    if error is not None:
        rec["error"] = {"type": type(error).__name__, "message": str(error)}
    atomic_write_json(done_dir / f"{name}.started.json", rec)


def stage_error(workdir: str | Path, name: str) -> dict[str, str] | None:
    """The exception stage ``name`` of ``workdir`` last stopped on (``type``, ``message``); None
    where it finished, is under way or never started."""
    done = Path(workdir) / ".done"
    started = done / f"{name}.started.json"
    if (done / f"{name}.json").exists() or not started.is_file():
        return None
    return json.loads(started.read_text()).get("error")


def _run_one(st: Stage, i: int, n: int, done_dir: Path, records: dict[str, dict], running: dict[str, _Running],
             echo: Callable[[str], None]) -> None:
    """Skip, run, or (background) start stage ``st``, number ``i`` of ``n``."""
    marker, started = done_dir / f"{st.name}.json", done_dir / f"{st.name}.started.json"
    options = json.loads(json.dumps(st.options))  # as stored: tuples become lists
    before = json.loads(started.read_text()) if started.exists() else None
    old = before.get("options", {}) if before is not None else options
    if before is not None and st.recorded is not None and old != options:
        try:
            old = json.loads(json.dumps(st.recorded(old)))
        except ValueError as e:
            raise UserError(f"{done_dir.parent}: stage {st.name!r} was run by an older version ({e}); "
                            f"use another --work, or remove {done_dir.parent} to start over") from None
    if old != options:
        diff = ", ".join(f"{k} {old.get(k)!r} -> {options.get(k)!r}" for k in sorted(set(old) | set(options))
                         if old.get(k) != options.get(k))
        raise UserError(f"{done_dir.parent}: stage {st.name!r} was run with other options ({diff}); "
                        f"use another --work, or remove {done_dir.parent} to start over")
    if marker.exists():
        records[st.name] = json.loads(marker.read_text())
        echo(f"[{i}/{n}] {st.name}: already done ({records[st.name]['seconds']:.1f} s earlier), skipping")
        return
    spent = float(before.get("seconds", 0.0)) if before else 0.0
    echo(f"[{i}/{n}] {st.name}: {st.description}" + (f" (resuming after {spent:.0f} s)" if before else "")
         + (" (in the background)" if st.background else ""))
    _record_started(done_dir, st.name, options, spent)
    t0 = time.perf_counter()
    try:
        result = st.run()
    except BaseException as e:  # keep the time spent, so a resumed stage reports its whole cost
        _record_started(done_dir, st.name, options, spent + time.perf_counter() - t0, e)
        raise
    if st.background:
        running[st.name] = _Running(result, i, options, spent, t0)
        return
    rec = {"seconds": spent + time.perf_counter() - t0, "summary": result or {}, "options": options}
    atomic_write_json(marker, rec)
    records[st.name] = rec
    echo(f"[{i}/{n}] {st.name}: done in {rec['seconds']:.1f} s")


class BackgroundCommand:
    """A command run beside the foreground stages at the lowest CPU priority (``nice -n 19``
    where there is ``nice``): it takes the cores the foreground leaves idle and little else.
    Its output goes to ``log``; ``summary()`` makes the stage's summary once it succeeded.

    It stays in the caller's process group, so a Ctrl-C or a kill of the whole job reaches it too.
    """

    def __init__(self, cmd: list[str], log: Path, summary: Callable[[], dict[str, Any]] = dict) -> None:
        self.cmd, self.log, self.summary = list(cmd), Path(log), summary
        self.proc: subprocess.Popen | None = None
        self.ended: float | None = None

    def start(self) -> "BackgroundCommand":
        nice = ["nice", "-n", "19"] if shutil.which("nice") else []
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log, "w") as out:  # the child holds its own descriptor
            self.proc = subprocess.Popen([*nice, *self.cmd], stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT)
        self._reaper = threading.Thread(target=self._reap, daemon=True)
        self._reaper.start()
        return self

    def _reap(self) -> None:  # notes when the command ends, whenever the stages look
        assert self.proc is not None
        self.proc.wait()
        self.ended = time.perf_counter()

    def running(self) -> bool:
        """Started and not yet ended."""
        return self.proc is not None and self.proc.poll() is None

    def wait(self) -> dict[str, Any]:
        """Wait for the command; its summary, or :class:`UserError` with the log's last line."""
        assert self.proc is not None, "wait() before start()"
        rc = self.proc.wait()
        self._reaper.join()  # so `ended` is set
        if rc != 0:
            lines = [ln for ln in self.log.read_text(errors="replace").splitlines() if ln.strip()] if self.log.exists() else []
            raise UserError(f"{self.log}: `{shlex.join(self.cmd)}` failed (exit {rc})" + (f": {lines[-1].strip()}" if lines else ""))
        return self.summary()

    def stop(self, grace: float = 30.0) -> None:
        """End the command: SIGTERM, then SIGKILL after ``grace`` s. Not SIGINT: a command started
        from a non-interactive shell's background job inherits SIGINT ignored, and Python then
        never turns it into KeyboardInterrupt (seen in CI). Work that writes atomically and
        resumes, as ``benchgen generate`` does, loses nothing but the frames in flight."""
        if not self.running():
            return
        assert self.proc is not None
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(grace)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
