"""One record per plugin, one registry per kind (policies, drivers, lidars), imported lazily.

A ``Plugin`` names its config dataclass, its factory and (drivers) its simulated device as
``"module:attr"`` strings (python-can's ``BACKENDS`` style): nothing is imported until used, so
reading a scenario never imports torch, pybullet or matplotlib. The built-in records sit in each
kind's package (``stack/policies/__init__.py``, ``stack/drivers/__init__.py``); plugins from
outside the tree come from

- the entry-point group ``formation_stack.<kind>`` (e.g. ``formation_stack.policies``) of an
  installed distribution: each entry point loads a ``Plugin`` (or a list of them);
- the environment variable ``FORMATION_STACK_PLUGINS``: module names (separated by ``,``), each
  with a list ``POLICIES`` / ``DRIVERS`` / ``LIDARS`` of records. Subprocesses (the fleet's
  agents) inherit it, so they find the same plugins.

``python -m stack.plugins`` prints every plugin's settings as markdown tables (``docs/settings.md``).
"""

from __future__ import annotations

import importlib
import logging
import os
import sys
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

log = logging.getLogger("stack.plugins")

ENV = "FORMATION_STACK_PLUGINS"
GROUP = "formation_stack.{kind}"


class PluginError(LookupError):
    """A plugin name that is not registered, or a record that does not resolve. ``str()`` is one line."""


def load(ref: str):
    """The object a ``"module:attr"`` string names (``attr`` may be dotted)."""
    module, _, attr = ref.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


@dataclass(frozen=True)
class Plugin:
    """A plugin's record: what a scenario, the command lines and the docs need to know of it."""

    name: str
    """The name a scenario and ``--policy`` / ``--driver`` use."""
    config: str | None
    """``"module:Class"`` of its settings dataclass (a docstring per field), or None: it takes none."""
    factory: str
    """``"module:callable"`` that builds it (a policy: ``(robot, **kw)``; a driver: its class)."""
    device: str | None = None
    """Drivers: ``"stack.sim_bridge.module:Class"`` of the simulated device the world hosts behind it."""
    key: str | None = None
    """The scenario block its settings sit under (``robot.<key>``); default: ``name``."""
    summary: str = ""
    """One line for the docs' tables."""

    @property
    def settings_key(self) -> str:
        return self.key or self.name

    def config_class(self) -> type | None:
        return load(self.config) if self.config else None

    def make(self):
        return load(self.factory)

    def device_class(self) -> type | None:
        return load(self.device) if self.device else None


class Registry(Mapping[str, Plugin]):
    """The records of one kind: the built-ins, then those from entry points and ``FORMATION_STACK_PLUGINS``
    (found on first use; a record that cannot be loaded is left out with a one-line warning)."""

    def __init__(self, kind: str, builtins: Iterable[Plugin]):
        self.kind = kind
        self.noun = kind[:-3] + "y" if kind.endswith("ies") else kind.rstrip("s")
        self._builtins = {p.name: p for p in builtins}
        self._all: dict[str, Plugin] | None = None

    def _records(self) -> dict[str, Plugin]:
        if self._all is None:
            out = dict(self._builtins)
            for origin, rec in _extras(self.kind):
                if not isinstance(rec, Plugin):
                    log.warning("%s: %s: not a stack.plugins.Plugin record (left out)", origin, rec)
                elif rec.name in out:
                    log.warning("%s: %s %r is already registered (left out)", origin, self.noun, rec.name)
                else:
                    out[rec.name] = rec
            self._all = out
        return self._all

    def __getitem__(self, name: str) -> Plugin:
        try:
            return self._records()[name]
        except KeyError:
            raise PluginError(f"{self.noun} {name!r} is not available (available: {', '.join(self)})") from None

    def __contains__(self, name: object) -> bool:
        return name in self._records()

    def get(self, name: str, default=None):
        return self._records().get(name, default)

    def __iter__(self) -> Iterator[str]:
        return iter(self._records())

    def __len__(self) -> int:
        return len(self._records())

    def names(self) -> tuple[str, ...]:
        return tuple(self._records())

    def by_key(self, key: str) -> Plugin | None:
        """The first record whose settings sit under ``robot.<key>``."""
        return next((p for p in self._records().values() if p.settings_key == key), None)

    def builtins(self) -> "Registry":
        """The in-tree records alone (what the docs list)."""
        reg = Registry(self.kind, self._builtins.values())
        reg._all = dict(self._builtins)
        return reg

    def reload(self) -> None:
        """Look for out-of-tree plugins again (tests; a process that changed its environment)."""
        self._all = None


def _extras(kind: str) -> Iterator[tuple[str, object]]:
    from importlib.metadata import entry_points

    for ep in entry_points(group=GROUP.format(kind=kind)):
        origin = f"entry point {ep.name} = {ep.value} ({ep.group})"
        try:
            obj = ep.load()
        except Exception as e:  # a broken plugin must not take every command line down
            log.warning("%s: cannot load: %s (left out)", origin, e)
            continue
        yield from ((origin, o) for o in (obj if isinstance(obj, (list, tuple)) else [obj]))
    for module in filter(None, (m.strip() for m in os.environ.get(ENV, "").split(","))):
        origin = f"{ENV} module {module}"
        try:
            mod = importlib.import_module(module)
        except Exception as e:
            log.warning("%s: cannot import: %s (left out)", origin, e)
            continue
        yield from ((origin, o) for o in getattr(mod, kind.upper(), ()))


def registries() -> dict[str, Registry]:
    """Every kind's registry, by kind."""
    from .drivers import DRIVERS, LIDARS
    from .policies import POLICIES

    return {"policies": POLICIES, "drivers": DRIVERS, "lidars": LIDARS}


def main(argv: list[str] | None = None) -> int:
    from .plugin_docs import settings_markdown

    sys.stdout.write(settings_markdown())
    return 0


if __name__ == "__main__":
    sys.exit(main())
