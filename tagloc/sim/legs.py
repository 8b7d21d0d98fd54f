"""The wearer's own legs and feet, as a chest camera pitched steeply down sees them.

A camera on the chest, about 1.3-1.9 m up and pitched 45-65 degrees down, with the reference
camera's 41 degree vertical field of view, sees the floor from 65-86 degrees below the horizon at
its bottom edge: from 0.1-0.9 m ahead of it. Walking, each heel lands about half a step length
ahead of the centre of mass (a step of 0.6-0.8 m at 1.2-1.6 m/s), and the shoe reaches another
0.2 m beyond the ankle, so the leading foot, and at the steepest pitches the shin above it, enter
the lower part of the image once per step. They are fixed to the body, not to the floor: a foot in
stance stands still on the floor, but the swinging foot moves forward at about twice the walking
speed, and the shins sweep with it.

The model (all lengths in metres). The simulated rig sits on the walk's path
(:mod:`tagloc.sim.walk`); a real vest's camera is on the chest, in front of the hips, so the legs
hang from the body's axis ``axis_behind_m`` behind the vest point (half a chest's depth, as the
shadow's body in :mod:`tagloc.sim.lamps`), and the feet land about that axis:

- **Footfalls** from the walk's step phase (``bob_m cos(phase)``: one step per 2 pi; the centre
  of mass is lowest at double support, so a heel strikes at phase pi, the left and right feet on
  alternate steps). At each strike, the heel lands ``heel_ahead`` of a step length (speed over
  cadence, both at that moment) ahead of the centre of mass, ``step_width_m / 2`` to its side,
  the foot along the path's heading. A standing walker's phase stops, and so do the feet.
- **Stance and swing**: a foot stays planted for ``stance_fraction`` of its gait cycle (two steps),
  then swings to its next footprint over the rest, along a minimum-jerk profile (a smooth start
  and stop, as measured foot trajectories have), lifted by up to ``swing_lift_m`` (less below
  ``full_lift_speed_mps``: a walker braking to a stop takes low steps and stands where the phase
  stops, on both feet).
- **Legs**: hips ``hip_half_width_m`` either side of the path at ``hip_height_m``; the knee from
  the two-link chain of thigh and shank (lengths from the hip, knee and ankle heights), bent
  forward. The shank and the thigh are capsules (``shin_radius_m``, ``thigh_radius_m``), the shoe
  a box.
- **Appearance**: dark safety shoes and work trousers (``shoe_albedo``, ``trouser_albedo``), flat
  shaded: a vertical surface under overhead lamps gets about half the light of the floor
  (``side_light``), a shoe's upper side all of it; the renderer's illumination, vignetting and
  noise apply on top. No texture on the cloth: the silhouettes, which move with the body, are
  what disturbs a floor tracker.

Not modelled: the knee's flexion profile over the swing beyond the two-link chain, the arms, the
torso's own shadow on the legs, and loose clothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from tagloc.sim.lamps import BODY_AXIS_BEHIND_M
from tagloc.sim.walk import Walk

__all__ = ["LegsConfig", "Legs", "Solid"]


@dataclass(frozen=True)
class LegsConfig:
    """An adult's lower body and gait (metres, fractions; see the module docstring).

    Figures: the hips' axis 0.12 m behind a chest-mounted vest point (half a chest's depth); step
    width 0.08-0.12 m between the feet's centre lines; stance 60 % of the gait cycle at a normal pace; a work shoe 0.28 x 0.11 x 0.10 m; knee 0.50 m and hip 0.92 m up for a
    1.75 m stature (0.285 and 0.53 of it); toe clearance in swing 1-2 cm, the foot's middle
    lifted a few centimetres.
    """

    axis_behind_m: float = BODY_AXIS_BEHIND_M
    step_width_m: float = 0.10
    stance_fraction: float = 0.6
    heel_ahead: float = 0.5
    shoe_length_m: float = 0.28
    shoe_width_m: float = 0.11
    shoe_height_m: float = 0.10
    ankle_from_heel_m: float = 0.07
    ankle_height_m: float = 0.09
    knee_height_m: float = 0.50
    hip_height_m: float = 0.92
    hip_half_width_m: float = 0.09
    shin_radius_m: float = 0.055
    thigh_radius_m: float = 0.08
    swing_lift_m: float = 0.04
    full_lift_speed_mps: float = 0.5
    shoe_albedo: float = 0.06
    trouser_albedo: float = 0.10
    side_light: float = 0.5


@dataclass(frozen=True)
class Solid:
    """One convex piece of the body in world coordinates: ``points`` (N, 3) on its surface (their
    projections' convex hull is its silhouette) and its reflectance ``value`` (0-255 on the
    renderer's floor scale)."""

    points: np.ndarray
    value: float


# Unit directions on a sphere for a capsule's end caps (26: the cube's faces, edges and corners).
_SPHERE = np.array(
    [(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)], float
)
_SPHERE /= np.linalg.norm(_SPHERE, axis=1)[:, None]


def _min_jerk(u: np.ndarray | float) -> np.ndarray | float:
    """The minimum-jerk profile 10u^3 - 15u^4 + 6u^5 on [0, 1]."""
    return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)


