"""The control step in process (stack/agents/step.py): time from clocks, not counts; frames; staleness.

No Zenoh, no world: a unicycle stands in for the robot, its odometry (and a lidar) arrive at their own rates
with jitter, gaps and a device clock of their own, and the pipeline is stepped on its own period.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import scenario_dict

from stack.agents.frames import OdomFrame, StreamClock, compose, inverse
from stack.agents.step import OdomSample, StepConfig, StepInputs, StepPipeline
from stack.comm.messages import Scan
from stack.scenario import parse_scenario

START = (2.0, -1.0, math.radians(30))


def _scenario(pose=(0.0, 0.0, 0.0), goal=(8.0, 0.0), policy="pid"):
    d = scenario_dict()
    d["robots"][0]["pose"] = [pose[0], pose[1], math.degrees(pose[2])]
    d["robots"][0]["policy"] = policy
    d["formation"]["goal"] = list(goal)
    return parse_scenario(d)


def _scan(sc, step: int = 0) -> Scan:
    lid = sc.robot(0).lidar
    return Scan(id=0, step=step, stamp=0.0, angle_min=-lid.fov / 2, angle_increment=lid.fov / (lid.beams - 1),
                range_max=lid.range, ranges=[lid.range] * lid.beams)


class Unicycle:
    """The true robot: exact arcs, driven by the (clamped) command."""

    def __init__(self, pose):
        self.x, self.y, self.yaw = pose
        self.v = self.w = 0.0

    def advance(self, h: float) -> None:
        if abs(self.w) < 1e-9:
            self.x += self.v * math.cos(self.yaw) * h
            self.y += self.v * math.sin(self.yaw) * h
        else:
            r = self.v / self.w
            self.x += r * (math.sin(self.yaw + self.w * h) - math.sin(self.yaw))
            self.y -= r * (math.cos(self.yaw + self.w * h) - math.cos(self.yaw))
        self.yaw = math.atan2(math.sin(self.yaw + self.w * h), math.cos(self.yaw + self.w * h))


def _drive(pipe: StepPipeline, sc, *, odom_hz=50.0, lidar_hz=10.0, duration=14.0, jitter=0.004, drop=0.1,
           device_offset=3.7, frame=lambda p: p, seed=0, noise=0.005):
    """Closed loop on the wall of a simulated clock: the truth moves in 2 ms steps, odometry (device stamps
    ``device_offset`` s off, arrival delayed 1-15 ms, ``drop`` of them lost) and the lidar come at their own
    rates, the pipeline steps every dt. Returns the largest estimate error and the end pose."""
    rng = np.random.default_rng(seed)
    robot = Unicycle(sc.robot(0).pose)
    clock = StreamClock()
    h, t = 0.002, 0.0
    next_odom, next_scan, next_step, k = 0.0, 0.0, 0.0, 0
    pending: list[OdomSample] = []
    in_flight: list[tuple[float, float, tuple]] = []  # (arrival, stamp, (v, w, pose))
    scan, scan_t, worst = None, None, 0.0
    while t < duration:
        if t >= next_odom:
            next_odom += 1.0 / odom_hz + rng.uniform(-jitter, jitter)
            if rng.random() >= drop:
                meas = (robot.v + rng.normal(0, noise), robot.w + rng.normal(0, noise), frame((robot.x, robot.y, robot.yaw)))
                in_flight.append((t + rng.uniform(0.001, 0.015), t + device_offset, meas))
        for item in [i for i in in_flight if i[0] <= t]:
            in_flight.remove(item)
            v, w, pose = item[2]
            pending.append(OdomSample(v=v, w=w, t=clock.time_of(item[1], item[0]), pose=pose))
        if t >= next_scan:
            next_scan += 1.0 / lidar_hz
            scan, scan_t = _scan(sc, k), t
        if t >= next_step:
            next_step += sc.dt
            out = pipe.step(StepInputs(step=k, t=t, t_run=t, now=t, odometry=tuple(pending), scan=scan, scan_t=scan_t))
            pending = []
            k += 1
            if pipe._t_odom is not None:
                worst = max(worst, math.hypot(out.pose.x - robot.x, out.pose.y - robot.y))
            robot.v, robot.w = out.v, out.w
        robot.advance(h)
        t += h
    return worst, (robot.x, robot.y, robot.yaw)


@pytest.mark.parametrize("lidar_hz", [7.0, 15.0, 25.0, 40.0])
def test_irregular_timing_the_estimate_stays_true_and_the_robot_arrives(lidar_hz):
    sc = _scenario()
    pipe = StepPipeline(sc, 0)
    worst, end = _drive(pipe, sc, lidar_hz=lidar_hz, seed=int(lidar_hz))
    assert worst < 0.15, worst
    assert math.hypot(end[0] - 8.0, end[1]) < sc.success.goal_tolerance


def test_the_estimator_advances_by_time_not_by_a_count_of_samples_or_steps():
    """Odometry at irregular intervals (12-45 ms), steps at irregular intervals (50-200 ms): driving 1 m/s
    straight for 3 s the estimate is 3 m on, which any count of samples or steps times a period misses."""
    sc = _scenario()
    pipe = StepPipeline(sc, 0)
    rng = np.random.default_rng(1)
    t_odom, t_step, samples, k = 0.0, 0.0, [], 0
    while t_odom < 3.0:
        samples.append(OdomSample(v=1.0, w=0.0, t=t_odom))
        t_odom += rng.uniform(0.012, 0.045)
        if t_odom >= t_step:
            pipe.step(StepInputs(step=k, t=t_odom, t_run=t_odom, now=t_odom, odometry=tuple(samples), scan=_scan(sc),
                                 scan_t=t_odom))
            samples, k = [], k + 1
            t_step += rng.uniform(0.05, 0.2)
    t_last = pipe._t_odom
    n = sum(pipe.decision.counts.values())
    assert pipe.estimator.pose.x == pytest.approx(t_last, abs=0.05)  # v (1 m/s, learnt from 0) x the time driven
    assert abs(n * sc.dt - t_last) > 0.3 and t_last > 2.9  # the number of steps times dt is not that time


def test_a_robot_turning_from_its_first_period_keeps_its_whole_turn():
    """The first sample (at rest) only places the estimator. Fused as a rate measurement, it left the second
    sample's rates without Q's random walk and averaged them with the rest: a leader that turned 3 deg in its
    first period carried a 1.5 deg yaw error (2.6 % of every metre driven, sideways) for the whole run."""
    sc = _scenario()
    pipe = StepPipeline(sc, 0)
    robot, dt = Unicycle((0.0, 0.0, 0.0)), 0.1
    for k in range(20):
        odo = OdomSample(v=robot.v, w=robot.w, t=k * dt, pose=(robot.x, robot.y, robot.yaw))
        pipe.estimate(StepInputs(step=k, t=k * dt, t_run=k * dt, now=k * dt, odometry=(odo,), scan=_scan(sc, k),
                                 scan_t=k * dt))
        p = pipe.estimator.pose
        assert abs(p.yaw - robot.yaw) < math.radians(0.05), (k, math.degrees(p.yaw - robot.yaw))
        assert math.hypot(p.x - robot.x, p.y - robot.y) < 0.002, k
        robot.v, robot.w = 0.3, -0.55  # from the first period on: the step's command
        robot.advance(dt)


def test_offset_rotated_odom_frame_gives_the_site_estimate():
    """A device that booted at the start pose (2, -1, 30 deg) reports odometry from (0, 0, 0) there."""
    sc = _scenario(pose=START)
    boot = inverse(START)  # odom <- site
    pipe = StepPipeline(sc, 0, config=StepConfig(odom_origin="boot"))
    worst, end = _drive(pipe, sc, frame=lambda p: compose(boot, p), lidar_hz=15.0)
    assert worst < 0.15 and math.hypot(end[0] - 8.0, end[1]) < sc.success.goal_tolerance
    # the same device with ``first``: its first sample is the start pose whatever its odom frame
    pipe = StepPipeline(sc, 0, config=StepConfig(odom_origin="first"))
    elsewhere = compose((-7.0, 4.0, math.radians(100)), boot)  # an odom frame that is neither site nor boot
    worst, end = _drive(pipe, sc, frame=lambda p: compose(elsewhere, p), lidar_hz=15.0)
    assert worst < 0.15 and math.hypot(end[0] - 8.0, end[1]) < sc.success.goal_tolerance
    # and ``site`` would put it where the odometry says, in the wrong frame: the setting matters
    pipe = StepPipeline(sc, 0, config=StepConfig(odom_origin="site"))
    pipe.step(StepInputs(step=0, t=0.0, t_run=0.0, now=0.0, odometry=(OdomSample(0.0, 0.0, 0.0, pose=(0.0, 0.0, 0.0)),),
                         scan=_scan(sc), scan_t=0.0))
    assert math.hypot(pipe.estimator.pose.x - START[0], pipe.estimator.pose.y - START[1]) > 2.0


def test_a_restarted_agent_on_a_boot_frame_device_starts_where_the_robot_is():
    """Restarted mid-run: the device did not reboot, its odometry is still from the start pose; ``boot`` puts
    the new agent's estimate where the robot is now, not at the start pose."""
    sc = _scenario(pose=START)
    here = (5.0, 0.5, math.radians(-10))  # the robot's site pose when the agent comes back
    pipe = StepPipeline(sc, 0, config=StepConfig(odom_origin="boot"))
    odo = OdomSample(0.0, 0.0, 40.0, pose=compose(inverse(START), here))
    pipe.step(StepInputs(step=400, t=40.0, t_run=40.0, now=40.0, odometry=(odo,), scan=_scan(sc), scan_t=40.0))
    p = pipe.estimator.pose
    assert (p.x, p.y, p.yaw) == pytest.approx(here, abs=1e-9)


