"""The generic settings reader (stack.settings) on a config of every kind of field it knows."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from stack.settings import SettingError, check, field_docs, read, rows, rule


@dataclass(frozen=True)
class Inner:
    RULE = (">= 0",)

    gain: float = 1.0
    """A gain."""
    steps: int = field(default=3, metadata=rule(">= 1", "<= 10"))
    """A count."""

    def __post_init__(self):
        check(self)


@dataclass(frozen=True)
class Outer:
    mode: Literal["a", "b"] = "a"
    """Which mode."""
    on: bool = True
    """A switch."""
    name: str | None = None
    """A name, or none."""
    span: tuple[float, float] = (0.0, 1.0)
    """Two numbers, low < high."""
    tags: tuple[str, ...] = ()
    """Any number of words."""
    inner: Inner = field(default_factory=Inner)
    """Nested settings."""

    def __post_init__(self):
        check(self)
        if not self.span[0] < self.span[1]:
            raise ValueError(f"span: low must be below high, got {list(self.span)}")


def test_values_are_read_by_type_and_merged_over_a_base():
    o = read(Outer, {"mode": "b", "span": [1, 2], "tags": ["x", "y"], "inner": {"steps": 5}}, "p")
    assert (o.mode, o.span, o.tags, o.inner) == ("b", (1.0, 2.0), ("x", "y"), Inner(1.0, 5))
    assert isinstance(o.span[0], float)
    o2 = read(Outer, {"inner": {"gain": 2}, "name": None}, "q", base=o)
    assert (o2.mode, o2.inner.steps, o2.inner.gain, o2.name) == ("b", 5, 2.0, None)
    assert read(Outer, None, "p") == Outer()


@pytest.mark.parametrize("value,message", [
    ({"mood": 1}, "p.mood: unknown field (allowed: inner, mode, name, on, span, tags)"),
    ({"mode": "c"}, "p.mode: expected one of a, b, got 'c'"),
    ({"on": "yes"}, "p.on: expected true or false, got text ('yes')"),
    ({"name": 3}, "p.name: expected text, got a number (3)"),
    ({"span": [1]}, "p.span: expected 2 numbers, got 1"),
    ({"span": [1, float("inf")]}, "p.span[1]: expected a finite number, got inf"),
    ({"span": [2, 1]}, "p.span: low must be below high, got [2.0, 1.0]"),
    ({"tags": "x"}, "p.tags: expected a list, got text ('x')"),
    ({"inner": {"steps": 11}}, "p.inner.steps: must be <= 10, got 11"),
    ({"inner": {"gain": -1}}, "p.inner.gain: must be >= 0, got -1"),
    ({"inner": {"steps": 2.0}}, "p.inner.steps: expected an integer, got a number (2.0)"),
    ({"inner": 3}, "p.inner: expected a mapping, got a number (3)"),
    ([1], "p: expected a mapping, got a list of 1"),
])
def test_a_bad_value_is_one_line_naming_its_path(value, message):
    with pytest.raises(SettingError) as e:
        read(Outer, value, "p")
    assert str(e.value) == message


def test_direct_construction_is_checked_too_and_docs_come_from_the_fields():
    with pytest.raises(ValueError, match="gain: must be >= 0, got -2"):
        Inner(gain=-2)
    assert field_docs(Outer)["span"] == "Two numbers, low < high."
    table = {key: (default, accepted) for key, default, accepted, _ in rows(Outer)}
    assert table["inner.steps"] == (3, "an integer >= 1, <= 10") and table["name"] == (None, "text, or null")
    assert table["mode"] == ("a", "one of a, b")
