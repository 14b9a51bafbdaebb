"""A fleet whose robots bring their own lidars: a MAVLink rover with a ROS 2 lidar (LaserScan over Zenoh) and
a CAN base with an RPLidar A1 on a serial port (mounted backwards, ahead of its centre), each behind its
simulated device (hardware-like: the rover's EKF origin at boot, the ODrives' 10 ms encoder samples; the
lidars at their own rates, layouts and times), on an obstacle course with the ``drl`` policy, in lock-step.

The agents' drivers and lidar sources are the code that runs on the robots; the world hosts the devices and
sends no scan of its own for these robots."""

from __future__ import annotations

import json

import pytest

from conftest import run_fleet, write_scenario


def course() -> dict:
    return {
        "name": "lidar-fleet", "seed": 1, "dt": 0.1, "duration": 20.0,
        "world": {"obstacles": [{"type": "cylinder", "x": 4.5, "y": 0.3, "radius": 0.6},
                                {"type": "box", "x": 7.0, "y": -3.0, "size_x": 1.0, "size_y": 1.0}]},
        "robot": {"radius": 0.4, "v_max": 1.0, "w_max": 1.0, "comm_range": 12.0,
                  "lidar": {"beams": 180, "fov_deg": 180, "range": 5.0}},
        "formation": {"leader": 0, "goal": [9.0, 0.0], "slots": {1: {"L": 2.5, "psi_deg": 180}}},
        "robots": [
            {"id": 0, "role": "leader", "pose": [0.0, 0.0, 0.0], "policy": "drl", "driver": "mavlink",
             "lidar": {"source": "ros2"}},
            {"id": 1, "role": "follower", "pose": [-2.5, 0.0, 0.0], "policy": "drl", "driver": "can",
             "lidar": {"source": "rplidar", "rplidar": {"model": "A1"}, "mount": [0.1, 0.0, 180]}},
        ],
        "success": {"goal_tolerance": 0.5, "max_time": 20.0, "no_collisions": True},
    }


@pytest.mark.fleet
def test_can_and_mavlink_robots_avoid_obstacles_with_their_own_lidars(tmp_path):
    out = tmp_path / "out"
    proc, rep = run_fleet(write_scenario(tmp_path / "lidar.yaml", course()), out, "--no-plots", "--no-record")
    assert proc.returncode == 0 and rep["success"], proc.stdout + proc.stderr
    assert rep["drivers"] == {"0": "mavlink", "1": "can"}
    assert rep["collisions"] == {"robot_robot": 0, "robot_obstacle": 0}
    assert rep["min_obstacle_distance_m"] > 0.4 and rep["late_steps"] == 0
    devices = json.loads((out / "devices.json").read_text())
    assert devices["0"]["lidar"]["source"] == "ros2" and devices["1"]["lidar"]["settings"]["port"].startswith("/dev/pts/")
    t = rep["sim_time_s"]
    r0, r1 = rep["robots"]["0"], rep["robots"]["1"]
    # each scan the agent used came through its lidar source, at the sensor's own rate (15 Hz, 5.5 Hz)
    assert 14 * t <= r0["scans_from_driver"] <= 15 * t + 2, (r0["scans_from_driver"], t)
    assert 5.0 * t <= r1["scans_from_driver"] <= 5.8 * t + 2, (r1["scans_from_driver"], t)
    assert r0["driver_fault"] is None and r1["driver_fault"] is None
