"""What a run directory holds on disk while training: the checkpoint and ``metrics.jsonl``.

The checkpoint is written atomically and only when every weight is finite
(:class:`TrainingDiverged` otherwise); metric lines are appended, and a resume drops those
written after the checkpoint it continues from.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import torch

from scenecore import dataset as D
from scenecore.cli import UserError

from osn.train.schedule import Phase
from osn.train.trainer import Trainer


def save_checkpoint(path: Path, trainer: Trainer) -> None:
    """Write ``trainer.state_dict()`` to ``path`` atomically (a kill leaves the previous one)."""
    buf = io.BytesIO()
    torch.save(trainer.state_dict(), buf)
    D.atomic_write_bytes(path, buf.getvalue())


class TrainingDiverged(UserError):
    """A loss or a weight became NaN or infinite; the message names the run, iteration, phase
    and what diverged. Checked before every checkpoint, so the last one written stays finite."""

    @classmethod
    def at(cls, out: Path, iteration: int, phase: Phase, what: str) -> "TrainingDiverged":
        return cls(f"{out}: training diverged at iteration {iteration} ({phase.name} phase): {what}; "
                   "the last checkpoint is kept (lower scale_lr, or check the inputs)")


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """The records of a run's ``metrics.jsonl`` (empty if absent). A line cut by a kill
    mid-write, or anything else that is not a record with an ``iteration``, is skipped."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    for ln in path.read_text().splitlines():
        try:
            rec = json.loads(ln)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and isinstance(rec.get("iteration"), int):
            out.append(rec)
    return out


def append_metrics(path: Path, record: dict[str, Any]) -> None:
    """Append one record as a JSON line."""
    with path.open("a") as fh:
        fh.write(json.dumps(record) + "\n")


def truncate_metrics(path: Path, iteration: int) -> None:
    """Drop metric lines written after the checkpoint being resumed (they will be rewritten)."""
    if not path.exists():
        return
    lines = [json.dumps(rec) for rec in read_metrics(path) if rec["iteration"] <= iteration]
    D.atomic_write_bytes(path, ("\n".join(lines) + "\n" if lines else "").encode())
