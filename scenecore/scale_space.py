"""The object scale network and configuration maths of an export, in numpy (float64).

Shared by the Blender add-on (Blender's bundled numpy only) and ``osn.export``: evaluating the
network on normalised scales, Eq. 1 (normalised <-> actual scales), placing an object in a
configuration, and the learned valid set's intervals and seeded samples.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from .cameras import scale_about
from .errors import EmptyValidSet, ExportFormatError

ACTIVATIONS = ("relu", "sigmoid", "softplus", "tanh", "identity")

__all__ = [
    "ACTIVATIONS", "scale_net_numpy", "denormalise", "normalise", "configured_poses", "scale_scores",
    "learned_intervals", "sample_valid_configurations", "SCENE_NEAR_FACTOR", "SCENE_FAR_FACTOR",
    "scale_range", "scene_volume", "eq1_box", "hit_and_run", "climb_into_set", "fill_from_set",
]

#: The scene volume of Eq. 1 is ``[SCENE_NEAR_FACTOR * min_k near_k, SCENE_FAR_FACTOR * max_k
#: far_k]``: below every object's nearest depth and beyond every object's farthest.
SCENE_NEAR_FACTOR = 0.3
SCENE_FAR_FACTOR = 1.5


def _activate(x: np.ndarray, name: str) -> np.ndarray:
    if name == "relu":
        return np.maximum(x, 0.0)
    if name == "sigmoid":
        # Split by sign so large |x| never overflows exp.
        e = np.exp(-np.abs(x))
        return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
    if name == "softplus":
        return np.logaddexp(0.0, x)
    if name == "tanh":
        return np.tanh(x)
    if name == "identity":
        return x
    raise ExportFormatError(f"unknown activation {name!r} (expected one of {ACTIVATIONS})")


def scale_net_numpy(
    layers: Sequence[tuple[np.ndarray, np.ndarray]],
    s_norm: np.ndarray,
    hidden: str = "relu",
    output: str = "sigmoid",
) -> np.ndarray:
    """Evaluate the object scale network on normalised scales.

    Args:
        layers: ``[(W, b), ...]`` with ``W (out, in)`` and ``b (out,)`` (torch ``nn.Linear`` layout).
        s_norm: ``(N, K-1)`` or ``(K-1,)`` normalised scales of the non-anchor objects.
        hidden, output: activation after every hidden layer and after the last one.

    Returns:
        ``(N,)`` validity scores (a scalar array for 1-D input), computed in float64.
    """
    x = np.atleast_2d(np.asarray(s_norm, dtype=np.float64))
    for i, (W, b) in enumerate(layers):
        x = x @ np.asarray(W, dtype=np.float64).T + np.asarray(b, dtype=np.float64)
        x = _activate(x, output if i == len(layers) - 1 else hidden)
    out = x[:, 0]
    return out if np.ndim(s_norm) > 1 else out[0]


def scale_range(scene_near: float, scene_far: float, near: float, far: float) -> tuple[float, float]:
    """Eq. 1's range ``[scene_near / near, scene_far / far]`` for one object whose depths span
    ``[near, far]``; ``ValueError`` instead of ever returning an inverted range."""
    vals = (scene_near, scene_far, near, far)
    if not all(np.isfinite(v) and v > 0 for v in vals):
        raise ValueError(f"near/far must be finite and positive, got scene {scene_near}, {scene_far}, object {near}, {far}")
    lo, hi = scene_near / near, scene_far / far
    if not lo < hi:
        raise ValueError(
            f"empty scale range [{lo:.4g}, {hi:.4g}]: the scene volume [{scene_near:.4g}, {scene_far:.4g}] "
            f"must be deeper (far/near) than the object's [{near:.4g}, {far:.4g}]"
        )
    return lo, hi


def scene_volume(nears: Sequence[float], fars: Sequence[float], near_factor: float = SCENE_NEAR_FACTOR,
                 far_factor: float = SCENE_FAR_FACTOR) -> tuple[float, float]:
    """Scene near/far of Eq. 1 from every object's depth range: below every near, beyond every far."""
    if not (0 < near_factor < 1 <= far_factor):
        raise ValueError(f"scene volume factors must satisfy 0 < near ({near_factor}) < 1 <= far ({far_factor})")
    return near_factor * min(nears), far_factor * max(fars)


