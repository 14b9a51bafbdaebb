"""Drivers behind one interface, chosen by name; backends are imported only when used.

>>> drv = make_driver("sim", robot_id=2, limits=DriverLimits(1.0, 1.0), session=s, keys=Keys("f"))
"""

from __future__ import annotations

import importlib

from .base import Driver, DriverError, DriverLimits, Odometry

# name -> "module:Class", imported lazily (python-can's BACKENDS style)
BACKENDS: dict[str, str] = {
    "sim": "stack.drivers.sim:SimDriver",
    "can": "stack.drivers.can:CanDriver",
    "mavlink": "stack.drivers.mavlink:MavlinkDriver",
    "jackal": "stack.drivers.jackal:JackalDriver",
}


class UnknownDriver(DriverError):
    pass


def driver_class(name: str) -> type[Driver]:
    if name not in BACKENDS:
        raise UnknownDriver(f"driver {name!r} is not available (available: {', '.join(sorted(BACKENDS))})")
    module, cls = BACKENDS[name].split(":")
    return getattr(importlib.import_module(module), cls)


def make_driver(name: str, robot_id: int, limits: DriverLimits, **kw) -> Driver:
    return driver_class(name)(robot_id, limits, **kw)


__all__ = ["BACKENDS", "Driver", "DriverError", "DriverLimits", "Odometry", "UnknownDriver", "driver_class", "make_driver"]
