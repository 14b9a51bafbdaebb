"""No livelock (issue 19): the stuck detector on a hand-built pinned-robot scene, the planned detour round a cross
wall whose gap lies off the robot's line, and the bounded hold."""

import math
from types import SimpleNamespace

import numpy as np

from stack.agents.decision import DecisionLayer, Neighbour
from stack.agents.detour import DetourConfig
from stack.agents.livelock import HoldConfig, StuckConfig, clear_side_waypoint
from stack.scenario import FormationConfig, Slot
from stack.train.drlworld import obstacle_distance, ray_cast

DT = 0.1
RADIUS = 0.5
BEAMS = np.linspace(-math.pi / 2, math.pi / 2, 180)
# a follower at the origin heading +x, pinned against a cylinder (surface 0.55 m from its centre) that stands
# between it and its slot (8, 0); a wall 1.4 m to its right, so the clear side is the left
CIRCLES = np.array([[1.05, 0.0, 0.5]])
BOXES = np.array([[2.0, -1.5, 4.0, 0.1, 0.0]])
FORMATION = FormationConfig(leader=0, goal=(30.0, 0.0), slots={1: Slot(L=3.0, psi=math.pi)})
LEADER = (11.0, 0.0)  # standing still: the slot is (8, 0)
SLOT = (8.0, 0.0)


BLIND = DetourConfig(enabled=False)  # the blind escapes alone (no plan on the scan memory)


def layer(**stuck) -> DecisionLayer:
    return DecisionLayer(1, "follower", FORMATION, goal=None, radius=RADIUS, comm_range=10.0, scan_range=5.0, dt=DT,
                         stuck=StuckConfig(**stuck))


def scan_at(x, y, yaw):
    return ray_cast(np.array(x), np.array(y), np.array(yaw), CIRCLES, BOXES, BEAMS, RADIUS + 0.01, 5.0)


def step(dl: DecisionLayer, t: float, x: float, y: float, yaw: float = 0.0):
    pose = SimpleNamespace(x=x, y=y, yaw=yaw, v=0.0, w=0.0)
    leader = Neighbour(0, "leader", *LEADER, 0.0, 0.0, 0.0, t, int(t / DT))
    s = scan_at(x, y, yaw)
    return dl.decide(pose, t, {0: leader}, s[None], float(s.min()), t_run=t)


def test_the_scene_pins_the_robot():
    assert RADIUS < obstacle_distance(np.array(0.0), np.array(0.0), CIRCLES, BOXES) < RADIUS + 0.1  # 5 cm off it
    s = scan_at(0.0, 0.0, 0.0)
    assert s[90] < 0.6 and s[BEAMS > 0.5].mean() > s[BEAMS < -0.5].mean()  # blocked ahead, clearer to the left


def test_a_pinned_robot_is_stuck_within_the_window_and_escapes_to_the_clear_side():
    dl = layer(detour=BLIND)
    t, first = 0.0, None
    while t < 12.0 and first is None:
        d = step(dl, t, 0.0, 0.0)
        if d.situation == "escape":
            first = (t, d)
        t = round(t + DT, 6)
    assert first is not None, "never flagged"
    t_stuck, d = first
    assert 8.0 - 1e-6 <= t_stuck <= 8.0 + DT + 1e-6  # the window T = 8 s, not later
    assert d.use_network and d.obs is not None and d.target == dl.stuck.waypoint
    wx, wy = d.target
    assert wy > 0.5 and math.hypot(wx, wy) <= 1.5 + 1e-9  # toward the clear (left) side, escape_distance at most
    assert obstacle_distance(np.array(wx), np.array(wy), CIRCLES, BOXES) > RADIUS  # a free place
    ll = dl.livelock()
    assert ll["episodes"] == 1 and ll["open"] == 1 and ll["events"][0]["event"] == "stuck"
    # the escape lasts escape_time at most; still pinned, the detector tries detours, then gives up: bounded
    situations = [step(dl, round(t + k * DT, 6), 0.0, 0.0).situation for k in range(400)]
    assert situations[: int(4.0 / DT) - 1] == ["escape"] * (int(4.0 / DT) - 1)
    ll = dl.livelock()
    assert ll["gave_up"] == 1 and ll["escape"] == ll["detour"] == 0
    assert any(e["event"] == "resolved" and e["by"] == "gave_up" and e["tries"] == 3 for e in ll["events"])


