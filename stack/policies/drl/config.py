"""``robot.drl``: the settings of ``--policy drl`` (no torch here: the scenario reader checks them)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from ..checks import check_numbers


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
    leader_hold: tuple[float, float] | None = (0.8, 0.95)
    """(start, stop), fractions of d_com: as a leader's farthest robot goes from start d_com to stop d_com,
    its speed after eq. (20) falls linearly to zero, so a follower held up at an obstacle stays in range
    (ours; null: the paper's eq. (20) alone)."""

    def __post_init__(self):
        check_numbers(self)  # shield, shield_horizon, shield_margin
        if self.leader_hold is not None:
            h = self.leader_hold
            ok = (isinstance(h, (list, tuple)) and len(h) == 2
                  and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in h)
                  and 0 < h[0] < h[1] <= 1)
            if not ok:
                raise ValueError(f"leader_hold: expected [start, stop] with 0 < start < stop <= 1 (fractions of d_com), "
                                 f"or null, got {h!r}")
            self.leader_hold = (float(h[0]), float(h[1]))
        if self.weights is not None and not Path(str(self.weights)).is_file():
            raise ValueError(f"weights: no such file: {self.weights}")
