"""Typed settings from plain data: one reader for every plugin's config dataclass.

A plugin declares its settings as a dataclass with a docstring under each field. What a field
accepts follows from its type (``bool``, ``int``, ``float`` (finite), ``str``, ``X | None``,
``tuple[...]``, ``Literal[...]``, a nested dataclass) and from an optional range rule in the
field's metadata (``field(default=..., metadata=rule("> 0", "<= 1"))``) or, for every number
field without one, the class attribute ``RULE`` (e.g. ``RULE = (">= 0",)``). Rules across fields
go in the class's ``__post_init__`` (after ``check(self)``), raising ``ValueError("field: what")``.
A nested dataclass field with ``metadata={"inline": True}`` takes its fields at the parent's level.

:func:`read` turns a mapping into an instance (unknown keys are errors) and raises
:class:`SettingError` naming the path, e.g. ``robots[2].qlearn.cell: must be > 0, got -0.5``.
"""

from __future__ import annotations

import ast
from collections import abc
import inspect
import math
import operator
import textwrap
import types
import typing
from dataclasses import MISSING, fields, is_dataclass, replace
from functools import lru_cache
from typing import Any, Literal, Union

_OPS = {">": operator.gt, ">=": operator.ge, "<": operator.lt, "<=": operator.le}


class SettingError(ValueError):
    """A setting that cannot be used: ``path`` names it, ``what`` says why; ``str()`` is ``path: what``."""

    def __init__(self, path: str, what: str):
        super().__init__(f"{path}: {what}" if path else what)
        self.path, self.what = path, what


def rule(*conds: str) -> dict:
    """Field metadata: range conditions such as ``"> 0"``, ``">= 1"``, ``"<= 1"`` (all must hold)."""
    for c in conds:
        _parse_cond(c)
    return {"rule": conds}


def _parse_cond(cond: str) -> tuple[str, float]:
    op, _, bound = cond.strip().partition(" ")
    if op not in _OPS:
        raise ValueError(f"bad rule {cond!r}: expected e.g. '> 0' or '<= 1'")
    return op, float(bound)


def kind(value: Any) -> str:
    """How a value reads in a message: ``a number (1.5)``, ``text ('x')``, ``nothing``..."""
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"a boolean ({value})"
    if isinstance(value, (int, float)):
        return f"a number ({value})"
    if isinstance(value, str):
        return f"text ({value!r})"
    if isinstance(value, (list, tuple)):
        return f"a list of {len(value)}"
    if isinstance(value, dict):
        return "a mapping"
    return type(value).__name__


@lru_cache(maxsize=None)
def hints(cls: type) -> dict[str, Any]:
    """The resolved field types of a dataclass (its module's names, ``from __future__`` strings included)."""
    return typing.get_type_hints(cls)


def rules_of(cls: type, f) -> tuple[str, ...]:
    return tuple(f.metadata.get("rule", getattr(cls, "RULE", ())))


# ---------------------------------------------------------------------------------------------
# one value against its type
# ---------------------------------------------------------------------------------------------

def _fail(name: str, what: str) -> ValueError:
    return ValueError(f"{name}: {what}")


def _optional(tp) -> tuple[bool, Any]:
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return True, (rest[0] if len(rest) == 1 else Union[tuple(rest)])
    return False, tp


def convert(tp, value: Any, name: str, conds: tuple[str, ...] = (), expect: str | None = None) -> Any:
    """``value`` checked against type ``tp`` and the range ``conds``, as the field stores it
    (lists become tuples, integers in a float field floats); ValueError ``name: what`` else."""
    opt, tp = _optional(tp)
    if value is None:
        if opt:
            return None
        raise _fail(name, f"expected {expect or describe(tp)}, got nothing")
    try:
        out = _convert(tp, value, name)
    except ValueError:
        if expect:
            raise _fail(name, f"expected {expect}, got {value!r}") from None
        raise
    for c in conds:
        op, bound = _parse_cond(c)
        if isinstance(out, (int, float)) and not isinstance(out, bool) and not _OPS[op](out, bound):
            raise _fail(name, f"must be {op} {bound:g}, got {out:g}")
    return out


