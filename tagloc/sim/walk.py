"""The operator's walk: a smooth, seeded trajectory along the map's sticker lines, plus torso motion.

Two motions are kept apart:

* **Path** (``T_world_path``): the walker's planned centre-of-mass path projected onto the floor
  (+x forward, +y left, +z up, z = 0). It follows the stickers' lines (aisles): straight on mostly,
  sometimes turning at a crossing, turning on the spot where a line ends, with a slowly varying
  speed and occasional stops. Position is C2 (a cubic spline through a 100 Hz kinematic simulation
  whose speed and turn rate are acceleration-limited), and the heading is smooth.
* **Torso motion** (``T_body_vest``): the rigid torso, which carries the vest and its cameras, moves
  on the path: vertical bobbing at the step frequency, lateral sway and torso yaw at half the step
  frequency, pitch jitter (gait part plus slow drift), a little roll (gait part plus slow drift:
  standing people shift their weight side to side as well as back and forth), and the **lean** of
  the whole body that walking needs (below). The rotations are about the centre of mass, on the
  path ``com_height_m`` up. ``T_world_camera = T_world_path @ T_body_vest @ T_body_camera``.

Lean: to walk a curve of radius R at speed v the ground force must supply the centripetal
acceleration a_c = v^2 / R = v omega, and a body in balance leans so that the resultant of gravity
and that force passes through its centre of mass: roll = atan(v omega / g) into the turn. Speeding
up or braking at a forward acceleration a likewise needs a pitch of atan(a / g) (forward when
speeding up). Both are computed from the path's own speed, turn rate and acceleration and follow
them through a first-order lag of the body's inverted-pendulum time constant sqrt(h_com / g)
(0.31 s at 0.95 m): the body cannot tilt faster than it falls. Turns on the spot (v ~ 0) need no
lean. (At 1.3 m/s on a 1.5 m arc: 6.5 deg; braking at 0.8 m/s^2: 4.7 deg.)

**Ground truth** (``T_world_body``): the vest point (on the torso, where the rig is mounted)
projected vertically onto the floor, with the horizontal heading of the torso's +x axis
(:func:`tagloc.core.rig.vest_planar`): it moves with the sway, the twist and the lean (the vest
point is ``vest_height - com_height`` above the lean's pivot), not with the bobbing.

All gait amplitudes are semi-amplitudes (half peak-to-peak), scaled by how fast the operator walks
(none when standing); the slow drifts of pitch and roll go on when standing.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from tagloc.core.errors import InputError
from tagloc.core.geometry import planar_T, wrap_angle
from tagloc.core.stickermap import StickerMap

_DT = 0.01  # kinematic simulation step (s); the spline makes the result continuous in time
G = 9.81  # gravity, m/s^2


@dataclass
class WalkConfig:
    """How the operator walks. Lengths in metres, times in seconds, angles in degrees.

    Attributes:
        seconds: length of the walk (the trajectory is defined a little beyond [0, seconds]).
        speed_mps: nominal walking speed.
        seed: random seed (same seed, same walk).
        speed_variation: relative standard deviation of the slow speed changes (clipped at +-2 sigma).
        stop_every_s: mean time between stops (0: never stop).
        stop_s: (min, max) duration of one stop.
        turn_probability: chance of leaving a line at a crossing instead of going straight on.
        lateral_offset_m: largest sideways offset of the path from the sticker line (per straight run).
        accel_mps2: largest forward acceleration/deceleration.
        turn_rate_dps: largest turn rate when turning on the spot.
        min_turn_radius_m: tightest curve while walking.
        step_hz: step frequency at the nominal speed (scales with speed**0.5).
        bob_m, sway_m: vertical bobbing (at step frequency) and lateral sway (at half of it).
        torso_yaw_deg, roll_deg: torso yaw and roll oscillation at half the step frequency.
        pitch_jitter_deg: camera pitch wobble (half at the step frequency, half slow drift).
        roll_drift_deg: slow roll drift of the vest (RMS, 1.5 s correlation like the pitch drift),
            walking or standing: people sway side to side less than back and forth (quiet-standing
            sway is ~0.7 times as large sideways), so 0.7 of the pitch drift's 0.5 deg.
        lean: lean into turns and with acceleration (see the module docstring).
        com_height_m: height of the centre of mass, the lean's and the torso rotations' pivot
            (about 0.55 of the stature; 0.95 m for a 1.75 m adult).
    """

    seconds: float = 20.0
    speed_mps: float = 1.3
    seed: int = 0
    speed_variation: float = 0.12
    stop_every_s: float = 12.0
    stop_s: tuple[float, float] = (1.0, 2.0)
    turn_probability: float = 0.2
    lateral_offset_m: float = 0.25
    accel_mps2: float = 0.8
    turn_rate_dps: float = 100.0
    min_turn_radius_m: float = 0.5
    step_hz: float = 1.9
    bob_m: float = 0.025
    sway_m: float = 0.02
    torso_yaw_deg: float = 2.5
    roll_deg: float = 0.7
    pitch_jitter_deg: float = 1.0
    roll_drift_deg: float = 0.35
    lean: bool = True
    com_height_m: float = 0.95

    def __post_init__(self) -> None:
        if not self.seconds > 0 or not self.speed_mps > 0:
            raise InputError(f"walk needs positive seconds and speed (got {self.seconds}, {self.speed_mps})")
        if not self.com_height_m > 0:
            raise InputError(f"walk needs a positive centre-of-mass height (got {self.com_height_m})")

    def with_gait_scale(self, factor: float) -> WalkConfig:
        """A copy whose gait motions (:data:`GAIT_AMPLITUDES`: bobbing, sway, torso twist and roll,
        pitch wobble, slow roll drift) are ``factor`` times this one's; the path and the lean, which
        follow from the walk's own speed and turns, are unchanged. Gait studies report the trunk's
        motion differing between people by a factor of two or more, so a localiser's figures on
        one walker say little about another's (``tagloc eval --gait-scale``)."""
        if not (math.isfinite(factor) and factor >= 0):
            raise InputError(f"the gait's scale must be a finite number >= 0, got {factor}")
        return replace(self, **{name: factor * getattr(self, name) for name in GAIT_AMPLITUDES})

    @property
    def lean_tau_s(self) -> float:
        """Time constant of the lean (s): the inverted pendulum's sqrt(h_com / g)."""
        return math.sqrt(self.com_height_m / G)


