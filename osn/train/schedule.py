"""The phases of a training run, in order, over one global iteration counter."""

from __future__ import annotations

from dataclasses import dataclass

from osn.train.config import TrainConfig


@dataclass
class Phase:
    """Iterations ``[start, end)`` of one phase; ``round`` is 0 for stage 1, then 1, 2, ..."""

    name: str  # "stage1", "scale", "fields"
    start: int
    end: int
    round: int


def build_schedule(cfg: TrainConfig, num_objects: int) -> list[Phase]:
    """Stage 1, then ``rounds`` x (scale phase, field phase), then a final scale phase.

    A single object has no scale phases; phases of 0 iterations are left out.
    """
    phases: list[Phase] = []
    it = 0

    def add(name: str, n: int, r: int) -> None:
        nonlocal it
        if n > 0:
            phases.append(Phase(name, it, it + n, r))
            it += n

    add("stage1", cfg.stage1_iters, 0)
    for r in range(1, cfg.rounds + 1):
        if num_objects > 1:
            add("scale", cfg.scale_iters, r)
        add("fields", cfg.field_iters, r)
    if num_objects > 1:
        add("scale", cfg.final_scale_iters, cfg.rounds + 1)
    return phases
