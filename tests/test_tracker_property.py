"""Property test of the tracker's safety invariants: whatever the sequence of frame times (equal,
backwards, tiny or huge gaps), fixes (late, vague, near-singular, malformed, of any source) and
odometry steps (NaN, enormous, zero or huge covariance) of several cameras, every published output
is finite with a symmetric positive definite covariance, its stamp never goes back, a TRACKING one
is within ``lost_sigma_m`` and ``lost_after_s`` of its last fix, and a prediction never makes the
pose more certain (found by a review: a vague fix made a track TRACKING; a late fix into a track
of unknown heading shrank the covariance on the next frame)."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tagloc.core.types import IdSource, PoseFix, SurveyPrior, TrackerOutput, TrackState
from tagloc.vision.odometry import OdometryStep
from tracker.config import TrackerConfig
from tracker.ekf import largest_eig_2x2
from tracker.tracker import Tracker

COVS = {
    "good": np.diag([1e-4, 1e-4, 1e-4]),
    "tiny": np.diag([1e-12] * 3),
    "vague": np.diag([0.8**2, 0.8**2, 0.01]),
    "huge": np.diag([1e11, 1e11, 1e3]),
    "singular": np.array([[1e-4, 1e-4, 0], [1e-4, 1e-4, 0], [0, 0, 1e-4]]),
    "negative": -np.eye(3) * 1e-4,
    "skewed": np.diag([1e-8, 4.0, 1e-4]),
}
STEPS = {
    "still": (np.zeros(3), np.eye(3) * 1e-6),
    "walk": (np.array([0.04, 0.0, 0.01]), np.eye(3) * 1e-6),
    "nan": (np.array([np.nan, 0.0, 0.0]), np.eye(3) * 1e-6),
    "enormous": (np.array([1e200, 0.0, 0.0]), np.eye(3) * 1e-6),
    "exact": (np.zeros(3), np.zeros((3, 3))),
    "vague": (np.zeros(3), np.eye(3) * 1e200),
}
OPS = st.lists(
    st.tuples(
        st.sampled_from(["predict", "fix", "odometry", "ahead"]),
        st.sampled_from([0.0, 1e-9, 1 / 30, 1 / 30, 0.1, 0.35, 2.0, 11.0, -1 / 30, -0.3, 1e5]),
        st.sampled_from([0, 1]),  # camera
        st.sampled_from(sorted(COVS)),
        st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-4, 4)),
        st.sampled_from([IdSource.DECODED, IdSource.DECODED, IdSource.CHECKED, IdSource.ORB]),
        st.integers(1, 6),  # sticker
        st.sampled_from([0.0, 0.0, 0.05, 0.2, 0.3]),  # how late a fix is
        st.sampled_from(sorted(STEPS)),
    ),
    min_size=5,
    max_size=40,
)


def _check(out: TrackerOutput, cfg: TrackerConfig) -> None:
    assert np.all(np.isfinite(out.pose)) and np.all(np.isfinite(out.cov)) and math.isfinite(out.t)
    np.testing.assert_allclose(out.cov, out.cov.T, atol=1e-12 * max(1.0, float(np.abs(out.cov).max())))
    assert np.linalg.eigvalsh(out.cov).min() > 0
    assert out.since_fix >= 0
    if out.state is TrackState.TRACKING:
        assert math.sqrt(largest_eig_2x2(out.cov)) <= cfg.lost_sigma_m * (1 + 1e-6)
        assert out.since_fix <= cfg.lost_after_s


def _sigma(out: TrackerOutput) -> float:
    return math.sqrt(largest_eig_2x2(out.cov))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(OPS)
def test_published_outputs_keep_the_safety_invariants(ops):
    tr = Tracker()
    cfg = tr.config
    tr.predict(0.0, 0)
    tr.update([PoseFix(np.eye(4), np.zeros(3), COVS["good"], 0.4)], 1, IdSource.DECODED, 0.0)
    t, frames, last_stamp = 0.0, {}, -math.inf
    for op, dt, camera, cov, pose, source, sticker, late, step in ops:
        if op == "predict":
            before = tr.output()
            tr.predict(t + dt, camera)
            t = max(t, t + dt)
            frames[camera] = tr.time
            after = tr.output()
            # No measurement, no sharper pose (below the caps, which bound what hours lost claim).
            if TrackState.INITIALISING not in (before.state, after.state) and _sigma(before) < 100.0:
                assert _sigma(after) >= _sigma(before) * (1 - 1e-4)
        elif op == "fix":
            fix = PoseFix(np.eye(4), np.array(pose), COVS[cov], 0.4)
            survey = SurveyPrior(np.array(pose[:2]), 0.01, 0.02)
            tr.update([fix], sticker, source, tr.time - late, survey)
        elif op == "odometry" and camera in frames and tr.time > frames[camera]:
            delta, C = STEPS[step]
            tr.update_odometry(OdometryStep(frames[camera], tr.time, delta, C, 0.5), camera)
        elif op == "ahead":
            now, ahead = tr.output(), tr.output(tr.time + abs(dt))
            _check(ahead, cfg)
            if now.state is not TrackState.INITIALISING and _sigma(now) < 100.0:
                assert _sigma(ahead) >= _sigma(now) * (1 - 1e-4)
        out = tr.output()
        _check(out, cfg)
        assert out.t >= last_stamp
        last_stamp = out.t
    assert tr.stats["numeric_errors"] == 0
