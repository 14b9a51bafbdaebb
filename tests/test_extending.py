"""docs/extending.md's worked example, run as a user would: the module cut from the markdown,
installed out of the tree (an entry point of an installed distribution, or FORMATION_STACK_PLUGINS),
read from a scenario, rejected when a setting is bad, and driven in a real fleet."""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

import pytest

from conftest import ROOT, run_cli, run_fleet, scenario_dict, write_scenario

DOC = ROOT / "docs" / "extending.md"


def example(name: str) -> str:
    """The fenced block after ``<!-- example: NAME -->`` in docs/extending.md."""
    m = re.search(rf"<!-- example: {re.escape(name)} -->\s*```python\n(.*?)```", DOC.read_text(), re.S)
    assert m, f"docs/extending.md has no example {name}"
    return m.group(1)


def install(site: Path) -> Path:
    """What ``pip install`` of a distribution with the entry point leaves in site-packages."""
    site.mkdir(parents=True, exist_ok=True)
    (site / "goto_policy.py").write_text(example("goto_policy.py"))
    info = site / "goto_policy-0.1.dist-info"
    info.mkdir(exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: goto-policy\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[formation_stack.policies]\ngoto = goto_policy:PLUGIN\n")
    return site


@pytest.fixture
def goto_installed(tmp_path, monkeypatch):
    from stack.policies import POLICIES

    site = install(tmp_path / "site")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(site), os.environ.get("PYTHONPATH", str(ROOT))]))
    monkeypatch.delenv("FORMATION_STACK_PLUGINS", raising=False)
    POLICIES.reload()
    yield site
    sys.modules.pop("goto_policy", None)
    monkeypatch.undo()
    POLICIES.reload()


def _goto_scenario(**goto) -> dict:
    d = scenario_dict(duration=4.0)
    d["robot"]["goto"] = goto
    for r in d["robots"]:
        r["policy"] = "goto"
    return d


def test_the_installed_example_is_a_policy_with_settings(goto_installed):
    from stack.policies import POLICIES, make_policy
    from stack.policies.base import Observation
    from stack.scenario import ScenarioError, parse_scenario

    assert "goto" in POLICIES and POLICIES.names()[-1] == "goto"
    sc = parse_scenario(_goto_scenario(speed=0.8, arrive=0.2), "s.yaml")
    cfg = sc.robot(1).config_for("goto")
    assert (cfg.speed, cfg.arrive, cfg.k_heading) == (0.8, 0.2, 1.5)
    pol = make_policy("goto", sc.robot(1))
    v, w = pol.act(Observation(d_g=3.0, alpha_g=0.4, v=0.0, w=0.0))
    assert 0 < v < 0.8 and w == pytest.approx(0.6)
    assert pol.act(Observation(d_g=0.1, alpha_g=0.4, v=0.0, w=0.0)) == (0.0, 0.0)
    with pytest.raises(ScenarioError) as e:
        parse_scenario(_goto_scenario(speed=1.5), "s.yaml")
    assert str(e.value) == "s.yaml: robot.goto.speed: must be <= 1, got 1.5"
    d = _goto_scenario()
    d["robots"][2]["goto"] = {"sped": 1}
    with pytest.raises(ScenarioError, match=r"^s\.yaml: robots\[2\]\.goto\.sped: unknown field"):
        parse_scenario(d, "s.yaml")


def test_a_bad_setting_is_one_line_exit_2_in_the_command_line(goto_installed, tmp_path):
    path = write_scenario(tmp_path / "bad.yaml", _goto_scenario(speed=1.5))
    proc = run_cli(["stack-fleet", "run", str(path), "--policy", "goto", "--out", str(tmp_path / "out")], timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == f"stack-fleet: {path}: robot.goto.speed: must be <= 1, got 1.5", proc.stderr


def test_the_environment_variable_finds_it_too(tmp_path, monkeypatch):
    from stack.policies import POLICIES

    site = tmp_path / "plain"
    site.mkdir()
    (site / "goto_policy.py").write_text(example("goto_policy.py"))  # no distribution: by name only
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setenv("FORMATION_STACK_PLUGINS", "goto_policy, no_such_plugin_module")
    try:
        POLICIES.reload()
        assert "goto" in POLICIES and "no_such_plugin_module" not in POLICIES.names()
        assert POLICIES["goto"].config_class().__name__ == "GotoConfig"
    finally:
        sys.modules.pop("goto_policy", None)
        monkeypatch.undo()
        POLICIES.reload()
    assert "goto" not in POLICIES


@pytest.mark.fleet
def test_a_fleet_runs_the_example_policy_and_the_robots_move(goto_installed, tmp_path):
    path = write_scenario(tmp_path / "goto.yaml", _goto_scenario(speed=0.8))
    proc, rep = run_fleet(path, tmp_path / "out", "--policy", "goto", "--duration", "4", "--no-plots", timeout=240)
    assert rep is not None, proc.stderr
    assert {r["policy"] for r in rep["robots"].values()} == {"goto"}, rep["robots"]
    moved = {rid: r["path_length_m"] for rid, r in rep["robots"].items()}
    assert all(m > 0.5 for m in moved.values()), moved  # 4 s at up to 0.8 m/s: every robot went somewhere
