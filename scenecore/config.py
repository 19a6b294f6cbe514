"""One way to validate configuration dataclasses (training, fields, preprocessing, evaluation).

A config is a dataclass whose ``__post_init__`` calls :func:`validate` with one :class:`Rule`
per checked field; YAML/dict input goes through :func:`from_dict`, which rejects misspelt keys.
Every error is a ``ValueError`` whose message names the section and key, e.g.
``training config: rays must be an integer >= 1, got 0``, so the CLI prints it as one line.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, TypeVar

C = TypeVar("C")


@dataclass(frozen=True)
class Rule:
    """A check of one value: ``ok(value)`` must hold; ``what`` completes "must be ..."."""

    ok: Callable[[Any], bool]
    what: str


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def integer(least: int | None = None, most: int | None = None) -> Rule:
    """An integer (not a bool, not 1.5), at least ``least`` and at most ``most`` when given."""
    if most is None:
        what = "an integer" + (f" >= {least}" if least is not None else "")
    else:
        what = f"an integer in {least if least is not None else '...'}..{most:,}"
    return Rule(lambda v: _is_int(v) and (least is None or v >= least) and (most is None or v <= most), what)


def number(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
           what: str | None = None) -> Rule:
    """A finite number in the interval given by ``lo``/``hi`` (closed unless ``*_open``)."""

    def ok(v: Any) -> bool:
        if not _is_number(v):
            return False
        if lo is not None and (v <= lo if lo_open else v < lo):
            return False
        return not (hi is not None and (v >= hi if hi_open else v > hi))

    if what is None:
        left = "" if lo is None else ("(" if lo_open else "[") + f"{lo:g}"
        right = "" if hi is None else f"{hi:g}" + (")" if hi_open else "]")
        if lo is not None and hi is not None:
            what = f"a number in {left}, {right}"
        elif lo is not None:
            what = f"a number {'>' if lo_open else '>='} {lo:g}"
        elif hi is not None:
            what = f"a number {'<' if hi_open else '<='} {hi:g}"
        else:
            what = "a finite number"
    return Rule(ok, what)


def choice(*values: Any) -> Rule:
    """One of ``values`` (a bool is not taken for ``0`` or ``1``)."""
    return Rule(lambda v: any(v == x and isinstance(v, bool) == isinstance(x, bool) for x in values),
                "one of " + ", ".join(str(x) for x in values))


def flag() -> Rule:
    """``true`` or ``false``."""
    return Rule(lambda v: isinstance(v, bool), "true or false")


def validate(obj: Any, section: str, rules: Mapping[str, Rule]) -> None:
    """Check ``getattr(obj, name)`` against every rule; the first failure raises ``ValueError``."""
    for name, rule in rules.items():
        v = getattr(obj, name)
        if not rule.ok(v):
            raise ValueError(f"{section} config: {name} must be {rule.what}, got {v!r}")


def check_keys(cls: type, d: Mapping[str, Any], section: str) -> None:
    """Reject keys that are not fields of ``cls`` (a misspelt key must not be silently ignored)."""
    unknown = set(d) - {f.name for f in dataclasses.fields(cls)}
    if unknown:
        raise ValueError(f"unknown {section} config keys: {sorted(unknown)}")


def from_dict(cls: type[C], d: Mapping[str, Any] | None, section: str,
              nested: Mapping[str, tuple[type, str]] | None = None) -> C:
    """Build ``cls`` from a plain dict (e.g. parsed YAML), checking keys at every level.

    ``nested`` maps a key to ``(dataclass, section)`` for sub-configs given as dicts.
    """
    d = dict(d or {})
    check_keys(cls, d, section)
    for key, (sub, sub_section) in (nested or {}).items():
        if key in d:
            value = d[key] or {}
            if not isinstance(value, Mapping):
                raise ValueError(f"{section} config: {key} must be a mapping, got {value!r}")
            d[key] = from_dict(sub, value, sub_section)
    try:
        return cls(**d)
    except TypeError as e:  # e.g. a value of the wrong type reaching a dataclass default factory
        raise ValueError(f"{section} config: {e}") from None
