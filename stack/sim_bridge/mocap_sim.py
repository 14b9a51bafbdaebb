"""A simulated motion-capture system: a robot's pose as ``geometry_msgs/PoseStamped`` on a Zenoh key.

What a Vicon or OptiTrack rigid body looks like through ``vrpn_mocap`` (or ``mocap4r2``) and
zenoh-bridge-ros2dds: a ``PoseStamped`` in the site frame (``frame_id`` ``world``) at the system's own rate,
stamped with the capture time, arriving ``latency_s`` after it. Between world steps the body is where it
drives on its arc (the unicycle model from the last step's pose and speeds), so a 100 Hz system sees 100
different poses a second, not ten repeated ones. It runs on the wall clock (real time only): a real robot
lives in real time.

``stack-world --mocap ID:KEY[:RATE_HZ[:LATENCY_MS]]`` hosts one per robot; a fleet's real robot names the key
as its ``pose_source``.
"""

from __future__ import annotations

import heapq
import threading
import time
from dataclasses import dataclass

import zenoh

from ..drivers.ros2cdr import encode_pose_stamped
from ..models.kinematics import arc_step


@dataclass(frozen=True)
class MocapSpec:
    """One simulated rigid body (``--mocap``)."""

    robot: int
    key: str
    rate_hz: float = 100.0
    latency_s: float = 0.0


def parse_mocap(text: str) -> MocapSpec:
    """``ID:KEY[:RATE_HZ[:LATENCY_MS]]`` -> MocapSpec; ValueError saying what is wrong."""
    from ..comm.keys import check_key_expr

    parts = text.split(":")
    if not 2 <= len(parts) <= 4 or not parts[0].isdigit():
        raise ValueError(f"expected ID:KEY[:RATE_HZ[:LATENCY_MS]], got {text!r}")
    if (why := check_key_expr(parts[1])) is not None:
        raise ValueError(f"{parts[1]!r} is not a Zenoh key ({why})")
    try:
        rate = float(parts[2]) if len(parts) > 2 else 100.0
        latency = float(parts[3]) / 1000.0 if len(parts) > 3 else 0.0
    except ValueError:
        raise ValueError(f"rate and latency must be numbers, got {text!r}") from None
    if not 0.0 < rate <= 1000.0 or not 0.0 <= latency <= 10.0:
        raise ValueError(f"rate must be in (0, 1000] Hz and latency in [0, 10000] ms, got {text!r}")
    return MocapSpec(int(parts[0]), parts[1], rate, latency)


class MocapSim:
    """Publishes one robot's pose at ``spec.rate_hz``, ``spec.latency_s`` late, from the world's newest body."""

    def __init__(self, spec: MocapSpec, session: zenoh.Session):
        self.spec = spec
        self._pub = session.declare_publisher(spec.key, congestion_control=zenoh.CongestionControl.DROP)
        self._body: tuple[float, float, float, float, float, float] | None = None  # x, y, yaw, v, w, wall
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"mocap-{spec.robot}", daemon=True)
        self.sent = 0

    def body(self, x: float, y: float, yaw: float, v: float, w: float) -> None:
        """The world's body of the robot, as of now (after a step)."""
        with self._lock:
            self._body = (x, y, yaw, v, w, time.monotonic())

    def start(self) -> "MocapSim":
        self._thread.start()
        return self

    def _run(self) -> None:
        period, queue, n = 1.0 / self.spec.rate_hz, [], 0
        t0 = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            while queue and queue[0][0] <= now:  # what the system delivers now
                self._pub.put(heapq.heappop(queue)[1])
                self.sent += 1
            if now >= t0 + n * period:
                n = int((now - t0) / period) + 1
                with self._lock:
                    body = self._body
                if body is not None:  # captured now, delivered latency_s later
                    x, y, yaw = arc_step(*body[:5], now - body[5])
                    heapq.heappush(queue, (now + self.spec.latency_s, encode_pose_stamped(time.time(), x, y, yaw)))
            due = min(t0 + n * period, queue[0][0]) if queue else t0 + n * period
            self._stop.wait(max(0.0, due - time.monotonic()))

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        self._pub.undeclare()
