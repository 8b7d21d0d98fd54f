"""Stochastic clones for floor odometry with one or several cameras.

A floor-odometry step of a camera measures the vest's motion from that camera's previous frame to
its current one. The filter has moved on since the previous frame (other cameras' frames, fixes,
other steps), so the odometry pose there is kept as a *clone*: a copy of ``M x`` (3,) at that time,
``M`` being :data:`tracker.ekf.M_ODO`, with its covariance and, what makes a later step exact, its
cross-covariance with the moving state. The clones of all cameras are held jointly, as one Gaussian
with the state::

    [x (DIM,), c_1 (3,), ..., c_k (3,)]     covariance [[P, X], [X^T, Pc]]

with ``X`` (DIM, 3k) the cross-covariance and ``Pc`` (3k, 3k) the clones' own covariance (the
clones of two cameras are correlated through the state they were both taken from). Each filter step
keeps that joint Gaussian exact:

- prediction ``x <- f(x) + w``: a clone is a fixed past value, so ``X <- F X`` (``w`` is
  independent of the past);
- a fix (a measurement of the state alone): each clone moves with its regression on the state,
  ``B = X^T P0^-1``: ``c += B dx``, ``Pc -= B (P0 - P1) B^T``, ``X = P1 B^T``; this equals the joint
  Kalman update over [state, clones] whatever the fix's model (linear Gaussian conditioning), so the
  fix path needs to know nothing of the clones;
- an odometry step (a measurement of the state and one clone): a Kalman update over the joint
  vector (:meth:`CloneSet.joint`, :meth:`CloneSet.absorb`).

Everything here is generic in the state's dimension (``P0.shape[0]``).
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from tagloc.core.geometry import wrap_angle
from tracker.ekf import sym_spd


class CloneSet:
    """The odometry clones of several cameras, jointly Gaussian with the filter's state.

    Attributes:
        keys: the camera of each clone (any hashable key; None for an unnamed single camera).
        t0: (k,) time of each clone, s.
        x: (3k,) the clones' odometry poses (x, y, yaw), stacked.
        P: (3k, 3k) their joint covariance.
        X: (n, 3k) their cross-covariance with the state (n = the state's dimension).
    """

    def __init__(self, dim: int) -> None:
        self.dim = int(dim)
        self.clear()

    def clear(self) -> None:
        """Drop every clone (a restarted or forgotten track has no past to measure from)."""
        self.keys: list[Hashable] = []
        self.t0 = np.zeros(0)
        self.x = np.zeros(0)
        self.P = np.zeros((0, 0))
        self.X = np.zeros((self.dim, 0))

    def copy(self) -> CloneSet:
        """An independent copy."""
        other = CloneSet(self.dim)
        other.keys = list(self.keys)
        other.t0, other.x, other.P, other.X = self.t0.copy(), self.x.copy(), self.P.copy(), self.X.copy()
        return other

    def __len__(self) -> int:
        return len(self.keys)

    def __contains__(self, key: Hashable) -> bool:
        return key in self.keys

    def time(self, key: Hashable) -> float | None:
        """Time of ``key``'s clone, or None."""
        return float(self.t0[self.keys.index(key)]) if key in self.keys else None

    def _keep(self, idx: Sequence[int]) -> None:
        cols = np.concatenate([np.arange(3 * i, 3 * i + 3) for i in idx]) if idx else np.zeros(0, int)
        self.keys = [self.keys[i] for i in idx]
        self.t0 = self.t0[list(idx)]
        self.x = self.x[cols]
        self.P = self.P[np.ix_(cols, cols)]
        self.X = self.X[:, cols]

    def drop(self, key: Hashable) -> None:
        """Drop ``key``'s clone (its step was fused: its frames must not be used again)."""
        if key in self.keys:
            i = self.keys.index(key)
            self._keep([j for j in range(len(self.keys)) if j != i])

    def advance(
        self,
        J: np.ndarray,
        x0: np.ndarray,
        P0: np.ndarray,
        M: np.ndarray,
        t0: float,
        t: float,
        new_keys: Iterable[Hashable],
        max_age: float,
    ) -> None:
        """The filter just predicted from (``x0`` (n,), ``P0`` (n, n)) at ``t0`` to ``t`` with Jacobian
        ``J`` (n, n): carry the clones (``X <- J X``), drop those older than ``max_age`` at ``t``,
        and clone ``M x0`` (M (3, n)) for each of ``new_keys`` (the cameras whose frames were at
        ``t0``; a camera's earlier clone is replaced)."""
        new_keys = list(dict.fromkeys(new_keys))
        self._keep([i for i, k in enumerate(self.keys) if t - self.t0[i] <= max_age and k not in new_keys])
        if not new_keys:
            self.X = J @ self.X
            return
        # The new clones' covariance with the old ones is through the state at t0: M X (before J).
        old_new = (M @ self.X).T  # (3k, 3)
        c = M @ x0
        Pcc = M @ P0 @ M.T
        cross_new = (J @ P0) @ M.T
        self.X = J @ self.X
        for key in new_keys:
            k = len(self.keys)
            P = np.zeros((3 * k + 3, 3 * k + 3))
            P[: 3 * k, : 3 * k] = self.P
            P[3 * k :, 3 * k :] = Pcc
            col = np.vstack([old_new, np.tile(Pcc, (k - old_new.shape[0] // 3, 1))]) if k else np.zeros((0, 3))
            P[: 3 * k, 3 * k :] = col
            P[3 * k :, : 3 * k] = col.T
            self.P = P
            self.keys.append(key)
            self.t0 = np.append(self.t0, t0)
            self.x = np.concatenate((self.x, c))
            self.X = np.hstack((self.X, cross_new))

    def carry(
        self,
        x0: np.ndarray,
        P0: np.ndarray,
        x1: np.ndarray,
        P1: np.ndarray,
        angles: Sequence[int],
        min_eig: float,
    ) -> bool:
        """Update the clones for a measurement of the state alone that took it from (``x0``, ``P0``)
        to (``x1``, ``P1``); ``angles``: indices of the state's angles (their change is wrapped).
        False (and the clones dropped) when ``P0`` is not positive definite."""
        if not self.keys:
            return True
        try:
            factor = cho_factor(P0)
        except (np.linalg.LinAlgError, ValueError):
            self.clear()
            return False
        dx = np.asarray(x1, float) - np.asarray(x0, float)
        for i in angles:
            dx[i] = wrap_angle(float(dx[i]))
        Bt = cho_solve(factor, self.X)  # (n, 3k) = B^T
        self.x = self.x + Bt.T @ dx
        self.x[2::3] = wrap_angle(self.x[2::3])
        self.P = _floored(self.P - Bt.T @ (P0 - P1) @ Bt, min_eig)
        self.X = P1 @ Bt
        return True

    def decorrelate(self, rows: slice) -> None:
        """The state's entries ``rows`` were just replaced by a new state independent of the past (a
        map-error slot given to another sticker): no clone is correlated with them."""
        self.X[rows, :] = 0.0

    def joint(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The joint mean (n + 3k,) and covariance of [state, clones] (the clones in ``keys`` order)."""
        n = len(x)
        Pj = np.zeros((n + len(self.x), n + len(self.x)))
        Pj[:n, :n] = P
        Pj[n:, n:] = self.P
        Pj[:n, n:] = self.X
        Pj[n:, :n] = self.X.T
        return np.concatenate((x, self.x)), Pj

    def absorb(self, xa: np.ndarray, Pa: np.ndarray) -> None:
        """Take the clones' part of a joint posterior (from :meth:`joint`'s layout)."""
        n = self.dim
        self.x = np.asarray(xa[n:], float).copy()
        self.x[2::3] = wrap_angle(self.x[2::3])
        P = Pa[n:, n:]
        self.P = 0.5 * (P + P.T)
        self.X = Pa[:n, n:].copy()


def _floored(C: np.ndarray, min_eig: float) -> np.ndarray:
    """``C`` symmetrised, eigenvalues floored at ``min_eig`` (the subtraction may round below zero)."""
    if not len(C):
        return C
    return sym_spd(C, min_eig)