def test_an_escape_that_frees_the_robot_is_counted():
    """A crude robot: 0.5 m/s straight at its decision's target unless that would bring it into an obstacle."""
    dl = layer(detour=BLIND)
    x, y, t = 0.0, 0.0, 0.0
    for _ in range(900):
        d = step(dl, t, x, y)
        tx, ty = d.target
        h = math.atan2(ty - y, tx - x)
        nx, ny = x + 0.5 * DT * math.cos(h), y + 0.5 * DT * math.sin(h)
        if math.hypot(tx - x, ty - y) > 0.05 and obstacle_distance(np.array(nx), np.array(ny), CIRCLES, BOXES) > RADIUS:
            x, y = nx, ny
        t = round(t + DT, 6)
    ll = dl.livelock()
    assert ll["episodes"] >= 1 and ll["escape"] + ll["detour"] + ll["target"] >= 1 and ll["gave_up"] == 0
    assert math.hypot(x - SLOT[0], y - SLOT[1]) < 1.0  # it got to its slot


def test_slow_but_real_progress_is_not_stuck():
    dl = layer()
    x = -3.0  # behind the scene, creeping toward the slot at 5 cm/s (0.4 m per 8 s window) on a free line
    for k in range(400):
        d = step(dl, k * DT, x, 3.0, yaw=math.atan2(-3.0, SLOT[0] - x))
        assert d.situation != "escape"
        x += 0.05 * DT
    assert dl.livelock()["episodes"] == 0


def test_a_robot_at_its_target_is_not_stuck_and_reaching_it_ends_the_episode():
    dl = layer(at_target=1.0)
    for k in range(200):
        assert step(dl, k * DT, SLOT[0], 0.6).situation != "escape"  # 0.6 m from its slot, standing: fine
    dl = layer(escape_time=0.5, max_tries=5, detour=BLIND)
    for k in range(120):
        step(dl, k * DT, 0.0, 0.0)
    assert dl.livelock()["open"] == 1
    step(dl, 12.5, SLOT[0] - 0.2, 0.3)
    ll = dl.livelock()
    assert ll["target"] == 1 and ll["open"] == 0


def test_the_escape_waypoint_picks_the_clearer_side():
    ranges = np.full(180, 5.0)
    ranges[BEAMS < 0] = 1.0  # right side blocked
    (wx, wy), side = clear_side_waypoint(0.0, 0.0, 0.0, ranges, math.pi, 5.0, RADIUS, 1.5)
    assert side == 1 and math.isclose(math.hypot(wx, wy), 1.5)
    # the most forward heading whose path keeps the body (0.6 m) off the returns 1 m away on the right: 40 deg
    assert math.isclose(math.atan2(wy, wx), math.radians(40))
    (wx, wy), side = clear_side_waypoint(0.0, 0.0, math.pi / 2, ranges, math.pi, 5.0, RADIUS, 1.5, side=-1)
    assert side == -1 and wx > 0  # heading +y, its right is +x, where returns stand 1 m off
    assert math.hypot(wx, wy) < 1.0 - RADIUS + 0.05  # the body stops short of them


def test_the_leaders_hold_gives_up_after_max_hold_and_says_why():
    fl = FormationConfig(leader=0, goal=(30.0, 0.0), slots={1: Slot(L=3.0, psi=math.pi)})
    dl = DecisionLayer(0, "leader", fl, goal=None, radius=RADIUS, comm_range=10.0, scan_range=5.0, dt=DT,
                       hold=HoldConfig(max_hold=20.0, resume_fraction=0.5))
    hold = (0.8, 0.95)
    pose = SimpleNamespace(x=0.0, y=0.0, yaw=0.0, v=0.0, w=0.0)
    speeds = []
    for k in range(300):  # the follower stays 9 m behind: the hold's factor (9.5 - 9) / 1.5 = 1/3
        t = k * DT
        far = Neighbour(1, "follower", pose.x - 9.0, 0.0, 0.0, 0.0, 0.0, t, k)
        dec = dl.decide(pose, t, {1: far}, np.full((1, 180), 5.0), math.inf, t_run=t)
        assert dec.situation != "escape"  # held on purpose (and, given up, moving): not stuck
        speeds.append(dl.hold_speed(1.0, dec.d_rmax, t, 5.0, hold, 10.0))
        pose.x += speeds[-1] * DT  # the follower keeps 9 m behind
    v20 = 5.0 / 9.0
    assert math.isclose(speeds[0], v20 / 3) and math.isclose(speeds[199], v20 / 3)  # held up to H = 20 s
    assert all(math.isclose(v, 0.5 * v20) for v in speeds[200:])  # then it gives up: half of eq. (20)
    ll = dl.livelock()
    assert ll["hold_give_ups"] == 1 and ll["episodes"] == 0
    g = [e for e in ll["events"] if e["event"] == "hold-gave-up"][0]
    assert g["robot"] == 1 and math.isclose(g["t"], 20.0) and g["d_rmax"] == 9.0 and "max_hold 20 s" in g["reason"]
    assert math.isclose(dl.hold_speed(1.0, 4.0, 31.0, 5.0, hold, 10.0), 1.0)  # back in range: released
    assert dl.livelock()["events"][-1]["event"] == "hold-released"
    # the static eq. (20) + hold is unchanged (unbounded, as before)
    assert math.isclose(DecisionLayer.leader_speed(1.0, 9.0, 5.0, hold, 10.0), v20 / 3)


