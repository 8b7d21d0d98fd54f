"""filterpy's ExtendedKalmanFilter specialised to the walking model and (x, y, yaw) pose fixes.

filterpy's ``predict()`` propagates the mean linearly (``F @ x``); here ``predict_x`` is overridden
with the CTRV model and ``F`` is its Jacobian, used only for the covariance. Gating needs the
innovation and its covariance *before* updating (filterpy computes its Mahalanobis distance after),
so :meth:`WalkingEKF.innovation` computes them from the prior; :meth:`WalkingEKF.fuse` then calls
filterpy's ``update`` with an angle-wrapping residual. After every step the covariance is
symmetrised, its eigenvalues floored and its variances capped, so it stays finite and SPD.

The state carries, besides the walking body (x, y, yaw, speed, yaw rate), the vest's offset from
that smooth walk (dx, dy, dyaw, world axes; the torso's sway and twist, see
:class:`TrackerConfig`), and the tilt offset (tx, ty, world axes) that floor odometry alone sees:
its fixed homography turns a change of the torso's lean into apparent floor motion
(:meth:`TrackerConfig.tilt_cov`). Each offset is a first-order Gauss-Markov process with the floor
covariance F as its stationary covariance. F and the correlation time follow the walk
(:meth:`TrackerConfig.floor_cov`, :meth:`TrackerConfig.floor_corr`): stated along and across the
walk, turned into world axes with the current heading, and grown with the speed (the gait makes
most of the wobble). A fix
measures the vest pose, ``body + offset``; an odometry step measures the vest's motion. So fixes of
one frame share the offset exactly, consecutive frames share most of it, and the wobble the
odometry integrates is bounded instead of accumulating: the filter separates the smooth walk
(body) from the ~1 Hz wobble (offset) by their dynamics. The operator's pose is the vest's,
body + offset (:func:`vest_pose`, :func:`vest_cov`).

The odometry's scale error ``e`` (one number, a slow random walk about 0) multiplies the translation
of every odometry step (a step measures ``1 + e`` times the vest's motion): the camera's height off
the rig's, and the floor flow's own bias, scale the floor's motion (see
:class:`TrackerConfig`). Fixes at both ends of a gap pin it, so between stickers the walk is
measured with the scale the last gaps showed.

Survey error of the map: a fix is its sticker's map pose composed with what the camera measured, so
a sticker surveyed ``e`` = (dx, dy, dyaw) off moves every one of its fixes by ``J e`` (``J``:
:func:`tagloc.core.geometry.map_error_jacobian`, the turn acting on the lever from the sticker to
the vest point). That error is the same in every frame that sees the sticker: treated as fresh
noise per fix, thirty fixes a second would average it away and claim to know the sticker's place
better than its survey; inflated per fix instead, the fixes (1 cm apart from the truth) would stop
counting. So each sticker being fixed gets its own error state ``e`` (constant: no process noise),
with the survey's covariance as its prior and zero mean, in one of ``MAP_SLOTS`` slots: a fix
measures ``vest + J e`` and the filter works out, from the fixes at changing levers and from the
odometry between stickers, how much of the disagreement is the map's. A slot is taken by the
least recently fixed sticker when a new one is accepted; its old sticker is then marginalised out
(its rows and columns dropped: exact). Seeing that sticker again much later starts a fresh prior,
which forgets what the track had learnt about it (slightly optimistic on a return visit; with four
slots a sticker is only dropped after four others were fixed since).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpotrf

from tagloc.core.geometry import wrap_angle
from tracker import motion
from tracker.config import TrackerConfig
from tracker.filterpy_kalman import ExtendedKalmanFilter

# Stickers whose survey error is a state at once: two or three are in view at a time (10 cm stickers
# 1.2-2 m apart under a ~1 x 1.5 m footprint), and a slot should outlive a short pass of another.
MAP_SLOTS = 4
POSE = slice(0, 3)
OFF = slice(motion.DIM, motion.DIM + 3)
TILT = slice(motion.DIM + 3, motion.DIM + 5)
SCALE = motion.DIM + 5  # the odometry's relative scale error (see TrackerConfig.odometry_scale_sigma)
MAP0 = motion.DIM + 6
DIM = MAP0 + 3 * MAP_SLOTS  # walking body + vest offset + odometry's tilt offset and scale + map errors
M_VEST = np.zeros((3, DIM))  # body + offset
M_VEST[:, POSE] = np.eye(3)
M_VEST[:, OFF] = np.eye(3)
M_VEST.flags.writeable = False
# What floor odometry follows: the vest pose plus the tilt offset (x, y only).
M_ODO = M_VEST.copy()
M_ODO[:2, TILT] = np.eye(2)
M_ODO.flags.writeable = False


def map_slot(k: int) -> slice:
    """State slice (3,) of map-error slot ``k``: the survey error (dx, dy, dyaw) of its sticker."""
    return slice(MAP0 + 3 * k, MAP0 + 3 * k + 3)


@dataclass(frozen=True)
class MapTerm:
    """How one fix depends on its sticker's survey error.

    Attributes:
        sticker_id: the sticker the fix came from.
        J: (3, 3) d fix / d map error (:func:`tagloc.core.geometry.map_error_jacobian`).
        prior: (3, 3) survey covariance of the sticker's map pose (dx, dy in m, dyaw in rad).
    """

    sticker_id: int
    J: np.ndarray
    prior: np.ndarray


_NO_NOISE = np.zeros((3, 3))
_NO_NOISE.flags.writeable = False


def vest_pose(x: np.ndarray) -> np.ndarray:
    """(3,) vest pose (body pose + offset) from the state mean ``x`` (DIM,); yaw not wrapped."""
    return x[POSE] + x[OFF]


def vest_cov(P: np.ndarray) -> np.ndarray:
    """(3, 3) covariance of the vest pose (body pose + offset) from the state covariance ``P`` (DIM, DIM)."""
    return P[POSE, POSE] + P[POSE, OFF] + P[OFF, POSE] + P[OFF, OFF]


def heading_widened(cov: np.ndarray) -> np.ndarray:
    """(3, 3) pose covariance ``cov`` with its (x, y) ellipse widened for the heading's uncertainty.

    The filter's (x, y) ellipse is oriented by the heading it believes: long across the walk when
    the heading is uncertain, short along it. That orientation is itself only as certain as the
    heading. Rotating a 2-D error by an angle drawn from N(0, s^2) (s^2 the yaw variance) keeps
    the mean of the ellipse's two variances and multiplies their difference by exp(-2 s^2) (the
    expectation of cos 2d). Here the minor axis is raised by what that takes from it and the major
    axis kept, so the result is never tighter than the filter's and stays positive semi-definite
    (a term is added along one axis). With the heading known to a degree the change is below a
    thousandth; after seconds blind in a turn (the heading off by a radian or more, the track
    extrapolating a turn the walker left) the ellipse tends to a disc of its major radius rather
    than staying thin where the walker may well be."""
    cov = np.array(cov, float)
    k = math.exp(-2.0 * max(float(cov[2, 2]), 0.0))
    a, b, c = cov[0, 0], cov[1, 1], cov[0, 1]
    half = math.hypot(0.5 * (a - b), c)  # half the difference of the two eigenvalues
    if half <= 0.0 or k >= 1.0:
        return cov
    # Minor axis (unit): the eigenvector of the smaller eigenvalue of [[a, c], [c, b]].
    ang = 0.5 * math.atan2(2.0 * c, a - b) + 0.5 * math.pi
    n = np.array([math.cos(ang), math.sin(ang)])
    cov[:2, :2] += (1.0 - k) * half * np.outer(n, n)
    return cov


def odometry_pose(x: np.ndarray) -> np.ndarray:
    """(3,) the pose floor odometry follows (vest pose + tilt offset on x, y) from the mean ``x`` (DIM,)."""
    return M_ODO @ x


def pose_residual(z: np.ndarray, hx: np.ndarray) -> np.ndarray:
    """``z - hx`` for stacked (x, y, yaw) blocks, each yaw difference wrapped."""
    y = np.asarray(z, float) - np.asarray(hx, float)
    y[2::3] = wrap_angle(y[2::3])
    return y


def odometry_model(
    x: np.ndarray, clone: np.ndarray, scale_at: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Measurement model of a floor-odometry step, beside the fix model (:meth:`WalkingEKF.innovation`).

    The step is the odometry pose now (the vest pose plus the tilt offset, :func:`odometry_pose`)
    seen from the odometry pose ``clone`` (3,) at the earlier frame, its translation scaled by the
    odometry's scale error ``e`` (``x[SCALE]``):
    ``h = ((1 + e) R(yaw0)^T (v1 - c)[:2], v1.yaw - yaw0)`` with ``v1`` the odometry pose of the
    state mean ``x`` (DIM,). Returns h (3,) and its Jacobian H (3, DIM + 3) over the joint state
    [x, clone (3)] (stochastic cloning). The scale's column is the step ``R(yaw0)^T (v1 - c)[:2]``;
    ``scale_at`` (2,), m, evaluates it at another estimate of that step (the tracker gives the
    filter's prediction, see ``Tracker._predicted_step``).
    """
    v1 = odometry_pose(x)
    yaw0 = clone[2]
    co, si = math.cos(yaw0), math.sin(yaw0)
    k = 1.0 + float(x[SCALE])
    Rt = np.array([[co, si], [-si, co]])  # world -> body at t0
    d = v1[:2] - clone[:2]
    body_d = Rt @ d
    hx = np.append(k * body_d, wrap_angle(float(v1[2] - yaw0)))
    H = np.zeros((3, DIM + 3))
    H[:2, :DIM] = k * (Rt @ M_ODO[:2])
    H[:2, SCALE] = body_d if scale_at is None else scale_at
    H[:2, DIM : DIM + 2] = -k * Rt
    H[:2, DIM + 2] = k * (np.array([[-si, co], [-co, -si]]) @ d)
    H[2, :DIM] = M_ODO[2]
    H[2, DIM + 2] = -1.0
    return hx, H


