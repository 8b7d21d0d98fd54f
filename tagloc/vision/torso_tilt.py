"""The torso's absolute pitch and roll between sticker fixes, for the floor odometry's tilt correction.

The floor odometry fits how much the camera's pitch and roll changed between two frames (see
``OdometryConfig.tilt_correction``) and takes the floor motion that change fakes out of the step.
Summed over a gap, those corrections add up to the tilt's change since the gap began, so the
position error they leave is the *lever* (about 1.5-1.9 m of floor per radian at the patch)
times the error of that summed change. Summed per-frame fits random-walk: each fit is
~0.3 degrees off (measured against the true vest tilt on simulated walks, which is as large as
the true per-frame change), so after 5 s the sum is ~5 degrees off, 10-15 cm of floor.

A torso's tilt, though, does not wander: it is a stationary process about upright (the gait's nod
and sway, the lean into turns and with starting and braking, each gone within a second or so).
This module keeps the absolute pitch and roll as two independent scalar Kalman filters:

- the process is Ornstein-Uhlenbeck about a prior mean (pitch: 0; roll: the odometry's lean
  into the turn under way; both plus the operator's own posture, learned from the fixes) with a
  stationary standard deviation ``sigma`` and correlation time ``tau``;
- each frame's fitted change is a measurement of ``theta_k - theta_{k-1}`` (the filter carries the
  previous value alongside for that step);
- a sticker fix measures the absolute tilt outright (the camera's pose from a sticker gives its
  pitch and roll to ~0.15 degrees RMS on simulated walks), anchoring the filter.

The odometry then corrects each step by the *filtered* change, so the corrections over a gap add
up to (estimate - truth) at its end minus the same at its start: bounded by the filter's error
instead of growing with the square root of the number of frames.

Two variances. The filter weighs each fitted change by a constant *design* standard deviation
(the flow's ``tilt_sigma``), which is what keeps the odometry best: weighed by their actual,
change-dependent errors, the estimate leaned on the prior through large changes and lagged them
(see ``FloorFlowConfig.tilt_sigma_rel``). But the variance that design implies is not the
estimate's error: a fit's actual error grows with the change it reports, so the filter's stated
spread between fixes was too narrow, and the tilt gate, which judges each fix's tilt against it,
refused 4.2 % of the fixes within 1 deg of the true tilt with a walker swinging twice as much
(0.8 % with the default walker; 0.1 % if honest). So each axis also carries ``var_true``: the
variance of its actual error, the filter's own gains applied to errors of the measurements'
actual variances (the sensitivity analysis of a filter whose gains are set apart from its
measurements' statistics). The gate judges by it (:meth:`TorsoTilt.predict`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

__all__ = ["TRUNK_TILT_RATE_SIGMA", "TiltAxis", "TorsoTilt"]

# The trunk's pitch and roll rate while walking (rad/s, standard deviation of each). From the gait:
# the trunk nods and sways by 1-2 deg at the step frequency (about 2 Hz), an RMS rate of
# 2 pi f A / sqrt(2) = 8-18 deg/s, and leans into a turn's start and with braking at similar rates
# for a fraction of a second. The simulator's walker: 5-7 deg/s on the field walks, 8-10 deg/s
# swinging twice as much (see ``OdometryConfig.tilt_rate_sigma``). 10 deg/s.
TRUNK_TILT_RATE_SIGMA = math.radians(10.0)


@dataclass
class TiltAxis:
    """One tilt angle's estimate (rad) and variance (rad^2) at time ``t`` (s), about the prior mean
    ``mean`` (rad) in force then; ``posture``: the operator's own offset, learned from the fixes.

    ``var`` is the variance the filter weighs by, from the measurements' *design* variances;
    ``var_true`` that of its actual error, the same gains applied to errors of the measurements'
    *actual* variances where the caller states them (see the module: the two differ on purpose)."""

    sigma: float
    tau: float
    rate_sigma: float = math.inf
    t: float | None = None
    value: float = 0.0
    var: float = 0.0
    var_true: float = 0.0
    mean: float = 0.0
    posture: float = 0.0
    posture_fixes: int = 0

    def _predicted(self, t: float, mean: float) -> tuple[float, float, float, float]:
        """(value, var, var_true, phi) carried from ``self.t`` to ``t`` about the new prior ``mean``.
        ``var_true``'s process increment is no larger than ``rate_sigma`` times the time (the tilt's
        actual change, which is smooth, where the process's own increment grows with the square root
        of the time; see :class:`TorsoTilt`)."""
        if self.t is None:
            return mean + self.posture, self.sigma**2, self.sigma**2, 0.0
        dt = max(t - self.t, 0.0)
        phi = math.exp(-dt / self.tau)
        q = self.sigma**2 * (1.0 - phi * phi)
        q_true = min(q, (self.rate_sigma * dt) ** 2)
        m0, m1 = self.mean + self.posture, mean + self.posture
        return m1 + phi * (self.value - m0), phi * phi * self.var + q, phi * phi * self.var_true + q_true, phi

    def step(
        self, t: float, mean: float, change: float | None, change_var: float, change_var_true: float | None = None
    ) -> float:
        """Move to time ``t`` (s) with prior ``mean`` (rad); fuse the measured ``change`` (rad) since
        the last time (None: none measured) of design variance ``change_var`` and actual variance
        ``change_var_true`` (None: the design's). Returns the estimated change (rad)."""
        before = self.value if self.t is not None else mean + self.posture
        v1, p1, pt, phi = self._predicted(t, mean)
        if change is not None and self.t is not None:
            # Joint Gaussian of (theta_t, theta_before): cov(theta_t, theta_before) = phi var.
            c = phi * self.var
            s = p1 - 2.0 * c + self.var + change_var
            gain = (p1 - c) / s
            v1 += gain * (change - (v1 - before))
            p1 -= gain * (p1 - c)
            # The new error is (1 - gain) e_t + gain e_before + gain v (e: estimate - truth before
            # the fit, v: the fit's error), with cov(e_t, e_before) = phi var_true.
            r = change_var if change_var_true is None else change_var_true
            pt = (
                (1.0 - gain) ** 2 * pt
                + gain * gain * (self.var_true + r)
                + 2.0 * gain * (1.0 - gain) * phi * self.var_true
            )
        self.t, self.value, self.var, self.var_true, self.mean = t, v1, max(p1, 0.0), max(pt, 0.0), mean
        return v1 - before

    def rebase(self, mean: float) -> None:
        """Take ``mean`` (rad) as the prior mean in force since the last time: the estimate keeps its
        value (the angle itself) and its deviation from the prior becomes the one from ``mean``."""
        self.mean = float(mean)

    def anchor(
        self, t: float, mean: float, measured: float, measured_var: float, posture_count: int, posture_prior: int
    ) -> None:
        """Fuse an absolute measurement ``measured`` (rad, variance ``measured_var``) at time ``t``;
        the posture offset averages the fixes' departures from the prior mean, shrunk towards 0
        as if ``posture_prior`` upright fixes came first, over the last ``posture_count`` or so
        (0: no posture offset)."""
        v1, p1, pt, _ = self._predicted(t, mean)
        gain = p1 / (p1 + measured_var)
        self.var_true = (1.0 - gain) ** 2 * pt + gain * gain * measured_var
        self.t, self.value, self.var, self.mean = t, v1 + gain * (measured - v1), (1.0 - gain) * p1, mean
        if posture_count > 0:
            self.posture_fixes = min(self.posture_fixes + 1, posture_count)
            self.posture += (measured - mean - self.posture) / (self.posture_fixes + posture_prior)


@dataclass
class TorsoTilt:
    """The torso's pitch and roll (rad) off the rig's nominal pose, between and at sticker fixes.

    ``sigma_pitch``, ``sigma_roll``: stationary standard deviations about the prior mean;
    ``tau``: correlation time (s); ``fit_sigma``: one frame's fitted change; ``anchor_sigma``: a
    sticker fix's tilt; ``posture_fixes``: how many fixes the operator's posture offset averages,
    ``posture_prior``: as if that many upright fixes came first (one odd fix cannot set it);
    ``rate_sigma``: the tilt's actual rate (rad/s, standard deviation), which bounds how far the
    stated variance (``var_true``) grows over a short time. The Ornstein-Uhlenbeck process the
    filter weighs by changes by sigma sqrt(2 dt / tau) over a short dt (0.77 deg in a frame at
    3 deg and 1 s), a real trunk's tilt by its rate times dt (a third of that): the process's
    increment keeps the fits followed closely, but as the spread of a prediction a frame ahead
    (the gate's in live's order, before the frame's odometry step) it was 2.4 times the actual
    error. Infinite: no bound.
    """

    sigma_pitch: float
    sigma_roll: float
    tau: float
    fit_sigma: float
    anchor_sigma: float
    posture_fixes: int
    posture_prior: int = 30
    rate_sigma: float = math.inf
    pitch: TiltAxis = field(init=False)
    roll: TiltAxis = field(init=False)

    def __post_init__(self) -> None:
        self.pitch = TiltAxis(self.sigma_pitch, self.tau, self.rate_sigma)
        self.roll = TiltAxis(self.sigma_roll, self.tau, self.rate_sigma)

    def step(
        self,
        t: float,
        lean_roll: float,
        d_pitch: float | None,
        d_roll: float | None,
        fit_sigma: float | None = None,
        fit_sigma_true: tuple[float, float] | None = None,
    ) -> tuple[float, float]:
        """Advance to ``t`` with the lean's roll ``lean_roll`` (rad) as the roll's prior and the
        fitted changes (rad; None: not fitted), weighed by the design standard deviation
        ``fit_sigma`` (rad; None: the configured ``fit_sigma``); ``fit_sigma_true``: the fits'
        actual (pitch, roll) standard deviations (rad; None: the design's), which only the stated
        variance (``var_true``) follows. Returns the estimated (pitch, roll) changes."""
        r = (self.fit_sigma if fit_sigma is None else fit_sigma) ** 2
        rp, rr = (None, None) if fit_sigma_true is None else (fit_sigma_true[0] ** 2, fit_sigma_true[1] ** 2)
        return self.pitch.step(t, 0.0, d_pitch, r, rp), self.roll.step(t, lean_roll, d_roll, r, rr)

    def predict(self, t: float, lean_roll: float) -> tuple[float, float, float, float]:
        """The expected (pitch, roll) (rad) at time ``t`` and the variances (rad^2) of their actual
        errors (``var_true``), without changing the estimate (before the first step or anchor: the
        prior)."""
        p, _, vp, _ = self.pitch._predicted(t, 0.0)
        r, _, vr, _ = self.roll._predicted(t, lean_roll)
        return p, r, vp, vr

    def consistent(
        self, t: float, lean_roll: float, pitch: float, roll: float, chi2: float, prior_sigma: float
    ) -> tuple[bool, float]:
        """Whether a measured (pitch, roll) (rad) at ``t`` is within ``chi2`` (squared Mahalanobis
        distance, 2 DoF) of the prediction, counting the measurement's own ``anchor_sigma``; and
        the distance. Before any estimate, the prior judges: within ``prior_sigma`` (rad) of the
        posture, and of the lean model's roll with half that lean again as its own uncertainty
        (the model's first step can be far off)."""
        if self.pitch.t is None or self.roll.t is None:
            v = prior_sigma**2
            p, r = self.pitch.posture, self.roll.posture + lean_roll
            vp, vr = v, v + (0.5 * lean_roll) ** 2
        else:
            p, r, vp, vr = self.predict(t, lean_roll)
        m = self.anchor_sigma**2
        d2 = (pitch - p) ** 2 / (vp + m) + (roll - r) ** 2 / (vr + m)
        return d2 <= chi2, d2

    def anchor(self, t: float, lean_roll: float, pitch: float, roll: float) -> None:
        """Fuse a sticker fix's measured (pitch, roll) (rad) at time ``t``."""
        r = self.anchor_sigma**2
        self.pitch.anchor(t, 0.0, pitch, r, self.posture_fixes, self.posture_prior)
        self.roll.anchor(t, lean_roll, roll, r, self.posture_fixes, self.posture_prior)

    def reset(self) -> None:
        """Forget the estimate (the posture learned so far is kept)."""
        for axis in (self.pitch, self.roll):
            axis.t, axis.value, axis.var, axis.var_true, axis.mean = None, 0.0, 0.0, 0.0, 0.0
