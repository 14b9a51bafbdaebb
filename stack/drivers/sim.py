"""``sim``: the simulated differential drive, over Zenoh.

Publishes ``stack/<fleet>/<id>/cmd_vel`` and reads ``.../odom`` and ``.../imu`` from the
world (``stack.sim_bridge``), which turns the commands into wheel speeds of a
differential-drive body with acceleration limits. The world steps the body, so there is
nothing to keep alive and no device to go stale: of the base's supervision only the command
watchdog applies (``liveness()`` still shows ``odom`` and ``imu``).
"""

from __future__ import annotations

import threading
from dataclasses import replace
import time
from typing import Callable

import zenoh

from ..comm import Keys, encode, receive
from ..comm.messages import CmdVel, Imu, Odom
from .base import Driver, DriverLimits, Odometry


class SimDriver(Driver):
    name = "sim"
    has_imu = True
    answers_steps = True

    def __init__(self, robot_id: int, limits: DriverLimits, *, session: zenoh.Session, keys: Keys,
                 stamp: Callable[[], float] = time.time, on_malformed: Callable[[str], None] | None = None,
                 on_odom: Callable[[Odometry], None] | None = None, clock: Callable[[], float] = time.monotonic,
                 **params):
        super().__init__(robot_id, limits, clock, on_malformed=on_malformed)
        if params:
            raise ValueError(f"sim driver: unknown settings {', '.join(sorted(params))}")
        self._session = session
        self._keys = keys
        self._stamp = stamp
        self._on_odom = on_odom
        self._latest: Odometry | None = None
        self._wz: tuple[int, float] | None = None
        self._data_lock = threading.Lock()
        self._pub = None
        self._subs: list = []

    def _open(self) -> None:
        self._pub = self._session.declare_publisher(self._keys.robot(self.robot_id, "cmd_vel"),
                                                    congestion_control=zenoh.CongestionControl.BLOCK)
        self._subs = [
            self._session.declare_subscriber(self._keys.robot(self.robot_id, "imu"), self._imu_cb),
            self._session.declare_subscriber(self._keys.robot(self.robot_id, "odom"), self._odom_cb),
        ]

    def _imu_cb(self, sample: zenoh.Sample) -> None:
        m = receive(sample, Imu, self._on_malformed)
        if m is None or not self._mine(m, sample):
            return
        with self._data_lock:
            self._wz = (m.step, m.wz)
            latest = self._latest
        self._alive("imu")
        # the odometry of the same step, again, now with its gyro rate. Only that one: the odom and imu callbacks run
        # on threads of their own, and an older sample handed over after the newer one had come (the imu of step k
        # read step k-1's sample, the odom of step k then went first) stood in the agent's queue as its newest,
        # without a gyro rate, and the lock-step agent waited for step k's for ever
        if self._on_odom is not None and latest is not None and latest.step == m.step:
            self._on_odom(latest)

    def _odom_cb(self, sample: zenoh.Sample) -> None:
        m = receive(sample, Odom, self._on_malformed)
        if m is None or not self._mine(m, sample):
            return
        with self._data_lock:
            pose = (m.x, m.y, m.yaw) if m.x is not None and m.y is not None and m.yaw is not None else None
            odo = self._latest = Odometry(v=m.v, w=m.w, stamp=m.stamp, step=m.step, pose=pose)
        self._alive("odom")
        if self._on_odom is not None:
            self._on_odom(odo)

    def _mine(self, m, sample: zenoh.Sample) -> bool:
        """A message on our key that names another robot is malformed."""
        if m.id == self.robot_id:
            return True
        self._on_malformed(str(sample.key_expr))
        return False

    def _send(self, v: float, w: float) -> None:
        self._send_step(v, w, -1)

    def _send_step(self, v: float, w: float, step: int) -> None:
        self._pub.put(encode(CmdVel(id=self.robot_id, step=step, stamp=self._stamp(), v=v, w=w)))

    def _read(self) -> Odometry | None:
        """The newest odometry, with the gyro rate of the same step when it has arrived."""
        with self._data_lock:
            odo, wz = self._latest, self._wz
        if odo is not None and wz is not None and wz[0] == odo.step:
            return replace(odo, wz_imu=wz[1])
        return odo

    def _close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._subs = []
        if self._pub is not None:
            self._pub.undeclare()
            self._pub = None
