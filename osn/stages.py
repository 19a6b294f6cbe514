"""Resumable multi-stage jobs: each stage runs once, records its time, and is skipped on re-runs.

A stage is done when its marker ``.done/<name>.json`` exists; the marker is written atomically
after the stage's own outputs, so a killed job re-runs only the stage it was in (which is itself
resumable). ``stages.json`` collects every stage's wall time so error can be put next to time.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from benchgen.dataset import atomic_write_json


@dataclass
class Stage:
    """A named step; ``run()`` returns a JSON-able summary stored with its time."""

    name: str
    description: str
    run: Callable[[], dict[str, Any] | None]


def run_stages(stages: list[Stage], workdir: str | Path, echo: Callable[[str], None] = print) -> dict[str, dict]:
    """Run ``stages`` in order under ``workdir``, skipping those already done; return their records."""
    work = Path(workdir)
    done_dir = work / ".done"
    done_dir.mkdir(parents=True, exist_ok=True)
    records: dict[str, dict] = {}
    n = len(stages)
    for i, st in enumerate(stages, 1):
        marker = done_dir / f"{st.name}.json"
        if marker.exists():
            records[st.name] = json.loads(marker.read_text())
            echo(f"[{i}/{n}] {st.name}: already done ({records[st.name]['seconds']:.1f} s earlier), skipping")
            continue
        echo(f"[{i}/{n}] {st.name}: {st.description}")
        t0 = time.perf_counter()
        summary = st.run() or {}
        rec = {"seconds": time.perf_counter() - t0, "summary": summary}
        atomic_write_json(marker, rec)
        records[st.name] = rec
        echo(f"[{i}/{n}] {st.name}: done in {rec['seconds']:.1f} s")
    atomic_write_json(work / "stages.json", records)
    return records
