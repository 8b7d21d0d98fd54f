"""The tracker imports filterpy's Kalman filters without scipy.stats, and they still behave as filterpy's."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _run(code: str) -> str:
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True, check=False
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_the_tracker_does_not_import_scipy_stats_or_ndimage():
    out = _run(
        """
        import sys
        import tracker.tracker
        from tagloc.pipeline.localiser import Localiser
        print(*(m in sys.modules for m in ("scipy.stats", "filterpy.stats", "scipy.ndimage", "filterpy.discrete_bayes")))
        """
    )
    assert out.split() == ["False"] * 4


def test_filterpy_discrete_bayes_is_filterpys_when_used():
    """Through the package's attribute (what filterpy's own ``__init__`` bound) and by a later import,
    the histogram filter is the real one."""
    out = _run(
        """
        import sys
        import numpy as np
        import tracker.filterpy_kalman
        import filterpy
        moved = filterpy.discrete_bayes.predict(np.array([0.0, 1.0, 0.0, 0.0]), 1, np.array([1.0]))
        import filterpy.discrete_bayes as db
        print(moved.tolist() == [0.0, 0.0, 1.0, 0.0], "scipy.ndimage" in sys.modules, db.predict is filterpy.discrete_bayes.predict)
        """
    )
    assert out.split() == ["True", "True", "True"]


def test_filterpy_likelihoods_still_come_from_filterpy_stats():
    """The stand-in's logpdf hands the call to the real filterpy.stats (imported then), and afterwards
    ``import filterpy.stats`` is the real module."""
    out = _run(
        """
        import math, sys
        import numpy as np
        from tracker.filterpy_kalman import ExtendedKalmanFilter
        ekf = ExtendedKalmanFilter(dim_x=1, dim_z=1)
        ekf.x = np.array([[0.0]]); ekf.P = np.array([[2.0]]); ekf.R = np.array([[1.0]])
        ekf.update(np.array([[1.5]]), HJacobian=lambda x: np.array([[1.0]]), Hx=lambda x: x)
        ll = ekf.log_likelihood  # innovation 1.5, its variance 2 + 1
        expected = -0.5 * (math.log(2 * math.pi * 3.0) + 1.5**2 / 3.0)
        import filterpy.stats
        print(abs(ll - expected) < 1e-9, "scipy.stats" in sys.modules, hasattr(filterpy.stats, "multivariate_gaussian"))
        """
    )
    assert out.split() == ["True", "True", "True"]


def test_a_filterpy_that_needs_more_of_filterpy_stats_is_imported_plainly():
    """A stand-in without ``logpdf`` makes filterpy.kalman's import fail, as a filterpy taking other
    names would: the import falls back to the real filterpy.stats (scipy.stats and all)."""
    out = _run(
        """
        import importlib, sys
        import tracker.filterpy_kalman as fk
        for m in [m for m in sys.modules if m.startswith("filterpy")]:
            del sys.modules[m]
        kalman = fk._import_kalman(offer_logpdf=False)
        import filterpy.stats
        print(hasattr(kalman, "ExtendedKalmanFilter"), hasattr(filterpy.stats, "multivariate_gaussian"))
        """
    )
    assert out.split() == ["True", "True"]
