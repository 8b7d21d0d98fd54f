"""The fleet in Rerun: the warehouse floor seen from above with every vest on it.

Entity tree::

    fleet/map/stickers          static: sticker outlines with their IDs
    fleet/map/extent            static: the floor's outline (stickers' extent plus 1 m)
    fleet/vests/markers         one point per vest, labelled "VEST state", coloured by state
    fleet/vests/heading         heading arrows (0.6 m)
    fleet/vests/ellipses        2-sigma position ellipses
    fleet/vests/safety          safety circles (FleetConfig.safety_radius_m)
    fleet/vests/trails          recent trails (at most TRAIL_POINTS points each, spread over the trail)
    warnings                    markdown: duplicate-ID, stale, expired, lost, initialising (no pose) and too-uncertain vests
    counts/{vests,received,invalid,expired,timeline_resets,warnings}   time series

Timeline ``time``: the monitor's clock (the wall clock for live MQTT, the bag's clock for recorded fleets).
Colours: tracking green, lost red, initialising/unknown blue-grey; a vest with a warning is drawn
orange, a stale one grey.
"""

from __future__ import annotations

import math
from pathlib import Path

from tagloc.core.stickermap import StickerMap
from tagloc.io.fleet import FleetState, ellipse_2sigma
from tagloc.io.rerun_view import (
    NETWORK_FLUSH_S,
    attach_sinks,
    circle,
    import_rerun,
    log_floor_plan,
    new_recording,
    top_down_view,
)

STATE_COLOURS = {
    "tracking": (40, 200, 60),
    "lost": (220, 40, 40),
    "initialising": (120, 140, 170),
    "unknown": (120, 140, 170),
}
WARN_COLOUR = (255, 150, 0)
STALE_COLOUR = (130, 130, 130)
HEADING_M = 0.6  # arrow length: about an arm's length, visible at warehouse scale
# Most points drawn per trail. Every redraw logs each trail whole: 30 s at 30 Hz is 900 points,
# 10 times a second, 0.4 GB an hour per vest in the viewer (25 kB/s on disk). 100 points over 30 s
# are 0.3 s (40 cm at walking pace) apart, finer than the markers at the fleet's scale.
TRAIL_POINTS = 100


