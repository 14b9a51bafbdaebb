"""The Slamtec RPLidar A-series serial protocol (A1, A2), as the vendor's "RPLIDAR Interface Protocol and
Application Notes" and its SDK define it: the one copy of the byte layouts, used by the ``rplidar`` driver
and the simulated device (``stack.sim_bridge.rplidar_sim``).

- **Request** (host -> device): ``A5 <cmd>``; a command with a payload adds ``<size> <payload...>
  <checksum>``, the checksum the XOR of every byte before it (``A5`` included). Commands: STOP ``25``,
  RESET ``40``, SCAN ``20``, FORCE_SCAN ``21``, EXPRESS_SCAN ``82`` (payload), GET_INFO ``50``,
  GET_HEALTH ``52``, GET_SAMPLERATE ``59``, SET_MOTOR_PWM ``F0`` (payload: uint16 PWM, A2 only: the A1's
  motor is switched by the adapter's DTR line). STOP and RESET have no answer.
- **Response descriptor** (device -> host): ``A5 5A``, a 32-bit little-endian word with the 30-bit
  response length and the 2-bit send mode in its top bits (0 single, 1 multiple: a stream of packets),
  then the data type: INFO ``04`` (20 bytes), HEALTH ``06`` (3), SAMPLERATE ``15`` (4), SCAN ``81``
  (5-byte packets, multiple).
- **Scan packet** (5 bytes): byte 0 = quality (6 bits) << 2 | not-S << 1 | S, S the start flag (the first
  sample of a new revolution); bytes 1-2 = angle_q6 << 1 | C (little-endian, C the check bit, always 1):
  the angle in degrees is angle_q6 / 64, **clockwise** seen from above; bytes 3-4 = distance_q2
  (little-endian): the distance in millimetres is distance_q2 / 4, 0 an invalid sample.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

SYNC, SYNC2 = 0xA5, 0x5A
STOP, RESET, SCAN, FORCE_SCAN, EXPRESS_SCAN = 0x25, 0x40, 0x20, 0x21, 0x82
GET_INFO, GET_HEALTH, GET_SAMPLERATE, SET_MOTOR_PWM = 0x50, 0x52, 0x59, 0xF0
WITH_PAYLOAD = frozenset({EXPRESS_SCAN, SET_MOTOR_PWM})
"""Commands sent with a size, a payload and a checksum (every command >= 0x80 in the protocol)."""
SINGLE, MULTIPLE = 0, 1
TYPE_INFO, TYPE_HEALTH, TYPE_SAMPLERATE, TYPE_SCAN = 0x04, 0x06, 0x15, 0x81
INFO_LEN, HEALTH_LEN, SAMPLERATE_LEN, SAMPLE_LEN, DESCRIPTOR_LEN = 20, 3, 4, 5, 7
HEALTH_GOOD, HEALTH_WARNING, HEALTH_ERROR = 0, 1, 2
MAX_PWM, DEFAULT_PWM = 1023, 660
"""A2 motor PWM range and the SDK's default (about 10 Hz)."""
MODELS = {"A1": 0x18, "A2": 0x28}
"""Model byte of GET_INFO (A1M8, A2M8): the series in the high nibble, as the SDK reads it (``model >> 4``)."""


class RplidarError(ValueError):
    """Bytes that are not the protocol's; ``kind`` names the counter (``bad_descriptor``, ``bad_sample``...)."""

    def __init__(self, kind: str, what: str):
        super().__init__(what)
        self.kind = kind


def checksum(data: bytes) -> int:
    c = 0
    for b in data:
        c ^= b
    return c


def request(cmd: int, payload: bytes = b"") -> bytes:
    """A request as the host sends it (with size, payload and checksum where the command takes one)."""
    if cmd not in WITH_PAYLOAD:
        return bytes((SYNC, cmd))
    head = bytes((SYNC, cmd, len(payload))) + payload
    return head + bytes((checksum(head),))


def descriptor(length: int, mode: int, dtype: int) -> bytes:
    return bytes((SYNC, SYNC2)) + struct.pack("<I", (length & 0x3FFFFFFF) | (mode << 30)) + bytes((dtype,))


