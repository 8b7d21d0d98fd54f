"""filterpy's ExtendedKalmanFilter specialised to the walking model and (x, y, yaw) pose fixes.

filterpy's ``predict()`` propagates the mean linearly (``F @ x``); here ``predict_x`` is overridden
with the CTRV model and ``F`` is its Jacobian, used only for the covariance. Gating needs the
innovation and its covariance *before* updating (filterpy computes its Mahalanobis distance after),
so :meth:`WalkingEKF.innovation` computes them from the prior; :meth:`WalkingEKF.fuse` then calls
filterpy's ``update`` with an angle-wrapping residual. After every step the covariance is
symmetrised, its eigenvalues floored and its variances capped, so it stays finite and SPD.

Fixes from one frame share the vest's offset from the nominal rig (the "floor" covariance F): they
are fused on a frame-augmented state ``[x (5), b (3)]`` where ``b ~ N(0, F)`` is that shared offset
and each fix measures ``pose + b`` with its own covariance. Fused one by one this is exact; ``b`` is
dropped when the frame ends. For a single fix it is the ordinary update with R = C + F.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from filterpy.kalman import update as kf_update

from tracker import motion
from tracker.config import TrackerConfig

POSE = slice(0, 3)


def wrap(a: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def pose_residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
    """``z - hx`` for stacked (x, y, yaw) blocks, each yaw difference wrapped."""
    y = np.asarray(z, float) - np.asarray(hx, float)
    y[2::3] = wrap(y[2::3])
    return y


def sym_spd(C: np.ndarray, min_eig: float) -> np.ndarray:
    """``C`` symmetrised with eigenvalues floored at ``min_eig`` (non-finite entries -> caller)."""
    C = 0.5 * (C + C.T)
    w, V = np.linalg.eigh(C)
    if w[0] >= min_eig:
        return C
    C = (V * np.maximum(w, min_eig)) @ V.T
    return 0.5 * (C + C.T)


_H_FRAME = np.hstack([np.eye(3), np.zeros((3, 2)), np.eye(3)])  # pose + shared offset


def frame_augment(mean: np.ndarray, cov: np.ndarray, floor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame-augmented state: (8,) mean ``[x, 0, 0, 0]`` and (8, 8) ``blockdiag(cov, floor)``."""
    x = np.r_[np.asarray(mean, float).ravel(), np.zeros(3)]
    P = np.zeros((8, 8))
    P[:5, :5] = cov
    P[5:, 5:] = floor
    return x, P


