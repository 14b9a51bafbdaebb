"""argparse value types shared by the command-line tools (each error is one line, exit 2)."""

from __future__ import annotations

import argparse
import re


def positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n


def fleet_name(text: str) -> str:
    """A fleet name: one key-expression chunk, ``stack/<fleet>/``."""
    if not re.fullmatch(r"[A-Za-z0-9_-]+", text):
        raise argparse.ArgumentTypeError(f"expected letters, digits, '_' or '-' (a key-expression chunk), got {text!r}")
    return text
