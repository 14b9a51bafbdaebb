"""A robot's own lidar, read by its driver (a bridged ROS 2 robot's ``LaserScan``), as the agent's ``Scan``.

The policies expect the scan the scenario describes (``robot.lidar``: beams evenly from -fov/2 to
+fov/2, ends included, ranges clipped at ``range``); a real sensor has its own geometry (a SICK
LMS111: 270 degrees in 0.5 degree steps). Each expected beam takes the sensor's beam nearest in
angle; an expected beam outside the sensor's span, or a reading beyond ``range``, reads ``range``.
"""

from __future__ import annotations

import numpy as np

from ..comm.messages import Scan


def resample(angle_min: float, angle_increment: float, ranges, beams: int, fov: float, range_max: float) -> np.ndarray:
    """The sensor's ``ranges`` (``angle_min + i * angle_increment``) at the configured beams' angles."""
    r = np.asarray(ranges, dtype=float)
    want = np.linspace(-fov / 2, fov / 2, beams) if beams > 1 else np.zeros(1)
    out = np.full(want.size, float(range_max))
    if r.size == 0 or not angle_increment:
        return out
    idx = np.rint((want - angle_min) / angle_increment).astype(int)
    ok = (idx >= 0) & (idx < r.size)
    out[ok] = np.clip(r[idx[ok]], 0.0, range_max)
    return out


def scan_from_driver(robot, data, step: int) -> Scan:
    """The driver's newest scan (``LaserScanData``) as step ``step``'s ``Scan`` of the robot's configured lidar."""
    lid = robot.lidar
    ranges = resample(data.angle_min, data.angle_increment, data.ranges, lid.beams, lid.fov, lid.range)
    inc = lid.fov / (lid.beams - 1) if lid.beams > 1 else 0.0
    return Scan(id=robot.id, step=step, stamp=data.stamp, angle_min=-lid.fov / 2 if lid.beams > 1 else 0.0,
                angle_increment=inc, range_max=lid.range, ranges=ranges.tolist())