def test_the_report_sums_the_agents_livelock_counters():
    """stack.fleet.metrics.livelock over the agents' Diag.stuck (what DecisionLayer.livelock() returns)."""
    from stack.fleet.metrics import diag_fields, livelock

    follower = layer(detour=BLIND)
    for k in range(500):  # pinned: stuck at 8 s, tries at 8, 20, 32 s, gave up at 44 s
        step(follower, round(k * DT, 6), 0.0, 0.0)
    leader = DecisionLayer(0, "leader", FORMATION, goal=None, radius=RADIUS, comm_range=10.0, scan_range=5.0, dt=DT,
                           hold=HoldConfig(max_hold=5.0))
    leader.farthest = (1, 9.2)
    for k in range(80):
        leader.hold_speed(1.0, 9.2, k * DT, 5.0, (0.8, 0.95), 10.0)
    diags = {0: SimpleNamespace(stuck=leader.livelock()), 1: SimpleNamespace(stuck=follower.livelock()),
             2: SimpleNamespace(stuck=None), 3: SimpleNamespace()}  # an agent without the detector
    ll = livelock(diags)
    assert ll["stuck_episodes"] == 1 and ll["resolved_by"]["gave_up"] == 1 and ll["stuck_robots"] == [1]
    assert ll["hold_give_ups"] == 1 and ll["hold_events"][0]["leader"] == 0 and ll["hold_events"][0]["robot"] == 1
    assert "waiting for robot 1 at 9.2 m" in ll["hold_events"][0]["reason"]
    assert livelock({0: SimpleNamespace(stuck=None)}) is None
    assert diag_fields(None)["stuck"] is None


def test_a_leader_held_by_the_static_eq_20_is_not_stuck_but_a_pinned_leader_is():
    """An agent that only calls the static leader_speed: the leader standing for a follower 9 m off (the default
    hold band) is waiting, not stuck; the same leader pinned with its followers near is stuck."""
    for d_far, stuck in ((9.0, False), (3.0, True)):
        dl = DecisionLayer(0, "leader", FORMATION, goal=None, radius=RADIUS, comm_range=10.0, scan_range=5.0, dt=DT)
        pose = SimpleNamespace(x=0.0, y=0.0, yaw=0.0, v=0.0, w=0.0)
        s = scan_at(0.0, 0.0, 0.0)
        seen = set()
        for k in range(120):
            t = round(k * DT, 6)
            far = Neighbour(1, "follower", -d_far, 0.0, 0.0, 0.0, 0.0, t, k)
            seen.add(dl.decide(pose, t, {1: far}, s[None], float(s.min()), t_run=t).situation)
        assert ("escape" in seen) == stuck, (d_far, seen)


# a cross wall at x = 3 whose gap (y 4.0..6.6, 2.6 m) lies 4 m off the line from the robot (0, 0) to its slot (8, 0)
CROSS = np.array([[3.0, -4.0, 0.1, 8.0, 0.0], [3.0, 9.3, 0.1, 2.7, 0.0]])  # [cx, cy, hx, hy, yaw]
NONE = np.array([[100.0, 100.0, 0.1]])  # no cylinder in reach (the ray caster wants one)


