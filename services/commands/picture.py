"""``zfusion picture``: the fuser's current tracks as one line of JSON (:mod:`services.picture`)."""

from __future__ import annotations

from fusion.lazy import lazy

from . import options

picture = lazy("services.picture")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("picture", help="print the fuser's current tracks as JSON (for late joiners)")
    p.add_argument("--timeout", type=options.seconds, default=2.0, metavar="S",
                   help="seconds to wait for a fuser's answer (default %(default)s)")
    options.fuser(p, "the fuser to ask (default: %(default)s; * every fuser, one line each)", every=True)
    options.fabric(p)
    p.set_defaults(main=run)


def run(args) -> int:
    return picture.main(values.keys(args), values.zopts(args), args.fuser, args.timeout)
