"""``zfusion run``: a scenario end to end as separate processes over Zenoh
(:mod:`services.launcher`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from fusion.lazy import lazy

from ..errors import UserError
from ..export.outputs import OUTPUTS
from ..rotation import rotated_path
from . import names, options

launcher = lazy("services.launcher")


def register(sub) -> None:
    p = sub.add_parser("run", help="run a scenario end to end as separate processes over Zenoh")
    options.scenario(p)
    options.topology(p)
    options.method(p)
    options.fusion_rule(p)
    p.add_argument("--speed", type=options.speed, default="1",
                   help="scenario seconds per wall second, or 'max' (default 1)")
    options.seed_option(p)
    p.add_argument("--rrd", help="recording path (default runs/<scenario>-<topology>-<time>.rrd)")
    p.add_argument("--json", help="write the summary JSON here")
    p.add_argument("--spawn", action="store_true",
                   help="also stream the recording live to a Rerun viewer (if a display is available)")
    p.add_argument("--rotate-s", type=options.seconds, metavar="N",
                   help="recording in files <stem>.<k>.rrd of N seconds of session time each, each complete")
    p.add_argument("--restart", action=argparse.BooleanOptionalAction, default=True,
                   help="restart the fuser, local trackers and recorder if they are killed (default: on)")
    for output in OUTPUTS:  # --geojson PATH, --cot URL: an exporter beside the recorder
        p.add_argument(f"--{output.name}", metavar=output.metavar, help=output.run_help)
    p.add_argument("--asterix-in", action="store_true",
                   help="the scenario's radars and ADS-B stations send ASTERIX (CAT048, CAT034, CAT021) over "
                        "loopback UDP to a zfusion ingest asterix, the rest publish on Zenoh (docs/asterix.md)")
    options.tracker_options(p)
    g = p.add_argument_group("live emulation (docs/live.md)")
    g.add_argument("--live", action="store_true",
                   help="run the scenario's processes as a live session on UTC time (scenario time 0 = start), "
                        "until Ctrl-C, --for, or the sources' end")
    g.add_argument("--standby", action="store_true",
                   help="live: a hot standby fuser beside the fuser (and beside each regional fuser), which takes "
                        "over within a second if its fuser's process dies (docs/reliability.md)")
    g.add_argument("--for", dest="for_s", type=options.seconds, metavar="SECONDS", help="live: stop after this long")
    g.add_argument("--oosm-window", type=options.seconds, default=10.0, metavar="S",
                   help="live: the fuser's re-filtering window (default %(default)s s; docs/live.md)")
    p.add_argument("--listen", metavar="ENDPOINT",
                   help="where the run's processes meet (default tcp/127.0.0.1:<a free port>); printed at start, "
                        "for another shell's `zfusion picture --connect ENDPOINT`")
    g.add_argument("--max-delay", type=options.non_negative, default=1.0, metavar="S",
                   help="live: the fuser waits at most S seconds for a lagging source (default %(default)s)")
    options.fabric(p, per_process=False)  # every child shares these
    p.set_defaults(main=run)


def run(args) -> int:
    if args.live and args.speed != "1":
        raise UserError("--live runs in real time: remove --speed")
    if not args.live and args.for_s is not None:
        raise UserError("--for is for live runs: add --live, or use --duration-s")
    if not args.live and args.standby:
        raise UserError("--standby is for live runs: add --live")
    names.check_scenario(args.scenario)
    names.check_method(args.method)
    names.check_settings(args.settings)
    check_outputs(args)
    return launcher.run(args)


def check_outputs(args) -> None:
    """Every file the run writes, checked before any process starts (a live session's
    summary too, which is written only when it ends)."""
    if args.rrd:
        options.writable_file(rotated_path(args.rrd, 0) if args.rotate_s else args.rrd, "--rrd")
    else:
        options.writable_dir(Path("runs"), "--rrd")  # the default, runs/<scenario>-<topology>-<time>.rrd
    if args.json:
        options.writable_file(args.json, "--json")
    for output in OUTPUTS:
        if getattr(args, output.name, None) is not None:
            output.prepare(getattr(args, output.name))
