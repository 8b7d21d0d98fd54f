"""filterpy's Kalman filters, imported without ``scipy.stats`` or ``scipy.ndimage`` until asked for.

Importing ``filterpy.kalman`` runs the ``filterpy`` package's ``__init__``, which imports every
filterpy subpackage. Two of them cost a third of ``tagloc replay``'s start-up, and the tracker uses
neither:

- ``filterpy.stats`` imports ``scipy.stats`` at its top (0.3-1.0 s of CPU with SciPy 1.17: it
  parses hundreds of docstrings to add array-API notes to them). Every module of ``filterpy.kalman``
  takes one name from it, ``logpdf``, for the filters' ``log_likelihood`` and ``likelihood``
  properties; the tracker never reads a filterpy likelihood (it gates on its own innovation,
  :meth:`tracker.ekf.WalkingEKF.innovation`).
- ``filterpy.discrete_bayes`` imports ``scipy.ndimage`` (0.12-0.19 s here, the same docstring
  work) for the histogram filter.

So ``filterpy.kalman`` is imported with a stand-in for each in ``sys.modules``: a module that
imports the real one on first use of any of its names and hands the name on (the stats stand-in
holds a ``logpdf`` of its own that does the same on its first call, as ``filterpy.kalman`` takes it
by name while importing). The filters behave exactly as filterpy's, likelihoods included. The
stand-ins leave ``sys.modules`` once ``filterpy.kalman`` is imported, so ``import filterpy.stats``
or ``import filterpy.discrete_bayes`` afterwards gives the real module; ``filterpy.stats.X`` on the
package without that import also works, through the stand-in. If either was imported already, or
``filterpy.kalman`` was, nothing is stood in; if a later filterpy takes more than ``logpdf`` from
``filterpy.stats`` while importing, the import falls back to the plain one.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

#: The filterpy subpackages stood in while ``filterpy.kalman`` imports (see the module docstring).
STOOD_IN = ("filterpy.stats", "filterpy.discrete_bayes")


def _logpdf(*args: Any, **kwargs: Any) -> Any:
    """filterpy.stats.logpdf, imported on first use."""
    return importlib.import_module("filterpy.stats").logpdf(*args, **kwargs)


def _stand_in(name: str, offer_logpdf: bool) -> types.ModuleType:
    """A module standing in for ``name``: any name taken from it comes from the real module, imported
    then (``offer_logpdf``: the stats stand-in's own lazy ``logpdf``, taken while filterpy imports)."""
    stand_in = types.ModuleType(name, f"stand-in for {name} while filterpy.kalman imports (tracker.filterpy_kalman)")

    def forward(attr: str) -> Any:
        if sys.modules.get(name) is stand_in:
            # Taken while filterpy.kalman imports: not offered, so that import fails and falls back
            # to the plain one (see _import_kalman).
            raise AttributeError(attr)
        return getattr(importlib.import_module(name), attr)

    stand_in.__getattr__ = forward  # type: ignore[method-assign]  # PEP 562: names not defined here
    if offer_logpdf and name == "filterpy.stats":
        stand_in.logpdf = _logpdf  # type: ignore[attr-defined]
    return stand_in


def _import_kalman(offer_logpdf: bool = True) -> types.ModuleType:
    """``filterpy.kalman``, imported with stand-ins for :data:`STOOD_IN` (the stats one offering
    ``logpdf`` unless told not to, for the test of the fallback); if that import fails (a filterpy
    that takes more from ``filterpy.stats``), imported plainly."""
    if any(m in sys.modules for m in (*STOOD_IN, "filterpy.kalman")):
        return importlib.import_module("filterpy.kalman")
    stand_ins = {name: _stand_in(name, offer_logpdf) for name in STOOD_IN}
    sys.modules.update(stand_ins)
    try:
        return importlib.import_module("filterpy.kalman")
    except ImportError:
        # Forget the half-imported package and import it the plain way, scipy.stats and all.
        for mod in [m for m in sys.modules if m == "filterpy" or m.startswith("filterpy.")]:
            del sys.modules[mod]
        return importlib.import_module("filterpy.kalman")
    finally:
        for name, stand_in in stand_ins.items():
            if sys.modules.get(name) is stand_in:
                del sys.modules[name]


kalman = _import_kalman()
ExtendedKalmanFilter = kalman.ExtendedKalmanFilter
update = kalman.update

__all__ = ["ExtendedKalmanFilter", "kalman", "update"]
