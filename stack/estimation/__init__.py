"""Pose estimation from the agent's own sensors (never ground truth). Imports numpy, filterpy and stack.models only.

``EkfConfig`` and ``PoseEKF`` are looked up when first asked for (PEP 562), so a module that needs only
``stack.estimation.pose`` (the policies' ``wrap``; the fleet and the world reading a scenario) does not
import filterpy and scipy.linalg.
"""

from .pose import Pose, wrap

__all__ = ["EkfConfig", "Pose", "PoseEKF", "wrap"]


def __getattr__(name: str):
    if name in ("EkfConfig", "PoseEKF"):
        from . import ekf

        return getattr(ekf, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
