"""Pose EKF (numpy, filterpy's equations): state [x, y, yaw, v, w], unicycle model of Bai 2022 eq. (1).

    x' = v cos(yaw),  y' = v sin(yaw),  yaw' = w,  v' = 0 + noise,  w' = 0 + noise

Each agent runs one of these on its own sensors only (never ground truth):

* ``predict(dt)``        the motion model over one period;
* ``update_odometry``    wheel encoders measure (v, w) directly, H = [0 0 0 1 0; 0 0 0 0 1];
* ``update_gyro``        the IMU measures w, H = [0 0 0 0 1];
* ``update_fix``         an absolute position fix measures (x, y), H = [I2 0], Mahalanobis-gated.

Call order and Q. Wheel odometry and the gyro report the rates over the period that has
just elapsed (a wheel encoder counts ticks over the period), so per period call

    update_odometry(v, w); update_gyro(wz); predict(dt); [update_fix(x, y) stamped at its end]

i.e. the (v, w) in the state are "the rates of the coming period" when ``predict`` runs, and
the motion over the period is driven by the rates measured for it. Q matches that order: v and
w random-walk between periods with 1-sigma steps accel_std dt and alpha_std dt, and x, y, yaw
get no process noise of their own (their growth comes from the rate uncertainty through F).
Tried and dropped, on the simulated runs of tests/test_estimation.py (mean yaw NEES, 1 dof,
so 1.0 is right): predict-then-update with the textbook Q = G diag(a^2, alpha^2) G' (dt^2/2 in
G's pose rows) integrates each period with the previous period's rates, lags the truth by
(v, w) dt / 2 and gave 1.46; this order with that Q gave 1.24 (the pose rows let the next
period's rate measurement correct the yaw of the period before); this order and Q: 1.03.

How the filter runs. The equations are those of filterpy's ``ExtendedKalmanFilter`` (its
``predict`` with ``predict_x`` overridden, its ``update``), written out in numpy in :class:`_Ekf`
so that an agent does not import filterpy, which imports scipy.stats (about 45 MB resident per
process; tests/test_lean.py checks the two agree on a run). ``predict`` propagates the mean by the
exact unicycle motion over dt (v, w constant over the period: the robot drives a circular arc),
not by ``F @ x``, and P = F P F' + Q with F the Jacobian of that motion at the prior. Measurements
are linear: S = H P H' + R, K = P H' S^-1, x = x + K (z - H x), and the Joseph form
P = (I-KH) P (I-KH)' + K R K'; we symmetrise P after every step. Fixes are gated first
(y = z - H x, S = H P H' + R, reject if y' S^-1 y > gate_chi2).

Robustness: any NaN/inf/negative input (value, dt or std) is dropped and counted in
``rejected_nan`` before it touches the filter; if a finite but absurd input would still make
x or P non-finite, the step is rolled back and counted there too. The yaw is wrapped to
(-pi, pi] after every predict and every update. No measurement has an angle residual (the
odometry and gyro measure rates, the fix measures position), so no residual needs wrapping.

Imports: numpy, the standard library and stack.models (ARCHITECTURE.md, estimation room).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..models.kinematics import arc_step, sinc
from .pose import Pose, wrap

__all__ = ["EkfConfig", "PoseEKF", "motion", "motion_jacobian"]

# State indices.
IX, IY, IYAW, IV, IW = range(5)

# Constant measurement Jacobians: H for each sensor (the models are linear in the state).
_H_ODOM = np.array([[0.0, 0.0, 0.0, 1.0, 0.0],
                    [0.0, 0.0, 0.0, 0.0, 1.0]])
_H_GYRO = np.array([[0.0, 0.0, 0.0, 0.0, 1.0]])
_H_FIX = np.array([[1.0, 0.0, 0.0, 0.0, 0.0],
                   [0.0, 1.0, 0.0, 0.0, 0.0]])


@dataclass(frozen=True)
class EkfConfig:
    """Noise model of the pose EKF. Every sensor std here is a floor: a larger std passed
    with a measurement (the scenario's or the driver's value) is used, a smaller one is not,
    so a sensor is never trusted more than configured and R never becomes singular."""

    odom_v_std: float = 0.02
    """Wheel-odometry speed noise, 1 sigma [m/s] (floor of R for v)."""
    odom_w_std: float = 0.02
    """Wheel-odometry yaw-rate noise, 1 sigma [rad/s] (floor of R for w)."""
    gyro_std: float = 0.01
    """IMU yaw-rate noise, 1 sigma [rad/s] (floor of R for the gyro)."""
    fix_std: float = 0.3
    """Absolute position fix noise per axis, 1 sigma [m] (floor of R for fixes)."""
    accel_std: float = 1.0
    """Process noise: linear acceleration, 1 sigma [m/s^2]; v may change by accel_std dt between periods."""
    alpha_std: float = 2.0
    """Process noise: angular acceleration, 1 sigma [rad/s^2]; w may change by alpha_std dt between periods."""
    gate_chi2: float = 13.8155
    """Mahalanobis gate for 2-D fixes: reject when y' S^-1 y exceeds it (chi-square, 2 dof, 99.9 %)."""
    init_pos_std: float = 0.05
    """Initial position uncertainty per axis, 1 sigma [m]."""
    init_yaw_std: float = 0.02
    """Initial yaw uncertainty, 1 sigma [rad]."""
    init_v_std: float = 1.0
    """Initial speed uncertainty, 1 sigma [m/s]: the filter starts at v = 0, the robot may not."""
    init_w_std: float = 1.0
    """Initial yaw-rate uncertainty, 1 sigma [rad/s]: the filter starts at w = 0, the robot may not."""

    def __post_init__(self) -> None:
        for name, val in vars(self).items():
            if not (math.isfinite(val) and val > 0):
                raise ValueError(f"EkfConfig.{name} must be finite and > 0, got {val}")


