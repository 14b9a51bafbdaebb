"""Pose estimation from the agent's own sensors (never ground truth). Imports numpy/filterpy only."""

from .odometry import OdometryIntegrator, Pose

__all__ = ["OdometryIntegrator", "Pose"]
