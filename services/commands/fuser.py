"""``zfusion fuser``: the command-centre fuser process (:mod:`services.fuser`)."""

from __future__ import annotations

from fusion.lazy import lazy

from . import options

fuser = lazy("services.fuser")
plan = lazy("services.plan")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("fuser", help="the command-centre fuser process")
    options.site_or_scenario(p)
    p.add_argument("--max-delay", type=options.non_negative, default=1.0, metavar="S",
                   help="live: wait at most S seconds of wall time for a lagging source (default %(default)s)")
    p.add_argument("--oosm-window", type=options.seconds, default=10.0, metavar="S",
                   help="live: measurements up to S seconds older than the released time are re-filtered "
                        "(out of sequence); older ones are refused as stale (default %(default)s)")
    options.method(p)
    options.fusion_rule(p)
    p.add_argument("--id", help="process id (default: fuser; a --region fuser's is its region's name, a --standby "
                                "FUSER's FUSER-standby)")
    p.add_argument("--standby", metavar="FUSER",
                   help="a hot standby of the fuser FUSER on the same inputs: the same work, published under "
                        "FUSER's identity only once FUSER's process is gone (leadership by Zenoh liveliness); "
                        "a regional fuser's standby: --region NAME --standby NAME")
    role = p.add_mutually_exclusive_group()
    role.add_argument("--region", metavar="NAME", type=options.key_id,
                      help="regional topology: the fuser of region NAME of the scenario's [regions] (its --id is NAME), "
                           "publishing its frames on regional/NAME for the system fuser")
    role.add_argument("--system", action="store_true",
                      help="regional topology: the system fuser over every region's fuser (docs/regional.md)")
    p.add_argument("--source-timeout", type=float, default=5.0, help="seconds of silence before a source is dead")
    p.add_argument("--start-grace", type=float, default=30.0, help="seconds a never-heard source gets at start")
    options.seed_option(p)
    p.add_argument("--json", metavar="PATH", help="scenario run: when done, print the result table and write the "
                                                  "summary JSON here (as zfusion run --json)")
    options.tracker_options(p)
    options.fabric(p)
    p.set_defaults(main=run)


def run(args) -> int:
    if args.json:  # written when the run is done: checked before it starts
        options.writable_file(args.json, "--json")
    method = args.method or values.defaults(args).get("method")
    if args.id is None:  # a regional fuser is named by its region, a standby after its fuser
        args.id = plan.standby_id(args.standby) if args.standby else args.region or plan.FUSER_ID
    return fuser.run(args.id, args.site or args.scenario, method, options.overrides(args), values.keys(args),
                     values.zopts(args), args.source_timeout, args.start_grace, seed=args.seed,
                     live=values.live(args), duration=args.duration_s, json_path=args.json,
                     standby_for=args.standby, region=args.region, system=args.system)
