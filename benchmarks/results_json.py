"""The one layout of a benchmark's results JSON (``benchmarks/results/*.json``).

Every figure README or docs show comes from such a file: ``scripts/docs_generate.py`` renders its
``tables`` into the Markdown between ``<!-- generated: FILE#TABLE -->`` and ``<!-- end generated -->``,
with one provenance line (command, commit, machine, time) above the table, and a test fails when
the Markdown differs from the file. Standard library only.

Layout::

    {"benchmark": "demo", "command": "make demo", "commit": "<sha>", "dirty": false,
     "machine": {"cpu": ..., "cores": 2, "platform": ..., "python": ...},
     "time": "<UTC ISO 8601>",
     "tables": {"NAME": {"columns": [str, ...], "rows": [[str, ...], ...]}},
     "data": {...}}                                  # raw figures, free-form per benchmark
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
from pathlib import Path
from typing import Any

KEYS = ("benchmark", "command", "commit", "dirty", "machine", "time", "tables")


def table(columns: list[str], rows: list[list[str]]) -> dict[str, Any]:
    """A results table: header cells and rows of already formatted cells (each as long as the header)."""
    bad = [r for r in rows if len(r) != len(columns)]
    if bad:
        raise ValueError(f"row {bad[0]!r} has {len(bad[0])} cells for {len(columns)} columns")
    return {"columns": [str(c) for c in columns], "rows": [[str(c) for c in r] for r in rows]}


def machine() -> dict[str, Any]:
    """What ran it: CPU model, cores this process may use, OS and Python."""
    cpu = platform.processor() or platform.machine()
    try:
        for ln in Path("/proc/cpuinfo").read_text().splitlines():
            if ln.startswith("model name"):
                cpu = ln.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu, "cores": cores, "platform": platform.platform(terse=True), "python": platform.python_version()}


def git_state(cwd: Path) -> tuple[str, bool]:
    """``(commit, dirty)`` of the checkout at ``cwd`` (``("unknown", True)`` outside git)."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd,
                                capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return "unknown", True
    return sha, bool(status.strip())


def write_results(path: Path, benchmark: str, command: str, tables: dict[str, dict], data: dict[str, Any],
                  cwd: Path) -> None:
    """Write one results JSON atomically (a temporary file renamed over ``path``)."""
    sha, dirty = git_state(cwd)
    doc = {"benchmark": benchmark, "command": command, "commit": sha, "dirty": dirty, "machine": machine(),
           "time": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(), "tables": tables, "data": data}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
    os.replace(tmp, path)


def read_results(path: Path) -> dict[str, Any]:
    """A results JSON, checked for the keys every one holds (``ValueError`` naming the file)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a readable results JSON ({e})") from None
    missing = [k for k in KEYS if not isinstance(doc, dict) or k not in doc]
    if missing:
        raise ValueError(f"{path}: not a results JSON (missing {', '.join(missing)})")
    for name, t in doc["tables"].items():
        if not isinstance(t, dict) or not isinstance(t.get("columns"), list) or not isinstance(t.get("rows"), list):
            raise ValueError(f"{path}: table {name!r} needs 'columns' and 'rows'")
    return doc
