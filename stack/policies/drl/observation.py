"""Bai 2022 section III-B: the observation's normalisation and the 15-action table.

  eq. (11)  d_g = d_g / d_n if d_g < d_n else 1.0          (d_n = 3 m, Table I)
  eq. (12)  alpha_g = alpha_g / pi
  o_v       [v, w], not normalised (v_max = 1 m/s, w_max = 1 rad/s)
  eq. (13)  d_j = d_j / d_com, alpha_j = alpha_j / pi       (d_com = 10 m, Table II), farthest first
  o_z       the last three scans of 180 beams, divided by d_scan = 5 m

Everything here is numpy and works on one observation or on a batch (leading axes), so the
training world (:mod:`stack.train.drlworld`) and the onboard policy normalise the same way; the
raw distances and bearings they normalise come from one builder too (:mod:`stack.models.observation`,
``tests/test_models.py`` checks that both give the same network inputs).
"""

from __future__ import annotations

import math

import numpy as np

D_N = 3.0  # Table I
D_COM = 10.0  # Table II
D_SCAN = 5.0  # Table II
N_SCANS = 3
BEAMS = 180
V_SET = (0.0, 0.5, 1.0)  # section III-B 2)
W_SET = (-1.0, -0.5, 0.0, 0.5, 1.0)
#: (15, 2) [v, w]: index = 5 * i_v + i_w
ACTIONS = np.array([(v, w) for v in V_SET for w in W_SET], dtype=np.float32)
N_ACTIONS = len(ACTIONS)


def goal_features(d_g, alpha_g, v, w) -> np.ndarray:
    """[o_g, o_v] = [min(d_g / d_n, 1), alpha_g / pi, v, w] (eq. 11-12), shape (..., 4)."""
    d = np.minimum(np.asarray(d_g, np.float32) / D_N, 1.0)
    return np.stack(np.broadcast_arrays(d, np.asarray(alpha_g, np.float32) / math.pi,
                                        np.asarray(v, np.float32), np.asarray(w, np.float32)), axis=-1).astype(np.float32)


def neighbour_features(neighbours: np.ndarray) -> np.ndarray:
    """o_r (eq. 13): (n, 2) [distance, bearing] farthest first -> [d / d_com, alpha / pi]."""
    nb = np.asarray(neighbours, np.float32).reshape(-1, 2)
    return (nb / np.array([D_COM, math.pi], np.float32)).astype(np.float32)


def scan_features(scans: np.ndarray, beams: int = BEAMS) -> np.ndarray:
    """o_z: (k, b) ranges [m], newest last -> (3, 180) in [0, 1].

    Fewer than three scans (the first steps of a run) repeat the oldest; a lidar with another
    beam count is resampled over its field of view; no scan at all reads as free space."""
    s = np.asarray(scans, np.float32)
    if s.ndim == 1:
        s = s[None]
    if s.size == 0:
        return np.ones((N_SCANS, beams), np.float32)
    if s.shape[-1] != beams:
        src = np.linspace(0.0, 1.0, s.shape[-1])
        dst = np.linspace(0.0, 1.0, beams)
        s = np.stack([np.interp(dst, src, row) for row in s]).astype(np.float32)
    s = s[-N_SCANS:]
    if len(s) < N_SCANS:
        s = np.concatenate([np.repeat(s[:1], N_SCANS - len(s), axis=0), s])
    return np.clip(s / D_SCAN, 0.0, 1.0).astype(np.float32)
