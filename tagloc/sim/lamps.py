"""Overhead lamps on a grid, and the shadow the operator's own body casts under them.

A warehouse floor is lit by high-bay luminaires on a regular grid (typically 6-8 m apart, 8-12 m
up). The vest camera looks at the floor a few tens of centimetres to two metres ahead of the chest,
and a lamp behind the operator throws the body's shadow forward into that view. The shadow moves
with the operator (the lamps do not), so to the camera it is a dark region that stays nearly still
while the floor streams past: the one pattern that pulls an optical-flow odometry towards zero.

Model (all lengths in metres, world frame, floor at z = 0):

* **Luminaires**: squares of side ``size_m`` at height ``height_m`` on a square grid of pitch
  ``spacing_m`` (its offset drawn from the seed), each a Lambertian emitter facing down, intensity
  ``I0 cos(theta)``. The illuminance one gives at a floor point at horizontal distance ``r`` is
  ``I0 cos^4(theta) / h^2`` with ``cos(theta) = h / sqrt(h^2 + r^2)`` (one cosine from the emitter,
  one from the floor's incidence, two from the inverse square of the slant distance). Lamps
  further than ``reach`` heights away are left out (cos^4 < 1 % of the lamp overhead).
* **Body**: vertical round segments standing on the floor about the torso's axis, ``axis_behind_m``
  behind the vest point (the rig is on the chest): two legs (``leg_radius_m`` each, ``leg_gap_m``
  apart, up to ``hip_m``), the torso (``torso_radius_m``, half the shoulder breadth, up to
  ``shoulder_m``) and the head (``head_radius_m``, up to ``stature_m``). The arms and feet are left
  out (at 65 degrees down and leaning forward the camera would see its wearer's toes; not
  modelled). The legs end 5 cm behind the vest point, out of a camera's view unless it looks
  behind its own vertical.
* **Penumbra**: a luminaire is not a point. Seen from a floor point, its rays fill a cone with the
  point at its apex; a fraction ``s`` of the way up to the lamp the cone is ``s * size_m / 2`` wide
  (half-width). The body's edge is taken as a straight edge across that cone at its closest approach
  to the ray, and the lamp's visible share is that of a disc cut by a chord. On the floor, the
  penumbra of the head's shadow (s ~ 0.2 under a 9 m lamp) is about 14 cm wide, that of the
  shoulders about 11 cm.

The illuminance is normalised so that the unshadowed floor averages 1 over a grid cell: the session's
``lux`` is the mean illuminance, as a light meter survey quotes it. With the defaults the grid itself
varies by +-1 %, and a lamp behind the operator takes 5-15 % of the light from its shadow.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tagloc.core.errors import InputError

#: The body's vertical axis lies this far behind a chest-mounted vest point (m): about half the
#: torso's 0.2-0.25 m depth. The shadow's body and the legs (:mod:`tagloc.sim.legs`) stand on it.
BODY_AXIS_BEHIND_M = 0.12


@dataclass(frozen=True)
class LampConfig:
    """The lamp grid and the operator's body as an occluder (see the module docstring).

    Attributes:
        spacing_m: pitch of the square lamp grid (high-bay warehouses: 6-8 m).
        height_m: luminaire height above the floor (8-12 m under racks of 6-10 m).
        size_m: side of a luminaire's emitting square (LED high-bay panels 0.4-0.6 m).
        reach: lamps further than ``reach * height_m`` away horizontally are left out.
        axis_behind_m: the body's vertical axis lies this far behind the vest point (about half
            the torso's 0.2-0.25 m depth).
        leg_radius_m, leg_gap_m, hip_m: each leg's radius, the distance between the legs' axes,
            and their top.
        torso_radius_m, shoulder_m: the torso's radius (half the shoulder breadth, 0.40-0.46 m for
            adults) and its top.
        head_radius_m, stature_m: the head's radius and the top of the head.
    """

    spacing_m: float = 6.0
    height_m: float = 9.0
    size_m: float = 0.6
    reach: float = 3.0
    axis_behind_m: float = BODY_AXIS_BEHIND_M
    leg_radius_m: float = 0.07
    leg_gap_m: float = 0.2
    hip_m: float = 0.9
    torso_radius_m: float = 0.21
    shoulder_m: float = 1.45
    head_radius_m: float = 0.09
    stature_m: float = 1.75

    def __post_init__(self) -> None:
        heights = self.height_m > self.stature_m > self.shoulder_m > self.hip_m > 0
        if not (self.spacing_m > 0 and heights and self.size_m >= 0):
            raise InputError("lamps: spacing > 0, height > stature > shoulders > hips > 0, and size >= 0 are needed")
        if not (min(self.leg_radius_m, self.torso_radius_m, self.head_radius_m) > 0 and self.reach > 0):
            raise InputError("lamps: body radii and reach must be positive")
        if not self.leg_gap_m >= 0:
            raise InputError("lamps: the legs' gap must be >= 0")


def _chord_share(u: np.ndarray) -> np.ndarray:
    """Share of a unit disc on the far side of a chord at signed distance ``u`` from its centre."""
    u = np.clip(u, -1.0, 1.0)
    return (np.arccos(u) - u * np.sqrt(1.0 - u * u)) / math.pi


class Lamps:
    """Illuminance of the floor under the lamp grid, with or without the body's shadow."""

    def __init__(self, config: LampConfig | None = None, seed: int = 0):
        self.config = config or LampConfig()
        c = self.config
        self.offset = np.random.default_rng([seed, 31]).uniform(0.0, c.spacing_m, 2)
        # One cell's mean of the unshadowed light: the normaliser that makes the floor average 1.
        g = (np.arange(24) + 0.5) / 24 * c.spacing_m
        cell = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + self.offset
        self._norm = float(self._contributions(cell)[2].sum(1).mean())

    def _lamps_near(self, xy: np.ndarray) -> np.ndarray:
        """Centres (M, 2) of the lamps within reach of any of the points ``xy`` (N, 2)."""
        c = self.config
        r = c.reach * c.height_m
        lo = np.floor((xy.min(0) - r - self.offset) / c.spacing_m)
        hi = np.ceil((xy.max(0) + r - self.offset) / c.spacing_m)
        i, j = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
        return np.c_[i.ravel(), j.ravel()] * c.spacing_m + self.offset

    def illuminance(self, xy: np.ndarray, body: np.ndarray | None = None) -> np.ndarray:
        """Relative illuminance (N,) at floor points ``xy`` (N, 2) m; about 1 on average.

        ``body`` (3,): where the body's vertical axis stands and which way it faces, (x, y, yaw) m and
        rad (:meth:`axis`; None: no body, no shadow).
        """
        xy = np.asarray(xy, float).reshape(-1, 2)
        if len(xy) == 0:
            return np.zeros(0)
        d, r2, e = self._contributions(xy)
        if body is not None:
            e *= self._visible(xy, d, r2, np.asarray(body, float))
        return e.sum(1) / self._norm

    def shadow(self, xy: np.ndarray, body: np.ndarray) -> np.ndarray:
        """Share (N,) of the light at floor points ``xy`` (N, 2) that the body ``body`` (3,) leaves."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        if len(xy) == 0:
            return np.zeros(0)
        d, r2, e = self._contributions(xy)
        lit = e.sum(1) / self._norm
        shaded = (e * self._visible(xy, d, r2, np.asarray(body, float))).sum(1) / self._norm
        return shaded / np.maximum(lit, 1e-12)

    def _contributions(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each lamp within reach seen from the floor points ``xy`` (N, 2): the horizontal offsets
        point -> lamp (N, M, 2), their squared lengths (N, M), and the illuminance each lamp gives
        (N, M), unnormalised (0 beyond reach)."""
        c = self.config
        d = self._lamps_near(xy)[None, :, :] - xy[:, None, :]
        r2 = np.einsum("nmk,nmk->nm", d, d)
        h2 = c.height_m**2
        e = (h2 / (h2 + r2)) ** 2  # cos^4(theta); the common I0 / h^2 goes into the normaliser
        e[r2 > (c.reach * c.height_m) ** 2] = 0.0
        return d, r2, e

    def _segments(self, body: np.ndarray) -> list[tuple[np.ndarray, float, float, float]]:
        """The body's round segments: (axis (2,), bottom, top, radius), m."""
        c = self.config
        x, y, yaw = body
        centre = np.array([x, y])
        left = 0.5 * c.leg_gap_m * np.array([-np.sin(yaw), np.cos(yaw)])
        return [
            (centre + left, 0.0, c.hip_m, c.leg_radius_m),
            (centre - left, 0.0, c.hip_m, c.leg_radius_m),
            (centre, c.hip_m, c.shoulder_m, c.torso_radius_m),
            (centre, c.shoulder_m, c.stature_m, c.head_radius_m),
        ]

    def _visible(self, xy: np.ndarray, d: np.ndarray, r2: np.ndarray, body: np.ndarray) -> np.ndarray:
        """Share (N, M) of each lamp's emitting area that the body leaves in view of each point."""
        c = self.config
        vis = np.ones(r2.shape)
        for centre, z0, z1, radius in self._segments(body):
            w = centre[None, None, :] - xy[:, None, :]  # floor point -> segment axis (N, 1, 2)
            # Along the ray up to the lamp, fraction s of the way, the horizontal offset from the
            # axis is w - s d; its closest approach within this segment's heights [z0, z1].
            s = np.einsum("nmk,nmk->nm", np.broadcast_to(w, d.shape), d) / np.maximum(r2, 1e-12)
            s = np.clip(s, z0 / c.height_m, z1 / c.height_m)
            gap = np.hypot(w[..., 0] - s * d[..., 0], w[..., 1] - s * d[..., 1]) - radius
            half = 0.5 * c.size_m * s  # the cone of the luminaire's rays, half-width there
            blocked = np.where(half > 1e-9, _chord_share(gap / np.maximum(half, 1e-9)), (gap < 0).astype(float))
            vis = np.minimum(vis, 1.0 - blocked)
        return vis

    def axis(self, T_world_body: np.ndarray, vest_point: np.ndarray) -> np.ndarray:
        """(3,) where the body's vertical axis stands and its heading, (x, y, yaw) m and rad, from the
        body pose (4, 4) and the vest point (3,)."""
        T = np.asarray(T_world_body, float)
        p = T[:3, :3] @ np.asarray(vest_point, float) + T[:3, 3]
        fwd = T[:2, 0]
        n = float(np.hypot(*fwd))
        fwd = fwd / n if n > 1e-9 else np.array([1.0, 0.0])
        xy = p[:2] - self.config.axis_behind_m * fwd
        return np.array([xy[0], xy[1], float(np.arctan2(fwd[1], fwd[0]))])
