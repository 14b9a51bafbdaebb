"""Exact 2D distances from robot centres to obstacle surfaces (for metrics and the training world)."""

from __future__ import annotations

import numpy as np


def distance_to_obstacles(px: np.ndarray, py: np.ndarray, obstacles) -> np.ndarray:
    """Distance from each point (any shape) to the nearest obstacle surface; 0 inside one; inf if none."""
    px = np.asarray(px, float)
    py = np.asarray(py, float)
    best = np.full(px.shape, np.inf)
    for o in obstacles:
        if o.type == "cylinder":
            d = np.hypot(px - o.x, py - o.y) - o.radius
        else:
            cx, cy, hx, hy, yaw = o.as_box()
            c, s = np.cos(yaw), np.sin(yaw)
            lx = c * (px - cx) + s * (py - cy)
            ly = -s * (px - cx) + c * (py - cy)
            qx, qy = np.abs(lx) - hx, np.abs(ly) - hy
            d = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0)) + np.minimum(np.maximum(qx, qy), 0)
        best = np.minimum(best, np.maximum(d, 0.0))
    return best


def pairwise_distances(x: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per row (time step) of (K, N) positions: min and max centre distance over robot pairs (masked robots out)."""
    K, N = x.shape
    if N < 2:
        return np.full(K, np.inf), np.zeros(K)
    dx = x[:, :, None] - x[:, None, :]
    dy = y[:, :, None] - y[:, None, :]
    d = np.hypot(dx, dy)
    iu = np.triu_indices(N, 1)
    pairs = d[:, iu[0], iu[1]]
    if mask is not None:
        ok = mask[:, iu[0]] & mask[:, iu[1]]
        dmin = np.where(ok, pairs, np.inf).min(axis=1)
        dmax = np.where(ok, pairs, -np.inf).max(axis=1)
        dmax = np.where(np.isfinite(dmax), dmax, 0.0)
        return dmin, dmax
    return pairs.min(axis=1), pairs.max(axis=1)
