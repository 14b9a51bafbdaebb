"""Fan 2021 improved Q-learning (stack.planning, stack-train qlearn): equations on hand cases, filling,
the concave trap, optimality against A*, map errors, the command line."""

from __future__ import annotations

import ast
import heapq
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stack.planning.grid import (ACTIONS, MapError, GridWorld, current_position_actions, find_map, load_map,
                                 map_to_text, parse_map, path_length, tends_to_concave)
from stack.planning.qlearning import (GPFInit, QLearningConfig, gpf, gpf_q_init, plan, plan_map, sa_epsilon,
                                      sa_temperature)
from stack.planning.tracking import formation_experiment, tracking_cost

ROOT = Path(__file__).resolve().parents[1]
FIG5 = ROOT / "maps" / "fan2021-fig5.txt"
TRAP = ROOT / "maps" / "concave-trap.txt"


def astar(occ: np.ndarray, start, goal) -> tuple[float, list]:
    """Plain A*, 8-connected, octile heuristic, no corner cutting (the grid world's motion rule)."""
    nx, ny = occ.shape

    def blocked(x, y):
        return not (0 <= x < nx and 0 <= y < ny) or occ[x, y]

    def h(c):
        dx, dy = abs(c[0] - goal[0]), abs(c[1] - goal[1])
        return max(dx, dy) + (math.sqrt(2) - 1) * min(dx, dy)

    g, prev, pq = {start: 0.0}, {}, [(h(start), start)]
    while pq:
        _, c = heapq.heappop(pq)
        if c == goal:
            path = [c]
            while c in prev:
                c = prev[c]
                path.append(c)
            return g[goal], path[::-1]
        for dx, dy in ACTIONS:
            n = (c[0] + dx, c[1] + dy)
            if blocked(*n) or (dx and dy and (blocked(c[0] + dx, c[1]) or blocked(c[0], c[1] + dy))):
                continue
            if g[c] + math.hypot(dx, dy) < g.get(n, math.inf) - 1e-12:
                g[n] = g[c] + math.hypot(dx, dy)
                prev[n] = c
                heapq.heappush(pq, (g[n] + h(n), n))
    return math.inf, []


def assert_valid_path(occ, path, start, goal):
    assert tuple(path[0]) == tuple(start) and tuple(path[-1]) == tuple(goal)
    for (x0, y0), (x1, y1) in zip(path, path[1:]):
        dx, dy = x1 - x0, y1 - y0
        assert max(abs(dx), abs(dy)) == 1, f"not one 8-connected step: {(x0, y0)} -> {(x1, y1)}"
        assert not occ[x1, y1], f"steps into an obstacle at {(x1, y1)}"
        if dx and dy:
            assert not occ[x0 + dx, y0] and not occ[x0, y0 + dy], f"clips a corner {(x0, y0)} -> {(x1, y1)}"


# ------------------------------------------------------------------ equations on hand cases

def test_gpf_initial_q_values_eq_8_9_hand_case():
    # 5 x 5, goal (4, 0), robot at (1, 1), obstacle at (2, 0); 26 px a cell, xi -10, eta 735, gamma 0.9, k_q 0.1
    occ = np.zeros((5, 5), bool)
    occ[2, 0] = True
    world = GridWorld(occ, (1, 1), (4, 0))
    row = GPFInit(world, QLearningConfig(variant="Q-L4"))(world.index((1, 1)))
    a = {name: i for i, name in enumerate(("up", "down", "left", "right", "upleft", "upright", "downleft", "downright"))}
    # downleft -> (0, 0): d = 4 cells = 104 px; U' = -10 * 104 / 839 = -1.23957; Q = 0.1 * 0.9 * U'
    assert row[a["downleft"]] == pytest.approx(-0.1115613826, abs=1e-9)
    # down -> (1, 0): d = 78 px; U' = -780 / 813
    assert row[a["down"]] == pytest.approx(-0.0863468635, abs=1e-9)
    # downright -> (2, 0) is an obstacle: r_q = -1; d = 52 px: 0.1 * (-1 + 0.9 * (-520 / 787))
    assert row[a["downright"]] == pytest.approx(-0.1594663278, abs=1e-9)
    # next to the goal: r_q = +1 and U'(goal) = 0
    assert GPFInit(world, QLearningConfig(variant="Q-L4"))(world.index((3, 1)))[a["downright"]] == pytest.approx(0.1)
    # the bare formulas
    assert gpf(0.0) == 0.0 and gpf(735.0) == pytest.approx(-5.0)
    assert gpf_q_init(104.0, 0.0) == pytest.approx(-0.1115613826, abs=1e-9)
    # nearer the goal is worth more: the GPF guides towards the target
    assert row[a["downleft"]] < row[a["down"]]