def largest_eig_2x2(P: np.ndarray) -> float:
    """Largest eigenvalue of the symmetric (x, y) block ``P[:2, :2]`` (closed form, no LAPACK call)."""
    a, b, c = float(P[0, 0]), 0.5 * float(P[0, 1] + P[1, 0]), float(P[1, 1])
    return 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)


def sym_spd(C: np.ndarray, min_eig: float) -> np.ndarray:
    """``C`` symmetrised with eigenvalues floored at ``min_eig`` (non-finite entries -> caller)."""
    C = 0.5 * (C + C.T)
    # The common case, at a tenth of the cost of eigh: C - min_eig I has a Cholesky factor, so every
    # eigenvalue of C exceeds min_eig and C stands as it is (LAPACK directly: numpy's wrapper costs
    # four times the factorisation of an 8x8 matrix).
    D = C.copy()
    D.flat[:: len(C) + 1] -= min_eig
    if dpotrf(D, lower=1, clean=0, overwrite_a=1)[1] == 0:
        return C
    w, V = np.linalg.eigh(C)
    if w[0] >= min_eig:
        return C
    C = (V * np.maximum(w, min_eig)) @ V.T
    return 0.5 * (C + C.T)


@dataclass
class Innovation:
    """Innovation of one pose fix against the prior.

    Attributes:
        y: (3,) residual z - h(x), yaw wrapped. S: (3, 3) its covariance. nis: y^T S^-1 y.
        R: (3, 3) measurement covariance used (fix + retrodiction noise).
    """

    y: np.ndarray
    S: np.ndarray
    nis: float
    R: np.ndarray