#: The gait scales the commands take (``tagloc simulate --gait-scale``, ``tagloc eval --gait-scale``;
#: 0: a torso carried along the path without any gait motion; 3: three times the default walker,
#: beyond the spread between people).
GAIT_SCALE_RANGE = (0.0, 3.0)

#: The WalkConfig fields that size the gait's own motions of the torso (see
#: :meth:`WalkConfig.with_gait_scale`).
GAIT_AMPLITUDES = ("bob_m", "sway_m", "torso_yaw_deg", "roll_deg", "pitch_jitter_deg", "roll_drift_deg")

# Columns of the walk's state spline (the lean is in PITCH and ROLL).
_X, _Y, _YAW, _V, _BOB, _SWAY, _TYAW, _PITCH, _ROLL, _LPITCH, _LROLL, _PHASE = range(12)


@dataclass
class Walk:
    """A simulated walk, defined for any time in ``[t_start, t_end]`` (s).

    Attributes:
        spline: cubic spline of the state columns (x, y, yaw, speed, bob, sway, torso yaw, pitch,
            roll, the lean's part of pitch and roll, rad, and the gait's step phase, rad: one step
            per 2 pi, the bobbing being ``bob_m cos(phase)``).
        stops: (K, 2) start and end times of the stops (standing still), s.
        waypoints: (M, 2) the points the walker steered at, world metres.
        config: what produced it.
    """

    spline: CubicSpline
    stops: np.ndarray
    waypoints: np.ndarray
    config: WalkConfig
    t_start: float = field(init=False)
    t_end: float = field(init=False)

    def __post_init__(self) -> None:
        self.t_start, self.t_end = float(self.spline.x[0]), float(self.spline.x[-1])

    def _state(self, t: float | np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(t, float), self.t_start, self.t_end)
        return self.spline(t)

    def planar(self, t: float | np.ndarray) -> np.ndarray:
        """Path (x, y, yaw) at ``t``: (3,) or (N, 3); yaw is continuous (not wrapped)."""
        return self._state(t)[..., :3]

    def speed(self, t: float | np.ndarray) -> np.ndarray:
        """Forward speed of the path (m/s) at ``t``, from its derivative."""
        d = self.spline(np.clip(np.asarray(t, float), self.t_start, self.t_end), 1)
        return np.hypot(d[..., _X], d[..., _Y])

    def phase(self, t: float | np.ndarray) -> np.ndarray:
        """The gait's step phase (rad, growing; one step per 2 pi) at ``t``: () or (N,)."""
        return self._state(t)[..., _PHASE]

    def lean(self, t: float | np.ndarray) -> np.ndarray:
        """The lean's (roll, pitch) at ``t`` (rad; roll > 0 tips the torso's top to the right, pitch
        > 0 forward): (2,) or (N, 2)."""
        s = self._state(t)
        return np.stack([s[..., _LROLL], s[..., _LPITCH]], axis=-1)

    def T_world_path(self, t: float | np.ndarray) -> np.ndarray:
        """The planned path's pose(s) on the floor: (4, 4) for a scalar ``t``, (N, 4, 4) for an array."""
        s = self._state(t)
        x, y, a = s[..., _X], s[..., _Y], s[..., _YAW]
        T = np.zeros(s.shape[:-1] + (4, 4))
        c, sn = np.cos(a), np.sin(a)
        T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -sn, sn, c
        T[..., 2, 2] = T[..., 3, 3] = 1.0
        T[..., 0, 3], T[..., 1, 3] = x, y
        return T

    def T_body_vest(self, t: float | np.ndarray) -> np.ndarray:
        """Torso motion on the path: (4, 4) or (N, 4, 4), rotating about the centre of mass (m)."""
        s = self._state(t)
        euler = np.stack([s[..., _ROLL], s[..., _PITCH], s[..., _TYAW]], axis=-1)
        R = Rotation.from_euler("xyz", euler.reshape(-1, 3)).as_matrix().reshape(s.shape[:-1] + (3, 3))
        offset = np.stack([np.zeros_like(s[..., _SWAY]), s[..., _SWAY], s[..., _BOB]], axis=-1)
        pivot = np.array([0.0, 0.0, self.config.com_height_m])
        T = np.zeros(s.shape[:-1] + (4, 4))
        T[..., :3, :3] = R
        # Rotate about the pivot, then translate: p' = R (p - pivot) + pivot + offset.
        T[..., :3, 3] = pivot + offset - np.einsum("...ij,j->...i", R, pivot)
        T[..., 3, 3] = 1.0
        return T

    def T_world_vest(self, t: float | np.ndarray) -> np.ndarray:
        """The tilted torso's frame(s) in the world: ``T_world_path @ T_body_vest``."""
        return self.T_world_path(t) @ self.T_body_vest(t)

    def T_world_camera(self, t: float | np.ndarray, T_body_camera: np.ndarray) -> np.ndarray:
        """True camera pose(s) with the torso motion: ``T_world_path @ T_body_vest @ T_body_camera``."""
        return self.T_world_vest(t) @ np.asarray(T_body_camera, float)

    def groundtruth(self, t: float | np.ndarray, vest_point: np.ndarray) -> np.ndarray:
        """Ground truth (x, y, yaw) at ``t``: (3,) or (N, 3), the vest point ``vest_point`` (3,) (body
        frame, m) projected onto the floor and the horizontal heading of the torso's +x axis."""
        T = self.T_world_vest(t)
        p = np.einsum("...ij,j->...i", T[..., :3, :3], np.asarray(vest_point, float)) + T[..., :3, 3]
        return np.stack([p[..., 0], p[..., 1], np.arctan2(T[..., 1, 0], T[..., 0, 0])], axis=-1)

    def T_world_body(self, t: float | np.ndarray, vest_point: np.ndarray) -> np.ndarray:
        """Ground-truth body pose(s) on the floor (z = 0, upright) from :meth:`groundtruth`:
        (4, 4) for a scalar ``t``, (N, 4, 4) for an array."""
        g = self.groundtruth(t, vest_point)
        if g.ndim == 1:
            return planar_T(*g)
        return np.stack([planar_T(*row) for row in g])


