"""The one value check the policies' settings share (``DrlConfig``, ``FuzzyConfig``, ``MrcConfig``, ``SupervisorConfig``)."""

from __future__ import annotations

import math
from dataclasses import fields


def check_numbers(cfg, positive: tuple[str, ...] = ()) -> None:
    """Every ``float`` / ``int`` field of the dataclass ``cfg`` a finite number >= 0 (> 0 where named in
    ``positive``), every ``bool`` field a bool: else ValueError naming the field."""
    for f in fields(cfg):
        v = getattr(cfg, f.name)
        kind = str(f.type)
        if kind == "bool":
            if not isinstance(v, bool):
                raise ValueError(f"{f.name}: expected true or false, got {v!r}")
        elif kind in ("float", "int"):
            ok = (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                  and (v > 0 if f.name in positive else v >= 0) and (kind == "float" or float(v).is_integer()))
            if not ok:
                what = "an integer" if kind == "int" else "a number"
                raise ValueError(f"{f.name}: expected {what} {'> 0' if f.name in positive else '>= 0'}, got {v!r}")