def eq1_box(nears: np.ndarray, fars: np.ndarray, near_factor: float = SCENE_NEAR_FACTOR,
            far_factor: float = SCENE_FAR_FACTOR) -> np.ndarray:
    """``(K, 2)`` Eq. 1 scale ranges of objects whose depths span ``[nears[k], fars[k]]``."""
    scene_near, scene_far = scene_volume(nears, fars, near_factor, far_factor)
    return np.array([scale_range(scene_near, scene_far, n, f) for n, f in zip(nears, fars)])


def denormalise(s_norm: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Eq. 1 on ``(..., K)`` normalised scales with per-object ``ranges (K, 2)``."""
    return ranges[:, 0] * (1.0 - s_norm) + ranges[:, 1] * s_norm


def normalise(sbar: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Inverse of :func:`denormalise`."""
    return (sbar - ranges[:, 0]) / (ranges[:, 1] - ranges[:, 0])


def configured_poses(object_to_scene: np.ndarray, camera_centres: np.ndarray, sbar: float) -> np.ndarray:
    """``(F, 4, 4)`` poses of one object scaled by ``sbar`` about each frame's training camera centre."""
    return np.stack([scale_about(c, float(sbar)) @ P for P, c in zip(object_to_scene, camera_centres)])


def scale_scores(
    layers: Sequence[tuple[np.ndarray, np.ndarray]] | None,
    sbar: np.ndarray,
    ranges: np.ndarray,
    anchor_index: int,
    hidden: str = "relu",
    output: str = "sigmoid",
) -> np.ndarray:
    """Validity scores ``(N,)`` of actual scales ``sbar (N, K)``: Eq. 1 inverted, anchor dropped,
    then the network (all ones without a network: a single object is always valid)."""
    sbar = np.atleast_2d(sbar)
    if layers is None:
        return np.ones(len(sbar))
    free = [k for k in range(sbar.shape[1]) if k != anchor_index]
    return scale_net_numpy(layers, normalise(sbar[:, free], ranges[free]), hidden, output)


#: Points scored along each chord of a climbing step: a set a few hundredths of the box across
#: along a chord holds several of them.
CHORD_POINTS = 128
#: Largest normalised coordinate: the box is [0, 1) per axis.
_TOP = 1.0 - 1e-9
#: Shrinkage proposals per hit-and-run step before a chain stays where it is (each rejected one
#: cuts the chord's interval at least in two about the chain's point, which always lies inside).
SHRINK_TRIES = 60


def _unit_directions(m: int, dim: int, rng: np.random.Generator) -> np.ndarray:
    d = rng.standard_normal((m, dim))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _chords(x: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the interval ``[lo, hi]`` of t (``lo <= 0 <= hi``) with ``x + t d`` in the box [0, 1)^D."""
    safe = np.where(d == 0.0, 1.0, d)  # a zero component never limits the chord
    a, b = -x / safe, (_TOP - x) / safe
    lo = np.where(d == 0.0, -np.inf, np.minimum(a, b)).max(1)
    hi = np.where(d == 0.0, np.inf, np.maximum(a, b)).min(1)
    return np.minimum(lo, 0.0), np.maximum(hi, 0.0)


def _chord_points(x: np.ndarray, rng: np.random.Generator, points: int) -> np.ndarray:
    """``(m, points, D)`` points of the box's chords through ``x (m, D)`` along random directions,
    on a stratified grid (one random offset per chord)."""
    m, dim = x.shape
    d = _unit_directions(m, dim, rng)
    lo, hi = _chords(x, d)
    t = lo[:, None] + (hi - lo)[:, None] * (np.arange(points) + rng.random((m, 1))) / points
    return np.clip(x[:, None] + t[..., None] * d[:, None], 0.0, _TOP)


def _shrinkage_moves(score: Callable[[np.ndarray], np.ndarray], x: np.ndarray, d: np.ndarray, threshold: float,
                     rng: np.random.Generator) -> np.ndarray:
    """Each row of ``x`` moved along its direction ``d`` to a point drawn uniformly from the set on
    its chord, by slice sampling's shrinkage (Neal 2003): propose uniformly on the chord's interval,
    and on a miss cut the interval at the proposal, keeping the side that holds the current point.
    For a uniform target this move is reversible whatever the set's shape."""
    x = x.copy()
    lo, hi = _chords(x, d)
    active = np.arange(len(x))
    for _ in range(SHRINK_TRIES):
        if not len(active):
            break
        t = lo[active] + (hi[active] - lo[active]) * rng.random(len(active))
        cand = np.clip(x[active] + t[:, None] * d[active], 0.0, _TOP)
        ok = np.asarray(score(cand), dtype=np.float64) > threshold
        x[active[ok]] = cand[ok]
        miss, tm = active[~ok], t[~ok]
        lo[miss[tm < 0]] = tm[tm < 0]
        hi[miss[tm >= 0]] = tm[tm >= 0]
        active = miss
    return x


def hit_and_run(
    score: Callable[[np.ndarray], np.ndarray], start: np.ndarray, count: int, threshold: float,
    rng: np.random.Generator, chains: int = 0, burn_in: int = 0, thin: int = 5,
) -> np.ndarray:
    """``(count, D)`` points drawn uniformly from the set ``{s in [0, 1)^D : score(s) > threshold}``
    by hit-and-run from points ``start (k, D)`` inside it.

    Each step moves every chain along a direction to a uniform point of the set on that line
    (:func:`_shrinkage_moves`). Half of the chains move at a time, along random directions or,
    alternately, along the difference of two chains of the other half: the direction does not
    depend on the moving chain, so each move is reversible with respect to the uniform
    distribution on the set, and differences of spread chains follow the set's long axes, which
    random directions almost never do on a thin slanted slab (an ensemble sampler, after
    Karamanis and Beutler's ensemble slice sampling). This is what draws a set far too small for
    uniform draws (a millionth of the box) uniformly. ``chains`` chains (default: 200, more for
    large counts so that each gives at most 50 points, at most 4096) start at points of ``start``
    (cycled), run ``burn_in`` steps (default ``40 + 10 D``) and then give a point every ``thin``
    steps. ``score`` maps ``(n, D)`` to ``(n,)``.
    """
    start = np.atleast_2d(np.asarray(start, dtype=np.float64))
    dim = start.shape[1]
    if count <= 0:
        return np.zeros((0, dim))
    chains = max(2, min(chains or min(4096, max(200, count // 50)), max(count, 2)))
    x = start[np.arange(chains) % len(start)].copy()
    halves = (np.arange(0, chains, 2), np.arange(1, chains, 2))
    burn_in = 40 + 10 * dim if burn_in <= 0 else burn_in
    out: list[np.ndarray] = []
    step, taken = 0, 0
    while taken < count:
        for k, (move, other) in enumerate((halves, halves[::-1])):
            d = _unit_directions(len(move), dim, rng)
            if (step + k) % 2:  # along differences of the other half's chains, where they differ
                a, b = rng.integers(len(other), size=(2, len(move)))
                diff = x[other[a]] - x[other[b]]
                norm = np.linalg.norm(diff, axis=1)
                use = norm > 0
                d[use] = diff[use] / norm[use, None]
            x[move] = _shrinkage_moves(score, x[move], d, threshold, rng)
        step += 1
        if step > burn_in and (step - burn_in) % thin == 0:
            out.append(x[: count - taken].copy())
            taken += len(out[-1])
    return np.concatenate(out)


def climb_into_set(
    score: Callable[[np.ndarray], np.ndarray], start: np.ndarray, threshold: float, rng: np.random.Generator,
    steps: int = 200, points: int = CHORD_POINTS, patience: int = 20,
) -> np.ndarray:
    """Points of ``{score > threshold}`` found by climbing from ``start (m, D)`` (e.g. the
    best-scoring uniform draws), ``(k, D)`` with k = 0 when none is found.

    Each step scores a random chord's grid through every point (:func:`_chord_points`) and moves
    each point to the best of them when that scores higher: a derivative-free ascent that finds a
    set uniform draws miss, to start :func:`hit_and_run` from. Stops once some point is inside,
    or after ``patience`` steps in which no point rose (a score flat to the last digit).
    """
    x = np.atleast_2d(np.asarray(start, dtype=np.float64)).copy()
    m, dim = x.shape
    p = np.asarray(score(x), dtype=np.float64)
    still = 0
    for _ in range(steps):
        if (p > threshold).any() or still >= patience:
            break
        cand = _chord_points(x, rng, points)
        q = np.asarray(score(cand.reshape(-1, dim)), dtype=np.float64).reshape(m, points)
        j = q.argmax(1)
        better = q[np.arange(m), j] > p
        x[better], p[better] = cand[np.arange(m), j][better], q[np.arange(m), j][better]
        still = 0 if better.any() else still + 1
    return x[p > threshold]


def fill_from_set(
    score: Callable[[np.ndarray], np.ndarray], inside: np.ndarray, best: np.ndarray, count: int, threshold: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """``(count, D)`` more points of ``{score > threshold}`` in [0, 1)^D, drawn by :func:`hit_and_run`
    from the points ``inside (k, D)`` already found there or, when there are none, from where
    :func:`climb_into_set` enters the set from ``best (m, D)`` (the best-scoring draws); ``(0, D)``
    when neither finds a point of the set. What every sampler of the learned set does once its
    uniform draws find too few."""
    start = inside if len(inside) else climb_into_set(score, best, threshold, rng) if len(best) else best
    if not len(start):
        return np.zeros((0, np.shape(inside)[-1]))
    return hit_and_run(score, start, count, threshold, rng)


#: :func:`learned_intervals` adds hit-and-run points where fewer uniform draws than this are valid.
MIN_INTERVAL_POINTS = 100


def learned_intervals(
    layers: Sequence[tuple[np.ndarray, np.ndarray]] | None,
    ranges: np.ndarray,
    anchor_index: int,
    threshold: float = 0.5,
    hidden: str = "relu",
    output: str = "sigmoid",
    draws: int = 200_000,
    seed: int = 0,
) -> np.ndarray:
    """``(K, 2)`` per-object actual-scale interval of the learned valid set (its bounding box).

    Monte-Carlo over the whole normalised domain [0, 1)^(K-1); where fewer than
    :data:`MIN_INTERVAL_POINTS` draws are valid (a set of a millionth of the box), also
    :func:`hit_and_run` from them (or from :func:`climb_into_set` when none is), so the box is that
    of the set and not of a few draws. The anchor's interval is [1, 1]. Raises
    :class:`~scenecore.errors.EmptyValidSet` when no valid point is found (the network accepts nothing), instead of
    returning an empty or inverted interval.
    """
    K = len(ranges)
    out = np.ones((K, 2))
    free = [k for k in range(K) if k != anchor_index]
    if not free:
        return out
    if layers is None:
        out[free] = ranges[free]
        return out
    rng = np.random.default_rng(seed)
    s = rng.random((draws, len(free)))
    p = scale_net_numpy(layers, s, hidden, output)
    inside = s[p >= threshold]
    if len(inside) < MIN_INTERVAL_POINTS:
        inside = np.concatenate([inside, fill_from_set(lambda x: scale_net_numpy(layers, x, hidden, output), inside,
                                                       s[np.argsort(-p, kind="stable")[:64]], 10 * MIN_INTERVAL_POINTS,
                                                       threshold, rng)])
        if not len(inside):
            raise EmptyValidSet(f"the scale network accepts none of {draws} uniform draws, nor a point climbing "
                                    "from the best of them: no valid configuration")
    sbar = denormalise(inside, ranges[free])
    out[free, 0], out[free, 1] = sbar.min(0), sbar.max(0)
    return out


def sample_valid_configurations(
    score: Callable[[np.ndarray], np.ndarray], intervals: np.ndarray, threshold: float, count: int, seed: int,
    max_draws: int = 1_000_000,
) -> np.ndarray:
    """``(count, K)`` actual scales drawn uniformly from the valid set inside ``intervals (K, 2)``.

    Seeded rejection sampling through ``score`` (actual scales ``(N, K)`` -> ``(N,)``, e.g.
    :meth:`ExportData.validity`), batch by batch, so the result depends only on ``seed``; when
    ``max_draws`` draws give too few (a set that fills little of its intervals' box), the rest
    are drawn by :func:`hit_and_run` from those found. Raises ``EmptyValidSet`` when no draw
    is valid.
    """
    rng = np.random.default_rng(seed)
    lo, hi = intervals[:, 0], intervals[:, 1]
    kept: list[np.ndarray] = []
    drawn = found = 0
    while found < count and drawn < max_draws:
        batch = lo + (hi - lo) * rng.random((4096, len(lo)))
        drawn += len(batch)
        kept.append(batch[score(batch) >= threshold])
        found += len(kept[-1])
    if not found:
        raise EmptyValidSet(f"no valid configuration in {drawn} draws inside the learned intervals")
    inside = np.concatenate(kept)[:count]
    if found < count:  # in the intervals' unit cube; ">= threshold" as the draws above
        span = np.where(hi > lo, hi - lo, 1.0)
        more = fill_from_set(lambda u: score(lo + (hi - lo) * u), (inside - lo) / span, np.zeros((0, len(lo))),
                             count - found, np.nextafter(threshold, -np.inf), rng)
        inside = np.concatenate([inside, lo + (hi - lo) * more])
    return inside
