"""The fleet view as a PNG (matplotlib): the same content as the Rerun fleet view, for reports and READMEs.

:func:`plot_floor` draws the floor plan (stickers with IDs, the floor's outline, a 1 m grid);
:func:`plot_fleet` adds every vest as :class:`tagloc.io.fleet_view.FleetView` draws it, and the
warnings beside the map.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from tagloc.core.stickermap import StickerMap
from tagloc.io.fleet import FleetState, ellipse_2sigma
from tagloc.io.fleet_view import HEADING_M, STALE_COLOUR, STATE_COLOURS, WARN_COLOUR
from tagloc.io.rerun_view import circle, map_corners, map_extent


def _rgb(c: tuple[int, int, int]) -> tuple[float, float, float]:
    return (c[0] / 255, c[1] / 255, c[2] / 255)


def plot_floor(ax, smap: StickerMap, labels: bool = True, box: tuple[float, float, float, float] | None = None) -> None:
    """Stickers (outlines, IDs), the floor outline and a 1 m grid on ``ax``, world x right and y up, metres."""
    x0, y0, x1, y1 = box or map_extent(smap)
    for c, sid in zip(map_corners(smap), smap.ids):
        sq = np.vstack([c[:, :2], c[:1, :2]])
        if not (x0 <= sq[:, 0].mean() <= x1 and y0 <= sq[:, 1].mean() <= y1):
            continue
        ax.plot(sq[:, 0], sq[:, 1], color="0.35", lw=0.8)
        if labels:
            ax.text(
                sq[:, 0].mean(), sq[:, 1].mean() - 0.25, str(int(sid)), fontsize=5, ha="center", va="top", color="0.3"
            )
    ex0, ey0, ex1, ey1 = map_extent(smap)
    ax.plot([ex0, ex1, ex1, ex0, ex0], [ey0, ey0, ey1, ey1, ey0], color="0.25", lw=1.0)
    ax.set_xticks(np.arange(math.floor(x0), math.ceil(x1) + 1, 1.0), minor=True)
    ax.set_yticks(np.arange(math.floor(y0), math.ceil(y1) + 1, 1.0), minor=True)
    ax.grid(which="minor", color="0.92", lw=0.5)
    ax.grid(which="major", color="0.85", lw=0.6)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_fleet(state: FleetState, smap: StickerMap, now: float, path: str | Path, title: str = "") -> None:
    """Write the fleet at ``now`` (its staleness clock) as a PNG: the floor plan with every vest, and the warnings."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = state.config
    warnings = state.warnings(now)
    flagged = {w.vest for w in warnings}
    stale = {w.vest for w in warnings if w.kind == "stale"}
    fig = plt.figure(figsize=(13, 6.5), dpi=110)
    ax = fig.add_axes([0.05, 0.08, 0.62, 0.86])
    plot_floor(ax, smap)
    for vest in sorted(state.vests):
        tr = state.vests[vest]
        if not tr.posed:
            continue
        d = tr.last
        colour = _rgb(STALE_COLOUR if vest in stale else WARN_COLOUR if vest in flagged else STATE_COLOURS[d.state])
        if len(tr.trail) > 1:
            trail = np.array([(x, y) for _, x, y in tr.trail])
            ax.plot(trail[:, 0], trail[:, 1], color=_rgb((255, 200, 0)), lw=1.2)
        a, b, ang = ellipse_2sigma(d.cov)
        e = circle((d.x, d.y), a, b, ang)
        ax.plot(e[:, 0], e[:, 1], color=colour, lw=1.2)
        s = circle((d.x, d.y), cfg.safety_radius_m, cfg.safety_radius_m, 0.0)
        ax.plot(s[:, 0], s[:, 1], color=_rgb((200, 60, 200)), lw=0.8, ls="--")
        ax.plot([d.x], [d.y], "o", color=colour, ms=6)
        ax.arrow(d.x, d.y, HEADING_M * math.cos(d.yaw), HEADING_M * math.sin(d.yaw), color=colour, width=0.05)
        ax.text(d.x + 0.3, d.y + 0.3, f"{vest} {d.state}", fontsize=7, color=colour, weight="bold")
    ax.set_title(title or "fleet (top-down)")
    side = fig.add_axes([0.70, 0.08, 0.28, 0.86])
    side.axis("off")
    c = state.counts()
    lines = [f"{c['vests']} vests, {len(warnings)} warnings", ""]
    lines += [f"{w.vest}  {w.kind}: {w.text}" for w in warnings] or ["all vests current and certain"]
    lines += [
        "",
        f"messages: {c['received']} received, {c['invalid']} invalid,",
        f"{c['reordered']} out of order, {c['expired']} expired,",
        f"{c['timeline_resets']} timeline resets",
        "",
        "green tracking, red lost, orange warning, grey stale;",
        f"dashed: {cfg.safety_radius_m:g} m safety circle; solid: 2-sigma ellipse",
    ]
    side.text(0.0, 1.0, "\n".join(lines), va="top", ha="left", fontsize=8, family="monospace", wrap=True)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def plot_walk(
    smap: StickerMap,
    stamps: np.ndarray,
    poses: np.ndarray,
    covs: np.ndarray,
    path: str | Path,
    groundtruth: tuple[np.ndarray, np.ndarray] | None = None,
    ellipse_every_s: float = 1.0,
    title: str = "",
) -> None:
    """Write one walk's floor plan as a PNG: the Rerun replay view's floor plan, drawn with matplotlib.

    Args:
        stamps: (N,) s; poses: (N, 3) body (x, y, yaw); covs: (N, 3, 3); only frames with a pose.
        groundtruth: (stamps (M,), T_world_body (M, 4, 4)) when known.
        ellipse_every_s: draw the 2-sigma position ellipse this often along the walk (s).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    pts = [poses[:, :2]] + ([groundtruth[1][:, :2, 3]] if groundtruth is not None else [])
    allp = np.vstack(pts) if len(poses) else np.zeros((1, 2))
    lo, hi = allp.min(axis=0) - 3.0, allp.max(axis=0) + 3.0
    side = max(hi - lo)  # a square box around the walk (the view's framing: the walk plus 3 m)
    c = (lo + hi) / 2
    plot_floor(ax, smap, box=(c[0] - side / 2, c[1] - side / 2, c[0] + side / 2, c[1] + side / 2))
    if groundtruth is not None:
        g = groundtruth[1][:, :2, 3]
        ax.plot(g[:, 0], g[:, 1], color=_rgb((160, 160, 160)), lw=2.5, label="ground truth")
    if len(poses):
        ax.plot(poses[:, 0], poses[:, 1], color=_rgb((255, 200, 0)), lw=1.5, label="estimate")
        next_t = -np.inf
        for t, p, cov in zip(stamps, poses, covs):
            if t >= next_t:
                a, b, ang = ellipse_2sigma(cov)
                e = circle((p[0], p[1]), a, b, ang)
                ax.plot(e[:, 0], e[:, 1], color=_rgb((230, 120, 0)), lw=1.0)
                next_t = t + ellipse_every_s
        ax.plot([], [], color=_rgb((230, 120, 0)), lw=1.0, label=f"2-sigma ellipse every {ellipse_every_s:g} s")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title or "walk (top-down)")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
