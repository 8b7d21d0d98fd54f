"""Survey error: the map the localiser is given is not exactly where the stickers are.

Stickers are placed by hand and surveyed with tape, laser or total station; each one's recorded
centre and yaw are off by a few centimetres and a degree or two (issue 14's field condition: 1-2
cm and 1-2 degrees per sticker). The simulator renders the stickers at their true poses and
writes the session's ``map.csv`` perturbed: each sticker's centre moved by a Gaussian error of
``sigma_m`` per axis and its yaw by one of ``sigma_deg``, independent between stickers, seeded.
With ``stated`` the map carries those sigmas in its optional ``sigma_m``/``sigma_deg`` columns
(a survey that states its accuracy); without, the localiser's default applies.

A site has one survey, whichever walk is recorded on it: with ``seed`` set, each sticker's error is
drawn from (that seed, its ID), so every session of the site gets the same mapped pose for it (by
default the errors are drawn in map order from each session's seed). ``moved``
adds stickers that were moved after the survey (replaced elsewhere, knocked by a pallet): on the
floor at their true pose, in the map still at the old place, off by a known (dx, dy) on top of the
survey error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tagloc.core.errors import InputError
from tagloc.core.geometry import wrap_angle
from tagloc.core.stickermap import StickerMap


@dataclass
class SurveyConfig:
    """Survey error of the map handed to the localiser (zeros: the true map).

    Attributes:
        sigma_m: standard deviation of each sticker centre's error, per axis, m.
        sigma_deg: standard deviation of each sticker yaw's error, degrees.
        stated: write ``sigma_m``/``sigma_deg`` columns stating them in the map.
        seed: the survey's own random seed (one survey per site); None: the session's seed.
        moved: ``(id, dx_m, dy_m)`` of stickers moved since the survey: the map row is off by
            (dx, dy) more than the survey error (the floor shows the sticker's true pose).
    """

    sigma_m: float = 0.0
    sigma_deg: float = 0.0
    stated: bool = False
    seed: int | None = None
    moved: tuple[tuple[int, float, float], ...] = ()

    def __post_init__(self) -> None:
        if not (self.sigma_m >= 0 and self.sigma_deg >= 0):
            raise InputError("survey error sigmas must be >= 0")
        for item in self.moved:
            if len(item) != 3 or not all(math.isfinite(float(v)) for v in item[1:]):
                raise InputError(f"survey: a moved sticker is (id, dx_m, dy_m), got {item!r}")
        self.moved = tuple((int(i), float(dx), float(dy)) for i, dx, dy in self.moved)

    @property
    def active(self) -> bool:
        """True when the map differs from the truth (or states sigmas)."""
        return self.sigma_m > 0 or self.sigma_deg > 0 or self.stated or bool(self.moved)


#: Issue 14's field condition: 1 cm per axis (1.4 cm RMS radial, within the 1-2 cm range) and
#: 1.5 degrees, not stated in the map.
FIELD_SURVEY = SurveyConfig(sigma_m=0.01, sigma_deg=1.5)


def surveyed_map(smap: StickerMap, survey: SurveyConfig, seed: int) -> StickerMap:
    """The map as surveyed: ``smap`` (the truth) with seeded per-sticker errors and the moved
    stickers' offsets (see the module docstring); ``seed`` is the session's (used unless
    ``survey.seed`` is set)."""
    if not survey.active:
        return smap
    n = len(smap)
    if survey.seed is None:
        rng = np.random.default_rng([seed, 37])
        z = np.column_stack([rng.standard_normal((n, 2)), rng.standard_normal(n)])
    else:
        # One survey of the site: each sticker's error comes from (survey seed, its ID), so a sticker
        # has the same mapped pose in every session's map whatever else is on the floor.
        z = np.array([np.random.default_rng([survey.seed, 37, int(i)]).standard_normal(3) for i in smap.ids])
        z = z.reshape(n, 3)
    dxy = z[:, :2] * survey.sigma_m
    for sid, dx, dy in survey.moved:
        if sid not in smap:
            raise InputError(f"survey: moved sticker {sid} is not in the map {smap.source}")
        dxy[smap.row(sid)] += (dx, dy)
    dyaw = z[:, 2] * math.radians(survey.sigma_deg)
    yaw = wrap_angle(smap.yaw + dyaw)
    sig_xy = np.full(n, survey.sigma_m if survey.stated else np.nan)
    sig_yaw = np.full(n, math.radians(survey.sigma_deg) if survey.stated else np.nan)
    return StickerMap(smap.ids.copy(), smap.xy + dxy, yaw, smap.source, sig_xy, sig_yaw)
