"""``zfusion export NAME``: the fused picture out, one exporter per record of
:data:`services.export.outputs.OUTPUTS` (:mod:`services.export.process`)."""

from __future__ import annotations

from fusion.lazy import lazy

from ..errors import UserError
from ..export.outputs import BY_NAME, OUTPUTS
from . import options

process = lazy("services.export.process")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("export", help="the fused picture out: a GeoJSON file, Cursor-on-Target for TAK")
    exporters = p.add_subparsers(dest="exporter", required=True, metavar="FORMAT")
    for output in OUTPUTS:
        q = exporters.add_parser(output.name, help=output.help)
        q.add_argument(output.option, required=True, metavar=output.metavar, help=output.option_help)
        output.options(q)
        options.site_or_scenario(q)  # --site: a live session, times in UTC; --scenario: scenario seconds
        q.add_argument("--id", default=output.process_id, help="process id (default: %(default)s)")
        options.fuser(q)
        options.fabric(q)
        q.set_defaults(main=run)


def run(args) -> int:
    output = BY_NAME[args.exporter]
    live = args.site is not None
    try:
        site = values.given(args)
    except UserError as e:
        raise UserError(f"{e}; give a site or scenario file") from None
    output.check(args)
    return process.run(args.id, values.keys(args), values.zopts(args), site, lambda: output.sink(args, site, live),
                       live=live, max_skew=args.max_skew, fuser=args.fuser)
