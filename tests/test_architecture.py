"""The rooms of ARCHITECTURE.md: which package may import which, checked on the source."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "stack"

FORBIDDEN = {
    "comm": {"stack.drivers", "stack.agents", "stack.sim_bridge", "stack.policies", "stack.estimation", "stack.fleet", "stack.scenario"},
    "drivers": {"stack.agents", "stack.sim_bridge", "stack.policies", "stack.estimation", "stack.fleet"},
    "estimation": {"stack.comm", "stack.drivers", "stack.agents", "stack.sim_bridge", "stack.policies", "stack.fleet", "zenoh"},
    "policies": {"stack.comm", "stack.drivers", "stack.agents", "stack.sim_bridge", "stack.fleet", "zenoh", "pybullet"},
    "agents": {"stack.sim_bridge", "stack.fleet", "pybullet"},
    # the Foxglove view of our messages and its writer, shared by the fleet's recorder and a robot's own view
    "viz": {"stack.sim_bridge", "stack.fleet", "stack.agents", "stack.drivers", "stack.policies", "stack.estimation",
            "stack.train", "pybullet", "matplotlib", "PIL", "torch"},
}


def _imports(path: Path, package: str) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ("stack." + package).split(".")
                mod = ".".join(base[: len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.add(mod)
    return out


@pytest.mark.parametrize("room", sorted(FORBIDDEN))
def test_room_imports(room):
    for path in (ROOT / room).rglob("*.py"):
        for mod in _imports(path, room):
            for bad in FORBIDDEN[room]:
                assert not (mod == bad or mod.startswith(bad + ".")), f"{path.relative_to(ROOT.parent)} imports {mod}"


def test_models_import_nothing_of_ours_and_only_numpy():
    """stack/models (the shared kinematics, geometry and observation builders) is the bottom room:
    every other room may import it, it imports only itself, numpy and the standard library."""
    files = list((ROOT / "models").rglob("*.py"))
    assert {p.name for p in files} >= {"kinematics.py", "geometry.py", "observation.py"}
    for path in files:
        for mod in _imports(path, "models"):
            top = mod.split(".")[0]
            ok = mod.startswith("stack.models") or top in {"numpy", "__future__"} or top in sys.stdlib_module_names
            assert ok and mod != "stack", f"{path.relative_to(ROOT.parent)} imports {mod}"


def test_rooms_use_the_shared_models():
    """One copy of each model: the world, the EKF, the decision layer and the training worlds import it."""
    for rel, model in (("sim_bridge/world.py", "kinematics"), ("estimation/ekf.py", "kinematics"),
                       ("train/drlworld.py", "kinematics"), ("train/fuzzyworld.py", "kinematics"),
                       ("agents/decision.py", "observation"), ("train/fuzzyworld.py", "observation"),
                       ("train/drlworld.py", "observation"), ("estimation/pose.py", "geometry")):
        pkg = rel.split("/")[0]
        assert f"stack.models.{model}" in _imports(ROOT / rel, pkg), f"{rel} does not use stack.models.{model}"


def test_the_agent_reaches_the_foxglove_sdk_only_through_its_view():
    """A robot's core install has no Foxglove SDK: only stack/agents/view.py (imported when --record or --viz is
    given) imports it, and the agent shares the fleet's builders and writer through stack.viz, not stack.fleet."""
    for path in (ROOT / "agents").rglob("*.py"):
        mods = _imports(path, "agents")
        if path.name != "view.py":
            assert not any(m.split(".")[0] == "foxglove" for m in mods), path
            assert "stack.viz.writer" not in mods, path
    view = _imports(ROOT / "agents" / "view.py", "agents")
    assert {"stack.viz", "stack.viz.writer"} <= view and not any(m.startswith("stack.fleet") for m in view)
    for rel in ("fleet/record.py", "fleet/viz_messages.py"):
        assert _imports(ROOT / rel, "fleet") & {"stack.viz.writer", "stack.viz.messages", "stack.viz.endpoint"}, rel


def test_every_zenoh_session_goes_through_the_session_helper():
    """Only stack/comm/session.py calls zenoh.open: scouting off and explicit endpoints everywhere."""
    for path in ROOT.rglob("*.py"):
        if path.name == "session.py":
            continue
        assert "zenoh.open(" not in path.read_text(), path


def test_agents_never_touch_ground_truth():
    """Agents estimate their own pose: no code in stack/agents, drivers or policies names the truth topic."""
    for room in ("agents", "drivers", "policies", "estimation"):
        for path in (ROOT / room).rglob("*.py"):
            text = path.read_text()
            assert '"truth"' not in text and "world/truth" not in text and "Truth" not in text, path