def _ou(rng: np.random.Generator, n: int, tau_s: float) -> np.ndarray:
    """Unit-variance first-order low-pass noise (correlation time ``tau_s``), n samples at ``_DT``."""
    a = math.exp(-_DT / tau_s)
    x = lfilter([math.sqrt(1 - a * a)], [1, -a], rng.standard_normal(n))
    # Start in the stationary state instead of at zero.
    return x + rng.standard_normal() * a ** np.arange(n)


def _with_inertia(x: np.ndarray, tau_s: float, inertia_s: float) -> np.ndarray:
    """A slow random drift of the body (its tilt, its walking speed) from :func:`_ou`'s unit-variance
    noise ``x`` (correlation time ``tau_s``): through a first-order lag of ``inertia_s``, scaled
    back to unit variance.

    The low-pass noise alone has no defined rate: it takes a fresh random step every ``_DT``, so
    its rate is white and grows as the step shrinks. For the tilt drift that was about 6 deg/s RMS
    for 0.5 deg over 1.5 s at a 10 ms step, most of it above 5 Hz; for the speed variation a white
    acceleration (0.6 m/s^2 RMS), which the lean then turned into a pitch rate just as rough. A body
    has inertia and is moved by muscles: it cannot tilt faster than it falls (the inverted
    pendulum's time constant, as for the lean), a standing person sways at under 1 deg/s, and a
    walker's speed changes over steps, not within a hundredth of a second. Through the lag the
    drift's rate is continuous and bounded (0.7 deg/s RMS for 0.5 deg of tilt); the gait's own nod,
    bob and sway are separate.
    """
    a, b = math.exp(-_DT / tau_s), math.exp(-_DT / inertia_s)
    # Stationary variance of an AR(1) (coefficient a, unit variance) through the lag b.
    var = (1.0 - b) ** 2 * (1.0 + a * b) / ((1.0 - b * b) * (1.0 - a * b))
    # Started at the first sample (the lag's steady state for it), as the lean is.
    return lfilter([1.0 - b], [1.0, -b], x, zi=[b * x[0]])[0] / math.sqrt(var)