def test_sa_temperature_and_epsilon_eq_10_11_from_a_step_history():
    steps = [30, 32, 28, 30, 30, 31, 29, 30, 30, 30]  # mean 30, squares 4 + 4 + 1 + 1 = 10, sample var 10 / 9
    T = sa_temperature(steps, i=0.1, k=0.03)
    assert T == pytest.approx(0.1 + 0.03 * math.sqrt(10 / 9))
    assert sa_epsilon(-0.2, -0.1, q=1.0, T=T) == pytest.approx(math.exp(-1.1 / 0.1316227766), rel=1e-9)
    assert sa_epsilon(-0.2, -0.1, q=1.0, T=T) == pytest.approx(2.3469677e-4, rel=1e-6)
    # converged history: T -> i, exploration all but off; hot start T0 = 10: epsilon ~ 0.9
    assert sa_temperature([26] * 10) == pytest.approx(0.1)
    assert sa_epsilon(0.0, 0.0, 1.0, 10.0) == pytest.approx(math.exp(-0.1))
    # inside the learner: the first n rounds run at T0 (Q = 0 in Q-L2: epsilon = exp(-q / T0)),
    # and epsilon changes only every n rounds (Algorithm 2)
    res = plan_map(load_map(FIG5), QLearningConfig(variant="Q-L2", seed=1, max_rounds=60))
    eps = res.epsilon_per_round
    assert eps[:10] == [pytest.approx(math.exp(-0.1))] * 10
    for b in range(0, len(eps), 10):
        assert len(set(eps[b:b + 10])) == 1
    assert eps[10] < eps[0]


def test_one_step_filling_of_fig_1_on_the_3x3_case():
    # Fig. 1: the robot (centre) inside a grey concave obstacle, the target to the lower right.
    # sensor[dx + 1, dy + 1]: right, lower right and down are obstacles (so is upper right).
    sensor = np.zeros((3, 3), bool)
    for dx, dy in ((1, 0), (1, -1), (0, -1), (1, 1)):
        sensor[dx + 1, dy + 1] = True
    robot, target = (5, 5), (9, 1)
    nearer = {ACTIONS.index((1, 0)), ACTIONS.index((1, -1)), ACTIONS.index((0, -1))}  # right, downright, down
    from stack.planning.grid import closer_actions
    assert set(closer_actions(robot, target)) == nearer  # Fig. 1(b): the dark grey cells
    assert current_position_actions(sensor, robot, target) == []
    assert tends_to_concave(sensor, robot, target)  # Fig. 1(c): fill the robot's cell
    open_sensor = sensor.copy()
    open_sensor[1 + 0, 1 - 1] = False  # down is free: not concave
    assert current_position_actions(open_sensor, robot, target) == [ACTIONS.index((0, -1))]
    assert not tends_to_concave(open_sensor, robot, target)

    # the same in the grid world: one step fills exactly the robot's cell, not its neighbours yet
    occ = np.zeros((10, 10), bool)
    for dx, dy in ((1, 0), (1, -1), (0, -1), (1, 1), (-1, -1)):
        occ[5 + dx, 5 + dy] = True
    w = GridWorld(occ, (5, 5), (9, 1))
    s = w.index((5, 5))
    assert np.array_equal(w.sense(s), sensor | np.array([[1, 0, 0], [0, 0, 0], [0, 0, 0]], bool))
    assert w.tends_to_concave(s)
    w.fill(s)
    assert w.virtual[5, 5] and w.virtual.sum() == 1 and not w.occupancy[5, 5]
    assert not w.ok[w.index((4, 5))][ACTIONS.index((1, 0))]  # stepping back in is now a collision
    assert not w.tends_to_concave(w.index((4, 6)))  # upper right of the pocket is still open


