"""The object scale network: validity score of a normalised scale vector (paper section 3.2).

Input: the K-1 normalised scales ``s`` in [0, 1) of every object but the anchor (fixed at
``sbar = 1`` and left out). Output: one logit; ``sigmoid`` of it is the validity score. Trained
with ``BCEWithLogits`` (never BCE on probabilities). Eq. 1 maps ``s`` to ``sbar``.
"""

from __future__ import annotations

import logging

from typing import Callable

import torch
from torch import nn

from osn.preprocess.inputs import denormalise_scales

log = logging.getLogger(__name__)

#: Score above which a configuration belongs to the learned valid set (the classifier's decision
#: boundary): used by sampling, the valid-set accuracy and the export. Training picks its stage-2
#: configurations with the stricter :data:`FIELD_STEP_THRESHOLD`.
VALID_THRESHOLD = 0.5
#: Score a field step's scale vector must exceed (the paper, Sec. 3.3 below Eq. 4: "above 0.95");
#: when no candidate does, the best one is used and counted (``Trainer.fallbacks``).
FIELD_STEP_THRESHOLD = 0.95


class NonFiniteScores(ValueError):
    """The scale network scored some candidates NaN (its weights diverged)."""


def check_scores(p: torch.Tensor, where: str = "") -> torch.Tensor:
    """``p (N,)`` unchanged if every score is a number; otherwise :class:`NonFiniteScores`
    (its message starts with ``where:`` when given, e.g. the checkpoint's path).

    ``p > threshold`` is False for NaN and ``argmax`` takes NaN as the maximum, so a NaN score
    would otherwise pick an arbitrary sample as "best".
    """
    bad = int(torch.isnan(p).sum())
    if bad:
        prefix = f"{where}: " if where else ""
        raise NonFiniteScores(f"{prefix}the scale network scores {bad} of {len(p)} candidates NaN (diverged weights)")
    return p


class ScaleNet(nn.Module):
    """MLP with ``layers`` hidden layers of ``width`` and a validity logit; the defaults are the
    paper's (appendix "Details of Networks", Object Scale Network: 4 hidden layers of 64 nodes)."""

    def __init__(self, num_free: int, width: int = 64, layers: int = 4, seed: int = 0) -> None:
        super().__init__()
        if num_free < 1:
            raise ValueError("the scale network needs at least one non-anchor object")
        self.num_free = num_free
        dims = [num_free] + [width] * layers
        mods: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            mods += [nn.Linear(a, b), nn.ReLU()]
        mods.append(nn.Linear(width, 1))
        self.mlp = nn.Sequential(*mods)
        g = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            for m in self.mlp:
                if isinstance(m, nn.Linear):
                    bound = (6.0 / m.in_features) ** 0.5 / 2
                    m.weight.uniform_(-bound, bound, generator=g)
                    m.bias.zero_()

    def forward(self, s: torch.Tensor) -> torch.Tensor:
        """Logits ``(N,)`` of normalised free scales ``s (N, K-1)``; inputs centred to [-1, 1)."""
        return self.mlp(s * 2.0 - 1.0)[:, 0]

    def prob(self, s: torch.Tensor) -> torch.Tensor:
        """Validity scores ``(N,)`` in (0, 1) of normalised free scales ``s (N, K-1)``."""
        return torch.sigmoid(self(s))


def full_sbar(s_free: torch.Tensor, ranges: torch.Tensor, anchor: int) -> torch.Tensor:
    """De-normalised ``(N, K)`` scale vectors from free normalised scales ``(N, K-1)``; anchor = 1.

    ``ranges (K, 2)`` is every object's Eq. 1 scale range (the anchor's row is ignored); the
    result has ``ranges``'s dtype on ``s_free``'s device.
    """
    K = ranges.shape[0]
    free = [k for k in range(K) if k != anchor]
    out = torch.ones(s_free.shape[0], K, dtype=ranges.dtype, device=s_free.device)
    out[:, free] = denormalise_scales(s_free.to(ranges.dtype), ranges[free])
    return out


def sample_valid(
    net: ScaleNet,
    ranges: torch.Tensor,
    anchor: int,
    generator: torch.Generator,
    candidates: int = 256,
    threshold: float = 0.95,
    warn: bool = True,
    near: Callable[[int], torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, float, bool]:
    """Draw one scale vector the network deems valid (score > ``threshold``).

    Uniform candidates in [0, 1)^(K-1) (``ranges (K, 2)`` as in :func:`full_sbar`); one of those
    above the threshold is picked uniformly.
    When none passes and ``near`` is given, ``near(candidates)`` supplies a second set ``(candidates, K-1)`` (e.g.
    around vectors labelled valid before: the valid share of the box shrinks exponentially with
    the object count, so uniform candidates can all miss it) and one of those that pass is
    picked; the uniform draw, which covers the whole valid set, stays the rule. When none
    passes, the best-scoring candidate of either set is used and a warning is logged (unless ``warn`` is
    False because the caller counts fallbacks). Raises :class:`NonFiniteScores` on a NaN score,
    never otherwise. Returns
    ``(sbar (K,), s_free (K-1,), score, fell_back)``.
    """
    dev = ranges.device
    s = torch.rand(candidates, net.num_free, generator=generator, device=generator.device).to(dev)
    with torch.no_grad():
        p = check_scores(net.prob(s))
    ok = torch.nonzero(p > threshold)[:, 0]
    if not len(ok) and near is not None:
        s2 = near(candidates).to(dev)
        with torch.no_grad():
            p2 = check_scores(net.prob(s2))
        # Both sets together: one passing near candidate is picked, or the best of either set.
        s, p = torch.cat([s, s2]), torch.cat([p, p2])
        ok = torch.nonzero(p > threshold)[:, 0]
    if len(ok):
        i = ok[torch.randint(len(ok), (1,), generator=generator, device=generator.device).to(dev)][0]
        fell_back = False
    else:
        i = torch.argmax(p)
        fell_back = True
        if warn:  # callers that count fallbacks themselves report them once, not per draw
            log.warning("no sampled scale vector scored above %.3g (best %.3g): using the best one", threshold, float(p[i]))
    s_i = s[i : i + 1]
    return full_sbar(s_i, ranges, anchor)[0], s_i[0], float(p[i]), fell_back
