"""``zfusion sensor``: one source process, a sensor, the truth clock or a jammer
(:mod:`services.source`)."""

from __future__ import annotations

import argparse
import math
import urllib.parse

from fusion.lazy import lazy

from ..errors import UserError
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
    p.add_argument("--asterix", metavar="udp://HOST:PORT",
                   help="a radar or ADS-B station with sac_sic: send CAT048/CAT034 or CAT021 datagrams there instead "
                        "of publishing on Zenoh, for zfusion ingest asterix (with --live: times of day in UTC; "
                        "else in scenario seconds, for its --scenario-run; docs/asterix.md)")
    p.add_argument("--asterix-pcap", metavar="FILE",
                   help="the same, written to a pcap capture (zfusion ingest asterix --pcap replays it)")
    p.add_argument("--run", type=int, default=0, help=argparse.SUPPRESS)
    options.fabric(p)
    p.set_defaults(main=run)


def udp_target(text: str) -> tuple[str, int]:
    """``udp://HOST:PORT`` -> (HOST, PORT); UserError otherwise."""
    u = urllib.parse.urlsplit(text)
    try:
        port = u.port
    except ValueError:
        port = None
    if u.scheme != "udp" or not u.hostname or port is None:
        raise UserError(f"--asterix {text!r}: give udp://HOST:PORT")
    return u.hostname, port


def run(args) -> int:
    speed = math.inf if args.speed == "max" else float(args.speed)
    out = None
    if args.asterix or args.asterix_pcap:
        out = source.AsterixOut(udp_target(args.asterix) if args.asterix else None, args.asterix_pcap)
    try:
        return source.run(args.id, args.scenario, values.keys(args), values.zopts(args), speed, args.start_at,
                          args.wait_for, run_index=args.run, seed=args.seed, live=args.live,
                          duration=args.duration_s, asterix=out)
    finally:
        if out is not None:
            out.close()
