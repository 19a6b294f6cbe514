"""``osn sample``: valid scale configurations drawn from a trained scale network (no ground truth).

:func:`sample_configurations` rejection-samples the normalised scale box of the non-anchor
objects and keeps the vectors the scale network scores above a threshold; :class:`Samples` is
what ``RUN/samples.npz`` holds, read by ``osn evaluate`` and ``osn export``.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenecore import dataset as D
from osn.model.run import TrainedRun
from osn.model.scale_net import VALID_THRESHOLD

log = logging.getLogger(__name__)


@dataclass
class Samples:
    """N scale vectors: normalised free scales ``s_free (N, K-1)``, de-normalised ``sbar (N, K)``
    (by object position), validity scores ``score (N,)``; ``fell_back`` of them scored below
    ``threshold`` (too few valid candidates were found)."""

    s_free: np.ndarray
    sbar: np.ndarray
    score: np.ndarray
    threshold: float
    seed: int
    fell_back: int = 0

    def save(self, path: str | Path) -> None:
        """Write an ``.npz`` atomically."""
        buf = io.BytesIO()
        np.savez(buf, s_free=self.s_free, sbar=self.sbar, score=self.score,
                 meta=np.array([self.threshold, self.seed, self.fell_back], dtype=np.float64))
        D.atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path) -> "Samples":
        """Read what :meth:`save` wrote; a missing or foreign file is one error naming it."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing (run `osn sample RUN` first)")
        try:
            z = np.load(path)
            meta = z["meta"]
            return cls(z["s_free"], z["sbar"], z["score"], float(meta[0]), int(meta[1]), int(meta[2]))
        except Exception as e:
            raise ValueError(f"{path}: not an osn samples file ({e})") from None


def sample_configurations(run: TrainedRun, n: int, threshold: float = VALID_THRESHOLD, seed: int = 0, max_draws: int = 2_000_000) -> Samples:
    """Draw ``n`` scale vectors with validity score above ``threshold`` (rejection sampling).

    Candidates are uniform in the normalised box [0, 1)^(K-1). If fewer than ``n`` pass within
    ``max_draws`` candidates, the best-scoring remaining candidates fill up with a logged
    warning (never an error). A single-object scene has one configuration (the anchor alone).
    """
    if n < 1:
        raise ValueError(f"the number of samples must be >= 1, got {n}")
    K = run.inputs.num_objects
    if K == 1:
        return Samples(np.zeros((1, 0)), np.ones((1, 1)), np.ones(1), threshold, seed)
    rng = np.random.default_rng(seed)
    kept_s, kept_p, drawn = [], [], 0
    best_s, best_p = np.zeros((0, K - 1)), np.zeros(0)
    batch = max(4 * n, 4096)
    while sum(len(p) for p in kept_p) < n and drawn < max_draws:
        s = rng.random((batch, K - 1))
        p = run.scores(s)
        drawn += batch
        ok = p > threshold
        kept_s.append(s[ok])
        kept_p.append(p[ok])
        # Fallback pool: only candidates not already kept, so no vector is returned twice.
        rest = np.flatnonzero(~ok)
        top = rest[np.argsort(-p[rest])[:n]]
        best_s, best_p = np.concatenate([best_s, s[top]]), np.concatenate([best_p, p[top]])
    s_all = np.concatenate(kept_s)[:n]
    p_all = np.concatenate(kept_p)[:n]
    fell = n - len(s_all)
    if fell:
        log.warning("only %d of %d candidates scored above %.3g after %d draws; using the best-scoring rest",
                    len(s_all), n, threshold, drawn)
        order = np.argsort(-best_p)
        s_all = np.concatenate([s_all, best_s[order[:fell]]])
        p_all = np.concatenate([p_all, best_p[order[:fell]]])
    return Samples(s_all, run.sbar(s_all), p_all, threshold, seed, fell)