def parse_descriptor(data: bytes) -> tuple[int, int, int]:
    """(length, send mode, data type) of a 7-byte response descriptor."""
    if len(data) != DESCRIPTOR_LEN or data[0] != SYNC or data[1] != SYNC2:
        raise RplidarError("bad_descriptor", f"not a response descriptor: {bytes(data).hex(' ')}")
    word = struct.unpack("<I", bytes(data[2:6]))[0]
    return word & 0x3FFFFFFF, word >> 30, data[6]


@dataclass(frozen=True)
class Sample:
    """One measurement of a standard scan."""

    start: bool
    """The first sample of a new revolution."""
    quality: int
    """0..63: the reflected pulse's strength (0 with an invalid sample)."""
    angle_deg: float
    """[deg] 0..360, clockwise seen from above."""
    distance_mm: float
    """[mm] 0: invalid."""


def encode_sample(start: bool, quality: int, angle_deg: float, distance_mm: float) -> bytes:
    q6 = int(round(angle_deg * 64.0)) % (360 * 64)
    d = min(0xFFFF, max(0, int(round(distance_mm * 4.0))))
    b0 = (min(63, max(0, quality)) << 2) | ((not start) << 1) | bool(start)
    return struct.pack("<BHH", b0, (q6 << 1) | 1, d)


def sample_ok(data: bytes | bytearray, i: int = 0) -> bool:
    """Whether the 5 bytes at ``i`` can be a scan packet: S and not-S differ, C is set, the angle < 360."""
    b0, b1, b2 = data[i], data[i + 1], data[i + 2]
    return (b0 & 1) != ((b0 >> 1) & 1) and (b1 & 1) == 1 and ((b2 << 7) | (b1 >> 1)) < 360 * 64


def decode_sample(data: bytes | bytearray, i: int = 0) -> Sample:
    if not sample_ok(data, i):
        raise RplidarError("bad_sample", f"not a scan packet: {bytes(data[i:i + 5]).hex(' ')}")
    b0, a, d = struct.unpack_from("<BHH", data, i)
    return Sample(start=bool(b0 & 1), quality=b0 >> 2, angle_deg=(a >> 1) / 64.0, distance_mm=d / 4.0)


@dataclass(frozen=True)
class Info:
    model: int
    firmware: tuple[int, int]  # (major, minor)
    hardware: int
    serial: bytes  # 16 bytes

    def encode(self) -> bytes:
        return bytes((self.model, self.firmware[1], self.firmware[0], self.hardware)) + self.serial[:16].ljust(16, b"\0")

    @classmethod
    def decode(cls, data: bytes) -> "Info":
        if len(data) != INFO_LEN:
            raise RplidarError("bad_info", f"GET_INFO data of {len(data)} bytes, not {INFO_LEN}")
        return cls(model=data[0], firmware=(data[2], data[1]), hardware=data[3], serial=bytes(data[4:20]))

    @property
    def series(self) -> str:
        """``A1``, ``A2``... from the model byte's high nibble."""
        return f"A{self.model >> 4}"


def encode_health(status: int, error_code: int = 0) -> bytes:
    return struct.pack("<BH", status, error_code)


def decode_health(data: bytes) -> tuple[int, int]:
    if len(data) != HEALTH_LEN or data[0] > HEALTH_ERROR:
        raise RplidarError("bad_health", f"GET_HEALTH data {bytes(data).hex(' ')}")
    status, code = struct.unpack("<BH", data)
    return status, code


__all__ = ["DEFAULT_PWM", "EXPRESS_SCAN", "FORCE_SCAN", "GET_HEALTH", "GET_INFO", "GET_SAMPLERATE", "HEALTH_ERROR",
           "HEALTH_GOOD", "HEALTH_WARNING", "Info", "MAX_PWM", "MODELS", "MULTIPLE", "RESET", "RplidarError", "SCAN",
           "SET_MOTOR_PWM", "SINGLE", "STOP", "Sample", "TYPE_HEALTH", "TYPE_INFO", "TYPE_SAMPLERATE", "TYPE_SCAN",
           "checksum", "decode_health", "decode_sample", "descriptor", "encode_health", "encode_sample",
           "parse_descriptor", "request", "sample_ok"]
