"""Cross-checks of our CANSimple code against an implementation we did not write: ``odrive-can``
(ROX Automation, on PyPI; its own copy of the vendor's DBC, decoded with choice names).

- our ``CanDriver`` against odrive-can's mock ODrive (``odrive_can.mock.ODriveCANMock``, one per
  axis, asyncio) on a python-can ``virtual`` bus: arming, velocity commands, encoder feedback,
  heartbeats, and the heartbeat timeout;
- odrive-can's client (``odrive_can.ODriveCAN``) against our simulated ODrive pair, on a
  ``virtual`` bus and through our simulated slcan adapter with python-can's ``slcan`` interface:
  it reads our heartbeats and encoder estimates, answers to its RTR requests, and its commands
  move our axes; our watchdog's error reaches it by name.

The mock's heartbeat comes every 200 ms (a real ODrive's every 100 ms), so the driver here
allows 1 s; the mock takes 0.5 s to change state, so opening allows 3 s.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import threading
import time

import can
import pytest
from odrive_can import ODriveCAN
from odrive_can.mock import ODriveCANMock
from odrive_can.odrive import DriveError

from conftest import wait_for
from stack.drivers import DriverLimits
from stack.drivers.can import CanConfig, CanDriver
from stack.sim_bridge.odrive_sim import ODrivePair, SlcanPtyBus

LIMITS = DriverLimits(v_max=1.0, w_max=2.0, cmd_timeout=5.0)
_channels = itertools.count()

logging.getLogger("odrive").setLevel(logging.WARNING)  # the mock and the client log every state change


def channel() -> str:
    return f"xcheck-odrive-{next(_channels)}-{os.getpid()}"


class MockAxes:
    """odrive-can's mock ODrive, one per node, each on its own ``virtual`` bus of ``channel``, in an
    asyncio loop on a thread (as ``ODriveCANMock.start`` would run it, but stoppable)."""

    def __init__(self, chan: str, nodes: tuple[int, ...]):
        self.loop = asyncio.new_event_loop()
        self.mocks: dict[int, ODriveCANMock] = {}
        self.tasks: dict[int, list[asyncio.Task]] = {}
        self._chan, self._nodes = chan, nodes
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="odrive-can-mock", daemon=True)
        self._thread.start()
        assert self._ready.wait(10.0), "odrive-can mock did not start"

    def _run(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_until_complete(self._start())
        self._ready.set()
        self.loop.run_forever()

    async def _start(self) -> None:
        for node in self._nodes:
            mock = ODriveCANMock(node, can_bus=can.Bus(interface="virtual", channel=self._chan))
            # its Notifier feeds an AsyncBufferedReader from a thread without the loop; python-can wants the loop given
            mock.notifier.stop()  # (which stops its reader too)
            mock.can_reader = can.AsyncBufferedReader()
            mock.notifier = can.Notifier(mock.bus, [mock.can_reader], loop=self.loop)
            mock.set_rate_of_change(40.0)  # [rev/s^2]
            self.mocks[node] = mock
            self.tasks[node] = [asyncio.ensure_future(c) for c in
                                (mock.heartbeat_loop(), mock.encoder_loop(), mock.message_handler())]

    def call(self, fn, timeout: float = 5.0):
        """Run ``fn()`` on the mock's loop (its state is the loop's) and return its result."""
        async def run():
            return fn()
        return asyncio.run_coroutine_threadsafe(run(), self.loop).result(timeout)

    def stop_heartbeats(self, node: int) -> None:
        self.call(lambda: self.tasks[node][0].cancel())

    def close(self) -> None:
        def cancel():
            for tasks in self.tasks.values():
                for t in tasks:
                    t.cancel()
        self.call(cancel)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5.0)
        for mock in self.mocks.values():
            mock.notifier.stop()
            mock.bus.shutdown()


@pytest.fixture
def mock_rig():
    chan = channel()
    cfg = CanConfig(interface="virtual", channel=chan, node_left=3, node_right=4, wheel_radius=0.1,
                    track_width=0.4, gear_ratio=2.0, heartbeat_timeout=1.0, open_timeout=3.0)
    mocks = MockAxes(chan, (cfg.node_left, cfg.node_right))
    malformed: list[str] = []
    driver = CanDriver(5, LIMITS, cfg, on_malformed=malformed.append)
    driver.malformed = malformed  # what it counted as malformed: nothing, from odrive-can's frames
    yield mocks, driver, cfg
    driver.close()
    mocks.close()


def test_driver_arms_commands_and_reads_odrive_can_mock(mock_rig):
    mocks, driver, cfg = mock_rig
    assert mocks.call(lambda: [str(m.odrive.axis_state) for m in mocks.mocks.values()]) == ["IDLE", "IDLE"]
    driver.open()  # Clear_Errors, Set_Controller_Mode, Set_Axis_State; the mock's heartbeats must confirm
    modes = mocks.call(lambda: [(str(m.odrive.axis_state), str(m.odrive.control_mode)) for m in mocks.mocks.values()])
    assert modes == [("CLOSED_LOOP_CONTROL", "VELOCITY_CONTROL")] * 2
    assert driver.counters["heartbeat"] >= 2 and driver.fault is None

    v, w = 0.5, 1.0
    driver.command(v, w)
    left, right = cfg.motor_velocities(v, w)  # the mock decodes our Set_Input_Vel with its own DBC
    assert wait_for(lambda: mocks.call(lambda: (mocks.mocks[3].odrive.model.setpoint,
                                                mocks.mocks[4].odrive.model.setpoint)) == pytest.approx((left, right)), 3.0)

    def tracking():
        odo = driver.read()
        return odo is not None and abs(odo.v - v) < 1e-3 and abs(odo.w - w) < 1e-3
    assert wait_for(tracking, 5.0), driver.read()  # its encoder estimates, through our kinematics
    assert driver.counters["encoder"] >= 4 and not driver.malformed
    odo = driver.read()
    assert time.time() - odo.stamp < 1.0

    driver.close()  # zero velocity, then IDLE
    assert wait_for(lambda: mocks.call(lambda: [(str(m.odrive.axis_state), m.odrive.model.setpoint)
                                                for m in mocks.mocks.values()]) == [("IDLE", 0.0)] * 2, 3.0)


def test_driver_faults_when_the_mock_stops_its_heartbeat(mock_rig):
    mocks, driver, cfg = mock_rig
    driver.open()
    driver.command(0.3, 0.0)
    mocks.stop_heartbeats(cfg.node_right)
    assert wait_for(lambda: driver.fault, 4.0)
    assert f"right axis (node {cfg.node_right}): no heartbeat" in driver.fault
    # the fault stop reached the mock: zero velocity on both axes (it ignores Estop, which it does not model)
    assert wait_for(lambda: mocks.call(lambda: [m.odrive.model.setpoint for m in mocks.mocks.values()]) == [0.0, 0.0], 3.0)


def test_driver_faults_when_a_mock_axis_leaves_closed_loop(mock_rig):
    mocks, driver, cfg = mock_rig
    driver.open()

    def drop():
        mocks.mocks[cfg.node_left].odrive.axis_state = "IDLE"
    mocks.call(drop)
    assert wait_for(lambda: driver.fault, 4.0)
    assert f"left axis (node {cfg.node_left}): left CLOSED_LOOP_CONTROL, now IDLE" in driver.fault


# --- odrive-can's client against our simulated ODrive -------------------------------------------
async def drive_our_axis(bus: can.BusABC, pair: ODrivePair, node: int) -> None:
    """What odrive-can's velocity-control example does, on our simulated axis ``node``."""
    samples: list[dict] = []
    client = ODriveCAN(node, can_bus=bus)
    client.feedback_callback = lambda msg, _drv: samples.append(msg.data)
    await asyncio.wait_for(client.start(), 5.0)  # until our first heartbeat
    try:
        client.check_alive()
        client.check_errors()
        assert client.axis_state == "IDLE"
        client.clear_errors()
        client.set_controller_mode("VELOCITY_CONTROL", "VEL_RAMP")
        await client.set_axis_state("CLOSED_LOOP_CONTROL")  # returns once our heartbeat says so
        await client.wait_for_heartbeat()
        client.check_errors()
        assert pair.axes[node].state == 8 and pair.axes[node].control_mode == 2 and pair.axes[node].input_mode == 2

        for _ in range(10):  # resent every 0.1 s, as its example does: our axis's watchdog stays fed
            client.set_input_vel(2.5)
            await asyncio.sleep(0.1)
        assert pair.vel(node) == pytest.approx(2.5)
        assert samples[-1]["Vel_Estimate"] == pytest.approx(2.5)
        assert samples[-1]["Pos_Estimate"] == pytest.approx(pair.axes[node].pos, abs=0.1)
        power = await client.get_bus_voltage_current()  # RTR, our reply
        assert power["Bus_Voltage"] == pytest.approx(24.0) and power["Bus_Current"] > 0.0
        # last: its one-slot response queue takes any frame with the reply's id, and our periodic
        # estimates (100 Hz) share it, so one may be left in the slot for the next request
        est = await client.get_encoder_estimates()
        assert est["Vel_Estimate"] == pytest.approx(2.5)
        client.check_errors()

        await asyncio.sleep(0.8)  # it stops commanding: our watchdog (0.5 s) disarms the axis
        await client.wait_for_heartbeat()
        with pytest.raises(DriveError, match="WATCHDOG_TIMER_EXPIRED"):
            client.check_errors()
        assert client.axis_state == "IDLE" and pair.vel(node) == 0.0
    finally:
        client.stop()  # sends IDLE; joins its reader thread
    client.clear_errors()
    await asyncio.sleep(0.3)
    assert pair.axes[node].errors == 0 and pair.axes[node].state == 1
    del client._bus  # the bus is the caller's: the client's destructor would shut it down a second time


