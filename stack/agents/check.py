"""``stack-agent --check``: open the robot's devices, listen for a while, say what is there; command nothing.

The driver opens through its normal path (``Driver.open``: handshakes, closed loop or arming, then its zero
command) and is closed again, zero velocity first, on every way out; nothing else is commanded. The lidar
comes from the robot's ``lidar.source`` (``LIDARS``), or from the driver where it carries the robot's own
scan (a Jackal's ``LaserScan``). The table printed says, per stream, its rate and shape, how its device
stamps relate to our clock, and where ``odom_origin`` puts the odometry in the site frame.

What a run needs, by the agent's own rules (``step.StepConfig``), and so what makes the exit 1:

- the policy loads (its extra, its weights);
- the router can be reached;
- the driver opens and does not fault;
- odometry, with no gap longer than ``odom_stale_s`` (the agent stops the robot on one);
- a scan: every policy's first control step waits for one (``StepPipeline`` decides once it has a scan), and a
  policy that reads the lidar (every one but ``pid``) stops on a gap longer than ``lidar_stale_s``;
- position fixes on ``stack/<fleet>/<id>/fix`` where the robot's ``fix:`` says the site sends them.

Reported, not judged: the driver's own fixes (a rover's autopilot), device clocks, the router host's clock.
"""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, TextIO

import numpy as np

from ..comm import Keys, receive
from ..comm.clockprobe import ClockOffset, router_offset
from ..comm.messages import Fix
from ..comm.session import ConfigFileError, SessionConfig, SessionError, open_session
from ..drivers import LIDARS, DriverError, DriverLimits, make_driver
from ..drivers.lidar import make_lidar
from ..policies import make_policy
from .frames import OdomFrame, StreamClock
from .step import StepConfig


CHECK_DURATION_S = 3.0
POLL_S = 0.005  # how often the driver's newest scan and fix are looked at


@dataclass
class Row:
    item: str
    state: str  # ok, MISSING, warn, info, -
    text: str


@dataclass
class _Stream:
    """One stream as it arrived: times on our monotonic clock; device stamps against our wall clock."""

    arrivals: list[float] = field(default_factory=list)
    offsets: list[float] = field(default_factory=list)  # device stamp - our time.time() at arrival
    own: int = 0  # samples the driver stamped itself on arrival (its wire carries no device time)
    clock: StreamClock = field(default_factory=StreamClock)
    first: Any = None
    last: Any = None

    def add(self, sample: Any, stamp: float, own: bool) -> None:
        mono = time.monotonic()
        self.first = sample if self.first is None else self.first
        self.last = sample
        self.arrivals.append(mono)
        self.clock.time_of(stamp, mono)
        if own:
            self.own += 1
        else:
            self.offsets.append(stamp - time.time())

    @property
    def n(self) -> int:
        return len(self.arrivals)

    def within(self, start: float, end: float) -> list[float]:
        """Arrivals while the check listened (the driver delivers some while it opens, too)."""
        return [t for t in self.arrivals if start <= t <= end]

    def rate(self, start: float = -math.inf, end: float = math.inf) -> float | None:
        a = self.within(start, end)
        return (len(a) - 1) / (a[-1] - a[0]) if len(a) >= 2 and a[-1] > a[0] else None

    def largest_gap(self, start: float, end: float) -> float:
        """The longest time without a sample in [start, end]."""
        a = [start, *self.within(start, end), end]
        return max(b - c for c, b in zip(a, a[1:]))

    def clock_text(self) -> str:
        if not self.n:
            return "no samples"
        if self.own == self.n:
            return "stamped by the driver on arrival (its wire carries no device time)"
        off = sorted(self.offsets)
        used = self.n - self.clock.unusable
        return (f"device stamps {off[len(off) // 2]:+.3f} s from our clock at arrival (spread {off[-1] - off[0]:.3f} s);"
                f" intervals taken from them for {used}/{self.n}")


