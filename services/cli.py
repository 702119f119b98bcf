"""The ``zfusion`` command line (contract: docs/design.md, "Command line")."""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
from pathlib import Path

from fusion.methods import SPLIT_METHODS, TOPOLOGIES, TRACK_FUSION_METHODS, track_fusion_rule
from fusion.track_fusion import FUSION_RULES
from schemas import KeySpace
from schemas.keys import DEFAULT_DEPLOYMENT

from .errors import INTERRUPTED, USAGE, UserError, one_line
from .node import ZenohOptions, setup_logging, split_override


def _ids(text: str) -> list[str]:
    return [s for s in text.split(",") if s]


def _speed(text: str) -> str:
    if text != "max":
        try:
            if not float(text) > 0 or not math.isfinite(float(text)):
                raise ValueError
        except ValueError:
            raise argparse.ArgumentTypeError(f"--speed takes a positive number or 'max', not {text!r}") from None
    return text


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is a non-negative integer, not {text!r}")
    return value


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, not {text!r}")
    return value


def _override(text: str) -> str:
    try:
        split_override(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _zenoh_file_and_overrides(g) -> None:
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="a Zenoh JSON5 config file (TLS, access control, client mode, ...; see deploy/zenoh/)")
    g.add_argument("--zenoh-set", action="append", type=_override, metavar="KEY=JSON5",
                   help="set one value of the Zenoh config, applied last, e.g. "
                        "transport/link/tls/connect_certificate=/etc/zfusion/certs/radar2d.pem "
                        "(a value that is not JSON5 is taken as a string); repeatable")


def _fabric(p: argparse.ArgumentParser, per_process: bool = True) -> None:
    g = p.add_argument_group("Zenoh fabric (default: peer-to-peer on loopback, no router)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="dial this Zenoh endpoint (router or peer), e.g. tcp/127.0.0.1:7447; repeatable "
                        "(with --zenoh-config: replaces the file's connect endpoints)")
    if per_process:  # one process, one identity: its mode and its own certificate
        g.add_argument("--zenoh-mode", choices=("peer", "client"),
                       help="Zenoh mode (default: the config file's, else peer); a client talks only to its router")
        _zenoh_file_and_overrides(g)
    else:
        g.add_argument("--zenoh-config", metavar="FILE",
                       help="a Zenoh JSON5 config file for every process (see deploy/zenoh/)")
    g.add_argument("--deployment", default=DEFAULT_DEPLOYMENT, help="key prefix zf/<deployment>/ (default: %(default)s)")
    p.add_argument("-v", "--verbose", action="store_true", help="log at debug level")