# ------------------------------------------------------------------ the variants

def test_concave_trap_q_l3_falls_in_and_q_l4_escapes():
    grid = load_map(TRAP)
    cup = {(x, y) for x in range(2, 8) for y in range(2, 8)}  # inside the U, which opens towards the start
    l3 = plan_map(grid, QLearningConfig(variant="Q-L3", seed=0, max_rounds=300))
    assert not l3.converged and not l3.greedy_reached
    assert tuple(l3.last_round_path[-1]) in cup  # trapped, oscillating in the concave obstacle
    assert tuple(l3.greedy_path[-1]) in cup
    l4 = plan_map(grid, QLearningConfig(variant="Q-L4", seed=0, max_rounds=300))
    assert l4.converged and l4.greedy_reached and l4.convergence_round < 100
    assert l4.virtual.sum() >= 10 and all(tuple(c) in cup for c in np.argwhere(l4.virtual))  # the U filled
    assert not set(map(tuple, l4.path)) & cup
    assert_valid_path(grid.occupancy, l4.path, grid.start, grid.goal)


def test_q_l5_path_within_5_percent_of_a_star_on_the_fig5_map():
    grid = load_map(FIG5)
    best, _ = astar(grid.occupancy, grid.start, grid.goal)
    assert 26 < best < 40
    res = plan_map(grid, QLearningConfig(variant="Q-L5", seed=0))
    assert res.converged and res.greedy_reached
    assert_valid_path(grid.occupancy, res.path, grid.start, grid.goal)
    assert res.path_length == pytest.approx(path_length(res.path))
    assert res.path_length <= 1.05 * best, (res.path_length, best)
    assert res.convergence_time_s < 4.8  # the paper's 48.3 s / 10


def test_same_seed_same_run_and_classic_variants_learn():
    grid = load_map(FIG5)
    a = plan_map(grid, QLearningConfig(variant="Q-L1", seed=3))
    b = plan_map(grid, QLearningConfig(variant="Q-L1", seed=3))
    c = plan_map(grid, QLearningConfig(variant="Q-L1", seed=4))
    assert a.steps_per_round == b.steps_per_round and a.path == b.path
    assert a.steps_per_round != c.steps_per_round
    assert a.converged and a.greedy_reached and a.virtual.sum() == 0  # no filling in Q-L1
    assert_valid_path(grid.occupancy, a.path, grid.start, grid.goal)


def test_plan_on_any_occupancy_and_warm_start_on_a_changed_grid():
    grid = load_map(FIG5)
    occ, start, goal = grid.occupancy.copy(), grid.start, grid.goal
    first = plan(occ, start, goal, QLearningConfig(variant="Q-L5", seed=0))
    assert first.greedy_reached
    occ2 = occ.copy()
    for c in first.path[8:11]:  # the fleet's lidar sees something new on the way
        occ2[c] = True
    again = plan(occ2, start, goal, QLearningConfig(variant="Q-L5", seed=0), warm_start=first)
    assert again.warm_started and again.converged and again.greedy_reached
    assert_valid_path(occ2, again.path, start, goal)
    # what is kept: after one round, rows that round did not touch are the old ones, except next to the change
    one = plan(occ2, start, goal, QLearningConfig(variant="Q-L5", seed=0, max_rounds=1), warm_start=first)
    ny = occ.shape[1]
    touched = {x * ny + y for x, y in one.last_round_path}
    changed = [tuple(c) for c in np.argwhere(occ2 != occ)]
    near = {(x + dx, y + dy) for x, y in changed for dx in (-1, 0, 1) for dy in (-1, 0, 1)}
    n_same = n_reset = 0
    for s_ in np.flatnonzero(~np.isnan(first.Q).any(axis=1)):
        if s_ in touched:
            continue
        if divmod(int(s_), ny) in near:
            assert np.isnan(one.Q[s_]).all()
            n_reset += 1
        else:
            assert np.array_equal(one.Q[s_], first.Q[s_])
            n_same += 1
    assert n_same > 20 and n_reset > 0  # both kinds of rows were there to check
    cold = plan(occ2, start, (19, 0), QLearningConfig(variant="Q-L5", seed=0, max_rounds=1), warm_start=first)
    assert not cold.warm_started  # another goal: nothing to reuse
    with pytest.raises(ValueError, match="obstacle"):
        plan(occ, start, (12, 9))