def frame_innovation(x: np.ndarray, P: np.ndarray, z: np.ndarray,
                     C: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(y (3,), S (3, 3), NIS) of pose ``z`` with own covariance ``C`` on the frame-augmented state."""
    y = pose_residual(z, _H_FRAME @ x)
    S = _H_FRAME @ P @ _H_FRAME.T + C
    S = 0.5 * (S + S.T)
    return y, S, float(y @ np.linalg.solve(S, y))


def frame_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of the frame-augmented state with pose ``z`` (covariance ``C``)."""
    hx = _H_FRAME @ x
    # filterpy's functional update subtracts plainly: hand it the measurement with the yaw unwrapped
    # next to the prediction, so that its residual is the wrapped one.
    z_near = hx + pose_residual(z, hx)
    x, P = kf_update(x, P, z_near, C, _H_FRAME)
    x = np.asarray(x, float).ravel()
    return x, 0.5 * (P + P.T)


@dataclass
class Innovation:
    """Innovation of one pose fix against the prior.

    Attributes:
        y: (3,) residual z - h(x), yaw wrapped. S: (3, 3) its covariance. nis: y^T S^-1 y.
        R: (3, 3) measurement covariance used (fix + floor + retrodiction noise).
    """

    y: np.ndarray
    S: np.ndarray
    nis: float
    R: np.ndarray


class WalkingEKF(ExtendedKalmanFilter):
    """5-state CTRV EKF (x, y, yaw, v, w) with (x, y, yaw) measurements."""

    def __init__(self, config: TrackerConfig):
        super().__init__(dim_x=motion.DIM, dim_z=3)
        self.cfg = config
        self._dt = 0.0
        self._caps = np.array([config.pos_var_cap, config.pos_var_cap, config.yaw_var_cap,
                               config.v_var_cap, config.w_var_cap])

    # -- state access -------------------------------------------------------------------------
    @property
    def mean(self) -> np.ndarray:
        """(5,) state mean."""
        return self.x[:, 0].copy()

    @property
    def cov(self) -> np.ndarray:
        """(5, 5) state covariance."""
        return self.P.copy()

    def set(self, mean: np.ndarray, cov: np.ndarray) -> None:
        """Replace the state (mean (5,), cov (5, 5)), then clip and condition it."""
        self.x = np.asarray(mean, float).reshape(motion.DIM, 1).copy()
        self.P = np.asarray(cov, float).copy()
        self._tidy()

    def reset(self, pose: np.ndarray, R: np.ndarray) -> None:
        """Start from a pose fix (3,) with covariance R (3, 3): speed and yaw rate unknown, zero mean."""
        P = np.zeros((motion.DIM, motion.DIM))
        P[POSE, POSE] = R
        P[motion.V, motion.V] = self.cfg.init_v_sigma**2
        P[motion.W, motion.W] = self.cfg.init_w_sigma**2
        self.set(np.r_[np.asarray(pose, float), 0.0, 0.0], P)

    def forget_motion(self) -> None:
        """Drop what is known about speed and yaw rate (zero mean, initial variance, uncorrelated)."""
        x, P = self.mean, self.cov
        x[3:] = 0.0
        P[3:, :] = 0.0
        P[:, 3:] = 0.0
        P[motion.V, motion.V] = self.cfg.init_v_sigma**2
        P[motion.W, motion.W] = self.cfg.init_w_sigma**2
        self.set(x, P)

    # -- prediction ---------------------------------------------------------------------------
    def predict_x(self, u: object = 0) -> None:
        """Nonlinear mean propagation (filterpy calls this from ``predict``)."""
        self.x = motion.propagate(self.x[:, 0], self._dt).reshape(motion.DIM, 1)

    def advance(self, dt: float) -> np.ndarray:
        """Predict ``dt`` >= 0 seconds ahead, in steps of at most ``max_step_s`` (then one last step).

        Returns the (5, 5) Jacobian of the new state with respect to the old one (the steps'
        ``F`` multiplied), which gives the cross-covariance with a clone of the old state.
        """
        F_total = np.eye(motion.DIM)
        if not dt > 0.0:
            return F_total
        cfg = self.cfg
        n = min(cfg.max_steps, max(1, math.ceil(dt / cfg.max_step_s)))
        steps = [cfg.max_step_s] * (n - 1)
        steps.append(dt - sum(steps))
        for h in steps:
            self._dt = h
            x = self.x[:, 0]
            self.F = motion.jacobian(x, h)
            self.Q = motion.process_noise(x, h, cfg.accel_psd, cfg.yaw_accel_psd, cfg.lateral_psd)
            self.predict()
            self._tidy()
            F_total = self.F @ F_total
        return F_total

    # -- measurement --------------------------------------------------------------------------
    def _model(self, lag: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h(x) (3,), H (3, 5), extra noise (3, 3)) of a pose measured ``lag`` s before the state."""
        x = self.x[:, 0]
        if lag <= 0.0:
            H = np.zeros((3, motion.DIM))
            H[:, POSE] = np.eye(3)
            return x[POSE].copy(), H, np.zeros((3, 3))
        cfg = self.cfg
        back = motion.propagate(x, -lag)
        F = motion.jacobian(x, -lag)
        Q = motion.process_noise(x, -lag, cfg.accel_psd, cfg.yaw_accel_psd, cfg.lateral_psd)
        return back[POSE], F[POSE], Q[POSE, POSE]

    def innovation(self, z: np.ndarray, R: np.ndarray, lag: float = 0.0) -> Innovation:
        """Innovation of pose ``z`` (3,) with covariance ``R`` (3, 3), measured ``lag`` s ago."""
        hx, H, Qb = self._model(lag)
        R = R + Qb
        y = pose_residual(z, hx)
        S = 0.5 * (H @ self.P @ H.T + R + (H @ self.P @ H.T + R).T)
        return Innovation(y, S, float(y @ np.linalg.solve(S, y)), R)

    def fuse(self, z: np.ndarray, R: np.ndarray, lag: float = 0.0) -> None:
        """Kalman update with one pose ``z`` (3,), covariance ``R`` (fix + floor), ``lag`` s old."""
        hx, H, Qb = self._model(lag)
        self.update(np.asarray(z, float).reshape(3, 1), lambda _x: H, lambda _x: hx.reshape(3, 1),
                    R=R + Qb, residual=pose_residual)
        self._tidy()

    # -- guards -------------------------------------------------------------------------------
    def _tidy(self) -> None:
        """Wrap yaw, clip speed and yaw rate to their limits, keep P symmetric, SPD and capped."""
        cfg = self.cfg
        x = self.x[:, 0]
        if not np.all(np.isfinite(x)):
            raise FloatingPointError("non-finite EKF state")
        x[motion.YAW] = wrap(x[motion.YAW])
        x[motion.V] = min(max(x[motion.V], cfg.v_min), cfg.v_max)
        x[motion.W] = min(max(x[motion.W], -cfg.w_max), cfg.w_max)
        self.x = x.reshape(motion.DIM, 1)
        P = self.P
        if not np.all(np.isfinite(P)):
            raise FloatingPointError("non-finite EKF covariance")
        P = sym_spd(P, cfg.min_eig)
        # Scaling rows and columns by the same positive factors keeps P SPD (a congruence).
        d = np.sqrt(np.minimum(1.0, self._caps / np.diag(P)))
        if d.min() < 1.0:
            P = P * np.outer(d, d)
        self.P = P