class WalkingEKF(ExtendedKalmanFilter):
    """EKF: CTRV body (x, y, yaw, v, w), vest offset (dx, dy, dyaw), tilt offset (tx, ty) and the survey
    errors of up to ``MAP_SLOTS`` stickers; vest-pose measurements (fixes) and odometry-pose steps."""

    def __init__(self, config: TrackerConfig) -> None:
        super().__init__(dim_x=DIM, dim_z=3)
        self.cfg = config
        self._dt = 0.0
        # Slot k holds the survey error of sticker slots[k] (None: free), last fixed at used[k].
        self.slots: list[int | None] = [None] * MAP_SLOTS
        self._used = [-math.inf] * MAP_SLOTS
        self._fixes = 0
        full = config.floor_cov(0.0)
        big = max(full[0, 0], full[1, 1])
        tilt = config.tilt_cov(0.0)
        big_tilt = max(tilt[0, 0], tilt[1, 1])
        self._caps = np.r_[
            config.pos_var_cap,
            config.pos_var_cap,
            config.yaw_var_cap,
            config.v_var_cap,
            config.w_var_cap,
            config.offset_var_cap_factor * np.array([big, big, full[2, 2]]),
            # (a floor above min_eig: with the tilt offset off, its variance sits at that floor)
            np.full(2, max(config.offset_var_cap_factor * big_tilt, 1e-6)),
            # The scale's random walk must not outgrow its prior while nothing pins it (a long gap).
            max(config.odometry_scale_sigma**2, 1e-6),
            # Map errors have no process noise: the cap only guards against numerical growth.
            np.full(3 * MAP_SLOTS, config.map_var_cap),
        ]

    def _decay(self, dt: float) -> float:
        """Correlation left in the vest offset after ``dt`` s at the current speed estimate."""
        tau = self.cfg.floor_corr(float(self.x[motion.V, 0]))
        return math.exp(-abs(dt) / tau) if tau > 0 else 0.0

    def _tilt_decay(self, dt: float) -> float:
        """Correlation left in the tilt offset after ``dt`` s."""
        tau = self.cfg.tilt_corr_s
        return math.exp(-abs(dt) / tau) if tau > 0 else 0.0

    # -- state access -------------------------------------------------------------------------
    @property
    def mean(self) -> np.ndarray:
        """(DIM,) state mean: body (x, y, yaw, v, w), vest offset (dx, dy, dyaw), tilt offset (tx, ty),
        odometry scale error, map errors (3 per slot)."""
        return self.x[:, 0].copy()

    @property
    def cov(self) -> np.ndarray:
        """(DIM, DIM) state covariance."""
        return self.P.copy()

    def set(self, mean: np.ndarray, cov: np.ndarray) -> None:
        """Replace the state (mean (DIM,), cov (DIM, DIM)), then clip and condition it."""
        self.x = np.asarray(mean, float).reshape(DIM, 1).copy()
        self.P = np.asarray(cov, float).copy()
        self._tidy()

    def reset(self, pose: np.ndarray, R: np.ndarray, scale: float = 0.0) -> None:
        """Start from a fix of the vest pose (3,) with its own covariance R (3, 3): the body is the fix
        less an offset of covariance F (so body and offset are anti-correlated); speed and yaw rate
        unknown, zero mean. The odometry's scale error starts at ``scale`` (a restarted track's:
        the vest and its wearer are the same) with its prior variance, so a value learnt on a track
        that went wrong is relearnt quickly."""
        F = self.cfg.floor_cov(float(pose[2]))
        P = np.zeros((DIM, DIM))
        P[POSE, POSE] = R + F
        P[OFF, OFF] = F
        P[POSE, OFF] = -F
        P[OFF, POSE] = -F
        P[TILT, TILT] = self.cfg.tilt_cov(float(pose[2]))
        P[SCALE, SCALE] = self.cfg.odometry_scale_sigma**2
        P[motion.V, motion.V] = self.cfg.init_v_sigma**2
        P[motion.W, motion.W] = self.cfg.init_w_sigma**2
        for k in range(MAP_SLOTS):
            P[map_slot(k), map_slot(k)] = self._free_slot_cov()
        self.slots = [None] * MAP_SLOTS
        self._used = [-math.inf] * MAP_SLOTS
        x = np.r_[np.asarray(pose, float), np.zeros(DIM - 3)]
        x[SCALE] = scale
        self.set(x, P)

    def reset_from_fix(self, pose: np.ndarray, R: np.ndarray, term: MapTerm | None, scale: float = 0.0) -> None:
        """:meth:`reset` from a fix whose sticker's survey error is ``term`` (None: an exact map): the
        vest is the fix less ``J e``, so it starts correlated with that error's new state."""
        self.reset(pose, R, scale)
        if term is None:
            return
        s = map_slot(self.claim_slot(term)[0])
        P = self.P.copy()
        JS = term.J @ term.prior
        P[POSE, s] = -JS
        P[s, POSE] = -JS.T
        P[POSE, POSE] = P[POSE, POSE] + JS @ term.J.T
        self.set(self.x[:, 0], P)

    def odometry_scale(self) -> float:
        """The odometry's relative scale error now (mean of ``x[SCALE]``)."""
        return float(self.x[SCALE, 0])

    def forget_motion(self) -> None:
        """Drop what is known about speed and yaw rate (zero mean, initial variance, uncorrelated)."""
        self._forget((motion.V, motion.W))

    def forget_turn(self) -> None:
        """Drop what is known about the yaw rate alone (zero mean, initial variance, uncorrelated)."""
        self._forget((motion.W,))

    def _forget(self, rates: tuple[int, ...]) -> None:
        """Reset the states ``rates`` (of V, W) to zero mean and their start-up variance, uncorrelated."""
        x, P = self.mean, self.cov
        start = {motion.V: self.cfg.init_v_sigma**2, motion.W: self.cfg.init_w_sigma**2}
        idx = list(rates)
        x[idx] = 0.0
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        for i in idx:
            P[i, i] = start[i]
        self.set(x, P)

    # -- prediction ---------------------------------------------------------------------------
    def predict_x(self, u: object = 0) -> None:
        """Nonlinear mean propagation (filterpy calls this from ``predict``)."""
        x = self.x[:, 0]
        body = motion.propagate(x[: motion.DIM], self._dt)
        # The offsets are linear: their blocks of F (set by ``advance`` for this step) are their decays.
        self.x = np.concatenate((body, self.F[OFF, OFF] @ x[OFF], self.F[TILT, TILT] @ x[TILT], x[SCALE:])).reshape(
            DIM, 1
        )

    def _transition(self, x: np.ndarray, h: float, extra_yaw_psd: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(F (DIM, DIM), Q (DIM, DIM)) of a step of ``h`` s (negative: backwards) from state ``x``,
        with ``extra_yaw_psd`` (rad^2/s^3) of yaw acceleration on top of the walking model's."""
        cfg = self.cfg
        a = self._decay(h)
        F = np.zeros((DIM, DIM))
        Q = np.zeros((DIM, DIM))
        F[: motion.DIM, : motion.DIM] = motion.jacobian(x[: motion.DIM], h)
        F[OFF, OFF] = a * np.eye(3)
        Q[: motion.DIM, : motion.DIM] = motion.process_noise(
            x[: motion.DIM], h, cfg.accel_psd, cfg.yaw_accel_psd + extra_yaw_psd, cfg.lateral_psd
        )
        Q[OFF, OFF] = (1.0 - a * a) * cfg.floor_cov(float(x[motion.YAW]), float(x[motion.V]))
        b = self._tilt_decay(h)
        F[TILT, TILT] = b * np.eye(2)
        F[SCALE:, SCALE:] = np.eye(DIM - SCALE)  # the scale random-walks; a survey error does not change
        Q[TILT, TILT] = (1.0 - b * b) * cfg.tilt_cov(float(x[motion.YAW]), float(x[motion.V]))
        Q[SCALE, SCALE] = cfg.odometry_scale_rw**2 * abs(h)
        return F, Q

    def advance(self, dt: float, extra_yaw_psd: float = 0.0) -> np.ndarray:
        """Predict ``dt`` >= 0 seconds ahead, in steps of at most ``max_step_s`` (then one last step),
        with ``extra_yaw_psd`` (rad^2/s^3) of yaw acceleration noise on top of the walking model's
        (a frame gap nothing measured, see ``TrackerConfig.gap_yaw_accel_psd``).

        Returns the (DIM, DIM) Jacobian of the new state with respect to the old one (the steps'
        ``F`` multiplied), which gives the cross-covariance with a clone of the old state.
        """
        F_total = np.eye(DIM)
        if not dt > 0.0:
            return F_total
        cfg = self.cfg
        n = min(cfg.max_steps, max(1, math.ceil(dt / cfg.max_step_s)))
        steps = [cfg.max_step_s] * (n - 1)
        steps.append(dt - sum(steps))
        for h in steps:
            self._dt = h
            self.F, self.Q = self._transition(self.x[:, 0], h, extra_yaw_psd)
            self.predict()
            self._tidy()
            F_total = self.F @ F_total
        return F_total

    # -- map-error slots -----------------------------------------------------------------------
    @staticmethod
    def _free_slot_cov() -> np.ndarray:
        """Covariance parked in a free slot: small, positive (keeps P SPD), uncorrelated."""
        return np.eye(3) * 1e-8

    def slot_of(self, sticker_id: int) -> int | None:
        """The map-error slot holding ``sticker_id``, or None."""
        try:
            return self.slots.index(int(sticker_id))
        except ValueError:
            return None

    def _take_slot(self, sticker_id: int) -> int:
        """A slot for a sticker that has none: a free one, else the least recently fixed one, whose
        sticker is marginalised out (its rows and columns zeroed: exact)."""
        k = self.slots.index(None) if None in self.slots else int(np.argmin(self._used))
        s = map_slot(k)
        x, P = self.x[:, 0].copy(), self.P.copy()
        x[s] = 0.0
        P[s, :] = 0.0
        P[:, s] = 0.0
        P[s, s] = self._free_slot_cov()
        self.x, self.P = x.reshape(DIM, 1), P
        self.slots[k] = int(sticker_id)
        return k

    def claim_slot(self, term: MapTerm) -> tuple[int, bool]:
        """The slot of ``term``'s sticker, marked as just fixed; a new sticker takes one (the least
        recently fixed one's sticker is marginalised out) with its survey prior. Returns (slot,
        whether it is fresh)."""
        k = self.slot_of(term.sticker_id)
        fresh = k is None
        if fresh:
            k = self._take_slot(term.sticker_id)
            P = self.P.copy()
            P[map_slot(k), map_slot(k)] = term.prior
            self.P = P
        self._fixes += 1
        self._used[k] = self._fixes
        return k, fresh

    def _map_columns(
        self, hx: np.ndarray, H: np.ndarray, R: np.ndarray, term: MapTerm | None, take: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Add the sticker's survey error to the model (hx (3,), H (3, DIM), R (3, 3)): through its
        slot when it has (or, with ``take``, gets) one, ``hx + J e`` and ``J`` in the slot's columns of
        ``H``; else as extra noise ``J prior J^T`` (what a fresh slot would add)."""
        if term is None:
            return hx, H, R
        k = self.claim_slot(term)[0] if take else self.slot_of(term.sticker_id)
        if k is None:
            return hx, H, R + term.J @ term.prior @ term.J.T
        H = np.array(H, float)
        H[:, map_slot(k)] = term.J
        return hx + term.J @ self.x[map_slot(k), 0], H, R

    # -- measurement --------------------------------------------------------------------------
    def _model(self, lag: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h(x) (3,), H (3, DIM), extra noise (3, 3)) of a vest pose measured ``lag`` s before the state
        (negative: after it, a rolling shutter's later rows)."""
        x = self.x[:, 0]
        if lag == 0.0:
            # Shared read-only constants: callers only combine them into new arrays.
            return vest_pose(x), M_VEST, _NO_NOISE
        # Retrodiction: the body runs CTRV backwards; a stationary Gauss-Markov offset is one
        # backwards too (decay a, fresh variance (1 - a^2) F). Ahead, the same model runs forwards.
        back = motion.propagate(x[: motion.DIM], -lag)
        F, Q = self._transition(x, -lag)
        H = np.zeros((3, DIM))
        H[:, : motion.DIM] = F[POSE, : motion.DIM]
        H[:, OFF] = F[OFF, OFF]
        Qb = Q[POSE, POSE] + Q[OFF, OFF]
        return back[POSE] + F[OFF, OFF] @ x[OFF], H, Qb

    def innovation(self, z: np.ndarray, R: np.ndarray, lag: float = 0.0, term: MapTerm | None = None) -> Innovation:
        """Innovation of vest pose ``z`` (3,) with its own covariance ``R`` (3, 3), measured ``lag`` s ago,
        from a sticker whose survey error is ``term`` (None: an exact map)."""
        hx, H, Qb = self._model(lag)
        hx, H, R = self._map_columns(hx, H, R + Qb, term, take=False)
        y = pose_residual(z, hx)
        S = H @ self.P @ H.T + R
        S = 0.5 * (S + S.T)
        return Innovation(y, S, float(y @ np.linalg.solve(S, y)), R)

    def fuse(self, z: np.ndarray, R: np.ndarray, lag: float = 0.0, term: MapTerm | None = None) -> None:
        """Kalman update with one vest pose ``z`` (3,), its own covariance ``R``, ``lag`` s old, from a
        sticker whose survey error is ``term`` (None: an exact map); the sticker takes a slot."""
        hx, H, Qb = self._model(lag)
        hx, H, R = self._map_columns(hx, H, R + Qb, term, take=True)
        self.update(
            np.asarray(z, float).reshape(3, 1),
            lambda _x: H,
            lambda _x: hx.reshape(3, 1),
            R=R,
            residual=pose_residual,
        )
        self._tidy()

    # -- guards -------------------------------------------------------------------------------
    def _tidy(self) -> None:
        """Wrap yaw, clip speed and yaw rate to their limits, keep P symmetric, SPD and capped."""
        cfg = self.cfg
        x = self.x[:, 0]
        # A NaN or an infinity anywhere makes the sum non-finite (the caps keep finite sums finite).
        if not math.isfinite(float(x.sum())):
            raise FloatingPointError("non-finite EKF state")
        x[motion.YAW] = wrap_angle(float(x[motion.YAW]))
        x[OFF.stop - 1] = wrap_angle(float(x[OFF.stop - 1]))
        x[motion.V] = min(max(x[motion.V], cfg.v_min), cfg.v_max)
        x[motion.W] = min(max(x[motion.W], -cfg.w_max), cfg.w_max)
        x[SCALE] = min(max(x[SCALE], -cfg.odometry_scale_max), cfg.odometry_scale_max)
        self.x = x.reshape(DIM, 1)
        P = self.P
        if not math.isfinite(float(P.sum())):
            raise FloatingPointError("non-finite EKF covariance")
        P = sym_spd(P, cfg.min_eig)
        diag = P.diagonal()
        if (diag > self._caps).any():
            # Scaling rows and columns by the same positive factors keeps P SPD (a congruence).
            d = np.sqrt(np.minimum(1.0, self._caps / diag))
            P = P * np.outer(d, d)
            if d[motion.YAW] < 1.0:
                # A heading at its cap is uniform: nothing follows from it. Scaled, its covariances
                # with the yaw rate and the position would keep their correlation at a variance
                # shrunk by d^2, so a fix's heading would set the yaw rate 1/d times what the walk
                # implies (2 rad off a track lost 40 s: a spin at 3 rad/s). Left out instead (a
                # principal submatrix and a positive diagonal: still SPD).
                y = motion.YAW
                P[y, :] = 0.0
                P[:, y] = 0.0
                P[y, y] = self._caps[y]
        self.P = P