def test_filling_walls_the_start_in_behind_a_wall_unless_guarded():
    # the way round leads away from the goal first: section 3.2 fills the wall's whole shadow
    occ = np.zeros((15, 12), bool)
    occ[6, 0:9] = True
    paper = plan(occ, (1, 1), (13, 2), QLearningConfig(variant="Q-L5", seed=0, max_rounds=300))
    assert not paper.converged and not paper.reached
    w = GridWorld(occ, (1, 1), (13, 2), virtual=paper.virtual)
    assert not w.connected()
    guarded = plan(occ, (1, 1), (13, 2), QLearningConfig(variant="Q-L5", seed=0, max_rounds=300, fill_guard=True))
    assert guarded.reached and GridWorld(occ, (1, 1), (13, 2), virtual=guarded.virtual).connected()
    assert_valid_path(occ, guarded.path, (1, 1), (13, 2))



def test_a_fill_the_guard_took_back_is_not_tried_again(monkeypatch):
    """Fills only add obstacles, so a fill that cut the start off once would again: held-out, a leader's plan
    flood-filled the grid 140 776 times (10 s in one control step) re-trying the same refused fills."""
    occ = np.zeros((15, 12), bool)
    occ[6, 0:9] = True
    calls: list[int] = []
    connected = GridWorld.connected
    monkeypatch.setattr(GridWorld, "connected", lambda self, *a: calls.append(1) or connected(self, *a))
    guarded = plan(occ, (1, 1), (13, 2), QLearningConfig(variant="Q-L5", seed=0, max_rounds=300, fill_guard=True))
    assert guarded.reached
    assert 0 < len(calls) <= occ.size  # each cell is filled for good or refused for good: one flood fill at most


# ------------------------------------------------------------------ maps

@pytest.mark.parametrize("text, line, col, what", [
    ("S..\n.k.\n..G\n", 2, 2, "unknown character 'k'"),
    ("S..\n....\n..G\n", 2, 4, "row has 4 cells, expected 3"),
    ("S..\n..\n..G\n", 2, 3, "row has 2 cells, expected 3"),
    ("...\n...\n..G\n", 3, 1, "no start 'S'"),
    ("S..\n...\n...\n", 3, 1, "no goal 'G'"),
    ("S..\n..S\n..G\n", 2, 3, "second start 'S' (the first is at 1:1)"),
    ("S.G\n...\n..G\n", 3, 3, "second goal 'G'"),
    ("S..\n. .\n..G\n", 2, 2, "unknown character ' '"),
    ("", 1, 1, "empty map"),
])
def test_malformed_maps_name_file_line_and_column(tmp_path, text, line, col, what):
    f = tmp_path / "bad.txt"
    f.write_text(text)
    with pytest.raises(MapError) as e:
        load_map(f)
    msg = str(e.value)
    assert msg.startswith(f"{f}:{line}:{col}: "), msg
    assert what in msg and "\n" not in msg


def test_map_contract_first_line_is_the_top_row_and_maps_are_found():
    g = parse_map("..G#\n....\nS#..\n")
    assert g.shape == (4, 3) and g.start == (0, 0) and g.goal == (2, 2)
    assert g.occupancy[3, 2] and g.occupancy[1, 0] and g.occupancy.sum() == 2
    assert map_to_text(g.occupancy, g.start, g.goal) == "..G#\n....\nS#..\n"
    assert parse_map("S.\r\n.G\r\n\n").goal == (1, 0)  # CRLF and trailing empty lines are fine
    assert find_map("fan2021-fig5").resolve() == FIG5.resolve() == find_map("maps/fan2021-fig5.txt").resolve()
    for name in ("fan2021-fig5.txt", "concave-trap.txt", "fan2021-fig8.txt"):
        m = load_map(name)
        assert m.occupancy.dtype == bool
    fig5 = load_map(FIG5)
    assert fig5.shape == (20, 20) and fig5.start == (0, 0) and fig5.goal == (19, 19)