def _convert(tp, value: Any, name: str) -> Any:
    origin = typing.get_origin(tp)
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(name, f"expected true or false, got {kind(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(name, f"expected an integer, got {kind(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(name, f"expected a number, got {kind(value)}")
        if not math.isfinite(value):
            raise _fail(name, f"expected a finite number, got {value}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise _fail(name, f"expected text, got {kind(value)}")
        return value
    if origin is Literal:
        options = typing.get_args(tp)
        if value not in options or isinstance(value, bool) != isinstance(options[0], bool):
            raise _fail(name, f"expected one of {', '.join(map(str, options))}, got {value!r}")
        return value
    if origin is tuple:
        return _tuple(tp, value, name)
    return value  # a type this reader does not know (a driver's Mapping): the class checks it


def _tuple(tp, value: Any, name: str) -> tuple:
    args = typing.get_args(tp)
    if len(args) == 2 and args[1] is Ellipsis:
        if not isinstance(value, (list, tuple)):
            raise _fail(name, f"expected a list, got {kind(value)}")
        return tuple(_convert(args[0], v, f"{name}[{i}]") for i, v in enumerate(value))
    what = f"{len(args)} numbers" if all(a is float for a in args) else f"a list of {len(args)}"
    if not isinstance(value, (list, tuple)):
        raise _fail(name, f"expected {what}, got {kind(value)}")
    if len(value) != len(args):
        raise _fail(name, f"expected {what}, got {len(value)}")
    return tuple(_convert(a, v, f"{name}[{i}]") for i, (a, v) in enumerate(zip(args, value)))


def describe(tp) -> str:
    """A type as the docs and messages say it: ``a number``, ``true or false``, ``one of a, b``..."""
    opt, tp = _optional(tp)
    origin = typing.get_origin(tp)
    if tp is bool:
        out = "true or false"
    elif tp is int:
        out = "an integer"
    elif tp is float:
        out = "a number"
    elif tp is str:
        out = "text"
    elif origin is Literal:
        out = "one of " + ", ".join(map(str, typing.get_args(tp)))
    elif origin is tuple:
        args = typing.get_args(tp)
        out = "a list" if args[-1:] == (Ellipsis,) else f"a list of {len(args)}"
    elif is_dataclass(tp) or tp is dict or origin in (dict, abc.Mapping):
        out = "a mapping"
    else:
        out = getattr(tp, "__name__", str(tp))
    return out + (", or null" if opt else "")


# ---------------------------------------------------------------------------------------------
# whole configs
# ---------------------------------------------------------------------------------------------

def check(cfg) -> None:
    """Every field of the dataclass instance ``cfg`` against its type and rules (call it first in
    ``__post_init__``); ValueError ``field: what``. Stores converted values (lists as tuples)."""
    cls = type(cfg)
    th = hints(cls)
    for f in fields(cls):
        v = getattr(cfg, f.name)
        if is_dataclass(th[f.name]) and is_dataclass(v):
            continue  # a nested config checked itself
        out = convert(th[f.name], v, f.name, rules_of(cls, f), f.metadata.get("expect"))
        if out is not v and out != v or type(out) is not type(v):
            object.__setattr__(cfg, f.name, out)


def _inline(cls: type) -> dict[str, str]:
    """Keys taken at this level from inline nested configs: key -> the field holding them."""
    th, out = hints(cls), {}
    for f in fields(cls):
        if f.metadata.get("inline"):
            own = {g.name for g in fields(cls)}
            out |= {g.name: f.name for g in fields(th[f.name]) if g.name not in own}
    return out


def keys(cls: type) -> set[str]:
    """The keys a mapping for ``cls`` may have."""
    return {f.name for f in fields(cls) if not f.metadata.get("inline")} | set(_inline(cls))


def read(cls: type, value: Any, path: str, base=None):
    """An instance of ``cls`` from a mapping (None: empty), over ``base`` (an instance: the defaults it
    refines) or the class defaults; :class:`SettingError` naming ``path.key`` on the first problem."""
    if value is None:
        value = {}
    if not isinstance(value, dict):
        raise SettingError(path, f"expected a mapping, got {kind(value)}")
    allowed = keys(cls)
    for k in value:
        if k not in allowed:
            raise SettingError(f"{path}.{k}", f"unknown field (allowed: {', '.join(sorted(map(str, allowed)))})")
    th, by_name, inline = hints(cls), {f.name: f for f in fields(cls)}, _inline(cls)
    own: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for k, v in value.items():
        if k in inline:
            holder = inline[k]
            sub = th[holder]
            g = next(g for g in fields(sub) if g.name == k)
            nested.setdefault(holder, {})[k] = _value(sub, g, v, f"{path}.{k}")
        elif is_dataclass(th[k]):
            prev = getattr(base, k) if base is not None else None
            own[k] = read(th[k], v, f"{path}.{k}", prev)
        else:
            own[k] = _value(cls, by_name[k], v, f"{path}.{k}")
    for holder, vals in nested.items():
        prev = getattr(base, holder) if base is not None else th[holder]()
        own[holder] = _build(lambda: replace(prev, **vals), path, set(vals))
    return _build(lambda: replace(base, **own) if base is not None else cls(**own), path, set(value))


def _value(cls: type, f, v: Any, path: str) -> Any:
    try:
        return convert(hints(cls)[f.name], v, f.name, rules_of(cls, f), f.metadata.get("expect"))
    except ValueError as e:
        raise _placed(e, path.rsplit(".", 1)[0], {f.name}) from None


def _build(make, path: str, given: set[str]):
    try:
        return make()
    except SettingError:
        raise
    except (TypeError, ValueError) as e:
        raise _placed(e, path, given) from None


def _placed(e: Exception, path: str, names: set[str]) -> SettingError:
    """``field: what`` from a check as ``path.field: what`` (``path: message`` when no field leads it)."""
    msg = str(e)
    head, sep, rest = msg.partition(": ")
    name = head.split("[", 1)[0]
    if sep and name.isidentifier():
        return SettingError(f"{path}.{head}", rest)
    return SettingError(path, msg)


# ---------------------------------------------------------------------------------------------
# what the docs say
# ---------------------------------------------------------------------------------------------

@lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (a string literal right after its annotation)."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for a, b in zip(body, body[1:]):
            if (isinstance(a, ast.AnnAssign) and isinstance(a.target, ast.Name) and isinstance(b, ast.Expr)
                    and isinstance(b.value, ast.Constant) and isinstance(b.value.value, str)):
                out[a.target.id] = " ".join(inspect.cleandoc(b.value.value).split())
    return out


def default_of(f) -> Any:
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    return MISSING


def rows(cls: type, prefix: str = "") -> list[tuple[str, Any, str, str]]:
    """(key, default, accepted, doc) for every setting of ``cls``; nested configs as ``key.sub``."""
    th, docs, out = hints(cls), field_docs(cls), []
    for f in fields(cls):
        tp = th[f.name]
        if is_dataclass(tp):
            out += rows(tp, prefix if f.metadata.get("inline") else f"{prefix}{f.name}.")
            continue
        opt, inner = _optional(tp)
        conds = rules_of(cls, f) if inner in (int, float) else ()
        accepted = f.metadata.get("expect") or (describe(inner) + "".join(f" {c}," for c in conds).rstrip(",")
                                                 + (", or null" if opt else ""))
        out.append((prefix + f.name, default_of(f), accepted, docs.get(f.name, "")))
    return out
