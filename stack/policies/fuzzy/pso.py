"""Particle swarm optimisation (Shi and Eberhart 1998), Chang 2020 eq. (17)-(18); minimises f.

  eq. (17)  v_i(k) <- w v_i(k) + c1 r1 (p_i(k) - s_i(k)) + c2 r2 (g(k) - s_i(k)),  |v_i(k)| <= v_lim(k)
  eq. (18)  s_i(k) <- s_i(k) + v_i(k)                                              (clipped to [lo, hi])

r1, r2 are drawn per particle and per element. ``evaluate`` maps a list of particles to their
fitness (a ``multiprocessing.Pool.map`` in ``stack-train fuzzy``, plain ``map`` by default).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class PsoConfig:
    particles: int = 20
    """Swarm size."""
    iterations: int = 50
    """Iterations (the paper's phase 2: 50)."""
    w: float = 0.7
    """Inertia weight."""
    c1: float = 1.5
    """Cognitive acceleration."""
    c2: float = 1.5
    """Social acceleration."""
    v_frac: float = 0.2
    """Velocity bound per element as a fraction of (hi - lo)."""
    init_spread: float = 1.0
    """Particles other than ``init`` start uniformly within init +- init_spread (hi - lo) / 2 (clipped)."""
    target: float | None = None
    """Stop once the best fitness is at or below this."""


@dataclass
class PsoResult:
    best: np.ndarray
    best_f: float
    curve: list[float] = field(default_factory=list)  # best-so-far fitness after each iteration (0: the initial swarm)
    evaluations: int = 0


def pso(f: Callable[[np.ndarray], float], lo, hi, cfg: PsoConfig | None = None, *, seed: int = 0,
        init: np.ndarray | None = None, evaluate: Callable | None = None,
        callback: Callable[[int, float], None] | None = None) -> PsoResult:
    cfg = cfg or PsoConfig()
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = hi - lo
    evaluate = evaluate or (lambda fn, xs: list(map(fn, xs)))
    n, d = cfg.particles, lo.size
    if init is None:
        s = lo + rng.random((n, d)) * span
    else:
        init = np.clip(np.asarray(init, float), lo, hi)
        s = np.clip(init + (rng.random((n, d)) - 0.5) * span * cfg.init_spread, lo, hi)
        s[0] = init  # the hand-set (or previous) solution is one of the particles
    vlim = cfg.v_frac * span
    v = (rng.random((n, d)) - 0.5) * vlim
    fit = np.array(evaluate(f, list(s)), float)
    p, pf = s.copy(), fit.copy()
    gi = int(np.argmin(pf))
    g, gf = p[gi].copy(), float(pf[gi])
    res = PsoResult(g.copy(), gf, [gf], n)
    if callback:
        callback(0, gf)
    for it in range(1, cfg.iterations + 1):
        if cfg.target is not None and gf <= cfg.target:
            break
        r1, r2 = rng.random((n, d)), rng.random((n, d))
        v = cfg.w * v + cfg.c1 * r1 * (p - s) + cfg.c2 * r2 * (g - s)  # eq. (17)
        v = np.clip(v, -vlim, vlim)
        s = np.clip(s + v, lo, hi)  # eq. (18)
        fit = np.array(evaluate(f, list(s)), float)
        res.evaluations += n
        better = fit < pf
        p[better], pf[better] = s[better], fit[better]
        gi = int(np.argmin(pf))
        if pf[gi] < gf:
            g, gf = p[gi].copy(), float(pf[gi])
        res.curve.append(gf)
        if callback:
            callback(it, gf)
    res.best, res.best_f = g, gf
    return res
