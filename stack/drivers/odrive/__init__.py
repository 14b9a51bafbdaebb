"""ODrive CANSimple (firmware 0.6.x) on python-can, described by the vendor's DBC.

One module for both ends of the wire: the CAN driver (``stack.drivers.can``) and the
simulated ODrive pair (``stack.sim_bridge.odrive_sim``) take every id, layout and error
name from ``odrive-cansimple-0.6.10.dbc`` (see SOURCE.md), loaded once with cantools.

The DBC lists nodes 0..7 with identical layouts; the ``Axis0_*`` messages serve as
templates for every node, and the arbitration id is ``node_id << 5 | cmd_id``::

    >>> msg = encode("Set_Input_Vel", 1, Input_Vel=1.5)
    >>> hex(msg.arbitration_id), msg.data.hex()
    ('0x2d', '0000c03f00000000')
    >>> decode(msg).signals["Input_Vel"]
    1.5
    >>> error_text(error_bit("WATCHDOG_TIMER_EXPIRED") | error_bit("ESTOP_REQUESTED"))
    'WATCHDOG_TIMER_EXPIRED|ESTOP_REQUESTED'
"""

from __future__ import annotations

import functools
import importlib.resources
from dataclasses import dataclass
from enum import IntEnum
from typing import Collection

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

DBC_FILE = "odrive-cansimple-0.6.10.dbc"
CMD_BITS = 5
CMD_MASK = (1 << CMD_BITS) - 1
MAX_NODE_ID = 0x3F  # 11-bit ids: 6 bits of node, 5 bits of command
UNADDRESSED_NODE_ID = 0x3F  # CANSimple: an axis that has no node id yet answers here; never configure it
MAX_AXIS_NODE_ID = UNADDRESSED_NODE_ID - 1


class AxisState(IntEnum):
    """``Axis_State`` of the heartbeat and ``Axis_Requested_State`` of Set_Axis_State."""

    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    SENSORLESS_CONTROL = 5
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14


class ControlMode(IntEnum):
    """``Control_Mode`` of Set_Controller_Mode."""

    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(IntEnum):
    """``Input_Mode`` of Set_Controller_Mode."""

    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class ProcedureResult(IntEnum):
    """``Procedure_Result`` of the heartbeat (the subset the simulated axis reports)."""

    SUCCESS = 0
    BUSY = 1
    CANCELLED = 2
    DISARMED = 3
    INVALID_STATE = 13


# which DBC signal each enum mirrors (tests check the two agree)
ENUM_SIGNALS: dict[type[IntEnum], tuple[str, str]] = {
    AxisState: ("Heartbeat", "Axis_State"),
    ControlMode: ("Set_Controller_Mode", "Control_Mode"),
    InputMode: ("Set_Controller_Mode", "Input_Mode"),
    ProcedureResult: ("Heartbeat", "Procedure_Result"),
}


class ProtocolError(ValueError):
    """A frame that is not CANSimple as the DBC describes it; ``kind`` names the reason
    (``error_frame``, ``extended_id``, ``fd_frame``, ``other_node``, ``unknown_cmd``, ``bad_dlc``) and
    serves as a counter key."""

    def __init__(self, kind: str, text: str):
        super().__init__(f"{kind}: {text}")
        self.kind = kind


@dataclass(frozen=True)
class Frame:
    """One decoded CANSimple frame: raw signal values (no choice names), or none for an RTR."""

    node_id: int
    name: str
    signals: dict
    remote: bool = False

    @property
    def cmd_id(self) -> int:
        return cmd_id(self.name)


# --- the DBC -----------------------------------------------------------------------------
@functools.cache
def database() -> Database:
    """The DBC, parsed once (package data of ``stack.drivers.odrive``)."""
    text = importlib.resources.files(__name__).joinpath(DBC_FILE).read_text(encoding="utf-8")
    return cantools.database.load_string(text, database_format="dbc")


@functools.cache
def _templates() -> dict[int, DbcMessage]:
    """cmd id -> the node-0 message (the layout every node shares)."""
    return {m.frame_id: m for m in database().messages if m.frame_id <= CMD_MASK}


def template(name: str) -> DbcMessage:
    """The DBC message of a CANSimple command, by its name without the axis prefix."""
    try:
        return database().get_message_by_name(f"Axis0_{name}")
    except KeyError:
        raise ValueError(f"no CANSimple message {name!r} in {DBC_FILE}") from None


def message_name(msg: DbcMessage) -> str:
    return msg.name.split("_", 1)[1]


def cmd_id(name: str) -> int:
    return template(name).frame_id