class _Heard:
    """What the check hears, from the driver's, the lidar's and zenoh's threads."""

    def __init__(self, robot_id: int):
        self.robot_id = robot_id
        self.lock = threading.Lock()
        self.odom, self.scan, self.fix, self.driver_fix = _Stream(), _Stream(), _Stream(), _Stream()
        self.malformed: dict[str, int] = {}
        self._own: set[float] = set()
        self._own_order: deque[float] = deque()
        self._last_odo: Any = None

    def stamp(self) -> float:
        """The driver's ``stamp``: our wall clock, remembered so that a sample stamped with it is known."""
        t = time.time()
        with self.lock:
            self._own.add(t)
            self._own_order.append(t)
            if len(self._own_order) > 100_000:
                self._own.discard(self._own_order.popleft())
        return t

    def on_odom(self, odo) -> None:
        with self.lock:
            if odo is self._last_odo:  # a base whose gyro comes separately delivers a sample twice
                return
            self._last_odo = odo
            self.odom.add(odo, odo.stamp, odo.stamp in self._own)

    def on_scan(self, scan) -> None:
        with self.lock:
            self.scan.add(scan, scan.stamp, False)

    def on_driver_fix(self, fix: tuple[float, float, float, float]) -> None:
        with self.lock:
            self.driver_fix.add(fix, fix[3], fix[3] in self._own)

    def on_fix(self, sample) -> None:
        m = receive(sample, Fix, self.on_malformed)
        if m is not None and m.id == self.robot_id:
            with self.lock:
                self.fix.add(m, m.stamp, False)

    def on_malformed(self, key: str) -> None:
        with self.lock:
            self.malformed[key] = self.malformed.get(key, 0) + 1


@dataclass
class _Run:
    """One check: the robot, what opened, what was heard, the rows so far."""

    cfg: Any  # AgentConfig
    robot: Any  # RobotConfig
    duration: float
    heard: _Heard
    rows: list[Row] = field(default_factory=list)
    driver: Any = None
    driver_error: str | None = None
    lidar_error: str | None = None
    lidar_name: str = ""
    needs_lidar: bool = True
    window: tuple[float, float] = (0.0, 0.0)

    def add(self, item: str, state: str, text: str) -> None:
        self.rows.append(Row(item, state, text))


def run_check(cfg, duration: float = CHECK_DURATION_S, out: TextIO | None = None) -> int:
    """The check of ``cfg``'s robot (an ``AgentConfig``); prints the table; 0 ready, 1 something missing."""
    out = out or sys.stdout
    run = _Run(cfg, cfg.scenario.robot(cfg.robot_id), duration, _Heard(cfg.robot_id))
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        _policy(run)
        _with_session(run)
    except KeyboardInterrupt:
        run.add("check", "MISSING", "interrupted before it finished")
    finally:
        signal.signal(signal.SIGTERM, previous)
    return _print(run, out)


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _policy(run: _Run) -> None:
    name = run.robot.policy
    try:
        policy = make_policy(name, run.robot)
    except Exception as e:  # noqa: BLE001 - a policy that cannot load, whatever its reason, is what is missing
        run.add("policy", "MISSING", f"{name}: cannot load: {e}")
        return
    run.needs_lidar = policy.needs_lidar
    run.add("policy", "ok", f"{name} loaded; {'reads the lidar' if policy.needs_lidar else 'drives without the lidar'}")


def _session_config(cfg) -> SessionConfig:
    return SessionConfig(mode="client", connect=cfg.connect.split(","), config_file=cfg.zenoh_config, allow_remote=cfg.allow_remote)


def _with_session(run: _Run) -> None:
    cfg = run.cfg
    try:
        session = open_session(_session_config(cfg))
    except ConfigFileError:
        raise  # bad input: exit 2
    except SessionError as e:
        run.add("router", "MISSING", str(e))
        return
    with session:
        keys = Keys(cfg.fleet)
        off = router_offset(session, _session_config(cfg), f"{keys.prefix}/{cfg.robot_id}/check")
        run.add("router", "ok", f"{cfg.connect}: {_router_text(off)}")
        _listen_to_devices(run, session, keys)


def _router_text(off: ClockOffset | str) -> str:
    if isinstance(off, str):
        return f"its host's clock {off}"
    return (f"its host's clock {off.offset_s * 1e3:+.1f} ms from ours (within {off.bound_s * 1e3:.1f} ms, "
            f"best of {off.probes} probes through it)")


def _listen_to_devices(run: _Run, session, keys: Keys) -> None:
    """Lidar source and fixes subscribed, the driver opened, ``duration`` of listening; everything closed again."""
    robot, heard = run.robot, run.heard
    closers = []
    if robot.fix is not None:
        sub = session.declare_subscriber(keys.robot(robot.id, "fix"), heard.on_fix)
        closers.append(sub.undeclare)
    try:
        driver = run.driver = _make_driver(run, session, keys)
        if not driver.provides_scan:
            closers.append(_open_lidar(run, session, keys).close)
        try:
            try:
                driver.open()
            except DriverError as e:
                run.driver_error = str(e)
            _listen(run)
        finally:
            driver.close()  # zero velocity first (a driver that did not open has commanded nothing)
    finally:
        for close in reversed(closers):
            close()
    _judge(run)


