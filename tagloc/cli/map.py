"""tagloc map: generate warehouse sticker maps and summarise map files."""

from __future__ import annotations

import argparse
from pathlib import Path

from tagloc.core.errors import InputError
from tagloc.core.sticker import MAX_ID

MAX_FLOOR_M = 10_000.0  # a floor side beyond 10 km is a typo
MAX_STICKERS = MAX_ID + 1

NAME = "map"
HELP = "generate a warehouse sticker map (grid), summarise one (info), audit or refine one from walks (audit, refine)"
DESCRIPTION = """grid: stickers along parallel aisles (running along y, spaced in x) and cross aisles, consecutive
stickers spacing-min..spacing-max apart, jittered sideways, at random yaws, with random distinct
5-digit IDs (or sequential ones); the same seed gives the same map. Written as id,x_m,y_m,yaw_deg.
info: count, bounds and nearest-neighbour spacing of a map file (after full validation).
audit: localise recorded sessions with the map and report missing, unmapped, misplaced and
hard-to-read stickers (report.md, floorplan.png, audit.json, unmapped.csv in the output directory).
refine: localise recorded sessions with the map and jointly re-estimate the stickers seen together
(in one frame, or in frames linked by the floor odometry) with the frames' camera poses, anchored by
each sticker's survey sigma; writes the refined map with sigma_m/sigma_deg columns and a Markdown
report of what moved.

examples:
  tagloc map grid -o maps/demo.csv --width 40 --depth 25 --aisle-spacing 3.0 \\
      --spacing-min 1.2 --spacing-max 2.0 --jitter 0.05 --seed 7
  tagloc map info maps/demo.csv
  tagloc map audit logs/walk1 logs/walk2 logs/walk3 --map site/map.csv -o out/audit
  tagloc map refine logs/walk1 logs/walk2 logs/walk3 --map site/map.csv -o site/map-refined.csv"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    g = sub.add_parser(
        "grid",
        help="generate a warehouse-like map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="generate a warehouse-like map\n\nexample:\n"
        "  tagloc map grid -o maps/demo.csv --width 40 --depth 25 --aisle-spacing 3.0 \\\n"
        "      --spacing-min 1.2 --spacing-max 2.0 --jitter 0.05 --seed 7",
    )
    g.add_argument("-o", "--out", type=Path, required=True, help="output map CSV")
    g.add_argument("--width", type=float, default=40.0, help="floor extent along x, m (default 40)")
    g.add_argument("--depth", type=float, default=25.0, help="floor extent along y, m (default 25)")
    g.add_argument("--aisle-spacing", type=float, default=3.0, help="distance between aisles, m (default 3)")
    g.add_argument("--spacing-min", type=float, default=1.2, help="min distance between stickers, m (default 1.2)")
    g.add_argument("--spacing-max", type=float, default=2.0, help="max distance between stickers, m (default 2.0)")
    g.add_argument("--jitter", type=float, default=0.05, help="max sideways offset from the line, m (default 0.05)")
    g.add_argument("--cross-aisles", type=int, default=2, help="number of cross aisles (default 2)")
    g.add_argument("--margin", type=float, default=1.0, help="distance of lines from the floor edge, m (default 1)")
    g.add_argument(
        "--sequential-ids",
        type=int,
        metavar="FIRST",
        default=None,
        help="number stickers FIRST, FIRST+1, ... instead of random distinct IDs",
    )
    g.add_argument("--seed", type=int, default=7, help="random seed (default 7)")
    i = sub.add_parser(
        "info",
        help="summarise a map file",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="summarise a map file: count, bounds and spacing\n\nexample:\n  tagloc map info maps/demo.csv",
    )
    i.add_argument("map", type=Path, help="map CSV (id,x_m,y_m,yaw_deg)")
    a = sub.add_parser(
        "audit",
        help="find missing, unmapped, misplaced and hard-to-read stickers from sessions",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Localise the sessions with the map and classify its stickers; writes report.md,\n"
        "floorplan.png, audit.json and unmapped.csv (ready-to-add map rows) to the output directory.\n\n"
        "example:\n  tagloc map audit logs/walk1 logs/walk2 logs/walk3 --map site/map.csv -o out/audit",
    )
    a.add_argument("sessions", type=Path, nargs="+", metavar="SESSION", help="recorded session directories")
    a.add_argument("--map", type=Path, help="map to audit (default: the first session's map.csv)")
    a.add_argument("-o", "--out", type=Path, default=Path("out/audit"), help="report directory (default out/audit)")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    r = sub.add_parser(
        "refine",
        help="refine sticker positions and yaws from sessions (joint least squares)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Jointly re-estimate the stickers and the camera poses of the frames that saw two or\n"
        "more of them, or one and a floor-odometry link to another such frame, anchored by each sticker's\n"
        "survey sigma; stickers whose survey the walks contradict are reported as moved.\n"
        "Writes the refined map (sigma_m, sigma_deg columns) and a report.\n\n"
        "example:\n  tagloc map refine logs/walk1 logs/walk2 logs/walk3 --map site/map.csv -o site/map-refined.csv",
    )
    r.add_argument("sessions", type=Path, nargs="+", metavar="SESSION", help="recorded session directories")
    r.add_argument("--map", type=Path, required=True, help="map to refine (its sigma_m/sigma_deg are the priors)")
    r.add_argument("-o", "--out", type=Path, required=True, help="refined map CSV to write")
    r.add_argument("--report", type=Path, help="Markdown report of what moved (default: OUT with .md)")
    r.add_argument("--sigma-m", type=float, default=0.02, help="survey sigma where the map states none, m (0.02)")
    r.add_argument("--sigma-deg", type=float, default=2.0, help="survey yaw sigma where the map states none, deg (2)")
    r.add_argument(
        "--no-odometry",
        action="store_true",
        help="use only frames that saw two or more stickers (no floor-odometry links between frames)",
    )
    r.add_argument("--quiet", action="store_true", help="no progress bar")


def _outputs_apart(args: argparse.Namespace, checks, outputs: list[tuple[str, Path]]) -> None:
    """Refuse outputs that name the same file or one the run reads: the map (``--map``, or the
    first session's map.csv), a session's own files or its frames."""
    from tagloc.io.session import FRAMES_DIR, MAP_FILE, SESSION_INPUTS

    smap = args.map if args.map is not None else args.sessions[0] / MAP_FILE
    inputs = [smap, *(s / name for s in args.sessions for name in SESSION_INPUTS)]
    checks.outputs_apart(outputs, inputs, [s / FRAMES_DIR for s in args.sessions])


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.sim.mapgen import GridMapConfig, map_info, write_grid_map

    if args.action == "info":
        print(map_info(args.map))
        return 0
    if args.action == "audit":
        from tagloc.eval.mapaudit import AUDIT_FILES, audit_sessions
        from tagloc.eval.mapobs import frames_text

        checks.output_dir(args.out, "-o")
        _outputs_apart(args, checks, [(f"-o ({name})", args.out / name) for name in AUDIT_FILES])
        res = audit_sessions(args.sessions, args.out, args.map, progress=not args.quiet)
        report = args.out / "report.md"
        read = [f.sticker_id for f in res.of("unmapped")]
        if res.unchecked:
            # Nothing tracked, nothing checked: every class empty is no all-clear. A refusal (exit 2),
            # with what the walks did read; the report says the same at its top.
            seen = (
                f"they decoded {len(read)} IDs the map lacks ({' '.join(map(str, read[:12]))}"
                f"{' ...' if len(read) > 12 else ''}): is it this floor's map?"
                if read
                else "they decoded no ID the map lacks: too dark, or off the mapped floor?"
            )
            raise InputError(
                f"{report}: NOT CHECKED: with {args.map or args.sessions[0] / 'map.csv'} the tracker hardly"
                f" tracked {', '.join(res.unchecked)} ({res.unchecked_text()}, under"
                f" {res.min_tracked_fraction:.0%}); {seen}"
            )
        counts = ", ".join(f"{len(res.of(k))} {k}" for k in ("missing", "unmapped", "misplaced", "hard"))
        if res.unplaced:
            counts += f" ({len(res.unplaced)} unmapped without a position)"
        print(f"{report}: {counts} (of {len(res.map)} mapped stickers, {frames_text(res.frames, res.skipped)})")
        return 0
    if args.action == "refine":
        from tagloc.eval.maprefine import RefineConfig, default_report, refine_sessions

        checks.number(args.sigma_m, "--sigma-m", 0, 100.0, lo_open=True)
        checks.number(args.sigma_deg, "--sigma-deg", 0, 180.0, lo_open=True)
        if args.out.suffix.lower() == ".md":
            # The report's default name is OUT with .md: it would be written over the refined map.
            raise InputError(f"{args.out}: -o is the refined map (a .csv); the Markdown report goes to --report")
        checks.output_file(args.out, "-o")
        report = args.report if args.report is not None else default_report(args.out)
        checks.output_file(report, "--report" if args.report is not None else "the report (OUT with .md)")
        _outputs_apart(args, checks, [("-o", args.out), ("--report" if args.report else "the report", report)])
        cfg = RefineConfig(
            default_sigma_m=args.sigma_m, default_sigma_deg=args.sigma_deg, odometry=not args.no_odometry
        )
        res = refine_sessions(args.sessions, args.map, args.out, report, cfg, progress=not args.quiet)
        moved = [c.sticker_id for c in res.changes if c.moved]
        print(
            f"{args.out}: {len(res.changes)} stickers refined from {res.frames_used} frames"
            f" ({len(moved)} moved: {' '.join(map(str, moved)) or 'none'}); {res.note or 'report beside it'}"
        )
        return 0
    for option, value in (("--width", args.width), ("--depth", args.depth)):
        checks.number(value, option, 0, MAX_FLOOR_M, lo_open=True)
    checks.number(args.aisle_spacing, "--aisle-spacing", 0, MAX_FLOOR_M, lo_open=True)
    checks.number(args.spacing_min, "--spacing-min", 0, MAX_FLOOR_M, lo_open=True)
    checks.number(args.spacing_max, "--spacing-max", 0, MAX_FLOOR_M, lo_open=True)
    checks.number(args.jitter, "--jitter", 0, MAX_FLOOR_M)
    checks.number(args.margin, "--margin", 0, MAX_FLOOR_M)
    checks.number(args.cross_aisles, "--cross-aisles", 0, 1000)
    if args.sequential_ids is not None:
        checks.number(args.sequential_ids, "--sequential-ids", 0, MAX_ID)
    checks.seed(args.seed)
    # Each aisle carries up to depth / spacing-min stickers, each cross aisle width / spacing-min.
    lines = args.width / args.aisle_spacing + 1
    estimate = lines * args.depth / args.spacing_min + args.cross_aisles * args.width / args.spacing_min
    if estimate > MAX_STICKERS:
        raise InputError(
            f"a {args.width:g} x {args.depth:g} m floor needs ~{estimate:.0f} stickers, more than "
            f"the {MAX_STICKERS} IDs there are"
        )
    checks.output_file(args.out, "-o")
    config = GridMapConfig(
        width_m=args.width,
        depth_m=args.depth,
        aisle_spacing_m=args.aisle_spacing,
        spacing_min_m=args.spacing_min,
        spacing_max_m=args.spacing_max,
        jitter_m=args.jitter,
        cross_aisles=args.cross_aisles,
        margin_m=args.margin,
        ids="random" if args.sequential_ids is None else "sequential",
        first_id=args.sequential_ids or 0,
        seed=args.seed,
    )
    print(write_grid_map(config, args.out))
    return 0
