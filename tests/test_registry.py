"""The plugin registries against the folders, every record resolving, and the docs made from them."""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import subprocess
import sys
from dataclasses import fields, is_dataclass

import pytest

from conftest import ROOT, SCENARIOS

import stack.drivers
import stack.policies
from stack.drivers import DRIVERS, LIDARS, Driver
from stack.plugins import Plugin, Registry, registries
from stack.policies import POLICIES, Policy
from stack.settings import field_docs

RECORDS = [(kind, name) for kind, reg in registries().items() for name in reg.builtins()]


def _modules(package) -> list[str]:
    return [m.name for m in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]


def _concrete(module: str, base: type) -> list[type]:
    mod = importlib.import_module(module)
    return [c for _, c in inspect.getmembers(mod, inspect.isclass)
            if c.__module__ == module and issubclass(c, base) and c is not base and not inspect.isabstract(c)]


@pytest.mark.parametrize("module", _modules(stack.policies))
def test_every_policy_module_is_registered(module):
    """A module under stack/policies that defines a Policy is the factory module of a record."""
    if not _concrete(module, Policy):
        return
    factories = {POLICIES[n].factory.partition(":")[0] for n in POLICIES.builtins()}
    assert module in factories, f"{module} defines a Policy but no record in stack/policies/__init__.py builds it"


@pytest.mark.parametrize("module", _modules(stack.drivers))
def test_every_driver_module_is_registered(module):
    """Every concrete Driver under stack/drivers is the class of a record."""
    classes = {DRIVERS[n].make() for n in DRIVERS.builtins()}
    for cls in _concrete(module, Driver):
        assert cls in classes, f"{module}.{cls.__name__} is a Driver but no record in stack/drivers/__init__.py names it"


@pytest.mark.parametrize("kind,name", RECORDS, ids=[f"{k}:{n}" for k, n in RECORDS])
def test_every_record_resolves(kind, name):
    rec = registries()[kind][name]
    assert isinstance(rec, Plugin) and rec.name == name
    assert callable(rec.make()), rec.factory
    cls = rec.config_class()
    if cls is not None:
        assert is_dataclass(cls), rec.config
        docs = field_docs(cls)
        undocumented = [f.name for f in fields(cls) if not docs.get(f.name)]
        assert not undocumented, f"{rec.config}: fields without a docstring: {undocumented}"
        cls()  # the defaults are valid
    if kind == "drivers":
        driver = rec.make()
        assert issubclass(driver, Driver) and driver.config_class is cls, (rec.factory, driver.config_class)
        if rec.device is not None:
            from stack.sim_bridge.devices import HostedDevice, device_class

            assert rec.device.startswith("stack.sim_bridge.") and issubclass(device_class(name), HostedDevice)
    if kind == "policies":
        assert POLICIES.by_key(rec.settings_key).config == rec.config  # one config per settings block


def test_choices_come_from_the_registries():
    from stack.agents.cli import parser as agent_parser
    from stack.fleet.cli import parser as fleet_parser
    from stack.scenario import DRIVERS as driver_names
    from stack.scenario import POLICIES as policy_names
    from stack.scenario import BenchConfig

    assert policy_names == POLICIES.names() and driver_names == DRIVERS.names()
    assert BenchConfig().policies == POLICIES.names()

    def choices(ap, flag):
        sub = next((a for a in ap._actions if a.dest == "cmd"), None)
        actions = (sub.choices["run"] if sub else ap)._actions
        return tuple(next(a for a in actions if flag in a.option_strings).choices)

    for ap in (agent_parser(), fleet_parser()):
        assert choices(ap, "--policy") == POLICIES.names() and choices(ap, "--driver") == DRIVERS.names()


def test_docs_settings_md_is_what_the_registries_say():
    from stack.plugin_docs import settings_markdown

    path = ROOT / "docs" / "settings.md"
    assert path.read_text() == settings_markdown(), "regenerate it: python -m stack.plugins > docs/settings.md"
    text = path.read_text()
    for kind, reg in registries().items():
        for name in reg.builtins():
            assert f"### `{name}`" in text
    assert "| `cell` | 0.5 | a number > 0 |" in text and "| `v_cruise` | 0.6 | a number >= 0, <= 1 |" in text


def test_reading_every_scenario_imports_no_torch_pybullet_or_matplotlib():
    code = ("import sys, glob\nfrom stack.scenario import load_scenario\n"
            f"for p in sorted(glob.glob({str(SCENARIOS / '*.yaml')!r})):\n"
            "    sc = load_scenario(p)\n    [r.config_for(r.policy_key) for r in sc.robots]\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'pybullet', 'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_registry_keeps_the_builtins_and_says_what_is_available():
    reg = Registry("policies", [Plugin("a", None, "x:y")])
    with pytest.raises(LookupError, match=r"^policy 'b' is not available \(available: a"):
        reg["b"]
    assert reg.get("b") is None and "a" in reg and reg.builtins().names() == ("a",)
    assert LIDARS["world"].make().__name__ == "WorldLidar"