def test_planning_imports_only_numpy_matplotlib_and_the_standard_library():
    allowed = {"numpy", "matplotlib"} | set(sys.stdlib_module_names)
    for path in (ROOT / "stack" / "planning").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module]
            for n in names:
                assert n.split(".")[0] in allowed, f"{path.name} imports {n}"


# ------------------------------------------------------------------ formation (section 4.1 / 5.2)

def test_follower_cost_eq_13_and_triangle_formation():
    assert tracking_cost((0, 0), (3, 4), False) == pytest.approx(0.09 * 5)
    assert tracking_cost((0, 0), (3, 4), True) == pytest.approx(0.09 * 5 + 1.0)
    free = formation_experiment(None)
    assert free.reached and free.formation_error.max() == 0.0
    assert free.followers[0][0] == (0, 2) and free.followers[1][0] == (2, 0)
    grid = load_map("fan2021-fig8.txt")
    obst = formation_experiment(grid.occupancy, grid.start, grid.goal)
    assert obst.reached and obst.formation_error.mean() < 1.0
    for traj in [obst.leader] + obst.follower_paths:
        for c in traj:
            assert not grid.occupancy[c]


# ------------------------------------------------------------------ stack-train qlearn

def _cli(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "stack.train.cli", "qlearn", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def test_cli_writes_qlearn_json_with_the_contract_fields(tmp_path):
    r = _cli("--map", "maps/fan2021-fig5.txt", "--variant", "Q-L4", "--seed", "2", "--out", str(tmp_path), "--no-progress")
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "qlearn.json").read_text())
    for key in ("converged", "convergence_round", "convergence_time_s", "steps", "path_length", "path"):
        assert key in doc
    assert doc["converged"] is True and isinstance(doc["convergence_round"], int) and doc["convergence_time_s"] > 0
    assert doc["path"][0] == [0, 0] and doc["path"][-1] == [19, 19] and doc["steps"] == len(doc["path"]) - 1
    assert doc["path_length"] == pytest.approx(path_length(doc["path"]), abs=1e-3)
    assert doc["variant"] == "Q-L4" and doc["seed"] == 2
    assert (tmp_path / "path_Q-L4.png").stat().st_size > 1000 and (tmp_path / "table2.md").is_file()
    assert "| Q-L4 |" in r.stdout


def test_cli_variant_all_prints_table_2(tmp_path):
    r = _cli("--map", "concave-trap.txt", "--variant", "all", "--seeds", "2", "--max-rounds", "200",
             "--out", str(tmp_path), "--no-plots", "--no-progress")
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "table2.json").read_text())["rows"]
    assert [row["variant"] for row in rows] == ["Q-L1", "Q-L2", "Q-L3", "Q-L4", "Q-L5"]
    assert all(row["runs"] == 2 for row in rows)
    l3 = rows[2]
    assert l3["converged"] == 0 and l3["convergence_round"] is None and l3["paper"] is None
    assert rows[4]["paper"]["rounds"] == 1010
    md = (tmp_path / "table2.md").read_text()
    assert md in r.stdout and "| Q-L3 |" in md and "479.0" in md
    doc = json.loads((tmp_path / "qlearn.json").read_text())
    assert doc["variant"] == "Q-L5" and len(doc["runs"]) == 10


def test_cli_bad_map_and_bad_flags_exit_2_with_one_line(tmp_path):
    bad = tmp_path / "x.txt"
    bad.write_text("S" + "." * 9 + "\n" + "." * 10 + "\n" + "......k...\n" + "." * 9 + "G\n")
    r = _cli("--map", str(bad), "--out", str(tmp_path / "o"))
    assert r.returncode == 2
    assert r.stderr.strip() == f"stack-train: {bad}:3:7: unknown character 'k' (expected '#', '.', 'S' or 'G')"
    assert "Traceback" not in r.stderr and r.stdout == ""
    r = _cli("--map", str(tmp_path / "missing.txt"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "no such map file" in r.stderr
    for args in (["--map", str(FIG5), "--variant", "Q-L9"], ["--map", str(FIG5), "--seeds", "0"], []):
        r = _cli(*args)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = subprocess.run([sys.executable, "-m", "stack.train", "nope"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