def motion(x: np.ndarray, dt: float) -> np.ndarray:
    """Exact unicycle motion over dt with v, w constant (a circular arc), eq. (1): the chord of the
    arc has length v dt sinc(w dt / 2) and heading yaw + w dt / 2 (:func:`stack.models.kinematics.arc_step`,
    the world's and the training worlds' motion too). Yaw is wrapped; v' = v, w' = w."""
    px, py, yaw, v, w = (float(a) for a in x.ravel())
    return np.array([[a] for a in (*arc_step(px, py, yaw, v, w, dt), v, w)])


def motion_jacobian(x: np.ndarray, dt: float) -> np.ndarray:
    """F = d motion / d x, evaluated at x (the prior)."""
    _, _, yaw, v, w = (float(a) for a in x.ravel())
    h = 0.5 * w * dt
    s, ds = sinc(h)
    chord, m = v * dt * s, yaw + h
    c, sn = math.cos(m), math.sin(m)
    dchord_dw = v * dt * ds * 0.5 * dt                  # d chord / d w (through h = w dt / 2)
    F = np.eye(5)
    F[IX, IYAW] = -chord * sn                           # dx'/dyaw
    F[IY, IYAW] = chord * c                             # dy'/dyaw
    F[IX, IV] = dt * s * c                              # dx'/dv
    F[IY, IV] = dt * s * sn                             # dy'/dv
    F[IX, IW] = dchord_dw * c - chord * sn * 0.5 * dt   # dx'/dw
    F[IY, IW] = dchord_dw * sn + chord * c * 0.5 * dt   # dy'/dw
    F[IYAW, IW] = dt                                    # dyaw'/dw
    return F


def _finite(*vals: float) -> bool:
    return all(math.isfinite(v) for v in vals)


class _Ekf:
    """The mean and covariance, stepped by filterpy's ``ExtendedKalmanFilter`` equations (same order of
    products) with the mean propagated by the exact unicycle model, not F @ x."""

    def __init__(self, x: np.ndarray, P: np.ndarray):
        self.x, self.P = x, P
        self.F, self.Q = np.eye(5), np.zeros((5, 5))
        self._I = np.eye(5)

    def predict(self, dt: float) -> None:
        """x = f(x, dt); P = F P F' + Q."""
        self.x = motion(self.x, dt)
        self.P = (self.F @ self.P) @ self.F.T + self.Q

    def update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> None:
        """K = P H' S^-1, x = x + K (z - H x), P = (I-KH) P (I-KH)' + K R K'."""
        PHT = self.P @ H.T
        K = PHT @ np.linalg.inv(H @ PHT + R)
        self.x = self.x + K @ (z - H @ self.x)
        I_KH = self._I - K @ H
        self.P = (I_KH @ self.P) @ I_KH.T + (K @ R) @ K.T


