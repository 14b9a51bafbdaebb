"""A real-time agent on its own clock: the ``jackal`` driver against its simulated device, the lidar at 15 Hz.

One agent (the formation's leader, alone) in this process on a loopback router; the simulated Jackal on a
second session, its body moved here on the wall clock from the device's own controller, its odometry at
the device's 50 Hz, its LaserScan at 15 Hz, not the control rate (10 Hz). When scans were counted as control
steps, this estimate ran 1.5x fast and the robot stopped short of its goal.
"""

from __future__ import annotations

import math
import threading
import time

import pytest
from conftest import scenario_dict

from stack.agents.agent import Agent, AgentConfig
from stack.comm import Keys
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session
from stack.scenario import parse_scenario
from stack.sim_bridge.devices import Body
from stack.sim_bridge.jackal_sim import JackalDevice

GOAL = (4.0, 1.0)
LIDAR_HZ = 15.0


def _move_body(dev: JackalDevice, sc, stop: threading.Event, truth: list) -> None:
    """The world's part on the wall clock: the device's controller moves the body; the lidar at 15 Hz."""
    x, y, yaw = sc.robot(0).pose
    lid = sc.robot(0).lidar
    h, t, next_scan = 0.005, dev.wall_time(), 0.0
    while not stop.is_set():
        time.sleep(h)
        now = dev.wall_time()
        dev.take_commands(t)
        v, w = dev.motion(now)
        dt = now - t
        x, y, yaw = x + v * math.cos(yaw + 0.5 * w * dt) * dt, y + v * math.sin(yaw + 0.5 * w * dt) * dt, yaw + w * dt
        dev.report(now, Body(x, y, yaw, v, w))
        truth[:] = [x, y, yaw]
        if now >= next_scan:
            next_scan = now + 1.0 / LIDAR_HZ
            dev.publish_scan(now, -lid.fov / 2, lid.fov / (lid.beams - 1), lid.range, [lid.range] * lid.beams)
        t = now


def test_real_time_jackal_agent_with_a_15_hz_lidar_reaches_its_goal():
    d = scenario_dict()
    d["formation"]["goal"] = list(GOAL)
    d["robots"][0] |= {"driver": "jackal", "jackal": {"namespace": "rt15/robot0"},
                       "device": {"jackal": {"lidar_rate_hz": LIDAR_HZ}}}  # a hardware-like Jackal, its lidar at 15 Hz
    sc = parse_scenario(d)
    ep, fleet = free_tcp_endpoint(), "rt15"
    stop_world = threading.Event()
    truth: list = list(sc.robot(0).pose)
    with open_session(SessionConfig(mode="router", listen=[ep])), \
            open_session(SessionConfig(connect=[ep])) as s_agent, open_session(SessionConfig(connect=[ep])) as s_world:
        dev = JackalDevice(sc.robot(0), session=s_world, keys=Keys(fleet), namespace="rt15/robot0")
        dev.start()
        world = threading.Thread(target=_move_body, args=(dev, sc, stop_world, truth), daemon=True)
        world.start()
        cfg = AgentConfig(robot_id=0, scenario=sc, fleet=fleet)
        agent = Agent(cfg, s_agent)
        runner = threading.Thread(target=agent.run, daemon=True)
        t0 = time.monotonic()
        runner.start()
        try:
            arrived = None
            while time.monotonic() - t0 < 40.0 and runner.is_alive():
                time.sleep(0.1)
                if math.hypot(truth[0] - GOAL[0], truth[1] - GOAL[1]) < sc.success.goal_tolerance:
                    arrived = time.monotonic() - t0
                    break
            time.sleep(1.0)  # it stays there (PID holds still within its arrival radius)
            err = math.hypot(truth[0] - GOAL[0], truth[1] - GOAL[1])
            p = agent.estimator.pose
            est_err = math.hypot(p.x - truth[0], p.y - truth[1])
            elapsed = time.monotonic() - t0
        finally:
            cfg.stop.set()
            runner.join(10)
            stop_world.set()
            world.join(5)
            dev.close()
    assert not runner.is_alive()
    assert arrived is not None and err < sc.success.goal_tolerance, (truth, err)
    assert est_err < 0.2, est_err
    # the scans came at the lidar's rate, the control steps at the scenario's (they are not the same count);
    # each step took the newest scan (at most one new one per period)
    assert dev.counters["scan"] == pytest.approx(LIDAR_HZ * elapsed, rel=0.3)
    assert agent.step + 1 == pytest.approx(elapsed / sc.dt, rel=0.3)
    assert 0.5 * (agent.step + 1) < agent.scans_from_driver <= agent.step + 1
    assert agent.driver.fault is None and agent.sensor_stale == 0