def test_odrive_can_client_drives_our_pair_on_a_virtual_bus():
    chan = channel()
    sim_bus = can.Bus(interface="virtual", channel=chan)
    host_bus = can.Bus(interface="virtual", channel=chan)
    pair = ODrivePair(sim_bus, node_ids=(0, 6), vel_ramp_rate=40.0).run_realtime()
    try:
        asyncio.run(drive_our_axis(host_bus, pair, 6))
        assert pair.axes[0].state == 1 and pair.axes[0].vel == 0.0  # the other axis heard nothing for it
        assert not {k for k in pair.counters if k not in ("rx", "tx")}, pair.counters
    finally:
        pair.stop()
        host_bus.shutdown()
        sim_bus.shutdown()


def test_odrive_can_client_drives_our_pair_through_our_slcan_adapter():
    adapter = SlcanPtyBus()
    pair = ODrivePair(adapter, node_ids=(0, 1), vel_ramp_rate=40.0).run_realtime()
    host_bus = can.Bus(interface="slcan", channel=adapter.slave_path, bitrate=500_000, sleep_after_open=0)
    try:
        asyncio.run(drive_our_axis(host_bus, pair, 1))
        assert adapter.bitrate == 500_000 and adapter.counters["frames"] > 10
        # before the host opened the channel our frames were dropped, and its opening ``C`` was refused
        # (the channel was not open), as a Lawicel adapter does; nothing else went wrong
        assert not set(adapter.counters) - {"frames", "dropped_closed", "nak"}, adapter.counters
        assert adapter.counters.get("nak", 0) <= 2
    finally:
        pair.stop()
        host_bus.shutdown()
        adapter.shutdown()
