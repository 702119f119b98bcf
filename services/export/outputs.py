"""The exporters, one record each: what ``zfusion export NAME`` takes and builds, and
what ``zfusion run --NAME VALUE`` starts beside the recorder.

An :class:`Output` names the option that says where the picture goes (``--file``,
``--to``), the exporter's further options, the checks a value must pass before
anything starts, and the sink its process feeds (:mod:`services.export.process`). The
command line (:mod:`services.commands.export`, :mod:`services.commands.run`) and the run's
plan (:mod:`services.plan`) read :data:`OUTPUTS`; adding an exporter is a sink and one
record here. Light on purpose: the sinks' modules load when a process builds one.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from fusion.lazy import lazy

from ..commands.options import writable_file
from ..errors import UserError
from .cot_types import STALE_S, TYPE_EMITTER, TYPE_TRACK

asterix = lazy("services.export.asterix")
cot = lazy("services.export.cot")
process = lazy("services.export.process")


@dataclass(frozen=True)
class Output:
    """One exporter.

    Attributes:
        name: ``zfusion export NAME``, ``zfusion run --NAME``; its process is ``export-NAME``.
        option: the exporter's option for where the picture goes, e.g. ``--file``.
        metavar, option_help: that option's.
        help: the ``zfusion export NAME`` command's.
        run_help: ``zfusion run --NAME``'s.
        options: adds the exporter's further options to its parser.
        prepare: the value of ``zfusion run --NAME`` as its child takes it (a path
            resolved, its directory made), or a :class:`UserError`.
        check: the ``zfusion export NAME`` command's checks of its options (a UserError).
        sink: ``(args, site, live) -> Sink``, built by the exporter process.
    """

    name: str
    option: str
    metavar: str
    option_help: str
    help: str
    run_help: str
    prepare: Callable[[str], str]
    check: Callable[[argparse.Namespace], None]
    sink: Callable[[argparse.Namespace, Any, bool], Any]
    options: Callable[[argparse.ArgumentParser], None] = lambda p: None

    @property
    def process_id(self) -> str:
        return f"export-{self.name}"

    @property
    def dest(self) -> str:
        """The attribute its option is parsed into (``--file``: ``file``)."""
        return self.option.lstrip("-").replace("-", "_")


# -- GeoJSON ---------------------------------------------------------------------------------


def _geojson_prepare(value: str) -> str:
    writable_file(value, "--geojson")
    return str(Path(value).resolve())


def _geojson_check(args) -> None:
    path = Path(args.file)
    if not path.parent.is_dir():
        raise UserError(f"--file {args.file}: no such directory {path.parent}, create it first")
    writable_file(path, "--file")


def _geojson_sink(args, site, live: bool):
    return process.GeoJSONSink(Path(args.file), site, live)


# -- Cursor-on-Target -------------------------------------------------------------------------


def _cot_url(value: str, option: str) -> str:
    try:
        cot.parse_url(value)
    except ValueError as e:
        raise UserError(f"{option} {e}") from None
    return value


def _cot_check(args) -> None:
    _cot_url(args.to, "--to")
    if not (args.stale_s > 0 and args.stale_s < float("inf")):
        raise UserError(f"--stale-s {args.stale_s:g}: must be a positive number of seconds")


def _cot_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--stale-s", type=float, default=STALE_S, help="seconds an event stays valid (default: %(default)s)")
    q.add_argument("--type-emitter", default=TYPE_EMITTER, help="CoT type of an emitter fix (default: %(default)s)")
    q.add_argument("--type-track", default=TYPE_TRACK, help="CoT type of a 3D track (default: %(default)s)")
    q.add_argument("--type-sensor", help="CoT type of every sensor (default: by kind, a-f-G-E-S, "
                                         "a-f-G-E-S-R for radars, a-f-A airborne)")


def _cot_sink(args, site, live: bool):
    types = cot.Types(track=args.type_track, emitter=args.type_emitter, sensor=args.type_sensor)
    return process.CoTSink(cot.sender_for(args.to), site, args.deployment, types, args.stale_s, live, args.fuser)


# -- ASTERIX ----------------------------------------------------------------------------------


def _host_port(value: str, option: str) -> str:
    host, _, port = value.rpartition(":")
    if not host or not port.isdigit():
        raise UserError(f"{option} {value}: expected HOST:PORT")
    return value


def _asterix_check(args) -> None:
    host, _, port = args.udp.rpartition(":")
    if not host or not port.isdigit() or not (0 <= args.sac <= 255 and 0 <= args.sic <= 255) \
            or not (args.period_s >= 0 and args.period_s < float("inf")):
        raise UserError("--udp HOST:PORT, --sac and --sic 0-255, --period-s 0 or more")


def _asterix_options(q: argparse.ArgumentParser) -> None:
    q.add_argument("--sac", type=int, default=0, help="SAC of this tracker, 0-255 (default %(default)s)")
    q.add_argument("--sic", type=int, default=0, help="SIC of this tracker, 0-255 (default %(default)s)")
    q.add_argument("--period-s", type=float, default=0.0,
                   help="send the whole picture this often (then a CAT065 end of batch); 0: every update "
                        "as it comes (default)")


def _asterix_sink(args, site, live: bool):
    host, _, port = args.udp.rpartition(":")
    return asterix.AsterixSink(cot.UdpSender(host.strip("[]"), int(port)), site, live, args.sac, args.sic,
                               args.period_s)


OUTPUTS: tuple[Output, ...] = (
    Output("geojson", "--file", "PATH", "the GeoJSON file (replaced atomically)",
           help="rewrite an RFC 7946 GeoJSON file after every update",
           run_help="also export the fused picture to this GeoJSON file",
           prepare=_geojson_prepare, check=_geojson_check, sink=_geojson_sink),
    Output("cot", "--to", "URL", "udp://HOST:PORT or tcp://HOST:PORT",
           help="send Cursor-on-Target events for every update and the sensors",
           run_help="also send it as Cursor-on-Target to udp://HOST:PORT or tcp://HOST:PORT",
           prepare=lambda value: _cot_url(value, "--cot"), check=_cot_check, sink=_cot_sink, options=_cot_options),
    Output("asterix", "--udp", "HOST:PORT", "where the datagrams go",
           help="send ASTERIX CAT062 system tracks and CAT065 status over UDP (docs/asterix.md)",
           run_help="also send it as ASTERIX CAT062 system tracks to HOST:PORT over UDP",
           prepare=lambda value: _host_port(value, "--asterix"), check=_asterix_check, sink=_asterix_sink,
           options=_asterix_options),
)
BY_NAME = {o.name: o for o in OUTPUTS}
