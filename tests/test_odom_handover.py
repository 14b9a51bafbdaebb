"""The sim driver's odometry and gyro come on two zenoh subscribers, each calling back on a thread of its own; the
agent queues what the driver hands over. A lock-step agent waited for ever (every agent then stopped after 30 s
without sensor data) when an older sample was handed over after the newer one: it stood in the queue as the newest,
without its gyro rate. Seen in about one run in eight on a loaded machine, hidden until then by the world's 2 s
lock-step timeout. The callbacks are called here in that order, on the real code."""

from __future__ import annotations

import threading
import types
from collections import deque

from stack.agents.agent import Agent, _Inbox
from stack.comm import Keys, encode
from stack.comm.messages import Imu, Odom
from stack.drivers.base import DriverLimits
from stack.drivers.sim import SimDriver


def _sample(keys: Keys, topic: str, msg):
    return types.SimpleNamespace(key_expr=keys.robot(0, topic), payload=types.SimpleNamespace(to_bytes=lambda: encode(msg)))


def _odom(k: int) -> Odom:
    return Odom(id=0, step=k, stamp=0.1 * k, v=0.5, w=0.1, x=0.05 * k, y=0.0, yaw=0.0)


def test_the_gyro_of_step_k_hands_over_only_step_k_odometry():
    keys, got = Keys("t"), []
    drv = SimDriver(0, DriverLimits(1.0, 1.0), session=None, keys=keys, on_odom=lambda o: got.append(o.step))
    drv._odom_cb(_sample(keys, "odom", _odom(119)))
    drv._imu_cb(_sample(keys, "imu", Imu(id=0, step=119, stamp=11.9, wz=0.1)))
    drv._imu_cb(_sample(keys, "imu", Imu(id=0, step=120, stamp=12.0, wz=0.1)))  # before step 120's odometry
    drv._odom_cb(_sample(keys, "odom", _odom(120)))
    assert got == [119, 119, 120]  # (it handed step 119's over a third time, with step 120's gyro)
    assert drv.read().step == 120 and drv.read().wz_imu == 0.1


def _agent_stub():
    """The agent's queueing state and nothing else (no driver: the sample is taken as handed over)."""
    a = types.SimpleNamespace(_in=_Inbox(), _cv=threading.Condition(), cfg=types.SimpleNamespace(lockstep=True),
                              _now=lambda: 0.0, odom_redelivered=0, id=0)
    a._in.odometry = deque()
    return a


def test_an_older_sample_handed_over_after_a_newer_one_is_dropped_and_counted():
    from stack.drivers.base import Odometry

    a = _agent_stub()
    s119, s120 = Odometry(0.5, 0.1, 11.9, step=119, wz_imu=0.1), Odometry(0.5, 0.1, 12.0, step=120, wz_imu=0.1)
    for s in (s119, s120, s119):
        Agent._on_odom(a, s)
    assert [o.step for o, _, _ in a._in.odometry] == [119, 120] and a.odom_redelivered == 1
    Agent._on_odom(a, s120)  # the newest again (its gyro pairing): not an older one
    assert [o.step for o, _, _ in a._in.odometry] == [119, 120] and a.odom_redelivered == 1


def test_a_stalled_step_says_what_it_lacks():
    import pytest

    from stack.comm.lockstep import StepBarrier
    from stack.comm.messages import Clock

    cv = threading.Condition()
    b = StepBarrier(0, cv, sensor_timeout_s=0.2)
    stop = threading.Event()
    with cv, pytest.raises(TimeoutError, match=r"for 0 s \(no clock after step 4\)"):
        b.wait_step(4, lambda k: False, lambda: 0, stop, lambda k: "odometry")
    with cv:
        b.on_clock(Clock(step=5, t=0.5, dt=0.1, answered=[], lockstep=True, dead=[], device_odom={}, device_scans={}))
    with cv, pytest.raises(TimeoutError, match=r"\(step 5: newest odometry of step 4 without its gyro rate\)"):
        b.wait_step(4, lambda k: False, lambda: 0, stop, lambda k: "newest odometry of step 4 without its gyro rate")
