"""Command-to-motion latency per driver: ``driver.command(v, w)`` -> the device's setpoint changes.

Each driver talks to the device the world hosts for it (``stack.sim_bridge.devices``), on its
own wall-clock thread as during a real-time run: ``sim`` through a Zenoh router to a world-side
subscriber, ``can`` over python-can's slcan on a pseudo-terminal to the simulated ODrive pair,
``mavlink`` over UDP loopback to the simulated rover, ``jackal`` as ROS 2 Twist CDR over Zenoh
to the simulated Jackal on both of its transports: as zenoh-bridge-ros2dds shows a robot
(``bridge``), and as a robot running rmw_zenoh_cpp (``rmw_zenoh``: rmw_zenoh's keys, an
attachment written and checked on every sample, graph tokens). The clock stops when the device holds the new setpoint (the
ODrive's input_vel, the rover's GUIDED target, the Jackal controller's cmd_vel); the
actuators' ramps start from there on the device's next tick (1 ms for ODrive and rover; the
Jackal's 50 Hz controller adds up to 20 ms on a real robot, and our world hands it commands
once per world step).

    python bench/driver_latency.py [--n 200] [--driver jackal ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stack.comm import Keys, decode  # noqa: E402
from stack.comm.messages import CmdVel  # noqa: E402
from stack.comm.session import SessionConfig, free_tcp_endpoint, open_session  # noqa: E402
from stack.drivers import DriverLimits, make_driver  # noqa: E402
from stack.scenario import load_scenario, with_overrides  # noqa: E402
from stack.sim_bridge.devices import make_device  # noqa: E402


def measure(drv, setpoint, n: int) -> list[float]:
    """Alternate w between +0.3 and -0.3; wall seconds from command() until ``setpoint()`` shows it."""
    out = []
    for i in range(n):
        w = 0.3 if i % 2 == 0 else -0.3
        t0 = time.perf_counter()
        drv.command(0.0, w)
        while True:
            s = setpoint()
            if s is not None and abs(s - w) < 1e-6:
                break
            if time.perf_counter() - t0 > 1.0:
                raise TimeoutError(f"{drv.name}: the device did not take w={w} within 1 s (it holds {s})")
            time.sleep(0.0001)  # let the device's threads (same process: the GIL) run
        out.append(time.perf_counter() - t0)
        time.sleep(0.005)
    return out


def bench(name: str, n: int, agent, world, keys: Keys, run_dir: Path, transport: str | None = None) -> list[float]:
    robot = with_overrides(load_scenario(ROOT / "scenarios" / "four-robot-diamond.yaml"), driver=name).robot(0)
    if transport is not None:  # the jackal's: driver and device both read it from the robot's settings
        params = dict(robot.driver_params) | {name: dict(robot.driver_params.get(name, {})) | {"transport": transport}}
        robot = dataclasses.replace(robot, driver_params=params)
    limits = DriverLimits(robot.v_max, robot.w_max, robot.cmd_timeout)
    if name == "sim":  # the world's side of cmd_vel
        last = {}
        got = threading.Event()

        def on_cmd(sample):
            last["w"] = decode(sample.payload.to_bytes(), CmdVel).w
            got.set()

        sub = world.declare_subscriber(keys.robot(robot.id, "cmd_vel"), on_cmd)
        try:
            with make_driver("sim", robot.id, limits, session=agent, keys=keys) as drv:
                return measure(drv, lambda: last.get("w"), n)
        finally:
            sub.undeclare()
    dev = make_device(name, robot, run_dir=run_dir, session=world, keys=keys)
    dev.start()
    try:
        params = dict(robot.driver_params.get(name, {})) | dev.driver_params()
        with make_driver(name, robot.id, limits, session=agent, keys=keys, **params) as drv:
            if name == "can":
                node = dev.config.node_right
                k = dev.config.motor_velocities(0.0, 1.0)[1]  # rev/s per rad/s on the right axis
                setpoint = lambda: dev.pair.axes[node].input_vel / k  # noqa: E731
            elif name == "mavlink":
                setpoint = lambda: dev.rover.target[1]  # noqa: E731
            else:  # the world hands the Jackal's controller its commands at each step: here every 1 ms
                stop = threading.Event()

                def pump():
                    while not stop.wait(0.001):
                        dev.take_commands(0.0)

                threading.Thread(target=pump, daemon=True).start()
                try:
                    return measure(drv, lambda: dev.target[1], n)
                finally:
                    stop.set()
            return measure(drv, setpoint, n)
    finally:
        dev.close()


RUNS = [("sim", None, "Zenoh cmd_vel via a loopback router"),
        ("can", None, "python-can slcan on a pty (Set_Input_Vel x2)"),
        ("mavlink", None, "UDP loopback (SET_POSITION_TARGET_LOCAL_NED)"),
        ("jackal", "bridge", "Zenoh, ROS 2 Twist CDR via a router (zenoh-bridge-ros2dds keys)"),
        ("jackal", "rmw_zenoh", "Zenoh, ROS 2 Twist CDR + attachment via a router (rmw_zenoh keys)")]
"""(driver, jackal transport or None, what goes over the wire)"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=200, help="commands per driver (default %(default)s)")
    ap.add_argument("--driver", action="append", choices=sorted({d for d, _, _ in RUNS}),
                    help="only this driver (repeatable; jackal runs on both transports); default all")
    a = ap.parse_args()
    ep = free_tcp_endpoint()
    keys = Keys("latency")
    print(f"| driver | wire | median [ms] | p95 [ms] | p99 [ms] | max [ms] | n |\n| --- | --- | ---: | ---: | ---: | ---: | ---: |")
    with tempfile.TemporaryDirectory() as tmp, open_session(SessionConfig(mode="router", listen=[ep])), \
            open_session(SessionConfig(connect=[ep])) as agent, open_session(SessionConfig(connect=[ep])) as world:
        for name, transport, wire in RUNS:
            if a.driver and name not in a.driver:
                continue
            lat = sorted(x * 1e3 for x in bench(name, a.n, agent, world, keys, Path(tmp), transport))
            q = lambda p: lat[min(len(lat) - 1, int(p * len(lat)))]  # noqa: E731
            label = name if transport is None else f"{name} ({transport})"
            print(f"| {label} | {wire} | {statistics.median(lat):.2f} | {q(0.95):.2f} | {q(0.99):.2f} | "
                  f"{lat[-1]:.2f} | {len(lat)} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