def drive(dl: DecisionLayer, boxes: np.ndarray, steps: int, x=0.0, y=0.0):
    """The crude robot (0.5 m/s straight at its decision's target, turning on the spot, stopped short of anything)
    against ``boxes``; the scan turns with its heading. Returns the final position and the situations seen."""
    yaw, seen = 0.0, []
    for k in range(steps):
        t = round(k * DT, 6)
        dl.stuck.runner.begin(k, t)  # what the step pipeline does first: plans that are due are adopted
        s = ray_cast(np.array(x), np.array(y), np.array(yaw), NONE, boxes, BEAMS, RADIUS + 0.01, 5.0)
        leader = Neighbour(0, "leader", *LEADER, 0.0, 0.0, 0.0, t, k)
        d = dl.decide(SimpleNamespace(x=x, y=y, yaw=yaw, v=0.0, w=0.0), t, {0: leader}, s[None], float(s.min()), t_run=t)
        seen.append(d.situation)
        tx, ty = d.target
        if math.hypot(tx - x, ty - y) < 0.05:
            continue
        yaw = math.atan2(ty - y, tx - x)
        nx, ny = x + 0.5 * DT * math.cos(yaw), y + 0.5 * DT * math.sin(yaw)
        if obstacle_distance(np.array(nx), np.array(ny), NONE, boxes) > RADIUS + 0.02:
            x, y = nx, ny
    return x, y, seen


def test_the_planned_detour_finds_the_gap_the_blind_escapes_miss():
    """Pressed against the cross wall, the blind escapes (1.5 m, then 3 m either side) never reach the gap 4 m
    off the line; the plan on what the lidar has seen runs along the wall, sees its end, and goes through."""
    x, y, _ = drive(layer(detour=BLIND), CROSS, 1200)
    assert x < 3.0  # still on the near side of the wall after 120 s
    dl = layer()
    x, y, seen = drive(dl, CROSS, 1200)
    assert math.hypot(x - SLOT[0], y - SLOT[1]) < 1.0, (x, y)  # at its slot
    ll = dl.livelock()
    assert ll["episodes"] >= 1 and ll["plan"] >= 1 and ll["gave_up"] == 0
    assert obstacle_distance(np.array(x), np.array(y), NONE, CROSS) > RADIUS


def test_the_detour_planned_beside_the_step_finds_the_gap_too():
    """The same with the plans on a worker thread, each one adopted at the step after it was asked (lock-step; an
    agent's runner): the robot drives its policy (a try's first plan) or its last path meanwhile."""
    from stack.planning.runner import ThreadRunner

    dl = layer()
    dl.stuck.runner = ThreadRunner(lockstep_steps=1)
    x, y, _ = drive(dl, CROSS, 1200)
    dl.stuck.runner.close()
    assert math.hypot(x - SLOT[0], y - SLOT[1]) < 1.0, (x, y)
    ll, st = dl.livelock(), dl.stuck.runner.stats()
    assert ll["plan"] >= 1 and ll["gave_up"] == 0 and st["adopted"] >= 3, (ll, st)
    assert abs(st["wait_max_s"] - DT) < 1e-9, st  # every plan drove from the next step


def test_the_plan_runs_on_the_memory_round_what_was_seen():
    """The memory keeps the wall's returns (world frame), not the neighbours'; the path keeps the body off it."""
    from stack.agents.detour import DetourPlanner, ScanMemory

    mem = ScanMemory(0.25)
    for yaw in (math.pi / 2, 0.0, -math.pi / 2):  # a look round from (2, 0): the wall, the lower gap edge
        s = ray_cast(np.array(2.0), np.array(0.0), np.array(yaw), NONE, CROSS, BEAMS, RADIUS + 0.01, 5.0)
        mem.add(2.0, 0.0, yaw, s, math.pi, 5.0, ignore=[(2.0, 3.0)])
    cells = np.array(list(mem.cells)) * 0.25
    assert len(cells) > 20 and np.all(np.abs(cells[:, 0] + 0.125 - 2.9) < 0.3)  # every cell on the wall's face
    pl = DetourPlanner(DetourConfig(), mem, RADIUS)
    assert pl.plan(0.0, (2.4, 0.0), SLOT) and not pl.clear_line((2.4, 0.0), SLOT)
    path = np.array(pl.path)
    assert np.all(path[:, 1] >= -1e-9) or np.all(path[:, 1] <= 1e-9)  # one way round the wall
    through = path[np.abs(path[:, 0] - 3.0) < 0.2]
    assert np.all(np.abs(through[:, 1]) > 4.0)  # it crosses x = 3 beyond the wall's seen end only
    wx, wy = pl.waypoint((2.4, 0.0))
    assert math.isclose(math.hypot(wx - 2.4, wy), 2.0, abs_tol=0.3)  # lookahead along the path
    assert pl.clear_line((6.0, 2.0), SLOT)  # beyond the wall: nothing in the way