def fleet_blueprint(smap: StickerMap):
    """The floor plan on the left; warnings and counters on the right."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Horizontal(
            top_down_view(smap, "fleet", "fleet (top-down)"),
            rrb.Vertical(
                rrb.TextDocumentView(origin="warnings", name="warnings"),
                rrb.TimeSeriesView(origin="counts", name="messages and vests (count)"),
                row_shares=[3, 2],
            ),
            column_shares=[3, 1],
        ),
        collapse_panels=True,
    )


class FleetView:
    """Draw a :class:`FleetState` in Rerun: to a file (``save``), a spawned viewer or a viewer URL."""

    def __init__(
        self,
        smap: StickerMap,
        *,
        save: str | Path | None = None,
        spawn: bool = False,
        connect: str | None = None,
        app_id: str = "tagloc-monitor",
    ):
        self.rec = new_recording(app_id, save, spawn, connect)
        self._network = attach_sinks(self.rec, fleet_blueprint(smap), save, spawn, connect, "use --save instead")
        log_floor_plan(self.rec, smap, "fleet")

    def update(self, state: FleetState, now: float, timestamp: bool = True, wall: float | None = None) -> None:
        """Draw every vest as of ``now`` on the fleet's staleness clock, on the timeline at ``wall``
        (default ``now``; ``timestamp``: it is epoch seconds)."""
        rr = import_rerun()
        rec = self.rec
        at = now if wall is None else wall
        if timestamp:
            rec.set_time("time", timestamp=at)
        else:
            rec.set_time("time", duration=at)
        cfg = state.config
        warnings = state.warnings(now)
        flagged = {w.vest for w in warnings}
        stale = {w.vest for w in warnings if w.kind == "stale"}
        pts, labels, colours, arrows, origins, ellipses, safety, trails = [], [], [], [], [], [], [], []
        for vest in sorted(state.vests):
            tr = state.vests[vest]
            if not tr.posed:
                continue
            d = tr.last
            colour = STALE_COLOUR if vest in stale else WARN_COLOUR if vest in flagged else STATE_COLOURS[d.state]
            pts.append([d.x, d.y, 0.05])
            labels.append(f"{vest} {d.state}")
            colours.append(colour)
            origins.append([d.x, d.y, 0.05])
            arrows.append([HEADING_M * math.cos(d.yaw), HEADING_M * math.sin(d.yaw), 0.0])
            a, b, ang = ellipse_2sigma(d.cov)
            ellipses.append(circle((d.x, d.y), a, b, ang))
            safety.append(circle((d.x, d.y), cfg.safety_radius_m, cfg.safety_radius_m, 0.0))
            if len(tr.trail) > 1:
                trails.append([[x, y, 0.01] for _, x, y in thinned(tr.trail)])
        if pts:
            rec.log("fleet/vests/markers", rr.Points3D(pts, labels=labels, colors=colours, radii=0.15))
            rec.log("fleet/vests/heading", rr.Arrows3D(origins=origins, vectors=arrows, colors=colours, radii=0.04))
            rec.log("fleet/vests/ellipses", rr.LineStrips3D(ellipses, colors=colours, radii=0.02))
            rec.log("fleet/vests/safety", rr.LineStrips3D(safety, colors=(200, 60, 200), radii=0.015))
        else:
            for e in ("markers", "heading", "ellipses", "safety"):
                rec.log(f"fleet/vests/{e}", rr.Clear(recursive=False))
        rec.log(
            "fleet/vests/trails",
            rr.LineStrips3D(trails, colors=(255, 200, 0), radii=0.02) if trails else rr.Clear(recursive=False),
        )
        rec.log("warnings", rr.TextDocument(warnings_markdown(state, now), media_type=rr.MediaType.MARKDOWN))
        counts = state.counts()
        for key in ("vests", "received", "invalid", "expired", "timeline_resets"):
            rec.log(f"counts/{key}", rr.Scalars(float(counts[key])))
        rec.log("counts/warnings", rr.Scalars(float(len(flagged))))

    def close(self) -> None:
        """Flush to the sinks and detach (waiting at most ``NETWORK_FLUSH_S`` for a viewer)."""
        try:
            self.rec.flush(timeout_sec=NETWORK_FLUSH_S if self._network else 1e9)
        except Exception:  # noqa: BLE001 - rerun raises a bare RuntimeError on timeout; nothing more to do
            pass
        self.rec.disconnect()


def thinned(trail, n: int = TRAIL_POINTS) -> list:
    """At most ``n`` points of ``trail``, evenly spread over it, its first and newest among them."""
    pts = list(trail)
    if len(pts) <= n:
        return pts
    last = len(pts) - 1
    return [pts[round(k * last / (n - 1))] for k in range(n)]


def warnings_markdown(state: FleetState, now: float) -> str:
    """The warning panel: one table row per warning, then the fleet's counters."""
    warnings = state.warnings(now)
    c = state.counts()
    lines = [f"**{c['vests']} vests**, {len(warnings)} warnings", ""]
    if warnings:
        lines += ["| vest | warning | detail |", "|---|---|---|"]
        lines += [f"| {w.vest} | {w.kind} | {w.text} |" for w in warnings]
    else:
        lines.append("all vests current and certain")
    lines += [
        "",
        f"messages: {c['received']} received, {c['invalid']} invalid, {c['reordered']} out of order, "
        f"{c['expired']} expired; {c['timeline_resets']} timeline resets",
    ]
    if state.last_error:
        lines.append(f"last invalid message: {state.last_error}")
    return "\n".join(lines)