def _site_or_scenario(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--scenario`` (a scenario run, as today) or ``--site`` (a live session: UTC time,
    open-ended, until SIGINT/SIGTERM), and the live session's clock check."""
    g = p.add_mutually_exclusive_group(required=required)
    g.add_argument("--scenario", help="built-in scenario name or path to a .toml file (a scenario run)")
    g.add_argument("--site", help="site file, or a scenario taken as its site: a live session on UTC time, "
                                  "until SIGINT/SIGTERM (docs/live.md)")
    p.add_argument("--max-skew", type=_seconds, default=5.0, metavar="S",
                   help="live: refuse stamps more than S seconds ahead of this host's clock (default %(default)s)")


def _non_negative(text: str) -> float:
    """``--max-delay``: 0 (release at once) or more seconds."""
    try:
        return 0.0 if float(text) == 0.0 else _seconds(text)
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected a non-negative number of seconds, not {text!r}") from None


def _live(args):
    """The live options of a process started with ``--site`` (None for ``--scenario``)."""
    from .live import LiveOptions

    if getattr(args, "site", None) is None:
        return None
    return LiveOptions(max_skew=args.max_skew, max_delay=getattr(args, "max_delay", 1.0),
                       oosm_window=getattr(args, "oosm_window", 10.0))


def _defaults(args) -> dict:
    """The ``[defaults]`` of ``--scenario`` or ``--site``; a bad file is one line, exit 2."""
    from .scenario import load, load_site

    return (load(args.scenario) if args.site is None else load_site(args.site)).defaults


def _setting(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--set``: a ``[tracker]`` key and its value, parsed as TOML (a
    bare word that is not TOML is taken as a string: ``motion=cv``)."""
    import tomllib

    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key or not value.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE (a [tracker] key and a TOML value), not {text!r}")
    try:
        return key, tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        if value.strip().replace("-", "").replace("_", "").isalnum():
            return key, value.strip()
        raise argparse.ArgumentTypeError(f"--set {key}: {value!r} is not a TOML value") from None


def _tracker_options(p: argparse.ArgumentParser, duration: bool = True) -> None:
    """``--set KEY=VALUE`` (repeatable) and, for scenario runs, ``--duration-s``."""
    p.add_argument("--set", dest="settings", action="append", type=_setting, default=[], metavar="KEY=VALUE",
                   help="override a [tracker] key for every method (value in TOML, e.g. q=0.05 or motion='cv'); "
                        "repeatable")
    if duration:
        p.add_argument("--duration-s", type=_seconds, metavar="N", help="override the scenario's duration (s)")


def _overrides(args) -> dict:
    """The command line's overrides of ``[tracker]``: ``--fusion-rule``, then ``--set``."""
    out = {"fusion_rule": args.fusion_rule} if getattr(args, "fusion_rule", None) else {}
    out.update(dict(getattr(args, "settings", None) or []))
    return out


def _zopts(args) -> ZenohOptions:
    return ZenohOptions(connect=args.connect or [], config_file=args.zenoh_config,
                        mode=getattr(args, "zenoh_mode", None), overrides=getattr(args, "zenoh_set", None) or [])


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="zfusion", description="Real-time multi-sensor fusion over Zenoh.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("run", help="run a scenario end to end as separate processes over Zenoh")
    p.add_argument("--scenario", required=True, help="built-in scenario name or path to a .toml file")
    p.add_argument("--topology", choices=TOPOLOGIES, help="process layout (default: the method's)")
    p.add_argument("--method", help="estimation method (default: the scenario's)")
    p.add_argument("--fusion-rule", choices=FUSION_RULES, help="track-to-track fusion rule of a track-fusion method")
    p.add_argument("--speed", type=_speed, default="1", help="scenario seconds per wall second, or 'max' (default 1)")
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    p.add_argument("--rrd", help="recording path (default runs/<scenario>-<topology>-<time>.rrd)")
    p.add_argument("--json", help="write the summary JSON here")
    p.add_argument("--spawn", action="store_true",
                   help="also stream the recording live to a Rerun viewer (if a display is available)")
    p.add_argument("--rotate-s", type=_seconds, metavar="N",
                   help="recording in files <stem>.<k>.rrd of N seconds of session time each, each complete")
    p.add_argument("--restart", action=argparse.BooleanOptionalAction, default=True,
                   help="restart the fuser, local trackers and recorder if they are killed (default: on)")
    p.add_argument("--geojson", metavar="PATH", help="also export the fused picture to this GeoJSON file")
    p.add_argument("--cot", metavar="URL", help="also send it as Cursor-on-Target to udp://HOST:PORT or tcp://HOST:PORT")
    _tracker_options(p)
    g = p.add_argument_group("live emulation (docs/live.md)")
    g.add_argument("--live", action="store_true",
                   help="run the scenario's processes as a live session on UTC time (scenario time 0 = start), "
                        "until Ctrl-C, --for, or the sources' end")
    g.add_argument("--for", dest="for_s", type=_seconds, metavar="SECONDS", help="live: stop after this long")
    g.add_argument("--oosm-window", type=_seconds, default=10.0, metavar="S",
                   help="live: the fuser's re-filtering window (default %(default)s s; docs/live.md)")
    p.add_argument("--listen", metavar="ENDPOINT",
                   help="where the run's processes meet (default tcp/127.0.0.1:<a free port>); printed at start, "
                        "for another shell's `zfusion picture --connect ENDPOINT`")
    g.add_argument("--max-delay", type=_non_negative, default=1.0, metavar="S",
                   help="live: the fuser waits at most S seconds for a lagging source (default %(default)s)")
    _fabric(p, per_process=False)  # every child shares these

    p = sub.add_parser("eval", help="Monte Carlo evaluation in-process, with the services' own estimators")
    p.add_argument("--scenario", required=True, help="built-in scenario name or path to a .toml file")
    p.add_argument("--runs", type=int, required=True, help="number of Monte Carlo runs")
    p.add_argument("--methods", nargs="+",
                   help="methods to evaluate (default: every method the scenario's sensors can feed)")
    p.add_argument("--fusion-rule", choices=FUSION_RULES, help="track-to-track fusion rule of the track-fusion methods")
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    p.add_argument("--json", help="write the summary JSON here")
    p.add_argument("--report", metavar="DIR", help="write a Markdown report with PNG plots into DIR")
    p.add_argument("--jobs", type=int, default=1, help="worker processes for the Monte Carlo runs (default 1)")
    _tracker_options(p)
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress line on stderr (default: when stderr is a terminal)")
    p.add_argument("-v", "--verbose", action="store_true", help="log at debug level; tracebacks for errors")

    sub.add_parser("scenarios", help="list the built-in scenarios")

    p = sub.add_parser("plan", help="the processes of a run and the exact command to start each by hand")
    p.add_argument("--scenario", required=True, help="built-in scenario name or path to a .toml file")
    p.add_argument("--topology", choices=TOPOLOGIES, help="process layout (default: the method's)")
    p.add_argument("--method", help="estimation method (default: the scenario's)")
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", metavar="ENDPOINT",
                   help="the router every process dials (default %(default)s)")
    p.add_argument("--speed", type=_speed, default="1", help="the sources' speed (default 1)")
    p.add_argument("--rrd", default="site.rrd", help="the recorder's file (default %(default)s)")
    p.add_argument("--json", default="result.json", help="the fuser's summary (default %(default)s)")

    p = sub.add_parser("view", help="open a recording in the Rerun viewer")
    p.add_argument("path")

    p = sub.add_parser("router", help="run a Zenoh router (tests and small sites; production: zenohd)")
    p.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (default: the config file's, else tcp/127.0.0.1:7447); repeatable")
    _zenoh_file_and_overrides(p)
    p.add_argument("-v", "--verbose", action="store_true", help="log at debug level; tracebacks for errors")

    p = sub.add_parser("sensor", help="one source process: a sensor, the truth clock or a jammer")
    p.add_argument("--scenario", required=True, help="built-in scenario name or path to a .toml file")
    p.add_argument("--id", required=True, help="sensor, jammer or 'truth'")
    p.add_argument("--speed", type=_speed, default="1", help="scenario seconds per wall second, or 'max' (default 1)")
    p.add_argument("--start-at", type=float, help="wall-clock epoch of scenario time 0 (default: when ready)")
    p.add_argument("--wait-for", type=_ids, default=[], help="comma-separated processes to wait for")
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    p.add_argument("--live", action="store_true",
                   help="live emulation: stamps on the UTC time base (scenario time 0 = --start-at), speed 1")
    p.add_argument("--duration-s", type=_seconds, metavar="N", help="override the scenario's duration (s)")
    p.add_argument("--run", type=int, default=0, help=argparse.SUPPRESS)
    _fabric(p)

    p = sub.add_parser("fuser", help="the command-centre fuser process")
    _site_or_scenario(p)
    p.add_argument("--max-delay", type=_non_negative, default=1.0, metavar="S",
                   help="live: wait at most S seconds of wall time for a lagging source (default %(default)s)")
    p.add_argument("--oosm-window", type=_seconds, default=10.0, metavar="S",
                   help="live: measurements up to S seconds older than the released time are re-filtered "
                        "(out of sequence); older ones are refused as stale (default %(default)s)")
    p.add_argument("--method", help="estimation method (default: the scenario's)")
    p.add_argument("--fusion-rule", choices=FUSION_RULES, help="track-to-track fusion rule of a track-fusion method")
    p.add_argument("--id", default="fuser", help="process id (default: %(default)s)")
    p.add_argument("--source-timeout", type=float, default=5.0, help="seconds of silence before a source is dead")
    p.add_argument("--start-grace", type=float, default=30.0, help="seconds a never-heard source gets at start")
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    p.add_argument("--json", metavar="PATH", help="scenario run: when done, print the result table and write the "
                                                  "summary JSON here (as zfusion run --json)")
    _tracker_options(p)
    _fabric(p)

    p = sub.add_parser("tracker", help="a local tracker process (distributed, feedback, two-stage topologies)")
    _site_or_scenario(p)
    p.add_argument("--sensor", required=True, help="the sensor this tracker runs beside")
    p.add_argument("--method", help="distributed method: HNV, PHHNV, DDHNV, KF+TR, MKF+TR (default: the scenario's)")
    p.add_argument("--fusion-rule", choices=FUSION_RULES, help="track-to-track fusion rule of a track-fusion method")
    p.add_argument("--fuser", default="fuser", help="process id of the fuser whose feedback to take")
    p.add_argument("--feedback-timeout", type=float, default=5.0,
                   help="seconds without an answer from the fuser before running alone")
    p.add_argument("--start-grace", type=float, default=30.0, help=argparse.SUPPRESS)
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    _tracker_options(p)
    _fabric(p)

    p = sub.add_parser("picture", help="print the fuser's current tracks as JSON (for late joiners)")
    p.add_argument("--timeout", type=_seconds, default=2.0, metavar="S",
                   help="seconds to wait for a fuser's answer (default %(default)s)")
    _fabric(p)

    p = sub.add_parser("record", help="the recorder process: everything into a Rerun .rrd file")
    p.add_argument("--rrd", required=True, help="the recording file to write (with --rotate-s: <stem>.<k>.rrd)")
    p.add_argument("--id", default="recorder", help="process id (default: %(default)s)")
    p.add_argument("--expect", type=_ids, default=[],
                   help="stop once these processes have reported done (default: run until signalled)")
    _site_or_scenario(p, required=False)
    p.add_argument("--seed", type=_seed, help="replace the scenario's seed (a non-negative integer)")
    p.add_argument("--spawn", action="store_true",
                   help="also stream to a Rerun viewer (started, or reused on port 9876) if a display is available")
    p.add_argument("--rotate-s", type=_seconds, metavar="N",
                   help="write <stem>.<k>.rrd, one file per N seconds of session time, each complete")
    p.add_argument("--duration-s", type=_seconds, metavar="N", help="override the scenario's duration (s)")
    _fabric(p)

    from .ingest.process import add_parser as add_ingest

    add_ingest(sub, _fabric)

    p = sub.add_parser("export", help="the fused picture out: a GeoJSON file, Cursor-on-Target for TAK")
    exporters = p.add_subparsers(dest="exporter", required=True, metavar="FORMAT")
    for name, what in (("geojson", "rewrite an RFC 7946 GeoJSON file after every update"),
                       ("cot", "send Cursor-on-Target events for every update and the sensors"),
                       ("asterix", "send ASTERIX CAT062 system tracks and CAT065 status over UDP (docs/asterix.md)")):
        q = exporters.add_parser(name, help=what)
        if name == "geojson":
            q.add_argument("--file", required=True, metavar="PATH", help="the GeoJSON file (replaced atomically)")
        elif name == "asterix":
            q.add_argument("--udp", required=True, metavar="HOST:PORT", help="where the datagrams go")
            q.add_argument("--sac", type=int, default=0, help="SAC of this tracker, 0-255 (default %(default)s)")
            q.add_argument("--sic", type=int, default=0, help="SIC of this tracker, 0-255 (default %(default)s)")
            q.add_argument("--period-s", type=float, default=0.0,
                           help="send the whole picture this often (then a CAT065 end of batch); 0: every update "
                                "as it comes (default)")
        else:
            from .export.cot import STALE_S, TYPE_EMITTER, TYPE_TRACK

            q.add_argument("--to", required=True, metavar="URL", help="udp://HOST:PORT or tcp://HOST:PORT")
            q.add_argument("--stale-s", type=float, default=STALE_S,
                           help="seconds an event stays valid (default: %(default)s)")
            q.add_argument("--type-emitter", default=TYPE_EMITTER, help="CoT type of an emitter fix (default: %(default)s)")
            q.add_argument("--type-track", default=TYPE_TRACK, help="CoT type of a 3D track (default: %(default)s)")
            q.add_argument("--type-sensor", help="CoT type of every sensor (default: by kind, a-f-G-E-S, "
                                                 "a-f-G-E-S-R for radars, a-f-A airborne)")
        _site_or_scenario(q)  # --site: a live session, times in UTC; --scenario: scenario seconds
        q.add_argument("--id", default=f"export-{name}", help="process id (default: %(default)s)")
        _fabric(q)
    return ap


class _Parser(argparse.ArgumentParser):
    """argparse with its errors as one line: ``zfusion <command>: <what> (see --help)``."""

    def error(self, message: str):
        self.exit(USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")


def main(argv: list[str] | None = None) -> int:
    """Run one command; a user's error is one line on stderr (services/errors.py)."""
    args = build_parser().parse_args(argv)
    setup_logging(getattr(args, "verbose", False))
    try:
        return _command(args)
    except KeyboardInterrupt:
        return INTERRUPTED
    except (Exception, SystemExit) as exc:
        said = one_line(exc)
        if said is None or getattr(args, "verbose", False):
            raise
        text, code = said
        print(text if text.startswith("zfusion ") else f"zfusion {_name(args)}: {text}", file=sys.stderr)
        return code


def _name(args) -> str:
    return " ".join(filter(None, (args.command, getattr(args, "exporter", None), getattr(args, "gateway", None))))


def _command(args) -> int:
    config = getattr(args, "zenoh_config", None)
    if config and not Path(config).is_file():
        raise UserError(f"--zenoh-config {config}: no such file; give a Zenoh JSON5 config file (see deploy/zenoh/)")
    if args.command == "run":
        from .launcher import run

        return run(args)
    if args.command == "eval":
        return _eval(args)
    if args.command == "scenarios":
        from sensors_sim import list_scenarios

        rows = list_scenarios()
        width = max(len(n) for n, _ in rows)
        for name, line in rows:
            print(f"{name:<{width}}  {line}")
        return 0
    if args.command == "plan":
        from .launcher import resolve_topology
        from .plan import format_plan, plan

        scenario = _scenario_of(args)
        topology, method = resolve_topology(scenario, args.topology, args.method)
        _check_overrides(scenario, [method], {}, "plan")
        print(format_plan(scenario, topology, method, plan(args.scenario, scenario, topology, method, args.connect,
                                                           args.speed, args.rrd, args.json)))
        return 0
    if args.command == "view":
        argv = viewer_argv(args.path, os.environ)
        os.execv(argv[0], argv)
    if args.command == "router":
        from .router import run as router

        return router(args.listen, args.zenoh_config, args.zenoh_set or [])
    keys = KeySpace(args.deployment)
    if args.command == "sensor":
        from .source import run as source

        speed = math.inf if args.speed == "max" else float(args.speed)
        return source(args.id, args.scenario, keys, _zopts(args), speed, args.start_at, args.wait_for,
                      run_index=args.run, seed=args.seed, live=args.live, duration=args.duration_s)
    if args.command == "fuser":
        from .fuser import run as fuser

        method = args.method or _defaults(args).get("method")
        return fuser(args.id, args.site or args.scenario, method, _overrides(args), keys, _zopts(args),
                     args.source_timeout, args.start_grace, seed=args.seed, live=_live(args), duration=args.duration_s,
                     json_path=args.json)
    if args.command == "tracker":
        from .tracker import run as tracker

        method = args.method or _defaults(args).get("method")
        if method not in SPLIT_METHODS:
            raise SystemExit(f"zfusion tracker: {method!r} has no local trackers (distributed methods: "
                             f"{', '.join(SPLIT_METHODS)})")
        return tracker(args.sensor, args.site or args.scenario, method, _overrides(args), keys, _zopts(args),
                       args.fuser, args.feedback_timeout, args.start_grace, seed=args.seed, live=_live(args),
                       duration=args.duration_s)
    if args.command == "picture":
        from .picture import main as picture

        return picture(keys, _zopts(args), args.timeout)
    if args.command == "export":
        return _export(args, keys)
    if args.command == "record":
        from .recording.recorder import run as record

        Path(args.rrd).parent.mkdir(parents=True, exist_ok=True)
        return record(args.id, keys, _zopts(args), args.rrd, args.expect,
                      spawn=args.spawn, scenario=args.site or args.scenario, seed=args.seed, rotate_s=args.rotate_s,
                      live=_live(args), duration=args.duration_s)
    if args.command == "ingest":
        from .ingest.process import main as ingest

        return ingest(args, keys, _zopts(args))
    raise AssertionError(args.command)


RRD_MAGIC = b"RRF2"  # how every Rerun recording file starts


def viewer_argv(path: str, env) -> list[str]:
    """The Rerun viewer's command line for ``zfusion view PATH`` (its server on loopback
    only), once the file is a recording and there is a display; else a :class:`UserError`."""
    file = Path(path)
    if not file.is_file():
        raise UserError(f"no such recording: {path}; give the .rrd file a run wrote (zfusion run --rrd PATH)")
    with file.open("rb") as f:
        if f.read(len(RRD_MAGIC)) != RRD_MAGIC:
            raise UserError(f"{path} is not a Rerun recording (it does not start as an .rrd file does); "
                            f"check that the file is whole and is the one a run wrote")
    if sys.platform.startswith("linux") and not (env.get("DISPLAY") or env.get("WAYLAND_DISPLAY")):
        raise UserError(f"no display here (neither DISPLAY nor WAYLAND_DISPLAY is set): copy {path} to a machine "
                        f"with one, or run rerun --serve-web --bind 127.0.0.1 {path} and tunnel ports 9090 and "
                        f"9876 (README)", code=1)
    exe = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    return [exe, "--bind", "127.0.0.1", path]


def _export(args, keys: KeySpace) -> int:
    from .errors import UserError
    from .export import cot, process
    from .scenario import load, load_site

    command = f"zfusion export {args.exporter}"
    live = args.site is not None
    try:
        site = load_site(args.site) if live else load(args.scenario)
    except UserError as e:
        print(f"{command}: {e}; give a site or scenario file", file=sys.stderr)
        return 2
    if args.exporter == "asterix":
        from .export import asterix

        host, _, port = args.udp.rpartition(":")
        if not host or not port.isdigit() or not (0 <= args.sac <= 255 and 0 <= args.sic <= 255) \
                or not (args.period_s >= 0 and math.isfinite(args.period_s)):
            print(f"{command}: --udp HOST:PORT, --sac and --sic 0-255, --period-s 0 or more", file=sys.stderr)
            return 2
        return process.run(args.id, keys, _zopts(args), site, lambda: asterix.AsterixSink(
            cot.UdpSender(host.strip("[]"), int(port)), site, live, args.sac, args.sic, args.period_s),
            live=live, max_skew=args.max_skew)
    if args.exporter == "geojson":
        path = Path(args.file)
        if not path.parent.is_dir():
            print(f"{command}: --file {args.file}: no such directory {path.parent}, create it first", file=sys.stderr)
            return 2
        return process.run(args.id, keys, _zopts(args), site, lambda: process.GeoJSONSink(path, site, live),
                           live=live, max_skew=args.max_skew)
    try:
        cot.parse_url(args.to)
    except ValueError as e:
        print(f"{command}: --to {e}", file=sys.stderr)
        return 2
    if not (args.stale_s > 0 and math.isfinite(args.stale_s)):
        print(f"{command}: --stale-s {args.stale_s:g}: must be a positive number of seconds", file=sys.stderr)
        return 2
    types = cot.Types(track=args.type_track, emitter=args.type_emitter, sensor=args.type_sensor)
    return process.run(args.id, keys, _zopts(args), site,
                       lambda: process.CoTSink(cot.sender_for(args.to), site, args.deployment, types, args.stale_s,
                                               live), live=live, max_skew=args.max_skew)


def _scenario_of(args):
    """``--scenario`` with ``--seed`` and ``--duration-s`` applied; a bad file is one line, exit 2."""
    from .scenario import load

    return load(args.scenario, args.seed, getattr(args, "duration_s", None))


def writable_dir(path: Path, option: str) -> None:
    """``path`` made if needed and written to once, or a :class:`UserError` saying why not."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".zfusion-probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise UserError(f"{option} {path}: cannot write there ({e.strerror or e}); choose a directory "
                        f"you may write to") from None


def _check_overrides(scenario, methods: list[str], overrides: dict, command: str) -> None:
    """Every method must be one the scenario's sensors can feed, and accept the scenario's
    ``[tracker]`` table with the overrides (an unknown key, a bad value): else one line on
    stderr and exit 2."""
    from fusion.methods import make_method, method_config
    from fusion.mtt import AssociationConfig

    from .evaluation import method_misfit
    from .scoring import many_targets

    for m in methods:
        misfit = method_misfit(scenario, m)
        if misfit:
            raise UserError(misfit)
        try:
            make_method(m, method_config(scenario.tracker, m, overrides))
        except ValueError as e:
            print(f"zfusion {command}: {e}", file=sys.stderr)
            raise SystemExit(2) from None
        if many_targets(scenario) and AssociationConfig.split(method_config(scenario.tracker, m, overrides))[0] is None:
            # a single-target method would follow one of them and be scored against all
            raise UserError(f"scenario {scenario.name} has {len(scenario.targets) or 'changing'} targets but no "
                            f"association: {m} alone follows one target; add association = \"gnn\" to its "
                            f"[tracker] table, or --set association=gnn")


def _eval(args) -> int:
    from .evaluation import default_methods, evaluate, variants_for
    from .summary import format_table

    if args.runs < 1:
        raise SystemExit("zfusion eval: --runs must be >= 1")
    if args.jobs < 1:
        raise SystemExit("zfusion eval: --jobs must be >= 1")
    scenario = _scenario_of(args)
    methods = args.methods or default_methods(scenario)
    if not methods:
        raise SystemExit(f"zfusion eval: no method can use the sensors of scenario {scenario.name}")
    if args.fusion_rule and not set(methods) & set(TRACK_FUSION_METHODS):
        raise SystemExit(f"zfusion eval: --fusion-rule applies to the track-fusion methods "
                         f"({', '.join(TRACK_FUSION_METHODS)}); none of {', '.join(methods)} fuses tracks")
    overrides = _overrides(args)
    _check_overrides(scenario, methods, overrides, "eval")
    if args.json:  # the outputs checked before the Monte Carlo, not after it
        writable_dir(Path(args.json).parent, "--json")
    if args.report:
        writable_dir(Path(args.report), "--report")
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            raise UserError("--report draws its plots with matplotlib, which is not installed: "
                            "pip install 'zfusion[report]', or leave out --report") from None
    show = sys.stderr.isatty() if args.progress is None else args.progress
    rule = args.fusion_rule or track_fusion_rule(scenario.tracker, methods)

    from tqdm import tqdm

    # Shown at once (before the first run ends), with the time left from the runs so far.
    bar = tqdm(total=args.runs, desc=f"{scenario.name}: run", file=sys.stderr, disable=not show, ascii=" #",
               bar_format="{desc} {n}/{total} [{bar:30}] {elapsed} spent, {remaining} left", mininterval=0.0)
    bar.refresh()
    try:
        doc = evaluate(scenario, variants_for(methods, overrides), args.runs, jobs=args.jobs,
                       progress=(lambda done, total: bar.update(done - bar.n)) if show else None,
                       fusion_rule=rule)
    except ValueError as exc:
        raise SystemExit(f"zfusion eval: {exc}") from None
    finally:
        bar.close()
    print(format_table(doc))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=1))
    if args.report:
        from .report import write_eval_report

        command = f"zfusion eval --scenario {args.scenario} --runs {args.runs}"
        command += f" --methods {' '.join(args.methods)}" if args.methods else ""
        command += f" --fusion-rule {args.fusion_rule}" if args.fusion_rule else ""
        command += f" --seed {args.seed}" if args.seed is not None else ""
        command += f" --duration-s {args.duration_s:g}" if args.duration_s else ""
        command += "".join(f" --set {k}={v!r}" for k, v in args.settings)
        path = write_eval_report(doc, Path(args.report), command=command)
        print(f"report: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
