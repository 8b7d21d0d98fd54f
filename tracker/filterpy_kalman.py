"""filterpy's Kalman filters, imported without ``scipy.stats`` until a likelihood is asked for.

Every module of ``filterpy.kalman`` takes one name from ``filterpy.stats``, ``logpdf`` (for the
filters' ``log_likelihood`` and ``likelihood`` properties), and ``filterpy.stats`` imports
``scipy.stats`` at its top for its other functions. With SciPy 1.17 that import costs 0.3-0.4 s of
CPU (it parses hundreds of docstrings to add array-API notes to them), a third of ``tagloc
replay``'s start-up, and the tracker never reads a filterpy likelihood (it gates on its own
innovation, :meth:`tracker.ekf.WalkingEKF.innovation`).

So ``filterpy.kalman`` is imported with a stand-in ``filterpy.stats`` in place whose ``logpdf``
imports the real module on its first call and hands the call on: the filters behave exactly as
filterpy's, likelihoods included. The stand-in is removed from ``sys.modules`` once
``filterpy.kalman`` is imported, so anyone importing ``filterpy.stats`` afterwards gets the real
module. If ``filterpy.stats`` or ``filterpy.kalman`` was imported already, nothing is stood in; if
a later filterpy takes more than ``logpdf`` from it, the import falls back to the plain one.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any


def _real_stats() -> types.ModuleType:
    return importlib.import_module("filterpy.stats")


def _logpdf(*args: Any, **kwargs: Any) -> Any:
    """filterpy.stats.logpdf, imported on first use."""
    return _real_stats().logpdf(*args, **kwargs)


def _import_kalman(offer_logpdf: bool = True) -> types.ModuleType:
    """``filterpy.kalman``, imported with a stand-in ``filterpy.stats`` (offering ``logpdf`` unless
    told not to, for the test of the fallback); if that import fails (a filterpy that takes more
    from ``filterpy.stats``), imported plainly."""
    if "filterpy.stats" in sys.modules or "filterpy.kalman" in sys.modules:
        return importlib.import_module("filterpy.kalman")
    stand_in = types.ModuleType("filterpy.stats", "stand-in while filterpy.kalman imports (tracker.filterpy_kalman)")
    if offer_logpdf:
        stand_in.logpdf = _logpdf  # type: ignore[attr-defined]
    sys.modules["filterpy.stats"] = stand_in
    try:
        return importlib.import_module("filterpy.kalman")
    except ImportError:
        # Forget the half-imported package and import it the plain way, scipy.stats and all.
        for mod in [m for m in sys.modules if m == "filterpy.kalman" or m.startswith("filterpy.kalman.")]:
            del sys.modules[mod]
        if sys.modules.get("filterpy.stats") is stand_in:
            del sys.modules["filterpy.stats"]
        return importlib.import_module("filterpy.kalman")
    finally:
        if sys.modules.get("filterpy.stats") is stand_in:
            del sys.modules["filterpy.stats"]


kalman = _import_kalman()
ExtendedKalmanFilter = kalman.ExtendedKalmanFilter
update = kalman.update

__all__ = ["ExtendedKalmanFilter", "kalman", "update"]
