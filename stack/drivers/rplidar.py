"""``rplidar``: a Slamtec RPLidar A1 or A2 on a serial port (pyserial), by the vendor's published protocol
(``stack.drivers.rplidar_protocol``: standard SCAN mode).

Opening: STOP, then GET_HEALTH (a sensor in protection stop gets one RESET; still in error: a one-line
``LidarError``), GET_INFO (model, firmware, serial number; a model other than ``model`` is logged), the
motor on (A1: the USB adapter's DTR line low; A2: SET_MOTOR_PWM ``motor_pwm``), then SCAN and its
descriptor. Each answer is waited for up to ``open_timeout``. A port without modem lines (a pseudo-terminal,
a serial-over-network link) cannot switch an A1's motor: logged once, the motor runs as wired.

Scanning: a thread reads the port and assembles revolutions: every 5-byte packet with a valid check
(start flag and its inverse differ, check bit set, angle < 360 deg) is a sample; a revolution ends at the
next sample with the start flag and is delivered as a :class:`~stack.drivers.lidar.LidarScan` stamped with
the driver's clock at that moment: angles counter-clockwise (the sensor measures clockwise), distance 0 as
NaN (invalid). Bytes that are no packet are skipped until the stream is in step again, counted once per
loss of step as ``bad_sample``; a revolution with fewer than ``min_samples`` samples is dropped as
``short_scan``. Closing: STOP, the motor off, the port closed.
"""

from __future__ import annotations

import errno
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Literal

import numpy as np

from .. import settings
from . import rplidar_protocol as rp
from .lidar import Lidar, LidarError, LidarScan

log = logging.getLogger(__name__)

READ_CHUNK = 4096


@dataclass(frozen=True)
class RplidarConfig:
    """Where the RPLidar is and what it is (defaults: an A1M8 on its USB adapter)."""

    port: str = "/dev/ttyUSB0"
    """Serial device of the lidar's USB adapter (a CP2102: ``/dev/ttyUSB0``; a udev name such as ``/dev/rplidar``)."""
    baud: int = 115200
    """[bit/s] 115200 (A1, A2M8) or 256000 (A2M12 and later)."""
    model: Literal["A1", "A2"] = "A1"
    """The series: A1 (motor on the adapter's DTR line) or A2 (motor by SET_MOTOR_PWM)."""
    motor_pwm: int = field(default=rp.DEFAULT_PWM, metadata=settings.rule(">= 1", "<= 1023"))
    """A2: motor PWM (the SDK's default 660: about 10 Hz)."""
    range_max: float = field(default=12.0, metadata=settings.rule("> 0"))
    """[m] the sensor's range (A1M8 and A2M8: 12 m); a reading beyond it is no return."""
    min_samples: int = field(default=50, metadata=settings.rule(">= 1"))
    """A revolution with fewer samples is dropped (``short_scan``): the motor still spinning up, bytes lost."""
    open_timeout: float = field(default=1.0, metadata=settings.rule("> 0"))
    """[s] how long each answer is waited for while opening."""
    reset_wait: float = field(default=0.5, metadata=settings.rule(">= 0"))
    """[s] after a RESET, how long the core takes to boot (its boot text is discarded)."""

    def __post_init__(self):
        settings.check(self)
        if self.baud not in (115200, 256000):
            raise ValueError(f"baud: expected 115200 or 256000, got {self.baud}")
        if not self.port:
            raise ValueError("port: expected a serial device, got nothing")