def _make_driver(run: _Run, session, keys: Keys):
    r = run.robot
    heard = run.heard
    return make_driver(r.driver, r.id, DriverLimits(r.v_max, r.w_max, r.cmd_timeout), session=session, keys=keys,
                       stamp=heard.stamp, on_malformed=heard.on_malformed, on_odom=heard.on_odom, clock=time.monotonic,
                       **r.driver_params.get(r.driver, {}))


def _open_lidar(run: _Run, session, keys: Keys):
    """The robot's lidar source from the registry (any source that calls ``on_scan`` with each scan)."""
    name = run.lidar_name = getattr(run.robot.lidar, "source", "world")
    if name == "world":
        return LIDARS[name].make()(run.robot.id, session=session, keys=keys, on_scan=run.heard.on_scan,
                                   on_malformed=run.heard.on_malformed)
    lidar = make_lidar(name, run.robot.id, session=session, keys=keys, clock=time.monotonic,
                       on_scan=run.heard.on_scan, on_malformed=run.heard.on_malformed, **run.robot.lidar.params)
    try:
        lidar.open()
    except DriverError as e:  # LidarError: the port missing, the sensor mute or in protection stop
        run.lidar_error = str(e)
    return lidar


def _listen(run: _Run) -> None:
    driver, heard = run.driver, run.heard
    start = time.monotonic()
    end = start + run.duration
    last_scan = last_fix = None
    while time.monotonic() < end:
        if driver.provides_scan and (scan := driver.read_scan()) is not None and scan is not last_scan:
            last_scan = scan
            heard.on_scan(scan)
        if (fix := driver.position_fix()) is not None and fix != last_fix:
            last_fix = fix
            heard.on_driver_fix(fix)
        time.sleep(POLL_S)
    run.window = (start, time.monotonic())


# --- judging ---------------------------------------------------------------------------------


def _judge(run: _Run) -> None:
    with run.heard.lock:
        _driver_rows(run)
        _odom_rows(run)
        _lidar_rows(run)
        _fix_rows(run)
        if run.heard.malformed:
            run.add("malformed", "warn", ", ".join(f"{k} {n}" for k, n in sorted(run.heard.malformed.items())))


def _driver_rows(run: _Run) -> None:
    d = run.driver
    if run.driver_error is not None:
        run.add("driver", "MISSING", f"{d.name}: {run.driver_error}")
        return
    if d.fault:
        run.add("driver", "MISSING", f"{d.name}: fault while listening: {d.fault}")
        return
    alive = ", ".join(f"{k} {age:.2f} s ago" for k, age in sorted(d.liveness().items())) or "no sign of life yet"
    counts = ", ".join(f"{k} {n}" for k, n in sorted(d.counters.items()) if n)
    run.add("driver", "ok", f"{d.name} open, no fault; last heard: {alive}" + (f"; counters: {counts}" if counts else ""))


def _stream_row(run: _Run, item: str, s: _Stream, stale_s: float | None, where: str, why: str) -> bool:
    """The rate row of one required stream; False when it is missing (nothing, or a gap the agent stops on)."""
    start, end = run.window
    n = len(s.within(start, end))
    if not n:
        run.add(item, "MISSING", f"nothing from {where} in {run.duration:g} s ({why})")
        return False
    gap = s.largest_gap(start, end)
    rate = s.rate(start, end)
    text = f"{where}: {rate:.1f} Hz ({n} samples), longest gap {gap:.2f} s" if rate else f"{where}: one sample"
    if stale_s is not None and (gap > stale_s or rate is None):
        run.add(item, "MISSING", f"{text}: the agent stops the robot on a gap over {stale_s:g} s ({why})")
        return False
    run.add(item, "ok", text)
    return True


def _odom_rows(run: _Run) -> None:
    s, r = run.heard.odom, run.robot
    if run.driver_error is not None:
        return
    if not _stream_row(run, "odometry", s, StepConfig().odom_stale_s, f"the {r.driver} driver", "every run needs it"):
        return
    run.add("odom frame", *_frame_text(r, s.first.pose))
    run.add("odom clock", "info", s.clock_text())


