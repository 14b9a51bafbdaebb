"""Lidar sources: where a robot's scans come from (the sensor drivers' room; ``LIDARS`` in
``stack/drivers/__init__.py``). In simulation that is the world: it publishes each robot's
:class:`~stack.comm.messages.Scan` on ``stack/<fleet>/<id>/scan``. Sources on their own wire
(ROS 2 ``LaserScan``, a serial lidar) register beside it with their config and simulated device.
"""

from __future__ import annotations

from typing import Callable

from ..comm import Keys, receive
from ..comm.messages import Scan


class WorldLidar:
    """The world's scans for one robot: each well-formed one for this robot goes to ``on_scan``;
    the rest are counted through ``on_malformed(key)``."""

    def __init__(self, robot_id: int, *, session, keys: Keys, on_scan: Callable[[Scan], None],
                 on_malformed: Callable[[str], None] | None = None):
        self.robot_id, self._on_scan, self._on_malformed = robot_id, on_scan, on_malformed
        self._key = keys.robot(robot_id, "scan")
        self._sub = session.declare_subscriber(self._key, self._deliver)

    def _deliver(self, sample) -> None:
        m = receive(sample, Scan, self._on_malformed)
        if m is None:
            return
        if m.id != self.robot_id:
            if self._on_malformed is not None:
                self._on_malformed(self._key)
            return
        self._on_scan(m)

    def close(self) -> None:
        self._sub.undeclare()