class RplidarLidar(Lidar):
    """One RPLidar A1/A2 on ``config.port``. ``serial_factory(port, baud)`` opens the port (default pyserial)."""

    name = "rplidar"
    config_class = RplidarConfig

    def __init__(self, robot_id: int, config: RplidarConfig | None = None, *, session: Any = None, keys: Any = None,
                 clock: Callable[[], float] = time.monotonic, on_scan=None, on_malformed=None,
                 serial_factory: Callable[[str, int], Any] | None = None, **params):
        super().__init__(robot_id, clock=clock, on_scan=on_scan, on_malformed=on_malformed)
        self.config = self._configure(config, params)
        self._factory = serial_factory or _pyserial
        self._port: Any = None
        self._thread: threading.Thread | None = None
        self._halt = threading.Event()
        self._buf = bytearray()
        self._in_step = True
        self._rev: list[rp.Sample] = []
        self._started = False  # a start flag seen since SCAN
        self.info: rp.Info | None = None
        self.health: tuple[int, int] | None = None

    # --- lifecycle ---------------------------------------------------------------------
    def _open(self) -> None:
        cfg = self.config
        try:
            self._port = self._factory(cfg.port, cfg.baud)
        except Exception as e:  # noqa: BLE001 - serial.SerialException, OSError: one line either way
            raise LidarError(f"rplidar {self.robot_id}: cannot open {cfg.port}: {e}") from None
        try:
            self._handshake()
        except BaseException:
            self._release()
            raise
        self._halt.clear()
        self._buf.clear()
        self._rev, self._started, self._in_step = [], False, True
        self._thread = threading.Thread(target=self._read_loop, name=f"rplidar-{self.robot_id}", daemon=True)
        self._thread.start()

    def _handshake(self) -> None:
        cfg = self.config
        self._send(rp.request(rp.STOP))
        time.sleep(0.002)  # the protocol: at least 1 ms before the next request
        self._port.reset_input_buffer()
        self.health = self._ask_health()
        if self.health[0] == rp.HEALTH_ERROR:
            log.warning("rplidar %s: protection stop (error %#x): RESET", self.robot_id, self.health[1])
            self._send(rp.request(rp.RESET))
            time.sleep(cfg.reset_wait)
            self._port.reset_input_buffer()
            self.health = self._ask_health()
            if self.health[0] == rp.HEALTH_ERROR:
                raise LidarError(f"rplidar {self.robot_id} on {cfg.port}: in protection stop (error code "
                                 f"{self.health[1]:#06x}) after a RESET")
        data = self._ask(rp.GET_INFO, rp.TYPE_INFO, rp.INFO_LEN)
        self.info = rp.Info.decode(data)
        if self.info.series != cfg.model:
            log.warning("rplidar %s: the sensor says it is an %s (model %#x), configured %s", self.robot_id,
                        self.info.series, self.info.model, cfg.model)
        log.info("rplidar %s on %s: %s firmware %d.%02d hardware %d serial %s", self.robot_id, cfg.port,
                 self.info.series, *self.info.firmware, self.info.hardware, self.info.serial.hex().upper())
        self._motor(True)
        self._send(rp.request(rp.SCAN))
        length, mode, dtype = rp.parse_descriptor(self._read_exact(rp.DESCRIPTOR_LEN, "SCAN"))
        if (length, mode, dtype) != (rp.SAMPLE_LEN, rp.MULTIPLE, rp.TYPE_SCAN):
            raise LidarError(f"rplidar {self.robot_id}: SCAN answered ({length}, {mode}, {dtype:#x}), not a scan stream")

    def _ask_health(self) -> tuple[int, int]:
        return rp.decode_health(self._ask(rp.GET_HEALTH, rp.TYPE_HEALTH, rp.HEALTH_LEN))

    def _ask(self, cmd: int, dtype: int, length: int) -> bytes:
        """One single-response request: its descriptor checked, its data returned."""
        name = {rp.GET_INFO: "GET_INFO", rp.GET_HEALTH: "GET_HEALTH"}.get(cmd, f"{cmd:#x}")
        self._send(rp.request(cmd))
        try:
            got = rp.parse_descriptor(self._read_exact(rp.DESCRIPTOR_LEN, name))
        except rp.RplidarError as e:
            raise LidarError(f"rplidar {self.robot_id}: {name}: {e}") from None
        if got != (length, rp.SINGLE, dtype):
            raise LidarError(f"rplidar {self.robot_id}: {name} answered {got}, expected ({length}, 0, {dtype:#x})")
        try:
            return self._read_exact(length, name)
        except rp.RplidarError as e:
            raise LidarError(f"rplidar {self.robot_id}: {name}: {e}") from None

    def _read_exact(self, n: int, what: str) -> bytes:
        deadline = time.monotonic() + self.config.open_timeout
        out = bytearray()
        while len(out) < n:
            if time.monotonic() > deadline:
                raise LidarError(f"rplidar {self.robot_id} on {self.config.port}: no answer to {what} within "
                                 f"{self.config.open_timeout:g} s (got {len(out)} of {n} bytes; powered, right port?)")
            out += self._port.read(n - len(out))
        return bytes(out)

    def _motor(self, on: bool) -> None:
        if self.config.model == "A2":
            self._send(rp.request(rp.SET_MOTOR_PWM, int(self.config.motor_pwm if on else 0).to_bytes(2, "little")))
            return
        try:
            self._port.dtr = not on  # the A1 adapter: DTR low runs the motor
        except OSError as e:
            if e.errno not in (errno.ENOTTY, errno.EINVAL):
                raise LidarError(f"rplidar {self.robot_id}: cannot switch the motor (DTR): {e}") from None
            if on:
                log.info("rplidar %s: %s has no modem lines: the motor runs as wired", self.robot_id, self.config.port)

    def _close(self) -> None:
        self._halt.set()
        t, self._thread = self._thread, None
        if t is not None:
            t.join(timeout=1.0)
        try:
            self._send(rp.request(rp.STOP))
            self._motor(False)
        except Exception as e:  # noqa: BLE001 - the sensor may be gone; closing must finish
            log.warning("rplidar %s: stopping the sensor failed: %s", self.robot_id, e)
        self._release()

    def _release(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            port.close()

    def _send(self, data: bytes) -> None:
        self._port.write(data)
        self.count("tx")

    # --- the scan stream (its own thread) --------------------------------------------------
    def _read_loop(self) -> None:
        while not self._halt.is_set():
            try:
                data = self._port.read(READ_CHUNK)
            except Exception as e:  # noqa: BLE001 - unplugged: the scans stop, the agent's staleness rule acts
                self.count("rx_error")
                log.error("rplidar %s: reading %s failed: %s", self.robot_id, self.config.port, e)
                return
            if data:
                self.feed(data)

    def feed(self, data: bytes) -> None:
        """Bytes of the scan stream, in order: samples out, revolutions delivered."""
        buf = self._buf
        buf += data
        i, n = 0, len(buf)
        while n - i >= rp.SAMPLE_LEN:
            if not rp.sample_ok(buf, i):
                if self._in_step:
                    self.count("bad_sample", malformed=True)
                    self._in_step = False
                i += 1
                continue
            self._in_step = True
            self._sample(rp.decode_sample(buf, i))
            i += rp.SAMPLE_LEN
        del buf[:i]

    def _sample(self, s: rp.Sample) -> None:
        if s.start:
            if self._started:
                self._revolution()
            self._started, self._rev = True, []
        if self._started:
            self._rev.append(s)

    def _revolution(self) -> None:
        rev = self._rev
        if len(rev) < self.config.min_samples:
            self.count("short_scan")
            return
        ang = np.array([s.angle_deg for s in rev])
        dist = np.array([s.distance_mm for s in rev]) / 1000.0
        bearings = np.radians(-ang)  # clockwise degrees -> counter-clockwise radians
        bearings = np.arctan2(np.sin(bearings), np.cos(bearings))
        ranges = np.where(dist > 0, dist, np.nan)
        self._deliver(LidarScan(stamp=self._clock(), angles=bearings, ranges=ranges, range_max=self.config.range_max))


def _pyserial(port: str, baud: int):
    import serial

    return serial.Serial(port, baud, timeout=0.05, write_timeout=1.0)


__all__ = ["RplidarConfig", "RplidarLidar"]
