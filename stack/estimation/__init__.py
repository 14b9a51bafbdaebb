"""Pose estimation from the agent's own sensors (never ground truth). Imports numpy and stack.models only."""

from .ekf import EkfConfig, PoseEKF
from .pose import Pose, wrap

__all__ = ["EkfConfig", "Pose", "PoseEKF", "wrap"]
