"""scenecore.config: one way to check a config, each error one line naming its section and key."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from scenecore.config import Rule, check_keys, choice, flag, from_dict, integer, number, validate


@dataclass
class Inner:
    size: int = 2
    rate: float = 0.5

    def __post_init__(self) -> None:
        validate(self, "inner", {"size": integer(1), "rate": number(0.0, 1.0, lo_open=True)})


@dataclass
class Outer:
    name: str = "a"
    verbose: bool = False
    inner: Inner = field(default_factory=Inner)

    def __post_init__(self) -> None:
        validate(self, "outer", {"name": choice("a", "b"), "verbose": flag()})


def test_integer_rejects_bools_fractions_and_values_below_the_least() -> None:
    rule = integer(1)
    assert rule.ok(1) and rule.ok(10**12)
    assert not rule.ok(0) and not rule.ok(True) and not rule.ok(1.5) and not rule.ok(2.0) and not rule.ok("3")
    assert integer().ok(-5) and not integer().ok(False)
    assert rule.what == "an integer >= 1" and integer().what == "an integer"


def test_number_rejects_nan_inf_bools_and_strings() -> None:
    rule = number()
    assert rule.ok(0) and rule.ok(-2.5) and rule.ok(1e300)
    for bad in (math.nan, math.inf, -math.inf, True, "1.0", None):
        assert not rule.ok(bad), bad
    assert rule.what == "a finite number"


@pytest.mark.parametrize(("rule", "inside", "outside", "what"), [
    (number(0.0, 1.0), [0, 0.5, 1.0], [-1e-9, 1.000001], "a number in [0, 1]"),
    (number(0.0, 1.0, hi_open=True), [0.0, 0.999999], [1.0], "a number in [0, 1)"),
    (number(0.0, 1.0, lo_open=True), [1e-12, 1.0], [0.0], "a number in (0, 1]"),
    (number(0.0, lo_open=True), [1e-300, 5], [0.0, -1], "a number > 0"),
    (number(0.0), [0.0, 5], [-1e-9], "a number >= 0"),
    (number(hi=2.0, hi_open=True), [-7, 1.9], [2.0], "a number < 2"),
    (number(hi=2.0), [2.0], [2.1], "a number <= 2"),
])
def test_number_bounds_are_open_or_closed(rule: Rule, inside: list, outside: list, what: str) -> None:
    assert all(rule.ok(v) for v in inside) and not any(rule.ok(v) for v in outside)
    assert rule.what == what


def test_choice_and_flag() -> None:
    assert choice("a", "b").ok("b") and not choice("a", "b").ok("c")
    assert choice(0, 1).ok(1) and not choice(0, 1).ok(True) and choice(True, 0).ok(True)
    assert choice("x", 3).what == "one of x, 3"
    assert flag().ok(False) and not flag().ok(0) and not flag().ok("true")


def test_validate_names_the_section_key_and_value() -> None:
    with pytest.raises(ValueError, match=r"^inner config: size must be an integer >= 1, got 0$"):
        Inner(size=0)
    with pytest.raises(ValueError, match=r"^inner config: size must be an integer >= 1, got True$"):
        Inner(size=True)
    with pytest.raises(ValueError, match=r"^inner config: size must be an integer >= 1, got 1.5$"):
        Inner(size=1.5)
    with pytest.raises(ValueError, match=r"^inner config: rate must be a number in \(0, 1\], got nan$"):
        Inner(rate=math.nan)
    with pytest.raises(ValueError, match=r"^outer config: verbose must be true or false, got 'yes'$"):
        Outer(verbose="yes")


def test_unknown_keys_are_rejected_at_every_level() -> None:
    check_keys(Inner, {"size": 3}, "inner")
    with pytest.raises(ValueError, match=r"^unknown outer config keys: \['nmae'\]$"):
        from_dict(Outer, {"nmae": "b"}, "outer", nested={"inner": (Inner, "inner")})
    with pytest.raises(ValueError, match=r"^unknown inner config keys: \['rat', 'szie'\]$"):
        from_dict(Outer, {"inner": {"szie": 3, "rat": 0.1}}, "outer", nested={"inner": (Inner, "inner")})


def test_from_dict_builds_nested_sections_and_names_them() -> None:
    nested = {"inner": (Inner, "inner")}
    assert from_dict(Outer, None, "outer") == Outer()
    assert from_dict(Outer, {"name": "b", "inner": {"size": 4}}, "outer", nested) == Outer(name="b", inner=Inner(size=4))
    assert from_dict(Outer, {"inner": None}, "outer", nested) == Outer()  # an empty YAML section
    with pytest.raises(ValueError, match=r"^inner config: size must be an integer >= 1, got -1$"):
        from_dict(Outer, {"inner": {"size": -1}}, "outer", nested)
    with pytest.raises(ValueError, match=r"^outer config: inner must be a mapping, got 3$"):
        from_dict(Outer, {"inner": 3}, "outer", nested)