class Legs:
    """The legs and feet of one walk at any time (see the module docstring)."""

    def __init__(
        self, walk: Walk, vest_point: np.ndarray | None = None, config: LegsConfig | None = None, dt: float = 0.005
    ):
        """``vest_point`` (3,): the rig's vest point in the body (path) frame, m (None: on the path)."""
        self.walk = walk
        self.config = cfg = config or LegsConfig()
        vp = np.zeros(3) if vest_point is None else np.asarray(vest_point, float)
        # The body's axis in the path frame: behind the vest point, on the floor.
        self._axis = np.array([vp[0] - cfg.axis_behind_m, vp[1]])
        t = np.arange(walk.t_start, walk.t_end + 1e-9, dt)
        phase = walk.phase(t)
        # Footfalls: the phase crossing pi + 2 pi k; even k the left foot, odd k the right.
        k0, k1 = math.ceil((phase[0] - math.pi) / (2 * math.pi)), math.floor((phase[-1] - math.pi) / (2 * math.pi))
        ks = np.arange(k0, k1 + 1)
        rate = np.gradient(phase, t)  # rad/s: 2 pi per step
        falls = []  # (k, time, heel (2,), yaw)
        for k in ks:
            target = math.pi + 2 * math.pi * k
            tk = float(np.interp(target, phase, t))  # the phase never decreases
            x, y, yaw = self._axis_at(tk)
            cadence = float(np.interp(tk, t, rate)) / (2 * math.pi)  # steps per second
            step = float(walk.speed(tk)) / cadence if cadence > 1e-6 else 0.0
            side = 1.0 if k % 2 == 0 else -1.0
            c, s = math.cos(yaw), math.sin(yaw)
            heel = np.array([x, y]) + cfg.heel_ahead * step * np.array([c, s])
            heel += side * cfg.step_width_m / 2 * np.array([-s, c])
            falls.append((int(k), tk, heel, yaw))
        self._falls = falls
        # Each foot's footfalls and their times, for a search by time (+1 left: even k; -1 right).
        self._by_side = {side: [f for f in falls if (f[0] % 2 == 0) == (side > 0)] for side in (1.0, -1.0)}
        self._times = {side: np.array([f[1] for f in mine]) for side, mine in self._by_side.items()}
        x, y, yaw = self._axis_at(walk.t_start)
        c, s = math.cos(yaw), math.sin(yaw)
        # Standing before the first step: side by side under the centre of mass, heels a little back.
        self._start = {
            side: (
                np.array([x, y])
                - cfg.ankle_from_heel_m * np.array([c, s])
                + side * cfg.step_width_m / 2 * np.array([-s, c]),
                yaw,
            )
            for side in (1.0, -1.0)
        }

    def _axis_at(self, t: float) -> tuple[float, float, float]:
        """The body's axis on the floor (x, y) and the path's heading at ``t``."""
        x, y, yaw = (float(v) for v in self.walk.planar(t))
        c, s = math.cos(yaw), math.sin(yaw)
        ax, ay = self._axis
        return x + c * ax - s * ay, y + s * ax + c * ay, yaw

    def feet(self, t: float) -> dict[float, tuple[np.ndarray, float, float]]:
        """Each foot's heel on the floor (2,), yaw (rad) and lift (m) at ``t`` (s), by side (+1 left,
        -1 right)."""
        cfg = self.config
        ph = float(self.walk.phase(t))
        out = {}
        for side in (1.0, -1.0):
            mine = self._by_side[side]
            i = int(np.searchsorted(self._times[side], t, side="right"))  # footfalls up to t
            last = mine[i - 1] if i > 0 else None
            nxt = mine[i] if i < len(mine) else None
            if last is None:
                heel, yaw = self._start[side]
                if nxt is None:
                    out[side] = (heel, yaw, 0.0)
                    continue
                last_phase = math.pi + 2 * math.pi * (nxt[0] - 2)
                last = (nxt[0] - 2, None, heel, yaw)
            else:
                last_phase = math.pi + 2 * math.pi * last[0]
            toe_off = last_phase + cfg.stance_fraction * 4 * math.pi
            if ph < toe_off or nxt is None:
                out[side] = (last[2], last[3], 0.0)
                continue
            u = min(1.0, (ph - toe_off) / (math.pi + 2 * math.pi * nxt[0] - toe_off))
            m = float(_min_jerk(u))
            heel = last[2] + m * (nxt[2] - last[2])
            yaw = last[3] + m * math.remainder(nxt[3] - last[3], 2 * math.pi)
            # A walker slowing to a stop takes low steps, and a stopped one stands on both feet.
            slow = min(1.0, float(self.walk.speed(t)) / cfg.full_lift_speed_mps)
            out[side] = (heel, yaw, cfg.swing_lift_m * math.sin(math.pi * u) * slow)
        return out

    def solids(self, t: float) -> list[Solid]:
        """The shoes, shanks and thighs at ``t`` (s) as convex solids in the world."""
        cfg = self.config
        x, y, yaw = self._axis_at(t)
        c, s = math.cos(yaw), math.sin(yaw)
        shank = cfg.knee_height_m - cfg.ankle_height_m
        thigh = cfg.hip_height_m - cfg.knee_height_m
        out = []
        for side, (heel, fyaw, lift) in self.feet(t).items():
            fc, fs = math.cos(fyaw), math.sin(fyaw)
            fwd, left = np.array([fc, fs, 0.0]), np.array([-fs, fc, 0.0])
            base = np.array([heel[0], heel[1], lift])
            box = [
                base
                + a * cfg.shoe_length_m * fwd
                + b * cfg.shoe_width_m / 2 * left
                + np.array([0, 0, h * cfg.shoe_height_m])
                for a in (0.0, 1.0)
                for b in (-1.0, 1.0)
                for h in (0.0, 1.0)
            ]
            out.append(Solid(np.array(box), 255.0 * cfg.shoe_albedo))
            ankle = base + cfg.ankle_from_heel_m * fwd + np.array([0.0, 0.0, cfg.ankle_height_m])
            hip = np.array([x, y, cfg.hip_height_m]) + side * cfg.hip_half_width_m * np.array([-s, c, 0.0])
            knee = _knee(hip, ankle, thigh, shank, np.array([c, s, 0.0]))
            value = 255.0 * cfg.trouser_albedo * cfg.side_light
            out.append(Solid(_capsule(ankle, knee, cfg.shin_radius_m), value))
            out.append(Solid(_capsule(knee, hip, cfg.thigh_radius_m), value))
        return out

    def paint(self, out: np.ndarray, T_world_camera: np.ndarray, K: np.ndarray, t: float, offset=(0, 0)) -> None:
        """Paint the legs at ``t`` over ``out`` (h, w) uint8, an ideal pinhole view ``K`` (3, 3) from
        ``T_world_camera`` (4, 4) whose pixel (0, 0) is the view's ``offset``; farthest first."""
        T_cw = np.linalg.inv(T_world_camera)
        K_off = K.copy()
        K_off[0, 2] -= offset[0]
        K_off[1, 2] -= offset[1]
        h, w = out.shape[:2]
        items = []
        for solid in self.solids(t):
            pc = solid.points @ T_cw[:3, :3].T + T_cw[:3, 3]
            # Only what lies in front of the camera (the thighs reach up beside and behind it).
            pc = pc[pc[:, 2] > 0.05]
            if len(pc) < 3:
                continue
            uv = pc @ K_off.T
            uv = uv[:, :2] / uv[:, 2:]
            if uv[:, 0].max() < 0 or uv[:, 1].max() < 0 or uv[:, 0].min() > w or uv[:, 1].min() > h:
                continue
            items.append((float(np.mean(pc[:, 2])), uv, solid.value))
        for _, uv, value in sorted(items, key=lambda it: -it[0]):
            hull = cv2.convexHull(np.round(np.clip(uv, -1e4, 1e4) * 16).astype(np.int32))
            cv2.fillConvexPoly(out, hull, int(round(value)), lineType=cv2.LINE_AA, shift=4)


def _capsule(a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """Surface points (52, 3) of the capsule from ``a`` to ``b`` (3,) of radius ``r``."""
    return np.vstack([a + r * _SPHERE, b + r * _SPHERE])


def _knee(hip: np.ndarray, ankle: np.ndarray, thigh: float, shank: float, forward: np.ndarray) -> np.ndarray:
    """The knee (3,) of the chain hip -> knee -> ankle, bent towards ``forward`` (3,) (a unit vector)."""
    d = ankle - hip
    n = float(np.linalg.norm(d))
    if n >= thigh + shank - 1e-9:
        return hip + d * (thigh / (thigh + shank))
    u = d / n
    along = (thigh * thigh - shank * shank + n * n) / (2 * n)
    off = math.sqrt(max(thigh * thigh - along * along, 0.0))
    perp = forward - u * float(forward @ u)
    norm = float(np.linalg.norm(perp))
    perp = perp / norm if norm > 1e-9 else np.array([0.0, 0.0, 0.0])
    return hip + along * u + off * perp
