"""Cross-check against an RPLidar implementation we did not write: ``rplidar-roboticia`` (the PyPI ``rplidar``
module, pyserial) reads our simulated A1/A2 on its pty: GET_INFO, GET_HEALTH, the A2's SET_MOTOR_PWM, SCAN and
whole revolutions, the same samples our driver assembles. A pseudo-terminal has no modem lines, so the
module's ``setDTR`` (the A1 motor switch on the USB adapter) is recorded instead of sent: that is the only
thing replaced."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import rplidar

from test_lidar_sources import STILL, robot, wall
from stack.sim_bridge.rplidar_sim import RplidarDevice


@pytest.mark.parametrize("model", ["A1", "A2"])
def test_rplidar_roboticia_reads_our_simulated_device(model):
    dev = RplidarDevice(robot({"source": "rplidar", "rplidar": {"model": model}, "device": {"invalid_prob": 0.0}}),
                        seed=5)
    dev.ray_caster = wall
    dev.start()
    lib = rplidar.RPLidar(dev.driver_params()["port"], timeout=2)
    dtr: list[bool] = []
    lib._serial.setDTR = dtr.append  # no modem lines on a pty
    stop = threading.Event()

    def world():  # the world's steps, in real time (the module reads 5 bytes at a time)
        t = 0.0
        while not stop.is_set():
            dev.report(t, t + 0.05, STILL, STILL)
            t += 0.05
            time.sleep(0.05)

    feeder = threading.Thread(target=world, daemon=True)
    try:
        info = lib.get_info()
        assert info["model"] == {"A1": 0x18, "A2": 0x28}[model] and info["firmware"] == (1, 29)
        assert lib.get_health() == ("Good", 0)
        feeder.start()
        scans = []
        for scan in lib.iter_scans(min_len=50):
            scans.append(scan)
            if len(scans) == 4:
                break
        lib.stop()
        lib.stop_motor()
    finally:
        stop.set()
        feeder.join(2.0)
        lib.disconnect()
        dev.close()
    assert dtr == [False, True]  # motor on for the scan, off after it
    # the module keeps the valid samples only: those on the wall, +-53 deg ahead (5 m at most), 29.5 % of a turn
    on_wall = {"A1": 2000 / 5.5, "A2": 2000 / 10.0}[model] * 2 * np.degrees(np.arccos(0.6)) / 360
    for scan in scans[1:]:  # the first may be the end of a revolution begun before the module started reading
        assert abs(len(scan) - on_wall) < 0.06 * on_wall + 2, (len(scan), on_wall)
        quality, angle, dist = map(np.array, zip(*scan))
        assert (quality == 47).all()
        assert (np.cos(np.radians(angle)) >= 0.59).all()
        # the module's clockwise degrees and millimetres: the wall where our rays put it
        want = wall(0.0, 0.0, 0.0, np.radians(-angle)) * 1000.0
        assert dist == pytest.approx(want, rel=3e-4, abs=0.5)  # angle_q6, distance_q2 quantised
