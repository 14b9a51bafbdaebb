"""What a robot installs: the core install (``pip install formation-stack``) runs an agent with its drivers;
the simulator, training, plots and DRL inference are extras (``sim``, ``train``, ``drl``).

Checked two ways, without a network: the dependency closure of the core requirements, read from the installed
distributions' metadata, and the modules a robot's code paths import, in a process that cannot import the extras.
"""

from __future__ import annotations

import re
import subprocess
import sys
import textwrap
import tomllib
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXTRAS_ONLY = ("pybullet", "torch", "matplotlib", "tqdm", "foxglove", "mcap", "PIL")
"""What a robot's own code never imports: the world, the network's training stack, plots, progress bars."""


def _name(req: str) -> str:
    return re.split(r"[\s<>=!~;\[(]", req.strip(), maxsplit=1)[0].lower().replace("_", "-")


def _closure(roots: list[str]) -> dict[str, str]:
    """Every distribution the requirements ``roots`` pull in (no extras, environment markers taken as true
    only when they hold here), mapped to the one that first required it."""
    seen: dict[str, str] = {}
    todo = [(_name(r), "formation-stack") for r in roots]
    while todo:
        name, parent = todo.pop()
        if name in seen:
            continue
        seen[name] = parent
        for req in metadata.requires(name) or []:
            if ";" in req:
                from packaging.requirements import Requirement

                if not Requirement(req).marker.evaluate({"extra": ""}):
                    continue
            todo.append((_name(req), name))
    return seen


def test_the_core_requirements_pull_no_simulator_and_no_torch():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = project["dependencies"]
    assert not {_name(r) for r in core} & set(EXTRAS_ONLY), core
    closure = _closure(core)
    assert "pybullet" not in closure and "torch" not in closure, closure
    # filterpy (the estimator) declares matplotlib; it is the only way in, and nothing of ours imports it
    assert closure.get("matplotlib") in (None, "filterpy"), closure.get("matplotlib")
    extras = project["optional-dependencies"]
    assert {_name(r) for r in extras["sim"]} >= {"pybullet", "matplotlib", "tqdm", "foxglove-sdk", "mcap"}
    assert "torch" in {_name(r) for r in extras["drl"]}


_BLOCK = textwrap.dedent("""
    import importlib.abc, sys
    BLOCKED = set(sys.argv[1].split(","))
    class Block(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)  # as a missing package does
    sys.meta_path.insert(0, Block())
""")


def _run_without_extras(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", _BLOCK + textwrap.dedent(code), ",".join(EXTRAS_ONLY)],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


def test_stack_agent_help_runs_without_the_extras():
    p = _run_without_extras("""
        import sys
        from stack.agents.cli import cli
        sys.argv = ["stack-agent", "--help"]
        try:
            cli()
        except SystemExit as e:
            assert e.code == 0, e.code
    """)
    assert p.returncode == 0, p.stderr
    assert "usage: stack-agent" in p.stdout and "--driver" in p.stdout


def test_a_robot_with_any_driver_and_a_numpy_policy_imports_no_extra():
    """The agent, every hardware driver, and every policy (drl on its default numpy runtime) build without the extras."""
    p = _run_without_extras("""
        import sys
        from stack.scenario import load_scenario
        from stack.policies import make_policy
        import stack.agents.agent, stack.drivers.can, stack.drivers.mavlink, stack.drivers.jackal, stack.drivers.sim
        sc = load_scenario("scenarios/four-robot-obstacles.yaml")
        robot = sc.robot(1)
        for name in ("pid", "aina", "qlearn", "fuzzy", "drl"):
            make_policy(name, robot, seed=0)
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in sys.argv[1].split(","))
        assert not loaded, loaded
        print("ok")
    """)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "ok"


def test_a_drl_robot_on_torch_without_torch_is_told_which_extra_in_one_line(tmp_path):
    """``robot.drl.runtime: torch`` where torch is not installed: one line naming the extra, exit 2, no traceback."""
    import yaml

    sc = yaml.safe_load((ROOT / "scenarios" / "four-robot-obstacles.yaml").read_text())
    sc.setdefault("robot", {})["drl"] = {"runtime": "torch"}
    path = tmp_path / "torch.yaml"
    path.write_text(yaml.safe_dump(sc))
    p = _run_without_extras(f"""
        import sys
        from stack.agents.cli import cli
        sys.argv = ["stack-agent", "--id", "1", "--role", "follower", "--scenario", {str(path)!r},
                    "--policy", "drl", "--connect", "tcp/127.0.0.1:9"]
        sys.exit(cli())
    """)
    assert p.returncode == 2, (p.stdout, p.stderr)
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stack-agent: ") and "runtime: torch needs the Python package 'torch'" in lines[0] \
        and "pip install 'formation-stack[drl]'" in lines[0], p.stderr
