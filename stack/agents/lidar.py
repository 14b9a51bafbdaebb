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


def to_robot_frame(angles, ranges, mount: tuple[float, float, float], range_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Samples (bearing, range) in the sensor's frame -> (bearing, range) from the robot's centre, for a sensor
    at ``mount`` = (x, y, yaw) on the robot. A sample without a return (>= ``range_max``) keeps that reading,
    along its ray from the mount point; an invalid one (NaN) stays NaN."""
    a, r = np.asarray(angles, float), np.asarray(ranges, float)
    mx, my, myaw = mount
    if mx == 0.0 and my == 0.0:
        return np.arctan2(np.sin(a + myaw), np.cos(a + myaw)), r
    reach = np.where(np.isfinite(r), np.minimum(r, range_max), range_max)
    px, py = mx + reach * np.cos(a + myaw), my + reach * np.sin(a + myaw)
    out = np.hypot(px, py)
    out = np.where(np.isnan(r), np.nan, np.where(r >= range_max, np.maximum(out, range_max), out))
    return np.arctan2(py, px), out


def resample_bearings(bearings, ranges, beams: int, fov: float, range_max: float) -> np.ndarray:
    """Irregular samples (a spinning lidar's, any order) at the configured beams' angles: each beam takes the
    valid sample nearest in bearing (around the circle) within 1.5 sample spacings, else ``range_max``."""
    b, r = np.asarray(bearings, float), np.asarray(ranges, float)
    want = np.linspace(-fov / 2, fov / 2, beams) if beams > 1 else np.zeros(1)
    out = np.full(want.size, float(range_max))
    if b.size < 2:
        return out
    spacing = np.median(np.diff(np.sort(b)))
    ok = np.isfinite(r)
    if not ok.any() or not spacing > 0:
        return out
    order = np.argsort(b[ok])
    bs, rs = b[ok][order], r[ok][order]
    ext_b = np.concatenate([bs - 2 * np.pi, bs, bs + 2 * np.pi])
    ext_r = np.concatenate([rs, rs, rs])
    i = np.clip(np.searchsorted(ext_b, want), 1, ext_b.size - 1)
    left, right = ext_b[i - 1], ext_b[i]
    pick = np.where(want - left <= right - want, i - 1, i)
    near = np.abs(ext_b[pick] - want) <= 1.5 * spacing
    out[near] = np.clip(ext_r[pick][near], 0.0, range_max)
    return out


def scan_from_lidar(robot, scan, step: int, stamp: float) -> Scan:
    """A sensor source's scan (``LidarScan``, in the sensor's frame) as the ``Scan`` of the robot's configured
    lidar (``robot.lidar``: beams, fov, range), through the sensor's ``mount``, stamped ``stamp``."""
    lid = robot.lidar
    b, r = to_robot_frame(scan.angles, scan.ranges, lid.mount, scan.range_max)
    ranges = resample_bearings(b, r, lid.beams, lid.fov, lid.range)
    inc = lid.fov / (lid.beams - 1) if lid.beams > 1 else 0.0
    return Scan(id=robot.id, step=step, stamp=stamp, angle_min=-lid.fov / 2 if lid.beams > 1 else 0.0,
                angle_increment=inc, range_max=lid.range, ranges=ranges.tolist())