# --- ids ---------------------------------------------------------------------------------
def arbitration_id(node_id: int, cmd: int) -> int:
    """``node_id << 5 | cmd_id``, the 11-bit CANSimple id."""
    if not 0 <= node_id <= MAX_NODE_ID:
        raise ValueError(f"ODrive node id {node_id} out of range 0..{MAX_NODE_ID}")
    if not 0 <= cmd <= CMD_MASK:
        raise ValueError(f"CANSimple command id {cmd} out of range 0..{CMD_MASK}")
    return node_id << CMD_BITS | cmd


def split_id(arbitration_id: int) -> tuple[int, int]:
    """(node id, cmd id) of an 11-bit id."""
    return arbitration_id >> CMD_BITS, arbitration_id & CMD_MASK


# --- frames ------------------------------------------------------------------------------
def encode(name: str, node_id: int, **signals: float) -> can.Message:
    """A data frame of message ``name`` for ``node_id``; signals not given are zero."""
    t = template(name)
    names = {s.name for s in t.signals}
    unknown = set(signals) - names
    if unknown:
        raise ValueError(f"{name} has no signal {', '.join(sorted(unknown))} (it has {', '.join(sorted(names)) or 'none'})")
    data = t.encode({n: signals.get(n, 0) for n in names}, strict=True) if names else b""
    return can.Message(arbitration_id=arbitration_id(node_id, t.frame_id), is_extended_id=False, data=data)


def request(name: str, node_id: int) -> can.Message:
    """An RTR frame asking ``node_id`` for message ``name`` (the "Get" messages)."""
    t = template(name)
    return can.Message(arbitration_id=arbitration_id(node_id, t.frame_id), is_extended_id=False,
                       is_remote_frame=True, dlc=t.length)


def decode(msg: can.Message, nodes: Collection[int] | None = None) -> Frame:
    """Decode one frame; raises ProtocolError for anything that is not CANSimple, or (given
    ``nodes``) for a frame of another node, whatever its content."""
    if msg.is_error_frame:
        raise ProtocolError("error_frame", "CAN error frame")
    if msg.is_extended_id:
        raise ProtocolError("extended_id", f"29-bit id 0x{msg.arbitration_id:08X}")
    if msg.is_fd:
        raise ProtocolError("fd_frame", f"CAN FD frame 0x{msg.arbitration_id:03X}")
    node, cmd = split_id(msg.arbitration_id)
    if nodes is not None and node not in nodes:
        raise ProtocolError("other_node", f"node {node}")
    t = _templates().get(cmd)
    if t is None:
        raise ProtocolError("unknown_cmd", f"node {node} cmd 0x{cmd:02X}")
    name = message_name(t)
    if msg.is_remote_frame:
        return Frame(node, name, {}, remote=True)
    if msg.dlc != t.length or len(msg.data) != t.length:
        raise ProtocolError("bad_dlc", f"node {node} {name} with {len(msg.data)} bytes, DBC says {t.length}")
    signals = t.decode(bytes(msg.data), decode_choices=False) if t.signals else {}
    return Frame(node, name, dict(signals))


# --- axis errors -------------------------------------------------------------------------
@functools.cache
def _error_choices() -> dict[int, str]:
    choices = template("Heartbeat").get_signal_by_name("Axis_Error").choices
    return {int(v): str(n) for v, n in choices.items() if int(v)}


def error_names(bits: int) -> list[str]:
    """The names of the set bits of an ``Axis_Error`` / ``Active_Errors`` word (DBC choices);
    a bit the DBC does not name reads ``0x...``."""
    names = _error_choices()
    return [names.get(1 << i, f"0x{1 << i:08X}") for i in range(32) if bits >> i & 1]


def error_text(bits: int) -> str:
    """``"NONE"`` or the set bits' names joined with ``|``."""
    return "|".join(error_names(bits)) or "NONE"


def error_bit(name: str) -> int:
    """The bit of an axis error by its DBC name (``"WATCHDOG_TIMER_EXPIRED"`` -> 0x01000000)."""
    for bit, n in _error_choices().items():
        if n == name:
            return bit
    raise ValueError(f"no axis error {name!r} in {DBC_FILE}")


def state_name(value: int) -> str:
    try:
        return AxisState(value).name
    except ValueError:
        return f"state {value}"


__all__ = [
    "AxisState", "ControlMode", "DBC_FILE", "ENUM_SIGNALS", "Frame", "InputMode", "MAX_AXIS_NODE_ID", "MAX_NODE_ID", "ProcedureResult", "UNADDRESSED_NODE_ID",
    "ProtocolError", "arbitration_id", "cmd_id", "database", "decode", "encode", "error_bit", "error_names",
    "error_text", "message_name", "request", "split_id", "state_name", "template",
]