class PoseEKF:
    """EKF over [x, y, yaw, v, w] (see the module docstring).

    ``rejected_fixes`` counts fixes refused by the Mahalanobis gate; ``rejected_nan`` counts
    inputs (a value, dt or a std) that were NaN, inf or negative and were dropped."""

    def __init__(self, x: float, y: float, yaw: float, cfg: EkfConfig = EkfConfig()):
        if not _finite(x, y, yaw):
            raise ValueError(f"initial pose must be finite, got {(x, y, yaw)}")
        self.cfg = cfg
        self._kf = _Ekf(np.array([[x], [y], [wrap(yaw)], [0.0], [0.0]]),
                        np.diag([cfg.init_pos_std ** 2, cfg.init_pos_std ** 2, cfg.init_yaw_std ** 2,
                                 cfg.init_v_std ** 2, cfg.init_w_std ** 2]))
        self.rejected_fixes = 0
        self.rejected_nan = 0

    # ---------------------------------------------------------------- predict
    def predict(self, dt: float) -> None:
        """Propagate over dt seconds. dt NaN/inf/negative: dropped and counted; dt = 0: no-op."""
        if not _finite(dt) or dt < 0:
            self.rejected_nan += 1
            return
        if dt == 0:
            return
        kf, cfg = self._kf, self.cfg
        kf.F = motion_jacobian(kf.x, dt)                # F = df/dx at the prior
        # Q = diag(0, 0, 0, (accel_std dt)^2, (alpha_std dt)^2): the rates random-walk between
        # periods; the pose gets no noise of its own, its uncertainty grows through F P F' from
        # that of v and w (see "Call order and Q" in the module docstring).
        Q = np.zeros((5, 5))
        Q[IV, IV] = (cfg.accel_std * dt) ** 2
        Q[IW, IW] = (cfg.alpha_std * dt) ** 2
        kf.Q = Q
        x0, P0 = kf.x.copy(), kf.P.copy()
        kf.predict(dt)                                  # x = f(x, dt); P = F P F' + Q
        self._settle(x0, P0)

    # ---------------------------------------------------------------- updates
    def update_odometry(self, v: float, w: float, v_std: float | None = None, w_std: float | None = None) -> bool:
        """Wheel odometry: z = [v, w], Hx = [v, w] of the state. Stds are floored by the config."""
        sv = self._std(v_std, self.cfg.odom_v_std)
        sw = self._std(w_std, self.cfg.odom_w_std)
        if sv is None or sw is None or not _finite(v, w):
            self.rejected_nan += 1
            return False
        z = np.array([[v], [w]])
        R = np.diag([sv * sv, sw * sw])                 # R = diag(sigma_v^2, sigma_w^2)
        return self._update(z, _H_ODOM, R)

    def update_gyro(self, wz: float, std: float | None = None) -> bool:
        """IMU yaw rate: z = [wz], Hx = [w]. The std is floored by ``cfg.gyro_std``."""
        s = self._std(std, self.cfg.gyro_std)
        if s is None or not _finite(wz):
            self.rejected_nan += 1
            return False
        return self._update(np.array([[wz]]), _H_GYRO, np.array([[s * s]]))  # R = sigma_gyro^2

    def update_fix(self, x: float, y: float, std: float | None = None) -> bool:
        """Absolute position fix: z = [x, y], Hx = [x, y] of the state, gated on y' S^-1 y.

        Rejected (False, ``rejected_fixes`` += 1, state untouched) when the squared Mahalanobis
        distance of the innovation exceeds ``cfg.gate_chi2``. The std is floored by ``cfg.fix_std``."""
        s = self._std(std, self.cfg.fix_std)
        if s is None or not _finite(x, y):
            self.rejected_nan += 1
            return False
        z = np.array([[x], [y]])
        R = np.eye(2) * (s * s)                         # R = sigma_fix^2 I2
        kf = self._kf
        yv = z - _H_FIX @ kf.x                          # y = z - H x (innovation)
        S = _H_FIX @ kf.P @ _H_FIX.T + R                # S = H P H' + R
        d2 = float((yv.T @ np.linalg.solve(S, yv))[0, 0])  # d^2 = y' S^-1 y
        if not d2 <= self.cfg.gate_chi2:
            self.rejected_fixes += 1
            return False
        return self._update(z, _H_FIX, R)

    # ---------------------------------------------------------------- state
    @property
    def pose(self) -> Pose:
        """The current estimate as a Pose (yaw in (-pi, pi])."""
        x = self._kf.x[:, 0]
        return Pose(float(x[IX]), float(x[IY]), wrap(float(x[IYAW])), float(x[IV]), float(x[IW]))

    @property
    def cov_trace(self) -> float:
        """Trace of the [x, y, yaw] block of P (m^2 + rad^2): the pose uncertainty, not v and w."""
        return float(np.trace(self._kf.P[:3, :3]))

    @property
    def P(self) -> np.ndarray:
        """A copy of the 5x5 state covariance P."""
        return self._kf.P.copy()

    @property
    def x(self) -> np.ndarray:
        """A copy of the state vector [x, y, yaw, v, w] (shape (5,))."""
        return self._kf.x[:, 0].copy()

    # ---------------------------------------------------------------- internals
    def _std(self, given: float | None, floor: float) -> float | None:
        """The std to use: max(given, floor); None when the given one is NaN/inf/negative."""
        if given is None:
            return floor
        if not _finite(given) or given < 0:
            return None
        return max(float(given), floor)

    def _update(self, z: np.ndarray, H: np.ndarray, R: np.ndarray) -> bool:
        """K = P H' S^-1, x = x + K y, P = (I-KH) P (I-KH)' + K R K' (filterpy's update)."""
        kf = self._kf
        x0, P0 = kf.x.copy(), kf.P.copy()
        kf.update(z, H, R)
        return self._settle(x0, P0)

    def _settle(self, x0: np.ndarray, P0: np.ndarray) -> bool:
        """Wrap yaw, symmetrise P; roll back (and count) if anything became non-finite."""
        kf = self._kf
        if not math.isfinite(float(kf.x.sum()) + float(kf.P.sum())):  # NaN/inf anywhere poisons the sum
            kf.x, kf.P = x0, P0
            self.rejected_nan += 1
            return False
        kf.x[IYAW, 0] = wrap(float(kf.x[IYAW, 0]))
        kf.P = 0.5 * (kf.P + kf.P.T)                    # keep P symmetric
        return True
