"""tagloc monitor: every vest on the warehouse map, live from MQTT or from a bag."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "monitor"
HELP = "show every vest on the map in Rerun, live from MQTT (or from a recorded bag)"
DESCRIPTION = """Subscribe to the vests' pose topics on an MQTT broker (connects out, never listens) and show the
fleet in Rerun: the map from above with sticker IDs, each vest labelled with its state colour, its
2-sigma ellipse, a safety circle and its trail, and a warning panel for vests whose ID two senders
share (duplicate), or that are stale (no new pose for --stale s), expired (pose older than --max-age s on arrival, epoch clocks), lost,
without a pose yet (initialising), or too uncertain (2-sigma above --max-2sigma m). Invalid messages
are counted, never shown; among them, a time more than --max-skew s ahead of the monitor's clock. --print-every S also prints the warnings
to the terminal (with no viewer, the way to watch); a summary is printed at the end.

examples:
  tagloc monitor mqtt://broker:1883/tagloc/+/pose --map map.csv --spawn
  tagloc monitor mqtt://127.0.0.1 --map maps/demo.csv --save fleet.rrd --max-seconds 60
  tagloc monitor mqtt://broker/tagloc/+/pose --map map.csv --print-every 5      # headless
  tagloc monitor --from-bag out/v1.bag2 --from-bag out/v2.bag2 --map maps/demo.csv --save fleet.rrd"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from tagloc.io.fleet_config import FleetConfig

    d = FleetConfig()
    p.add_argument("url", nargs="?", help="mqtt://HOST[:PORT][/TOPIC] (topic filter default tagloc/+/pose)")
    p.add_argument(
        "--from-bag",
        type=Path,
        action="append",
        default=[],
        metavar="BAG",
        help="replay the pose topics of a bag instead (repeatable: one bag per vest, merged in time)",
    )
    p.add_argument("--map", type=Path, required=True, help="sticker map CSV")
    p.add_argument("--save", type=Path, metavar="FILE.rrd", help="record to a Rerun file")
    p.add_argument("--spawn", action="store_true", help="start a Rerun viewer")
    p.add_argument("--connect", metavar="URL", help="stream to a running Rerun viewer")
    p.add_argument("--stale", type=float, default=d.stale_s, help=f"s without a message: stale (default {d.stale_s})")
    p.add_argument("--max-age", type=float, default=d.max_age_s, help=f"s old on arrival: expired ({d.max_age_s})")
    p.add_argument("--max-2sigma", type=float, default=d.max_2sigma_m, help=f"m: too uncertain ({d.max_2sigma_m})")
    p.add_argument(
        "--max-skew",
        type=float,
        default=d.max_skew_s,
        help=f"s a message's time may be ahead of the monitor's clock before it is refused ({d.max_skew_s})",
    )
    p.add_argument("--safety-radius", type=float, default=d.safety_radius_m, help=f"m ({d.safety_radius_m})")
    p.add_argument("--trail", type=float, default=d.trail_s, help=f"s of trail per vest ({d.trail_s})")
    p.add_argument("--refresh", type=float, default=10.0, help="redraws per second (default 10)")
    p.add_argument("--max-seconds", type=float, help="stop after this many seconds (live)")
    p.add_argument("--print-every", type=float, metavar="S", help="print counts and warnings every S seconds (live)")
    p.add_argument("--png", type=Path, metavar="FILE.png", help="write the fleet at the end as a PNG (matplotlib)")


def run(args: argparse.Namespace) -> int:
    from tagloc.apps.monitor import MonitorConfig, run_monitor
    from tagloc.cli import checks
    from tagloc.io.fleet_config import FleetConfig

    for option, value in (
        ("--stale", args.stale),
        ("--max-age", args.max_age),
        ("--max-2sigma", args.max_2sigma),
        ("--max-skew", args.max_skew),
    ):
        checks.number(value, option, 0, lo_open=True)
    for option, value in (("--safety-radius", args.safety_radius), ("--trail", args.trail)):
        checks.number(value, option, 0)
    checks.number(args.refresh, "--refresh", 0, 1000, lo_open=True)
    for option, value in (("--max-seconds", args.max_seconds), ("--print-every", args.print_every)):
        if value is not None:
            checks.number(value, option, 0, lo_open=True)
    checks.output_file(args.save, "--save")
    checks.output_file(args.png, "--png", suffixes=(".png",))

    summary = run_monitor(
        MonitorConfig(
            map=args.map,
            url=args.url,
            from_bag=args.from_bag,
            save=args.save,
            spawn=args.spawn,
            connect=args.connect,
            fleet=FleetConfig(
                stale_s=args.stale,
                max_age_s=args.max_age,
                max_2sigma_m=args.max_2sigma,
                max_skew_s=args.max_skew,
                safety_radius_m=args.safety_radius,
                trail_s=args.trail,
            ),
            refresh_hz=args.refresh,
            max_seconds=args.max_seconds,
            png=args.png,
            print_every_s=args.print_every,
        )
    )
    print(summary.format())
    # Scripts watching the fleet must not take "no broker" for "no vests".
    return 0 if summary.broker_reached else 1
