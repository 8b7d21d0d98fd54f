"""The fleet view's bounds, apart from :mod:`tagloc.io.fleet` so that building the CLI's parser
(which shows these defaults) does not import numpy and the MQTT sink."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FleetConfig:
    """Bounds of the fleet view (SI units).

    Attributes:
        stale_s: a vest with no message for longer than this is stale. 1 s: 30 missed messages at
            30 fps, and 1.3 m walked at nominal speed, as far as the safety circle reaches.
        max_age_s: a message older than this on arrival is expired (needs epoch clocks on both
            sides). 0.5 s: half the staleness bound, so a pose arriving that late is not shown as current.
        max_2sigma_m: a vest whose 2-sigma position ellipse's major half-axis exceeds this is too
            uncertain to place next to robots. 0.5 m: half an aisle-width margin.
        safety_radius_m: radius of the safety circle drawn around each vest (a robot manager's
            keep-out distance; 1.0 m by default, configurable per site).
        trail_s: seconds of trail kept per vest.
        trail_max: most trail points kept per vest (bounds memory at high message rates).
    """

    stale_s: float = 1.0
    max_age_s: float = 0.5
    max_2sigma_m: float = 0.5
    safety_radius_m: float = 1.0
    trail_s: float = 30.0
    trail_max: int = 1000
