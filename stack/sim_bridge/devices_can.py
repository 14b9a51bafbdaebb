"""The ``can`` robot's device: two simulated ODrive axes behind a simulated slcan USB-CAN adapter.

The adapter holds a pseudo-terminal (``SlcanPtyBus``); the agent's ``can`` driver opens
python-can's own ``slcan`` interface on its slave end, exactly as it would open a CANable on
``/dev/ttyACM0``. The axes (``ODrivePair``) turn the wheels: their velocities, through the
robot's wheel radius, track, gear and mounting (the same ``can:`` settings its driver has),
are the body speeds the world moves the body with; their encoder estimates and heartbeats
go out after the world has moved the body, so they describe it at the end of the step.

Its settings (``OdriveDeviceConfig``, the robot's ``device:``): hardware-like (``ideal:
false``, the default) each axis's encoder reads its shaft angle at power-up (an absolute encoder: a
fraction of a turn, seeded, or ``power_up_pos_rev``) and counts turns from there, and every
encoder estimate of a step goes out at its own time (100 Hz, as on the bus), not only the
newest. Ideal: positions from 0, the newest estimate per step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..drivers import odrive
from ..drivers.can import CanConfig
from .devices import SIM_OPEN_TIMEOUT_S, Body, DeviceConfig, DeviceError, HostedDevice, check_number
from .odrive_sim import ODrivePair, SlcanPtyBus


@dataclass(frozen=True)
class OdriveDeviceConfig(DeviceConfig):
    """How the simulated ODrive pair behaves (scenario: the robot's ``device:``); used only with ``ideal: false`` (the default)."""

    power_up_pos_rev: tuple[float, float] | None = None
    """[rev] (left, right) encoder positions at power-up; None: each axis's shaft angle, a seeded fraction of a turn."""
    all_encoder_samples: bool = True
    """Every encoder estimate (each 10 ms) goes out at its own time; False: only the newest per world step."""

    def __post_init__(self):
        super().__post_init__()
        if self.power_up_pos_rev is not None:
            p = tuple(self.power_up_pos_rev) if isinstance(self.power_up_pos_rev, (list, tuple)) else ()
            if len(p) != 2:
                raise ValueError(f"power_up_pos_rev must be [left_rev, right_rev], not {self.power_up_pos_rev!r}")
            for side, value in zip(("left", "right"), p):
                check_number(f"power_up_pos_rev {side}", value, low=-1e6, high=1e6)
            object.__setattr__(self, "power_up_pos_rev", tuple(float(v) for v in p))
        if not isinstance(self.all_encoder_samples, bool):
            raise ValueError(f"all_encoder_samples must be true or false, not {self.all_encoder_samples!r}")


class OdriveDevice(HostedDevice):
    kind = "can"
    config_class = OdriveDeviceConfig

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
        cfg, dev = self.config, self.device_config
        nodes = (cfg.node_left, cfg.node_right)
        self.pair = ODrivePair(self.adapter, nodes, clock=self.wall_time, all_samples=not dev.ideal and dev.all_encoder_samples)
        if not dev.ideal:  # the encoders power up where the shafts are
            pos0 = dev.power_up_pos_rev or tuple(np.random.default_rng([self.seed, self.robot_id, 17]).random(2))
            for node, p in zip(nodes, pos0):
                self.pair.axes[node].pos = float(p)
        self.pair.run_realtime()

    def driver_params(self) -> dict:
        # open_timeout: the whole fleet starts at once on this machine; a real ODrive answers in 100 ms
        return {"interface": "slcan", "channel": self.adapter.slave_path, "bus_options": {"sleep_after_open": 0},
                "open_timeout": max(self.config.open_timeout, SIM_OPEN_TIMEOUT_S)}

    def take_commands(self, t_sim: float) -> None:
        if self.in_lockstep:
            self.pair.receive(self.device_time(t_sim))
        self.wire_received = self.adapter.counters.get("frames", 0)  # every frame the host sent, now handled

    def _restart_timers(self, t_dev: float) -> None:
        self.pair.restart_timers(t_dev)

    def _send_status(self, t_sim: float) -> None:
        """Both axes' heartbeats (what a driver opening waits for: closed loop, no error)."""
        self.pair.send(self.pair.heartbeats())

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


__all__ = ["OdriveDevice", "OdriveDeviceConfig"]
