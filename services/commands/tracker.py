"""``zfusion tracker``: a local tracker process of the distributed, feedback and
two-stage topologies (:mod:`services.tracker`)."""

from __future__ import annotations

import argparse

from fusion.lazy import lazy

from ..errors import UserError
from . import options

methods = lazy("fusion.methods")
tracker = lazy("services.tracker")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("tracker", help="a local tracker process (distributed, feedback, two-stage topologies)")
    options.site_or_scenario(p)
    p.add_argument("--sensor", required=True, help="the sensor this tracker runs beside")
    options.method(p, "distributed method: HNV, PHHNV, DDHNV, KF+TR, MKF+TR (default: the scenario's)")
    options.fusion_rule(p)
    options.fuser(p, "the fuser whose feedback to take (default: %(default)s)")
    p.add_argument("--feedback-timeout", type=float, default=5.0,
                   help="seconds without an answer from the fuser before running alone")
    p.add_argument("--start-grace", type=float, default=30.0, help=argparse.SUPPRESS)
    options.seed_option(p)
    options.tracker_options(p)
    options.fabric(p)
    p.set_defaults(main=run)


def run(args) -> int:
    method = args.method or values.defaults(args).get("method")
    if method not in methods.SPLIT_METHODS:
        raise UserError(f"{method!r} has no local trackers (distributed methods: {', '.join(methods.SPLIT_METHODS)})")
    return tracker.run(args.sensor, args.site or args.scenario, method, options.overrides(args), values.keys(args),
                       values.zopts(args), args.fuser, args.feedback_timeout, args.start_grace, seed=args.seed,
                       live=values.live(args), duration=args.duration_s)