class _Router:
    """Picks the next waypoint along the map's sticker lines (a seeded walk on the sticker graph)."""

    def __init__(self, smap: StickerMap, cfg: WalkConfig, rng: np.random.Generator):
        self.xy = smap.xy
        self.cfg = cfg
        self.rng = rng
        self.recent: list[int] = []
        self.offset = 0.0

    def start(self) -> tuple[np.ndarray, float, np.ndarray]:
        """Start pose (x, y), heading, and the first waypoint: behind a sticker, facing a neighbour."""
        k = int(self.rng.integers(len(self.xy)))
        d = np.hypot(*(self.xy - self.xy[k]).T)
        d[k] = np.inf
        if np.isfinite(d).any() and d.min() < 4.0:
            j = int(np.argmin(d))
            heading = math.atan2(*(self.xy[j] - self.xy[k])[::-1])
        else:
            heading = float(self.rng.uniform(-math.pi, math.pi))
        self.recent = [k]
        u = np.array([math.cos(heading), math.sin(heading)])
        self.offset = self._new_offset()
        start = self.xy[k] - 1.2 * u + self.offset * np.array([-u[1], u[0]])
        return start, heading, self._place(k, u)

    def _new_offset(self) -> float:
        return float(self.rng.uniform(-1, 1) * self.cfg.lateral_offset_m)

    def _place(self, k: int, u: np.ndarray) -> np.ndarray:
        return self.xy[k] + self.offset * np.array([-u[1], u[0]])

    def next(self, pos: np.ndarray, heading: float) -> tuple[np.ndarray, bool]:
        """The waypoint after ``pos`` for a walker facing ``heading``, and whether the line ends here
        (the walker then turns on the spot)."""
        rel = self.xy - self.xy[self.recent[-1]] if self.recent else self.xy - pos
        dist = np.hypot(*rel.T)
        ang = np.abs(wrap_angle(np.arctan2(rel[:, 1], rel[:, 0]) - heading))
        free = (dist > 0.6) & (dist < 3.5)
        free[self.recent] = False
        ahead = np.flatnonzero(free & (ang < math.radians(30)))
        # Leaving a line mid-way only onto a crossing line (a near neighbour to the side).
        side = np.flatnonzero(free & (dist < 2.3) & (ang > math.radians(55)) & (ang < math.radians(125)))
        back = np.flatnonzero(free)
        turn = self.rng.random() < self.cfg.turn_probability
        line_end = len(ahead) == 0
        if len(ahead) and not (turn and len(side)):
            k = int(ahead[np.argmin(dist[ahead] + 2.0 * ang[ahead])])
        elif len(side):
            k = int(self.rng.choice(side[np.argsort(dist[side])[:3]]))
        elif len(back):  # end of a line: turn round
            k = int(back[np.argmin(dist[back])])
        else:
            others = np.flatnonzero(dist > 0.6)
            if len(others) == 0:  # a lone sticker: circle round it
                a = heading + self.rng.uniform(0.5, 1.5)
                return self.xy[0] + 1.2 * np.array([math.cos(a), math.sin(a)]), False
            k = int(others[np.argmin(dist[others])])
            self.recent = []
        base = self.xy[self.recent[-1]] if self.recent else pos
        u = self.xy[k] - base
        u = u / max(float(np.hypot(*u)), 1e-9)
        if abs(wrap_angle(math.atan2(u[1], u[0]) - heading)) > math.radians(30):
            self.offset = self._new_offset()  # a new line: a new side offset
        self.recent = (self.recent + [k])[-8:]
        return self._place(k, u), line_end


