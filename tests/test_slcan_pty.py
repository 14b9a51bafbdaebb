"""The simulated slcan adapter's pty: a host that stops reading loses whole frames, never part of one."""

from __future__ import annotations

import os

from stack.sim_bridge.odrive_sim import TX_BACKLOG, SlcanPtyBus

LINE = "t02D80000c03f00000000\r"  # node 1 Set_Input_Vel 1.5 rev/s, as an slcan line


def _drain(fd: int) -> bytes:
    out = b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            return out
        if not chunk:
            return out
        out += chunk


def test_a_full_pty_drops_whole_frames_and_counts_them():
    bus = SlcanPtyBus()
    fd = os.open(bus.slave_path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    try:
        for _ in range(5000):  # far more than the pty and the backlog hold: nobody reads
            bus._write(LINE)
        assert len(bus._tx) <= TX_BACKLOG + len(LINE)
        dropped = bus.counters["overrun"]
        assert dropped > 0
        data = b""
        for _ in range(300):  # the host reads again, the adapter keeps sending
            data += _drain(fd)
            bus._write(LINE)
        data += _drain(fd)
        frames = data.split(b"\r")
        assert frames[-1] == b"" or LINE.encode().startswith(frames[-1])  # only the newest may be in flight
        assert len(frames) > 1000
        assert set(frames[:-1]) == {LINE[:-1].encode()}, "a frame reached the host cut or glued to another"
    finally:
        os.close(fd)
        bus.shutdown()
