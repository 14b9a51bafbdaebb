"""Bai 2022 Fig. 5 in numpy: the forward pass of :class:`.network.DuelingQNet` on its exported weights.

A robot runs the trained network with this (``robot.drl.runtime: numpy``, the default), so its agent
imports no torch (about 200 MB resident less per process). ``tests/test_lean.py`` checks it against torch on
random and real observations: in float64 the two agree to 1e-10; in float32 (what runs) both lie within
float32 rounding (3e-5; torch's own float32 pass is up to 1.6e-5 from its float64 pass) and act alike.

The weights are the state_dict of ``DuelingQNet`` as a ``.npz`` (the same names, float32):
``stack-train drl --export OUT.npz [--init WEIGHTS.pt]`` writes one (:func:`export_npz`, needs torch),
the shipped ``weights/drl.npz`` is ``weights/drl.pt`` exported. Layers, as torch computes them:

  Conv1d  y[o, t] = b[o] + sum_{c,k} W[o, c, k] x[c, s t + k]
  LSTM    [i f g o] = W_ih x_t + b_ih + W_hh h + b_hh;  c = sig(f) c + sig(i) tanh(g);  h = sig(o) tanh(c)
  Linear  y = x W' + b;  Q = V + A - mean(A)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .observation import BEAMS, N_ACTIONS, N_SCANS

LSTM = 16


def shapes(beams: int = BEAMS, n_scans: int = N_SCANS, n_actions: int = N_ACTIONS, lstm: int = LSTM) -> dict[str, tuple]:
    """The state_dict of ``DuelingQNet``: name -> shape."""
    n_conv = 32 * (((beams - 5) // 2 + 1 - 3) // 2 + 1)
    return {"conv.0.weight": (32, n_scans, 5), "conv.0.bias": (32,), "conv.2.weight": (32, 32, 3), "conv.2.bias": (32,),
            "fc_scan.1.weight": (32, n_conv), "fc_scan.1.bias": (32,),
            "lstm.weight_ih_l0": (4 * lstm, 2), "lstm.weight_hh_l0": (4 * lstm, lstm),
            "lstm.bias_ih_l0": (4 * lstm,), "lstm.bias_hh_l0": (4 * lstm,),
            "fc.0.weight": (128, 32 + lstm + 4), "fc.0.bias": (128,), "value.weight": (1, 128), "value.bias": (1,),
            "advantage.weight": (n_actions, 128), "advantage.bias": (n_actions,)}


def check_weights(weights: dict[str, np.ndarray], where: str, dtype=np.float32) -> dict[str, np.ndarray]:
    """The weights as ``dtype`` arrays, or ValueError (one line, naming ``where``) when a name or shape differs."""
    want = shapes()
    if set(weights) != set(want):
        missing, extra = sorted(set(want) - set(weights)), sorted(set(weights) - set(want))
        raise ValueError(f"{where}: not DuelingQNet weights (missing {missing}, unexpected {extra})")
    for k, shape in want.items():
        if tuple(weights[k].shape) != shape:
            raise ValueError(f"{where}: {k} has shape {tuple(weights[k].shape)}, expected {shape}")
    return {k: np.ascontiguousarray(weights[k], dtype) for k in want}


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """The exported weights at ``path`` (ValueError, one line, when it is not such a file)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return check_weights({k: z[k] for k in z.files}, str(path))
    except (OSError, ValueError) as e:
        msg = str(e)
        raise ValueError(msg if msg.startswith(str(path)) else f"{path}: not a numpy .npz of weights ({msg})") from None


def export_npz(state_dict: dict, path: str | Path) -> Path:
    """Write a torch state_dict of ``DuelingQNet`` as the ``.npz`` that :class:`NumpyQNet` loads."""
    arrays = check_weights({k: v.detach().cpu().numpy() for k, v in state_dict.items()}, "state_dict")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        np.savez(f, **arrays)
    return path


def _sigmoid(x: np.ndarray) -> np.ndarray:
    one = x.dtype.type(1.0)
    return one / (one + np.exp(-x))


def _conv1d(x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int) -> np.ndarray:
    """(B, C, L) -> (B, O, T), no padding."""
    k = w.shape[2]
    win = np.lib.stride_tricks.sliding_window_view(x, k, axis=2)[:, :, ::stride]  # (B, C, T, k)
    cols = win.transpose(0, 2, 1, 3).reshape(x.shape[0], win.shape[2], -1)  # (B, T, C k)
    return (cols @ w.reshape(w.shape[0], -1).T + b).transpose(0, 2, 1)


class NumpyQNet:
    """``DuelingQNet.forward`` in numpy on a weights dict (:func:`load_npz`), in float32 as torch runs it
    (``dtype=np.float64``: the network's exact values, for checks)."""

    def __init__(self, weights: dict[str, np.ndarray], dtype=np.float32):
        self.dtype = dtype
        self.p = check_weights(weights, "weights", dtype)

    def _lstm_last(self, nb: np.ndarray) -> np.ndarray:
        """(B, T, 2) -> the last hidden state (B, 16)."""
        p = self.p
        B = nb.shape[0]
        h = np.zeros((B, LSTM), self.dtype)
        c = np.zeros((B, LSTM), self.dtype)
        xs = nb @ p["lstm.weight_ih_l0"].T + p["lstm.bias_ih_l0"]  # (B, T, 64)
        for t in range(nb.shape[1]):
            g = xs[:, t] + (h @ p["lstm.weight_hh_l0"].T + p["lstm.bias_hh_l0"])
            i, f, gg, o = np.split(g, 4, axis=1)
            c = _sigmoid(f) * c + _sigmoid(i) * np.tanh(gg)
            h = _sigmoid(o) * np.tanh(c)
        return h

    def __call__(self, scans: np.ndarray, goal_vel: np.ndarray, nb: np.ndarray | None = None) -> np.ndarray:
        """scans (B, 3, 180), goal_vel (B, 4), nb (B, T, 2) farthest first (all T valid) -> Q (B, 15)."""
        p = self.p
        z = np.maximum(_conv1d(np.asarray(scans, self.dtype), p["conv.0.weight"], p["conv.0.bias"], 2), 0)
        z = np.maximum(_conv1d(z, p["conv.2.weight"], p["conv.2.bias"], 2), 0)
        z = np.maximum(z.reshape(z.shape[0], -1) @ p["fc_scan.1.weight"].T + p["fc_scan.1.bias"], 0)
        if nb is None or nb.shape[1] == 0:
            h = np.zeros((z.shape[0], LSTM), self.dtype)
        else:
            h = self._lstm_last(np.asarray(nb, self.dtype))
        x = np.concatenate([z, h, np.asarray(goal_vel, self.dtype)], axis=1)
        x = np.maximum(x @ p["fc.0.weight"].T + p["fc.0.bias"], 0)
        a = x @ p["advantage.weight"].T + p["advantage.bias"]
        return (x @ p["value.weight"].T + p["value.bias"]) + a - a.mean(axis=1, keepdims=True)
