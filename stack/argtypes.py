"""argparse value types shared by the command-line tools (each error is one line, exit 2)."""

from __future__ import annotations

import argparse
import re


def _number(text: str, kind: type, low: float, what: str):
    """``text`` as ``kind`` (int or float), finite and >= ``low``; else one line naming ``what`` was expected."""
    try:
        x = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not (low <= x < float("inf")):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return x


def positive_int(text: str) -> int:
    return _number(text, int, 1, "a positive integer")


def nonnegative_int(text: str) -> int:
    return _number(text, int, 0, "an integer >= 0")


def nonnegative_float(text: str) -> float:
    return _number(text, float, 0.0, "a number >= 0")


def fleet_name(text: str) -> str:
    """A fleet name: one key-expression chunk, ``stack/<fleet>/``."""
    if not re.fullmatch(r"[A-Za-z0-9_-]+", text):
        raise argparse.ArgumentTypeError(f"expected letters, digits, '_' or '-' (a key-expression chunk), got {text!r}")
    return text
