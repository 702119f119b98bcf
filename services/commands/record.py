"""``zfusion record``: the recorder process, everything into a Rerun recording
(:mod:`services.recording.recorder`)."""

from __future__ import annotations

from fusion.lazy import lazy

from ..rotation import rotated_path
from . import options

recorder = lazy("services.recording.recorder")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("record", help="the recorder process: everything into a Rerun .rrd file")
    p.add_argument("--rrd", required=True, help="the recording file to write (with --rotate-s: <stem>.<k>.rrd)")
    p.add_argument("--id", default="recorder", help="process id (default: %(default)s)")
    p.add_argument("--expect", type=options.ids, default=[],
                   help="stop once these processes have reported done (default: run until signalled)")
    options.site_or_scenario(p, required=False)
    options.seed_option(p)
    p.add_argument("--spawn", action="store_true",
                   help="also stream to a Rerun viewer (started, or reused on port 9876) if a display is available")
    p.add_argument("--rotate-s", type=options.seconds, metavar="N",
                   help="write <stem>.<k>.rrd, one file per N seconds of session time, each complete")
    options.duration_option(p)
    options.fuser(p)
    options.fabric(p)
    p.set_defaults(main=run)


def run(args) -> int:
    options.writable_file(rotated_path(args.rrd, 0) if args.rotate_s else args.rrd, "--rrd")
    return recorder.run(args.id, values.keys(args), values.zopts(args), args.rrd, args.expect, spawn=args.spawn,
                        scenario=args.site or args.scenario, seed=args.seed, rotate_s=args.rotate_s,
                        live=values.live(args), duration=args.duration_s, fuser=args.fuser)
