"""The fleet view's bounds, apart from :mod:`tagloc.io.fleet` so that building the CLI's parser
(which shows these defaults) does not import numpy and the MQTT sink."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class FleetConfig:
    """Bounds of the fleet view (SI units).

    Attributes:
        stale_s: a vest with no new pose for longer than this is stale. 1 s: 30 missed messages at
            30 fps, and 1.3 m walked at nominal speed, as far as the safety circle reaches.
        max_age_s: a message older than this on arrival is expired (needs epoch clocks on both
            sides). 0.5 s: half the staleness bound, so a pose arriving that late is not shown as current.
        max_2sigma_m: a vest whose 2-sigma position ellipse's major half-axis exceeds this is too
            uncertain to place next to robots. 0.5 m: half an aisle-width margin.
        safety_radius_m: radius of the safety circle drawn around each vest (a robot manager's
            keep-out distance; 1.0 m by default, configurable per site).
        trail_s: seconds of trail kept per vest.
        trail_max: most trail points kept per vest (bounds memory at high message rates).
        max_skew_s: a message whose epoch ``t`` or ``wall_t`` is further ahead of its arrival than
            this is refused (only when the monitor's clock is the epoch). Both are stamped before the
            message leaves the vest, so with clocks in sync they are behind its arrival; NTP keeps a
            LAN's clocks within milliseconds, so a lead of seconds is a wrong clock or a corrupt time.
            Taken, such a message would hold the vest's genuine poses back as "out of order". 2 s:
            hundreds of times NTP's error (room for a client still converging after boot), yet a
            message taken just inside it holds the vest's next poses back for 2 s at most (1 s at
            30 fps once ``timeline_reset_n`` takes over), about the staleness bound.
        timeline_reset_n: after this many messages in a row from one vest older than its newest, the
            vest is taken to have restarted its clock (a new session) and its new timeline is
            followed. One MQTT connection at QoS 0 never reorders, so a run this long is a restart (or
            one corrupt far-future time before it), not reordering. 30: 1 s at 30 fps, the
            staleness bound, so a restarted vest is back within about the time it is flagged stale.
        cov_tol: tolerance (m^2, rad^2) of the covariance checks: mirrored entries may differ, and the
            smallest eigenvalue be negative, by this much. The sender rounds each entry to 1e-9
            (``TrackerOutput.to_json``): mirrored entries then differ by at most one step (1e-9), and
            the eigenvalues move by at most the rounding's norm, 3 entries x 0.5e-9 = 1.5e-9 (a
            39 micrometre sigma: nothing a real covariance needs and nothing a broken one hides in).
        max_message_bytes: a longer message is refused unread. A pose message is about 400 bytes
            (under 1 kB with the longest vest ID and every number at full length); 64 KiB leaves room
            for fields a later schema adds, while a broker passes up to 256 MB by default, which
            decoded held the monitor's network thread and its view for seconds and took gigabytes.
        duplicate_hold_s: a vest whose ID two senders were seen sharing (their runs interleaving) is
            flagged ``duplicate`` until this long after the last interleaving message. While both
            send, they interleave at every frame and the warning stays; 10 s keeps it up long enough
            for someone to see it after one of them stops (a glance at the panel), without holding it
            for the rest of a shift.
        max_runs: sender runs remembered per vest ID (the earliest forgotten first): a vest restarts
            its process a few times a shift, and two senders need two entries.
    """

    stale_s: float = 1.0
    max_age_s: float = 0.5
    max_2sigma_m: float = 0.5
    safety_radius_m: float = 1.0
    trail_s: float = 30.0
    trail_max: int = 1000
    max_skew_s: float = 2.0
    timeline_reset_n: int = 30
    cov_tol: float = 1.5e-9
    max_message_bytes: int = 65536
    duplicate_hold_s: float = 10.0
    max_runs: int = 8
