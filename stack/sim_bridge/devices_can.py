"""The ``can`` robot's device: two simulated ODrive axes behind a simulated slcan USB-CAN adapter.

The adapter holds a pseudo-terminal (``SlcanPtyBus``); the agent's ``can`` driver opens
python-can's own ``slcan`` interface on its slave end, exactly as it would open a CANable on
``/dev/ttyACM0``. The axes (``ODrivePair``) turn the wheels: their velocities, through the
robot's wheel radius, track, gear and mounting (the same ``can:`` settings its driver has),
are the body speeds the world moves the body with; their encoder estimates and heartbeats
go out after the world has moved the body, so they describe it at the end of the step.
"""

from __future__ import annotations

from ..drivers import odrive
from ..drivers.can import CanConfig
from .devices import SIM_OPEN_TIMEOUT_S, Body, DeviceError, HostedDevice
from .odrive_sim import ODrivePair, SlcanPtyBus


class OdriveDevice(HostedDevice):
    kind = "can"

    def __init__(self, robot, **kw):
        super().__init__(robot, **kw)
        self.config = self.driver_config(CanConfig)
        self.adapter: SlcanPtyBus | None = None
        self.pair: ODrivePair | None = None
        self._due: list = []

    def start(self) -> None:
        try:
            self.adapter = SlcanPtyBus()
        except OSError as e:
            raise DeviceError(f"robot {self.robot_id}: cannot make a pseudo-terminal for the slcan adapter: {e}") from None
        cfg = self.config
        self.pair = ODrivePair(self.adapter, (cfg.node_left, cfg.node_right), clock=self.wall_time).run_realtime()

    def driver_params(self) -> dict:
        # open_timeout: the whole fleet starts at once on this machine; a real ODrive answers in 100 ms
        return {"interface": "slcan", "channel": self.adapter.slave_path, "bus_options": {"sleep_after_open": 0},
                "open_timeout": max(self.config.open_timeout, SIM_OPEN_TIMEOUT_S)}

    def take_commands(self, t_sim: float) -> None:
        if self.in_lockstep:
            self.pair.receive(self.device_time(t_sim))

    def motion(self, t_sim_next: float) -> tuple[float, float]:
        if self.in_lockstep:
            self._due = self.pair.advance(self.device_time(t_sim_next))
        cfg = self.config
        return cfg.body_velocity(self.pair.vel(cfg.node_left), self.pair.vel(cfg.node_right))

    def report(self, t_sim_next: float, body: Body) -> None:
        if self._due:
            # heartbeats first: once the driver has the step's odometry sample (the last encoder frame), it has
            # the step's heartbeats too (one wire, in order), so its heartbeat check sees the same every run
            enc = odrive.cmd_id("Get_Encoder_Estimates")
            is_enc = [odrive.split_id(m.arbitration_id)[1] == enc for m in self._due]
            self.pair.send([m for m, e in zip(self._due, is_enc) if not e] + [m for m, e in zip(self._due, is_enc) if e])
            self.odom_sent += sum(is_enc) // len(self.pair.axes)  # the driver makes one sample of both axes' estimates
            self._due = []

    def fail(self) -> str:
        self.pair.mute_heartbeats()
        return "both ODrive axes stopped sending heartbeats"

    def _stop_realtime(self) -> None:
        if self.pair is not None:
            self.pair.stop()

    def close(self) -> None:
        self._stop_realtime()
        if self.adapter is not None:
            self.adapter.shutdown()
            self.adapter = None
