"""``robot.drl``: the settings of ``--policy drl`` (no torch here: the scenario reader checks them)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ...settings import check

_HOLD = "[start, stop] with 0 < start < stop <= 1 (fractions of d_com), or null"


@dataclass
class DrlConfig:
    """``robot.drl`` (scenario): settings of ``--policy drl``. Unknown keys are errors."""

    RULE = (">= 0",)

    weights: str | None = None
    """The network's weights: a ``.npz`` export (``stack-train drl --export``) or a torch state_dict file of
    :class:`DuelingQNet` (default: the shipped ``weights/drl.npz``, the export of ``weights/drl.pt``)."""
    runtime: Literal["numpy", "torch"] = "numpy"
    """Where the network runs: ``numpy`` (no torch on the robot; the same Q values, tests/test_lean.py) or
    ``torch`` (the ``drl`` extra). Torch-file weights need torch either way."""
    shield: bool = True
    """Mask the actions whose arc would bring the robot within ``shield_margin`` of a lidar return in
    ``shield_horizon`` (ours, a safety layer under the network; the network alone: False)."""
    shield_horizon: float = 0.6
    """[s] how far ahead each action's arc (v, w held) is checked."""
    shield_margin: float = 0.1
    """[m] clearance kept beyond the robot's radius."""
    centre_heading: bool = True
    """Follower situation 3 (an obstacle within d_safe): the network's alpha_g aims at the centre of the robots
    ahead (eq. 21-22, the paper); False: at the robot's slot, the bearing it had in every training scene."""
    leader_hold: tuple[float, float] | None = field(default=(0.8, 0.95), metadata={"expect": _HOLD})
    """(start, stop), fractions of d_com: as a leader's farthest robot goes from start d_com to stop d_com,
    its speed after eq. (20) falls linearly to zero, so a follower held up at an obstacle stays in range
    (ours; null: the paper's eq. (20) alone)."""

    def __post_init__(self):
        check(self)
        h = self.leader_hold
        if h is not None and not 0 < h[0] < h[1] <= 1:
            raise ValueError(f"leader_hold: expected {_HOLD}, got {list(h)!r}")
        if self.weights is not None and not Path(self.weights).is_file():
            raise ValueError(f"weights: no such file: {self.weights}")
        torch_file = self.weights is not None and Path(self.weights).suffix != ".npz"
        if (self.runtime == "torch" or torch_file) and not _have_torch():
            what = "runtime: torch" if self.runtime == "torch" else f"weights: {self.weights} (a torch file)"
            raise ValueError(f"{what} needs the Python package 'torch', not installed here "
                             "(install the 'drl' extra: pip install 'formation-stack[drl]'; or runtime: numpy "
                             "on weights exported by stack-train drl --export)")


def _have_torch() -> bool:
    """Whether torch can be imported here (found, not imported)."""
    import importlib.util

    try:
        return importlib.util.find_spec("torch") is not None
    except (ImportError, ValueError):  # a finder that refuses it (tests/test_install.py) reads as missing
        return False
