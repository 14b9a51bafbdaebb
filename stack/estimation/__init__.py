"""Pose estimation from the agent's own sensors (never ground truth). Imports numpy/filterpy only."""

from .ekf import EkfConfig, PoseEKF
from .odometry import OdometryIntegrator, Pose, wrap

__all__ = ["EkfConfig", "OdometryIntegrator", "Pose", "PoseEKF", "wrap"]
