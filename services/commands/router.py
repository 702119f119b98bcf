"""``zfusion router``: a Zenoh router (:mod:`services.router`)."""

from __future__ import annotations

from fusion.lazy import lazy

from . import options

router = lazy("services.router")


def register(sub) -> None:
    p = sub.add_parser("router", help="run a Zenoh router (tests and small sites; production: zenohd)")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (default: the config file's, else tcp/127.0.0.1:7447); repeatable")
    options.zenoh_file_and_overrides(p)
    options.verbose(p, tracebacks=True)
    p.set_defaults(main=run)


def run(args) -> int:
    return router.run(args.listen, args.zenoh_config, args.zenoh_set or [])
