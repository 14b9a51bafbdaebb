"""The value check of the policies' settings that declare no rules of their own (``MrcConfig``, ``SupervisorConfig``)."""

from __future__ import annotations

from dataclasses import fields

from ..settings import convert, hints


def check_numbers(cfg, positive: tuple[str, ...] = ()) -> None:
    """Every ``float`` / ``int`` field of the dataclass ``cfg`` a finite number >= 0 (> 0 where named in
    ``positive``), every ``bool`` field a bool: else ValueError ``field: what`` (as :mod:`stack.settings` says it)."""
    th = hints(type(cfg))
    for f in fields(cfg):
        if th[f.name] in (bool, int, float):
            conds = () if th[f.name] is bool else ("> 0",) if f.name in positive else (">= 0",)
            object.__setattr__(cfg, f.name, convert(th[f.name], getattr(cfg, f.name), f.name, conds))
