"""A simulated Slamtec RPLidar A1/A2 on a pseudo-terminal: the ``rplidar`` lidar source's device.

:class:`RplidarPty` holds the pty master and speaks the vendor's protocol (``stack.drivers.rplidar_protocol``)
to whatever opens the slave (``slave_path``), as the sensor's USB adapter does on ``/dev/ttyUSB0``: a thread
answers GET_INFO, GET_HEALTH, GET_SAMPLERATE, SCAN / FORCE_SCAN (the scan descriptor, then the stream),
STOP, RESET (the scan stops, the core reboots and prints its boot text, as the real one does) and
SET_MOTOR_PWM (A2). EXPRESS_SCAN is not offered (no answer, counted ``unsupported``); bytes that are no
request are counted (``junk``, ``bad_checksum``, ``unknown_cmd``) and ignored. A pty has no modem lines: an
A1's motor (the adapter's DTR) always runs; an A2's runs while its PWM is above 0.

:class:`RplidarDevice` is what the world hosts (``lidar_devices.HostedLidar``): the head spins at
``rate_hz`` (an A2: scaled by PWM / 660), each revolution's rate wobbling by ``rate_wobble``, and takes
``sample_rate_hz`` samples a second (standard scan: 2 kHz on an A1/A2, about 360 a revolution at 5.5 Hz, at
angles that drift from one revolution to the next, never whole degrees). Each sample is the world's ray at
its own time and angle (cast in ``CAST_CHUNK_S`` groups at the pose of their middle time); the sensor
measures clockwise, so a sample at angle a [deg] is the ray at -a in the sensor's frame. A ray without a
return within the world's range, and a fraction ``invalid_prob`` of the rest, read distance 0 (invalid,
quality 0); ``corrupt_prob`` of the packets get one byte flipped on the wire.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import struct
import threading
import time
import tty
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ..drivers import rplidar_protocol as rp
from ..drivers.rplidar import RplidarConfig
from .devices import DeviceError, check_choice, check_number
from .lidar_devices import HostedLidar, LidarDeviceConfig

log = logging.getLogger(__name__)

TX_BACKLOG = 65536  # [bytes] what the adapter buffers toward a host that is not reading; beyond: dropped
CAST_CHUNK_S = 0.01  # [s] samples cast together, at the pose of the chunk's middle time
BOOT_TEXT = b"RP LIDAR System.\r\nFirmware Ver 1.29 - rc9, HW Ver 7\r\nModel: 18\r\n"
BOOT_DELAY_S = 0.05
TYPICAL_RATE_HZ = {"A1": 5.5, "A2": 10.0}  # [Hz] the datasheets' typical scan rates (A2: at PWM 660)


def _count(counters: dict[str, int], key: str, n: int = 1) -> None:
    counters[key] = counters.get(key, 0) + n


class RplidarPty:
    """The sensor end of an RPLidar's serial link on a pseudo-terminal (see the module docstring)."""

    def __init__(self, model: str = "A1", serial: bytes = b"SIMRPLIDAR000001"):
        self.model = model
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.slave_path = os.ttyname(self._slave)
        self.info = rp.Info(model=rp.MODELS[model], firmware=(1, 29), hardware=7, serial=serial)
        self.health = (rp.HEALTH_GOOD, 0)
        self.error_persists = False  # a protection stop that a RESET does not clear
        self.scanning = False
        self.pwm = 0  # A2 motor PWM
        self.counters: dict[str, int] = {}
        self._rx = bytearray()
        self._tx = bytearray()
        self._lock = threading.Lock()  # guards _tx and the state the world's thread reads
        self._boot_at: float | None = None
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"rplidar-pty-{self.slave_path}", daemon=True)
        self._thread.start()

    @property
    def spinning(self) -> bool:
        return self.model == "A1" or self.pwm > 0

    # --- the wire ------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        """Bytes toward the host; what the pty does not take waits, up to ``TX_BACKLOG`` (then dropped)."""
        with self._lock:
            self._tx += data
            self._flush()
            if len(self._tx) > TX_BACKLOG:
                _count(self.counters, "overrun", len(self._tx) - TX_BACKLOG)
                del self._tx[TX_BACKLOG:]

    def _flush(self) -> None:
        if not self._tx:
            return
        try:
            sent = os.write(self._master, self._tx)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError as e:
            if e.errno != errno.EIO:  # EIO: nobody has the slave open
                raise
            sent = 0
        del self._tx[:sent]

    def _run(self) -> None:
        while not self._halt.is_set():
            with self._lock:
                pending = bool(self._tx)
            try:
                ready, _, _ = select.select([self._master], [], [], 0.005 if pending or self._boot_at else 0.05)
            except (OSError, ValueError):
                return
            if ready:
                try:
                    self._feed(os.read(self._master, 4096))
                except (BlockingIOError, InterruptedError):
                    pass
                except OSError:
                    pass  # EIO while no host holds the slave
            with self._lock:
                self._flush()
            if self._boot_at is not None and time.monotonic() >= self._boot_at:
                self._boot_at = None
                self.write(BOOT_TEXT)

    # --- requests ------------------------------------------------------------------------
    def _feed(self, chunk: bytes) -> None:
        buf = self._rx
        buf += chunk
        while buf:
            if buf[0] != rp.SYNC:
                _count(self.counters, "junk")
                del buf[0]
                continue
            if len(buf) < 2:
                return
            cmd = buf[1]
            if cmd < 0x80:
                del buf[:2]
                self._request(cmd, b"")
                continue
            if len(buf) < 3 or len(buf) < 4 + buf[2]:
                return
            n = buf[2]
            frame, payload = bytes(buf[:4 + n]), bytes(buf[3:3 + n])
            del buf[:4 + n]
            if rp.checksum(frame[:-1]) != frame[-1]:
                _count(self.counters, "bad_checksum")
                continue
            self._request(cmd, payload)

    def _request(self, cmd: int, payload: bytes) -> None:
        _count(self.counters, f"req_{cmd:02x}")
        if cmd == rp.SET_MOTOR_PWM:
            if self.model == "A2" and len(payload) == 2:
                self.pwm = min(rp.MAX_PWM, struct.unpack("<H", payload)[0])
            return
        self.scanning = False  # any other request ends a scan
        if cmd == rp.STOP:
            return
        if cmd == rp.RESET:
            self.pwm = 0
            self.health = self.health if self.error_persists else (rp.HEALTH_GOOD, 0)
            self._boot_at = time.monotonic() + BOOT_DELAY_S
            return
        answers: dict[int, Callable[[], bytes]] = {
            rp.GET_INFO: lambda: rp.descriptor(rp.INFO_LEN, rp.SINGLE, rp.TYPE_INFO) + self.info.encode(),
            rp.GET_HEALTH: lambda: rp.descriptor(rp.HEALTH_LEN, rp.SINGLE, rp.TYPE_HEALTH) + rp.encode_health(*self.health),
            rp.GET_SAMPLERATE: lambda: (rp.descriptor(rp.SAMPLERATE_LEN, rp.SINGLE, rp.TYPE_SAMPLERATE)
                                        + struct.pack("<HH", 500, 250)),
        }
        if cmd in answers:
            return self.write(answers[cmd]())
        if cmd in (rp.SCAN, rp.FORCE_SCAN):
            if self.health[0] == rp.HEALTH_ERROR:
                return  # in protection stop the core does not scan
            self.write(rp.descriptor(rp.SAMPLE_LEN, rp.MULTIPLE, rp.TYPE_SCAN))
            self.scanning = True
            return
        _count(self.counters, "unsupported" if cmd == rp.EXPRESS_SCAN else "unknown_cmd")

    def shutdown(self) -> None:
        self._halt.set()
        self._thread.join(timeout=1.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


@dataclass(frozen=True)
class RplidarDeviceConfig(LidarDeviceConfig):
    """How the simulated RPLidar behaves (scenario: the robot's ``lidar.device``)."""

    rate_hz: float | None = None
    """[Hz] rotation rate (A2: at PWM 660, and it scales with the PWM); None: the model's typical, A1 5.5 Hz
    (1-10), A2 10 Hz (5-15)."""
    sample_rate_hz: float = 2000.0
    """[Hz] samples a second in standard SCAN mode (A1, A2: 2000)."""
    rate_wobble: float = 0.02
    """Each revolution's rate differs from ``rate_hz`` by up to this fraction (uniform): motors are not exact."""
    invalid_prob: float = 0.01
    """Probability that a sample with a return still reads 0 (no measurement: dark or glancing surfaces)."""
    corrupt_prob: float = 0.0
    """Probability that a packet has one byte flipped on the wire."""
    quality: int = 47
    """Quality of a valid sample (0..63; an A1 reports about 47 on good returns)."""

    def __post_init__(self):
        if self.rate_hz is not None:
            check_number("rate_hz", self.rate_hz, high=20.0, low_open=True)
        check_number("sample_rate_hz", self.sample_rate_hz, high=16000.0, low_open=True)
        check_number("rate_wobble", self.rate_wobble, high=0.5)
        check_number("invalid_prob", self.invalid_prob, high=1.0)
        check_number("corrupt_prob", self.corrupt_prob, high=1.0)
        if isinstance(self.quality, bool) or not isinstance(self.quality, int) or not 0 <= self.quality <= 63:
            raise ValueError(f"quality must be an integer 0..63, not {self.quality!r}")


class RplidarDevice(HostedLidar):
    """The RPLidar on one robot, on a pty the robot's ``rplidar`` source opens (``driver_params``: its port)."""

    kind = "rplidar"
    config_class = RplidarDeviceConfig

    def __init__(self, robot, **kw):
        super().__init__(robot, **kw)
        try:
            self.config = RplidarConfig(**{k: v for k, v in self.params.items() if k != "port"})
        except (TypeError, ValueError) as e:
            raise DeviceError(f"robot {robot.id}: rplidar device: {e}") from None
        check_choice("model", self.config.model, tuple(rp.MODELS))
        self.pty: RplidarPty | None = None
        self._angle = float(self.rng.uniform(0.0, 360.0))  # [deg] where the head points (clockwise)
        self._rev_hz = self._next_rate()
        self._t_next: float | None = None  # time of the next sample
        self._starts = 0  # start flags sent in this scan
        self.samples_sent = 0

    def start(self) -> None:
        try:
            self.pty = RplidarPty(self.config.model)
        except OSError as e:
            raise DeviceError(f"robot {self.robot_id}: cannot make a pseudo-terminal for the rplidar: {e}") from None

    def driver_params(self) -> dict[str, Any]:
        return {"port": self.pty.slave_path}

    def close(self) -> None:
        if self.pty is not None:
            self.pty.shutdown()
            self.pty = None

    def _next_rate(self) -> float:
        w, rate = self.device_config.rate_wobble, self.device_config.rate_hz
        rate = rate if rate is not None else TYPICAL_RATE_HZ[self.config.model]
        return rate * (1.0 + (self.rng.uniform(-w, w) if w > 0 else 0.0))

    # --- samples -----------------------------------------------------------------------------
    def _emit(self, t0: float, t1: float, pose_at) -> None:
        pty, cfg = self.pty, self.device_config
        if self._t_next is None or self._t_next < t0:
            self._t_next = t0 + 1.0 / cfg.sample_rate_hz
        n = int(np.floor((t1 - self._t_next) * cfg.sample_rate_hz + 1e-9)) + 1
        if n <= 0:
            return
        times = self._t_next + np.arange(n) / cfg.sample_rate_hz
        self._t_next = float(times[-1] + 1.0 / cfg.sample_rate_hz)
        scale = 1.0 if self.config.model == "A1" else pty.pwm / rp.DEFAULT_PWM
        if scale <= 0 or not pty.spinning:
            return  # the motor stands: no samples
        scanning = pty.scanning
        if not scanning:
            self._starts = 0
        angles, starts = self._advance(n, scale)
        if not scanning:
            return
        ranges = self._ranges(times, angles, pose_at)
        self._send(angles, starts, ranges)

    def _advance(self, n: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """The head's angle at each of the next ``n`` samples, and where a revolution starts."""
        out, starts = np.empty(n), np.zeros(n, bool)
        step_of = lambda: 360.0 * self._rev_hz * scale / self.device_config.sample_rate_hz  # noqa: E731
        a, step = self._angle, step_of()
        for i in range(n):
            a += step
            if a >= 360.0:
                a -= 360.0
                starts[i] = True
                self._rev_hz = self._next_rate()
                step = step_of()
            out[i] = a
        self._angle = a
        return out, starts

    def _ranges(self, times: np.ndarray, angles: np.ndarray, pose_at) -> np.ndarray:
        """The world's range [m] of each sample (clockwise angle -> counter-clockwise ray), in time chunks."""
        out = np.empty(times.size)
        chunk = max(1, int(round(CAST_CHUNK_S * self.device_config.sample_rate_hz)))
        for s in range(0, times.size, chunk):
            sl = slice(s, s + chunk)
            out[sl] = self.cast(pose_at(float(times[sl].mean())), np.radians(-angles[sl]))
        return out

    def _send(self, angles: np.ndarray, starts: np.ndarray, ranges: np.ndarray) -> None:
        cfg = self.device_config
        no_return = ranges >= self.robot.lidar.range - 1e-6
        invalid = no_return | (self.rng.random(ranges.size) < cfg.invalid_prob)
        corrupt = self.rng.random(ranges.size) < cfg.corrupt_prob if cfg.corrupt_prob > 0 else None
        out = bytearray()
        for i in range(ranges.size):
            d = 0.0 if invalid[i] else ranges[i] * 1000.0
            pkt = bytearray(rp.encode_sample(bool(starts[i]), 0 if invalid[i] else cfg.quality, angles[i], d))
            if corrupt is not None and corrupt[i]:
                pkt[int(self.rng.integers(0, 5))] ^= 1 << int(self.rng.integers(0, 8))
            out += pkt
            if starts[i]:
                self._starts += 1
                if self._starts > 1:
                    self.scans_sent += 1  # the driver has a whole revolution once the next one starts
        self.samples_sent += ranges.size
        self.pty.write(bytes(out))


__all__ = ["RplidarDevice", "RplidarDeviceConfig", "RplidarPty"]
