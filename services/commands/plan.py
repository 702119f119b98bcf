"""``zfusion plan``: the processes of a run and the command that starts each by hand
(:mod:`services.plan`, the list ``zfusion run`` starts itself)."""

from __future__ import annotations

from ..lazy import lazy
from . import options

plan = lazy("services.plan")
request = lazy("services.request")


def register(sub) -> None:
    p = sub.add_parser("plan", help="the processes of a run and the exact command to start each by hand")
    options.scenario(p)
    options.topology(p)
    options.method(p)
    options.seed_option(p)
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                   help="the router every process dials (default %(default)s)")
    p.add_argument("--speed", type=options.speed, default="1", help="the sources' speed (default 1)")
    p.add_argument("--rrd", default="site.rrd", help="the recorder's file (default %(default)s)")
    p.add_argument("--json", default="result.json", help="the fuser's summary (default %(default)s)")
    p.set_defaults(main=run)


def run(args) -> int:
    scenario = request.scenario_of(args)
    topology, method = request.resolve_topology(scenario, args.topology, args.method)
    request.check_methods(scenario, [method], {})
    fabric = ["--zenoh-mode", "client", "--connect", args.connect]
    print(plan.RunPlan.build(args.scenario, scenario, topology, method, fabric=fabric, speed=args.speed,
                             rrd=args.rrd, json_path=args.json, router=args.connect).format())
    return 0
