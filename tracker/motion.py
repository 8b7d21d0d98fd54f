"""Walking-motion model on the floor plane: constant turn rate and velocity (CTRV).

State (5,): ``x, y`` (m, world), ``yaw`` (rad, heading of body +x), ``v`` (m/s, forward speed),
``w`` (rad/s, yaw rate). Over a step of ``dt`` seconds the walker moves on a circular arc::

    phi = w dt,  a = yaw + phi/2,  g = sinc(phi/2) = sin(phi/2) / (phi/2)
    x' = x + v dt g cos(a)
    y' = y + v dt g sin(a)
    yaw' = yaw + phi,  v' = v,  w' = w

This is the textbook form ``x + v/w (sin(yaw + phi) - sin(yaw))`` rewritten with
``sin(b) - sin(c) = 2 cos((b+c)/2) sin((b-c)/2)``: the chord of the arc has length ``v dt g`` and
points along the mid-arc heading ``a``. It has no division by ``w``, so w -> 0 (straight walking)
needs no special case. Negative ``dt`` runs the model backwards (used to retrodict late fixes).

Jacobian ``F = d state' / d state`` (identity plus), with ``L = v dt g`` and
``g' = d sinc(u)/du`` at ``u = phi/2`` (``da/dw = dt/2``, ``dg/dw = g' dt/2``)::

    dx'/dyaw = -L sin(a)                 dy'/dyaw =  L cos(a)
    dx'/dv   = dt g cos(a)               dy'/dv   = dt g sin(a)
    dx'/dw   = v dt^2/2 (g' cos(a) - g sin(a))
    dy'/dw   = v dt^2/2 (g' sin(a) + g cos(a))
    dyaw'/dw = dt

Process noise: white longitudinal acceleration (PSD ``q_a``), white yaw acceleration (PSD
``q_alpha``) and a white lateral velocity (PSD ``q_lat``, sidestepping). Integrating each over the
step gives the usual continuous-white-noise blocks, mapped onto x, y through the mid-arc heading
(unit vectors ``u`` forward and ``n`` left)::

    Q[xy, xy] = q_a dt^3/3 u u^T + q_lat |dt| n n^T      Q[xy, v] = q_a dt^2/2 u   Q[v, v] = q_a |dt|
    Q[yaw, yaw] = q_alpha |dt|^3/3    Q[yaw, w] = q_alpha dt^2/2    Q[w, w] = q_alpha |dt|

(with the sign of dt on the odd powers' cross terms when running backwards). Yaw-acceleration
noise leaking into position within one step is second order in dt and left out; it enters over
successive steps through F, which is why long predictions are split into short steps.
"""

from __future__ import annotations

import math

import numpy as np

X, Y, YAW, V, W = range(5)
DIM = 5


def sinc(u: float) -> float:
    """sin(u)/u, 1 at u = 0."""
    return math.sin(u) / u if abs(u) > 1e-6 else 1.0 - u * u / 6.0


def dsinc(u: float) -> float:
    """Derivative of sin(u)/u; the series near 0 avoids 0/0 (error < 1e-12 below |u| = 1e-2)."""
    if abs(u) < 1e-2:
        u2 = u * u
        return u * (-1.0 / 3.0 + u2 / 30.0 - u2 * u2 / 840.0)
    return (u * math.cos(u) - math.sin(u)) / (u * u)


def propagate(state: np.ndarray, dt: float) -> np.ndarray:
    """State (5,) after ``dt`` seconds of constant turn rate and speed (yaw not wrapped)."""
    x, y, yaw, v, w = np.asarray(state, float).ravel().tolist()
    half = 0.5 * w * dt
    a = yaw + half
    chord = v * dt * sinc(half)
    return np.array([x + chord * math.cos(a), y + chord * math.sin(a), yaw + 2.0 * half, v, w])


def jacobian(state: np.ndarray, dt: float) -> np.ndarray:
    """``F`` (5, 5): derivative of :func:`propagate` with respect to the state (see module doc)."""
    _, _, yaw, v, w = np.asarray(state, float).ravel().tolist()
    half = 0.5 * w * dt
    a = yaw + half
    ca, sa = math.cos(a), math.sin(a)
    g, dg = sinc(half), dsinc(half)
    chord = v * dt * g
    k = 0.5 * v * dt * dt
    F = np.eye(DIM)
    F[X, YAW], F[Y, YAW] = -chord * sa, chord * ca
    F[X, V], F[Y, V] = dt * g * ca, dt * g * sa
    F[X, W], F[Y, W] = k * (dg * ca - g * sa), k * (dg * sa + g * ca)
    F[YAW, W] = dt
    return F


def process_noise(
    state: np.ndarray, dt: float, accel_psd: float, yaw_accel_psd: float, lateral_psd: float
) -> np.ndarray:
    """``Q`` (5, 5) accumulated over ``dt`` (see module doc); symmetric positive semi-definite."""
    _, _, yaw, _, w = np.asarray(state, float).ravel().tolist()
    a = yaw + 0.5 * w * dt
    u = np.array([math.cos(a), math.sin(a)])
    n = np.array([-u[1], u[0]])
    h = abs(dt)
    Q = np.zeros((DIM, DIM))
    Q[:2, :2] = accel_psd * h**3 / 3.0 * np.outer(u, u) + lateral_psd * h * np.outer(n, n)
    Q[:2, V] = Q[V, :2] = accel_psd * dt * h / 2.0 * u
    Q[V, V] = accel_psd * h
    Q[YAW, YAW] = yaw_accel_psd * h**3 / 3.0
    Q[YAW, W] = Q[W, YAW] = yaw_accel_psd * dt * h / 2.0
    Q[W, W] = yaw_accel_psd * h
    return Q
