"""Zero-order TSK fuzzy system with Gaussian membership functions (Chang 2020 eq. 3-6).

  eq. (3)  R_i: If x_1 is A_i1 And ... And x_M is A_iM Then y is a_i   (a_i a real vector)
  eq. (4)  mu_ij(x_j) = exp(-((x_j - m_ij) / sigma_ij)^2)
  eq. (5)  Phi_i = prod_j mu_ij(x_j)
  eq. (6)  y = sum_i Phi_i a_i / sum_i Phi_i            (weighted-average defuzzification)

The firing strengths are computed in the log domain and shifted by their maximum before the
exponential: eq. (6) is invariant to a common factor of all Phi_i, so this is the same number,
but it stays defined far from every centre (where each Phi_i underflows to 0 and the printed
ratio would be 0/0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SIGMA_MIN = 1e-3  # a width below this is raised to it (PSO may propose ~0)


@dataclass
class TSK:
    """r rules over M inputs with K outputs: centres ``m`` (r, M), widths ``sigma`` (r, M), consequents ``a`` (r, K)."""

    m: np.ndarray
    sigma: np.ndarray
    a: np.ndarray

    def __post_init__(self):
        self.m = np.asarray(self.m, float)
        self.sigma = np.maximum(np.abs(np.asarray(self.sigma, float)), SIGMA_MIN)
        self.a = np.asarray(self.a, float)
        if self.a.ndim == 1:
            self.a = self.a[:, None]
        if self.m.shape != self.sigma.shape or self.a.shape[0] != self.m.shape[0]:
            raise ValueError(f"TSK shapes disagree: m {self.m.shape}, sigma {self.sigma.shape}, a {self.a.shape}")

    @property
    def rules(self) -> int:
        return self.m.shape[0]

    def firing(self, x) -> np.ndarray:
        """Normalised firing strengths Phi_i / sum Phi (eq. 4-5), shape (r,)."""
        z = (np.asarray(x, float)[None, :] - self.m) / self.sigma
        logphi = -np.sum(z * z, axis=1)  # log of eq. (5): sum of the logs of eq. (4)
        phi = np.exp(logphi - logphi.max())
        return phi / phi.sum()

    def __call__(self, x) -> np.ndarray:
        """Eq. (6): the K outputs for input x (M,)."""
        return self.firing(x) @ self.a

    # a particle of the PSO is the flat vector [m, sigma, a]
    def to_vector(self) -> np.ndarray:
        return np.concatenate([self.m.ravel(), self.sigma.ravel(), self.a.ravel()])

    @classmethod
    def from_vector(cls, vec, rules: int, inputs: int, outputs: int) -> "TSK":
        vec = np.asarray(vec, float)
        n = rules * inputs
        if vec.size != 2 * n + rules * outputs:
            raise ValueError(f"expected {2 * n + rules * outputs} parameters, got {vec.size}")
        return cls(vec[:n].reshape(rules, inputs), vec[n:2 * n].reshape(rules, inputs),
                   vec[2 * n:].reshape(rules, outputs))

    def to_dict(self) -> dict:
        return {"m": self.m.tolist(), "sigma": self.sigma.tolist(), "a": self.a.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "TSK":
        return cls(np.array(d["m"]), np.array(d["sigma"]), np.array(d["a"]))