def test_a_leader_no_hold_slows_is_judged_even_with_a_follower_far():
    """aina and qlearn drive themselves (no eq. (20) hold slows them): their leader pinned with a follower 9 m off
    (a slot 8 m out keeps it there) is stuck, not waiting."""
    dl = DecisionLayer(0, "leader", FORMATION, goal=None, radius=RADIUS, comm_range=10.0, scan_range=5.0, dt=DT)
    dl.static_hold = False
    pose = SimpleNamespace(x=0.0, y=0.0, yaw=0.0, v=0.0, w=0.0)
    s = scan_at(0.0, 0.0, 0.0)
    seen = {dl.decide(pose, k * DT, {1: Neighbour(1, "follower", -9.0, 0.0, 0.0, 0.0, 0.0, k * DT, k)}, s[None],
                      float(s.min()), t_run=k * DT).situation for k in range(120)}
    assert "escape" in seen


def test_the_memory_forgets_nothing_seen_and_the_neighbours():
    """A lidar's no-return value with its noise (a little under range_max) and the returns of known robots are not
    obstacles to plan round; a real return is."""
    from stack.agents.detour import ScanMemory

    mem = ScanMemory(0.25)
    rng = np.random.default_rng(1)
    mem.add(0.0, 0.0, 0.0, np.clip(5.0 + rng.normal(0, 0.01, 180), 0, 5.0), math.pi, 5.0)
    assert not mem.cells
    ranges = np.full(180, 5.0)
    ranges[85:95] = 2.0  # something 2 m ahead
    mem.add(0.0, 0.0, 0.0, ranges, math.pi, 5.0, ignore=[(2.2, 0.0)])
    assert not mem.cells  # a neighbour stands there
    mem.add(0.0, 0.0, 0.0, ranges, math.pi, 5.0)
    cells = np.array(list(mem.cells)) * 0.25
    assert len(cells) and np.all(np.abs(np.hypot(cells[:, 0] + 0.125, cells[:, 1] + 0.125) - 2.0) < 0.25)


def test_a_robot_stuck_with_its_way_open_is_driven_down_it_then_handed_back():
    """Deng's obstacle term can refuse a 3 m gap whose edges its sectors see: the robot stands still with the straight
    way to its slot open in its memory. The plan then drives down that way (rather than a blind escape to a side)
    for ``open_horizon`` metres and hands back to the policy."""
    dl = layer()
    x, y = 0.0, 3.0
    yaw = math.atan2(SLOT[1] - y, SLOT[0] - x)  # facing the slot: the cylinder is 2 m off the line
    t = 0.0
    while not dl.stuck.planned and t < 12.0:
        step(dl, t, x, y, yaw)
        t = round(t + DT, 6)
    assert dl.stuck.planned and dl.stuck.straight, "a stuck robot with an open way gets no plan down it"
    wx, wy = dl.stuck.waypoint
    ux, uy = math.cos(yaw), math.sin(yaw)
    # down the way: about lookahead (2 m) along an 8-connected grid path, which stairs round the straight line
    assert abs((wx - x) * uy - (wy - y) * ux) < 0.75 and 1.2 < (wx - x) * ux + (wy - y) * uy < 2.5
    travelled = 0.0
    while dl.stuck.planned and t < 40.0:  # it drives down the way at 1 m/s (10 s, straight_time, would be 10 m)
        x, y, travelled = x + 0.1 * ux, y + 0.1 * uy, travelled + 0.1
        step(dl, t, x, y, yaw)
        t = round(t + DT, 6)
    assert not dl.stuck.planned
    assert 6.0 - 1e-6 <= travelled <= 7.0 + 1e-6  # handed back once open_horizon along (at the next re-plan, each 1 s)
    for _ in range(5):  # the policy drives on: the progress since the hand-back resolves the episode
        x, y, t = x + 0.1 * ux, y + 0.1 * uy, round(t + DT, 6)
        step(dl, t, x, y, yaw)
    assert dl.livelock()["plan"] == 1 and dl.livelock()["open"] == 0
