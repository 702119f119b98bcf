"""``zfusion sensor``: one source process, a sensor, the truth clock or a jammer
(:mod:`services.source`)."""

from __future__ import annotations

import argparse
import math

from ..lazy import lazy
from . import options

source = lazy("services.source")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("sensor", help="one source process: a sensor, the truth clock or a jammer")
    options.scenario(p)
    p.add_argument("--id", required=True, help="sensor, jammer or 'truth'")
    p.add_argument("--speed", type=options.speed, default="1",
                   help="scenario seconds per wall second, or 'max' (default 1)")
    p.add_argument("--start-at", type=float, help="wall-clock epoch of scenario time 0 (default: when ready)")
    p.add_argument("--wait-for", type=options.ids, default=[], help="comma-separated processes to wait for")
    options.seed_option(p)
    p.add_argument("--live", action="store_true",
                   help="live emulation: stamps on the UTC time base (scenario time 0 = --start-at), speed 1")
    options.duration_option(p)
    p.add_argument("--run", type=int, default=0, help=argparse.SUPPRESS)
    options.fabric(p)
    p.set_defaults(main=run)


def run(args) -> int:
    speed = math.inf if args.speed == "max" else float(args.speed)
    return source.run(args.id, args.scenario, values.keys(args), values.zopts(args), speed, args.start_at,
                      args.wait_for, run_index=args.run, seed=args.seed, live=args.live, duration=args.duration_s)
