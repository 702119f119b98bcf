"""``zfusion plan``: the processes of a run and the command that starts each by hand
(:mod:`services.plan`, the list ``zfusion run`` starts itself)."""

from __future__ import annotations

from pathlib import Path

from fusion.lazy import lazy

from . import options

launcher = lazy("services.launcher")
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
    p.add_argument("--asterix-in", nargs="?", const="127.0.0.1:8600", metavar="HOST:PORT",
                   help="the radars and ADS-B stations send ASTERIX to a zfusion ingest asterix on HOST:PORT "
                        "(default %(const)s); writes the scenario with their SAC/SIC beside --rrd (docs/asterix.md)")
    p.add_argument("--standby", action="store_true",
                   help="a hot standby beside the fuser and beside each regional fuser (docs/reliability.md)")
    p.set_defaults(main=run)


def run(args) -> int:
    scenario = request.scenario_of(args)
    topology, method = request.resolve_topology(scenario, args.topology, args.method)
    request.check_methods(scenario, [method], {})
    fabric = ["--zenoh-mode", "client", "--connect", args.connect]
    asterix = launcher.asterix_route(args.scenario, scenario, Path(args.rrd), args.asterix_in) \
        if args.asterix_in else None
    print(plan.RunPlan.build(args.scenario, scenario, topology, method, fabric=fabric, speed=args.speed,
                             rrd=args.rrd, json_path=args.json, router=args.connect, standby=args.standby,
                             asterix=asterix).format())
    return 0
