"""Command-line flags generated from a job dataclass (CleanRL style: the dataclass is the one place).

Each field of the dataclass becomes ``--field-name``; its help is the field's docstring (the
string literal right below it) with the default appended. What argparse needs beyond the
annotation goes in the field's metadata, through :func:`flag`:

* ``type``: the value parser (e.g. :func:`stack.argtypes.positive_int`; default: the annotation's type);
* ``name``: another flag name (``--walls`` for ``max_walls``); ``choices``, ``metavar``;
* ``off``: an extra flag that sets a boolean field False (``--mse`` for ``huber``);
* ``cli=False``: no flag for this field.

Booleans get ``--name/--no-name``; ``X | None = None`` fields take an X and stay None when not given.
:func:`job_from_args` builds the dataclass back from the parsed namespace.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
import typing
from pathlib import Path

__all__ = ["add_job_arguments", "field_docs", "flag", "job_from_args"]


def flag(default=dataclasses.MISSING, *, default_factory=dataclasses.MISSING, **meta):
    """A dataclass field with command-line metadata (see the module docstring)."""
    kw = {"default": default} if default_factory is dataclasses.MISSING else {"default_factory": default_factory}
    return dataclasses.field(metadata=meta, **kw)


def field_docs(cls) -> dict[str, str]:
    """Field name -> its docstring (the string literal after the field in the class body), one line."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body
    docs = {}
    for node, nxt in zip(body, body[1:]):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str)):
            docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


def _base_type(hint):
    """The X of ``X`` or ``X | None``."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if args else hint


def add_job_arguments(p: argparse.ArgumentParser, cls) -> None:
    """One flag per field of the dataclass ``cls`` (its docstring as help)."""
    docs, hints = field_docs(cls), typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        meta = f.metadata
        if not meta.get("cli", True):
            continue
        name = meta.get("name", "--" + f.name.replace("_", "-"))
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        shown = "" if default is None else f" (default {default})"
        kw = {"dest": f.name, "default": default, "help": docs.get(f.name, "") + shown}
        base = _base_type(hints[f.name])
        if base is bool:
            p.add_argument(name, action=argparse.BooleanOptionalAction, **kw)
            if "off" in meta:
                p.add_argument(meta["off"], dest=f.name, action="store_false", help=f"same as --no-{name[2:]}")
            continue
        kw["type"] = meta.get("type", Path if base is Path else base)
        for k in ("choices", "metavar"):
            if k in meta:
                kw[k] = meta[k]
        p.add_argument(name, **kw)


def job_from_args(cls, args: argparse.Namespace, **extra):
    """The dataclass ``cls`` from the parsed flags (fields without a flag keep their defaults)."""
    kw = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if f.metadata.get("cli", True)}
    return cls(**(kw | extra))