def _frame_text(robot, first) -> tuple[str, str]:
    """Where ``odom_origin`` puts the odometry in the site frame (a warning where that looks wrong)."""
    x0, y0, yaw0 = robot.pose
    start = f"({x0:.2f}, {y0:.2f}, {math.degrees(yaw0):.0f} deg)"
    if first is None:
        return "info", f"wheel speeds only (no pose): the estimate starts at the start pose {start}"
    frame = OdomFrame(robot.pose, robot.odom_origin)
    site = frame.site_pose(first)
    text = (f"odom_origin {robot.odom_origin}: first odom pose ({first[0]:.2f}, {first[1]:.2f}, "
            f"{math.degrees(first[2]):.0f} deg) is site ({site[0]:.2f}, {site[1]:.2f}, {math.degrees(site[2]):.0f} deg);"
            f" start pose {start}")
    off = math.hypot(site[0] - x0, site[1] - y0)
    if off > 0.5 and robot.odom_origin != "first":
        return "warn", f"{text}: {off:.1f} m apart (has it moved since it booted, or is the odom frame another?)"
    return "info", text


def _lidar_rows(run: _Run) -> None:
    s, r, d = run.heard.scan, run.robot, run.driver
    summary = LIDARS[run.lidar_name].summary.replace("<fleet>", run.cfg.fleet).replace("<id>", str(r.id)) \
        if not d.provides_scan else ""
    where = f"the {d.name} driver's own scan" if d.provides_scan else f"lidar source {run.lidar_name} ({summary})"
    why = (f"the {r.policy} policy reads it" if run.needs_lidar else
           "the first control step waits for a scan; this policy drives on without one later")
    if d.provides_scan and run.driver_error is not None:
        run.add("lidar", "MISSING", f"{where}: the driver did not open")
        return
    if run.lidar_error is not None:
        run.add("lidar", "MISSING", f"{where}: {run.lidar_error}")
        return
    if not _stream_row(run, "lidar", s, StepConfig().lidar_stale_s if run.needs_lidar else None, where, why):
        return
    scan, lid = s.last, r.lidar
    n = len(scan.ranges)
    if hasattr(scan, "angles"):  # a sensor source's LidarScan: bearings of its own
        fov = math.degrees(float(np.nanmax(scan.angles) - np.nanmin(scan.angles))) if n > 1 else 0.0
    else:
        fov = math.degrees(scan.angle_increment * (n - 1)) if n > 1 else 0.0
    run.rows[-1].text += (f"; {n} beams over {fov:.0f} deg to {scan.range_max:g} m, taken as the configured {lid.beams}"
                          f" beams over {math.degrees(lid.fov):.0f} deg to {lid.range:g} m")
    run.add("lidar clock", "info", s.clock_text())


def _fix_rows(run: _Run) -> None:
    r, h = run.robot, run.heard
    if r.fix is not None:
        _stream_row(run, "fixes", h.fix, None, f"stack/{run.cfg.fleet}/{r.id}/fix",
                    f"robot.fix says {r.fix[0]:g} Hz")
    if h.driver_fix.n:
        rate = h.driver_fix.rate(*run.window)
        std = h.driver_fix.last[2]
        run.add("driver fixes", "info", f"the {r.driver} driver's own position ({h.driver_fix.n} fixes"
                f"{f', {rate:.1f} Hz' if rate else ''}, std {std:g} m): the estimator takes each")
    elif r.fix is None:
        run.add("fixes", "-", "none configured (robot.fix) and none from the driver")


def _print(run: _Run, out: TextIO) -> int:
    r = run.robot
    print(f"stack-agent --check: robot {r.id} ({r.role or 'peer'}, policy {r.policy}, driver "
          f"{r.driver}), fleet {run.cfg.fleet}, listened {run.duration:g} s", file=out)
    width = max(len(row.item) for row in run.rows)
    for row in run.rows:
        print(f"  {row.item:<{width}}  {row.state:<7}  {row.text}", file=out)
    missing = [row for row in run.rows if row.state == "MISSING"]
    print(f"result: {'ready' if not missing else f'{len(missing)} missing'}", file=out, flush=True)
    for row in missing:
        print(f"stack-agent --check: robot {r.id}: {row.item}: {row.text}", file=sys.stderr)
    return 1 if missing else 0
