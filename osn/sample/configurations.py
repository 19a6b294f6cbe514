"""``osn sample``: valid scale configurations drawn from a trained scale network (no ground truth).

:func:`sample_configurations` draws uniformly from the learned valid set (the vectors of the
non-anchor objects' normalised scale box that the scale network scores above a threshold):
rejection sampling of the box, and where the set is too small for that (its share of the box
falls exponentially with the number of objects) hit-and-run inside it; :class:`Samples` is what
``RUN/samples.npz`` holds, read by ``osn evaluate`` and ``osn export``.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenecore import dataset as D
from scenecore.scale_space import fill_from_set
from osn.model.run import TrainedRun
from osn.model.scale_net import VALID_THRESHOLD

log = logging.getLogger(__name__)


@dataclass
class Samples:
    """N scale vectors: normalised free scales ``s_free (N, K-1)``, de-normalised ``sbar (N, K)``
    (by object position), validity scores ``score (N,)``; the last ``chained`` of them were drawn
    by hit-and-run (uniform draws found too few), and the last ``fell_back`` scored below
    ``threshold`` (no valid vector was found at all)."""

    s_free: np.ndarray
    sbar: np.ndarray
    score: np.ndarray
    threshold: float
    seed: int
    fell_back: int = 0
    chained: int = 0

    def save(self, path: str | Path) -> None:
        """Write an ``.npz`` atomically."""
        buf = io.BytesIO()
        np.savez(buf, s_free=self.s_free, sbar=self.sbar, score=self.score,
                 meta=np.array([self.threshold, self.seed, self.fell_back, self.chained], dtype=np.float64))
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
            chained = int(meta[3]) if len(meta) > 3 else 0  # files written before hit-and-run have three
            return cls(z["s_free"], z["sbar"], z["score"], float(meta[0]), int(meta[1]), int(meta[2]), chained)
        except Exception as e:
            raise ValueError(f"{path}: not an osn samples file ({e})") from None


#: Most configurations one call draws: 10 million scale vectors of a few objects are a few
#: hundred MB; more is a typo, not a benchmark.
MAX_SAMPLES = 10_000_000
#: Candidates scored at once: memory stays bounded whatever ``n`` is.
BATCH = 1 << 18


def sample_configurations(run: TrainedRun, n: int, threshold: float = VALID_THRESHOLD, seed: int = 0, max_draws: int = 2_000_000) -> Samples:
    """Draw ``n`` scale vectors uniformly from the set whose validity score is above ``threshold``.

    Candidates are uniform in the normalised box [0, 1)^(K-1), scored in batches of at most
    :data:`BATCH`, and kept when they pass. If fewer than ``n`` pass within ``max_draws``
    candidates (at least one batch), the rest are drawn by hit-and-run inside the set
    (:func:`scenecore.scale_space.hit_and_run`), starting from those that passed or, when none
    did, from where climbing from the best-scoring candidates enters the set. Only when that
    finds no valid vector either do the best-scoring candidates fill up, with a logged warning
    (never an error). A single-object scene has one configuration (the anchor alone).
    ``ValueError`` for ``n`` outside 1..:data:`MAX_SAMPLES` or a threshold that is not a finite
    number in [0, 1) (scores are sigmoids: none exceeds 1).
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"the number of samples must be an integer in 1..{MAX_SAMPLES:,}, got {n}")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0.0 <= threshold < 1.0:
        raise ValueError(f"the validity threshold must be a number in [0, 1), got {threshold}")
    K = run.inputs.num_objects
    if K == 1:
        return Samples(np.zeros((1, 0)), np.ones((1, 1)), np.ones(1), threshold, seed)
    rng = np.random.default_rng(seed)
    kept_s, kept_p, drawn, kept = [], [], 0, 0
    best_s, best_p = np.zeros((0, K - 1)), np.zeros(0)
    batch = min(max(4 * n, 4096), BATCH)
    while kept < n and (drawn == 0 or drawn < max_draws):
        s = rng.random((batch, K - 1))
        p = run.scores(s)
        drawn += batch
        ok = p > threshold
        kept_s.append(s[ok][: n - kept])
        kept_p.append(p[ok][: n - kept])
        kept += len(kept_p[-1])
        # Fallback pool: the best n of the candidates not kept, so no vector is returned twice.
        rest = np.flatnonzero(~ok)
        best_s, best_p = np.concatenate([best_s, s[rest]]), np.concatenate([best_p, p[rest]])
        top = np.argsort(-best_p, kind="stable")[: n - kept]
        best_s, best_p = best_s[top], best_p[top]
    s_all = np.concatenate(kept_s)
    p_all = np.concatenate(kept_p)
    chained = 0
    if len(s_all) < n:
        more = fill_from_set(run.scores, s_all, best_s[:64], n - len(s_all), threshold, rng)
        if len(more):
            chained = len(more)
            log.info("%d of %d candidates scored above %.3g in %d uniform draws; %d more drawn by hit-and-run inside the set",
                     len(s_all), n, threshold, drawn, chained)
            s_all, p_all = np.concatenate([s_all, more]), np.concatenate([p_all, run.scores(more)])
    fell = n - len(s_all)
    if fell:
        log.warning("only %d of %d candidates scored above %.3g after %d draws; using the best-scoring rest",
                    len(s_all), n, threshold, drawn)
        s_all = np.concatenate([s_all, best_s[:fell]])
        p_all = np.concatenate([p_all, best_p[:fell]])
    return Samples(s_all, run.sbar(s_all), p_all, threshold, seed, fell, chained)