def test_fixes_refine_the_site_from_odom_transform():
    frame = OdomFrame(START, "boot")
    frame.site_pose((0.0, 0.0, 0.0))
    assert frame.T == pytest.approx(START)
    frame.refine((2.5, -1.0, math.radians(30)), (0.0, 0.0, 0.0))  # a fix found the robot 0.5 m further east
    assert frame.site_pose((1.0, 0.0, 0.0))[:2] == pytest.approx((2.5 + math.cos(START[2]), -1.0 + math.sin(START[2])))
    with pytest.raises(ValueError, match="odom_origin"):
        OdomFrame(START, "odom")


def test_device_stamps_give_the_intervals_and_a_clock_seconds_off_does_not_matter():
    clock = StreamClock(max_skew_s=0.25)
    arrivals = [10.001, 10.031, 10.042, 10.07, 10.081]  # transport delays of 1-11 ms
    stamps = [1003.7, 1003.72, 1003.74, 1003.76, 1003.78]  # another host's clock, 20 ms apart
    times = [clock.time_of(s, a) for s, a in zip(stamps, arrivals)]
    assert np.diff(times) == pytest.approx([0.02] * 4) and all(t <= a for t, a in zip(times, arrivals))
    # a stamp that stands still (a driver that stamps nothing useful) or jumps: the arrival then
    assert clock.time_of(1003.78, 10.1) == 10.1 and clock.time_of(2000.0, 10.12) == 10.12 and clock.unusable == 2


