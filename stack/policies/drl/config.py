"""``robot.drl``: the settings of ``--policy drl`` (no torch here: the scenario reader checks them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path


@dataclass
class DrlConfig:
    """``robot.drl`` (scenario): settings of ``--policy drl``. Unknown keys are errors."""

    weights: str | None = None
    """A state_dict file of :class:`DuelingQNet` (default: the shipped ``weights/drl.pt``)."""
    shield: bool = True
    """Mask the actions whose arc would bring the robot within ``shield_margin`` of a lidar return in
    ``shield_horizon`` (ours, a safety layer under the network; the network alone: False)."""
    shield_horizon: float = 0.6
    """[s] how far ahead each action's arc (v, w held) is checked."""
    shield_margin: float = 0.1
    """[m] clearance kept beyond the robot's radius."""

    def __post_init__(self):
        if not isinstance(self.shield, bool):
            raise ValueError(f"shield: expected true or false, got {self.shield!r}")
        for k in ("shield_horizon", "shield_margin"):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{k}: expected a number >= 0, got {v!r}")
        if self.weights is not None and not Path(str(self.weights)).is_file():
            raise ValueError(f"weights: no such file: {self.weights}")
