"""Resumable multi-stage jobs: each stage runs once, records its time, and is skipped on re-runs.

A stage is done when its marker ``.done/<name>.json`` exists; the marker is written atomically
after the stage's own outputs, so a killed job re-runs only the stage it was in (which is itself
resumable). ``stages.json`` collects every stage's wall time, summed over the invocations that
worked on it (a ``kill -9`` loses the killed invocation's share: only a normal end, an
exception or Ctrl-C records it), so error can be put next to time.

Each stage names the options its outputs depend on. They are recorded when the stage starts; a
later call with different values stops with one line instead of skipping (or resuming) the
stage with outputs made under the old ones.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from scenecore.dataset import atomic_write_json
from scenecore.cli import UserError


@dataclass
class Stage:
    """A named step; ``run()`` returns a JSON-able summary stored with its time."""

    name: str
    description: str
    run: Callable[[], dict[str, Any] | None]
    options: dict[str, Any] = field(default_factory=dict)


def run_stages(stages: list[Stage], workdir: str | Path, echo: Callable[[str], None] = print) -> dict[str, dict]:
    """Run ``stages`` in order under ``workdir``, skipping those already done; return their records.

    Raises:
        UserError: a stage was started or finished with other values of its options.
    """
    work = Path(workdir)
    done_dir = work / ".done"
    done_dir.mkdir(parents=True, exist_ok=True)
    records: dict[str, dict] = {}
    n = len(stages)
    for i, st in enumerate(stages, 1):
        marker, started = done_dir / f"{st.name}.json", done_dir / f"{st.name}.started.json"
        options = json.loads(json.dumps(st.options))  # as stored: tuples become lists
        before = json.loads(started.read_text()) if started.exists() else None
        if before is not None and before.get("options", {}) != options:
            old = before.get("options", {})
            diff = ", ".join(f"{k} {old.get(k)!r} -> {options.get(k)!r}" for k in sorted(set(old) | set(options))
                             if old.get(k) != options.get(k))
            raise UserError(f"{work}: stage {st.name!r} was run with other options ({diff}); "
                            f"use another --work, or remove {work} to start over")
        if marker.exists():
            records[st.name] = json.loads(marker.read_text())
            echo(f"[{i}/{n}] {st.name}: already done ({records[st.name]['seconds']:.1f} s earlier), skipping")
            continue
        spent = float(before.get("seconds", 0.0)) if before else 0.0
        echo(f"[{i}/{n}] {st.name}: {st.description}" + (f" (resuming after {spent:.0f} s)" if before else ""))
        atomic_write_json(started, {"options": options, "seconds": spent})
        t0 = time.perf_counter()
        try:
            summary = st.run() or {}
        except BaseException:  # keep the time spent, so a resumed stage reports its whole cost
            atomic_write_json(started, {"options": options, "seconds": spent + time.perf_counter() - t0})
            raise
        rec = {"seconds": spent + time.perf_counter() - t0, "summary": summary, "options": options}
        atomic_write_json(marker, rec)
        records[st.name] = rec
        echo(f"[{i}/{n}] {st.name}: done in {rec['seconds']:.1f} s")
    atomic_write_json(work / "stages.json", records)
    return records