def test_stale_odometry_stops_every_robot_and_a_stale_lidar_the_policies_that_need_it():
    for policy, lidar_stops in (("pid", False), ("aina", True)):
        sc = _scenario(policy=policy)
        pipe = StepPipeline(sc, 0)
        odo = lambda t: (OdomSample(0.0, 0.0, t, pose=(0.0, 0.0, 0.0)),)  # noqa: E731
        out = pipe.step(StepInputs(step=0, t=0.0, t_run=0.0, now=0.0, odometry=odo(0.0), scan=_scan(sc), scan_t=0.0))
        assert out.stale is None and out.v > 0
        out = pipe.step(StepInputs(step=1, t=1.0, t_run=1.0, now=1.0, odometry=odo(1.0), scan=_scan(sc), scan_t=0.0))
        assert (out.stale == "lidar") is lidar_stops and (out.v == 0.0) is lidar_stops
        out = pipe.step(StepInputs(step=2, t=2.0, t_run=2.0, now=2.0, scan=_scan(sc), scan_t=2.0))
        assert out.stale == "odometry" and (out.v, out.w) == (0.0, 0.0)


def test_stacked_scans_are_one_control_period_apart_at_any_lidar_rate():
    """A 40 Hz lidar: four scans per period; o_z holds the newest of each of the last three periods."""
    sc = _scenario()
    pipe = StepPipeline(sc, 0)
    newest = []
    for k in range(6):
        scans = [_scan(sc, 4 * k + i) for i in range(4)]
        scans[-1] = Scan(**{**{f: getattr(scans[-1], f) for f in scans[-1].__struct_fields__},
                            "ranges": [float(k % 5)] * sc.robot(0).lidar.beams})
        newest.append(k % 5)
        pipe.step(StepInputs(step=k, t=0.1 * k, t_run=0.1 * k, now=0.1 * k, scan=scans[-1], scan_t=0.1 * k,
                             odometry=(OdomSample(0.0, 0.0, 0.1 * k),)))
    assert [s[0] for s in pipe.scans] == newest[-3:]


@pytest.mark.parametrize("centre", [True, False])
def test_robot_drl_centre_heading_reaches_the_followers_decision_layer(centre):
    """``robot.drl.centre_heading`` (default true, Bai's eq. 21-22) decides where a drl follower in situation 3
    aims; pid never aims at the centre."""
    d = scenario_dict()
    d["robot"]["drl"] = {"centre_heading": centre}
    sc = parse_scenario(d)
    assert StepPipeline(sc, 1, policy="drl").decision.centre_heading is centre
    assert StepPipeline(sc, 1, policy="pid").decision.centre_heading is False


@pytest.mark.parametrize("tracker", ["pid", "policy"])
def test_robot_stuck_detour_tracker_says_what_drives_a_planned_detour(tracker):
    """``robot.stuck.detour.tracker``: a stuck robot's planned detour is driven by the PID path tracker (``pid``, the
    default) or by the robot's own policy (``policy``: bench/heldout.py's drl-alone, the network that sees the other
    robots); a blind escape is always the policy's."""
    from stack.agents.decision import Decision
    from stack.policies.base import Observation

    d = scenario_dict()
    d["robot"]["stuck"] = {"detour": {"tracker": tracker}}
    pipe = StepPipeline(parse_scenario(d), 1, policy="drl")
    assert pipe.role == "follower"
    calls = []
    pipe.pid = type("Pid", (), {"act": lambda self, obs: calls.append("pid") or (0.3, 0.0)})()
    pipe.policy.act = lambda obs: calls.append("policy") or (0.5, 0.0)
    stuck = pipe.decision.stuck
    obs = Observation(d_g=2.0, alpha_g=0.0, v=0.0, w=0.0)
    for kind in ("plan", "escape"):
        stuck.waypoint, stuck.open = (3.0, 1.0), {"kind": kind}
        pipe._act(Decision("escape", True, obs, (3.0, 1.0), 1.0, 4.0, 1.0), 0.0)
    assert calls == [tracker, "policy"]