def _lean(speed: np.ndarray, turn_rate: np.ndarray, cfg: WalkConfig) -> tuple[np.ndarray, np.ndarray]:
    """(roll, pitch) of the body's lean (rad) at the ``_DT`` samples of ``speed`` (m/s) and
    ``turn_rate`` (rad/s): atan(v omega / g) into the turn (a left turn tips the top to the left,
    roll < 0 about +x), atan(a / g) forward when speeding up, each through the pendulum's lag."""
    if not cfg.lean:
        return np.zeros_like(speed), np.zeros_like(speed)
    accel = np.gradient(speed, _DT)
    a = math.exp(-_DT / cfg.lean_tau_s)
    lag = functools.partial(lfilter, [1.0 - a], [1.0, -a])
    # Started at the first sample's demand (the lag's steady state), not at zero.
    roll_demand = -np.arctan(speed * turn_rate / G)
    pitch_demand = np.arctan(accel / G)
    roll = lag(roll_demand, zi=[a * roll_demand[0]])[0]
    pitch = lag(pitch_demand, zi=[a * pitch_demand[0]])[0]
    return roll, pitch


def plan_walk(smap: StickerMap, cfg: WalkConfig) -> Walk:
    """Simulate a seeded walk over ``smap``'s sticker lines (see the module docstring)."""
    if len(smap) == 0:
        raise InputError(f"{smap.source}: cannot plan a walk over an empty map")
    rng = np.random.default_rng([cfg.seed, 7])
    t0, t1 = -1.0, cfg.seconds + 1.0
    n = int(math.ceil((t1 - t0) / _DT)) + 1
    t = t0 + _DT * np.arange(n)
    v_nom = cfg.speed_mps
    speed_cmd = v_nom * (1 + cfg.speed_variation * np.clip(_with_inertia(_ou(rng, n, 3.0), 3.0, cfg.lean_tau_s), -2, 2))
    stop_mask = np.zeros(n, bool)
    stops = []
    if cfg.stop_every_s > 0:
        s = t0 + 2.0 + rng.exponential(cfg.stop_every_s)
        while s < t1:
            d = rng.uniform(*cfg.stop_s)
            # Slow down beforehand so that the operator stands still for the whole stop.
            lead = 1.05 * speed_cmd[min(n - 1, int((s - t0) / _DT))] / cfg.accel_mps2
            stop_mask[(t >= s - lead) & (t < s + d)] = True
            stops.append((s, s + d))
            s += d + rng.exponential(cfg.stop_every_s)
    # Slow pitch drift of the vest (half of the jitter budget), drawn now to keep the RNG order fixed.
    drift = _with_inertia(_ou(rng, n, 1.5), 1.5, cfg.lean_tau_s)

    router = _Router(smap, cfg, rng)
    pos, heading, wp = router.start()
    waypoints = [wp]
    v = speed_cmd[0]
    omega = 0.0
    spinning = False
    w_spin = math.radians(cfg.turn_rate_dps)
    states = np.zeros((n, 4))
    turn_rate = np.zeros(n)
    for i in range(n):
        states[i] = pos[0], pos[1], heading, v
        turn_rate[i] = omega
        to_wp = wp - pos
        dist = float(np.hypot(*to_wp))
        if dist < max(0.35, 0.5 * v):
            wp, line_end = router.next(pos, heading)
            waypoints.append(wp)
            spinning = spinning or line_end
            to_wp = wp - pos
            dist = float(np.hypot(*to_wp))
        err = float(wrap_angle(math.atan2(to_wp[1], to_wp[0]) - heading)) if dist > 1e-6 else 0.0
        # Turns at line ends and U-turns are made standing: stop, turn on the spot, walk on.
        if abs(err) > math.radians(100):
            spinning = True
        elif abs(err) < math.radians(8):
            spinning = False
        if spinning or stop_mask[i]:
            v_target = 0.0
        else:
            v_target = speed_cmd[i] * max(0.35, math.cos(err) ** 2)
        v += float(np.clip(v_target - v, -cfg.accel_mps2 * _DT, cfg.accel_mps2 * _DT))
        if spinning and v < 0.1:
            w_max = w_spin
        else:
            w_max = max(v, 0.05) / cfg.min_turn_radius_m
        w_target = float(np.clip(3.0 * err, -w_max, w_max)) if not stop_mask[i] or spinning else 0.0
        omega += float(np.clip(w_target - omega, -6.0 * _DT, 6.0 * _DT))
        heading += omega * _DT
        pos = pos + v * _DT * np.array([math.cos(heading), math.sin(heading)])

    speed = states[:, 3]
    # Gait: step phase advances with a speed-dependent cadence; amplitude fades when standing.
    cadence = cfg.step_hz * np.sqrt(np.clip(speed / v_nom, 0.0, 2.0))
    phase = 2 * math.pi * np.cumsum(cadence) * _DT + rng.uniform(0, 2 * math.pi)
    g = np.clip(speed / min(0.6, v_nom), 0.0, 1.0) ** 2 * np.clip(speed / v_nom, 0.0, 1.3)
    bob = cfg.bob_m * g * np.cos(phase)
    sway = cfg.sway_m * g * np.sin(phase / 2)
    tyaw = math.radians(cfg.torso_yaw_deg) * g * np.sin(phase / 2 + 0.4)
    # Drawn from its own stream, so that adding it left every other draw (and so the paths) as it was.
    roll_drift = _with_inertia(_ou(np.random.default_rng([cfg.seed, 8]), n, 1.5), 1.5, cfg.lean_tau_s)
    roll = math.radians(cfg.roll_deg) * g * np.sin(phase / 2 - 0.3) + math.radians(cfg.roll_drift_deg) * roll_drift
    pj = math.radians(cfg.pitch_jitter_deg)
    pitch = pj * (0.5 * g * np.sin(phase + 1.0) + 0.5 * drift)
    lean_roll, lean_pitch = _lean(speed, turn_rate, cfg)
    cols = np.column_stack(
        [states, bob, sway, tyaw, pitch + lean_pitch, roll + lean_roll, lean_pitch, lean_roll, phase]
    )
    return Walk(CubicSpline(t, cols), np.array(stops).reshape(-1, 2), np.array(waypoints), cfg)
