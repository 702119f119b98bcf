"""The options commands share, and the types that check them as they are parsed.

Light on purpose (the standard library and :mod:`fusion.topology` only): every command
registers its sub-parser from here, so ``zfusion --help`` and an argument error never
load numpy, Zenoh or Rerun. What a value means once a command runs (a Zenoh config, a
key space, a live session) is :mod:`services.commands.values`, loaded then.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import tomllib
from pathlib import Path

from fusion.topology import FUSION_RULES, LAYOUTS, TOPOLOGIES

from ..errors import UserError

# The key space's default deployment and fuser (schemas.keys.DEFAULT_DEPLOYMENT and
# DEFAULT_FUSER, which a test checks these are: schemas loads numpy, which the command
# line does not).
DEFAULT_DEPLOYMENT = "default"
DEFAULT_FUSER = "fuser"
_KEY_ID = re.compile(r"^[A-Za-z0-9_.+-]{1,64}$")  # schemas.keys.check_id's rule

__all__ = ["FUSION_RULES", "TOPOLOGIES", "DEFAULT_DEPLOYMENT", "DEFAULT_FUSER"]


class Parser(argparse.ArgumentParser):
    """argparse with its errors as one line: ``zfusion <command>: <what> (see --help)``."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def ids(text: str) -> list[str]:
    return [s for s in text.split(",") if s]


def speed(text: str) -> str:
    if text != "max":
        try:
            if not float(text) > 0 or not math.isfinite(float(text)):
                raise ValueError
        except ValueError:
            raise argparse.ArgumentTypeError(f"--speed takes a positive number or 'max', not {text!r}") from None
    return text


def key_id(text: str) -> str:
    """An id that names a key chunk (a process, a fuser): ``[A-Za-z0-9_.+-]``, 1-64."""
    if not _KEY_ID.match(text):
        raise argparse.ArgumentTypeError(f"{text!r}: an id is 1-64 characters of [A-Za-z0-9_.+-]")
    return text


def seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is a non-negative integer, not {text!r}")
    return value


def seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive number of seconds, not {text!r}")
    return value


def non_negative(text: str) -> float:
    """``--max-delay``: 0 (release at once) or more seconds."""
    try:
        return 0.0 if float(text) == 0.0 else seconds(text)
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected a non-negative number of seconds, not {text!r}") from None


def split_override(item: str) -> tuple[str, str]:
    """``KEY=VALUE`` of a ``--zenoh-set`` option, e.g.
    ``transport/link/tls/connect_certificate=/etc/zfusion/certs/radar2d.pem``."""
    key, sep, value = item.partition("=")
    if not sep or not key.strip("/ ") or not value:
        raise ValueError(f"expected KEY=VALUE (a Zenoh config path and a JSON5 value), not {item!r}")
    return key.strip(), value


def override(text: str) -> str:
    try:
        split_override(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def setting(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` of ``--set``: a ``[tracker]`` key and its value, parsed as TOML (a
    bare word that is not TOML is taken as a string: ``motion=cv``)."""
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


def zenoh_file_and_overrides(g) -> None:
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="a Zenoh JSON5 config file (TLS, access control, client mode, ...; see deploy/zenoh/)")
    g.add_argument("--zenoh-set", action="append", type=override, metavar="KEY=JSON5",
                   help="set one value of the Zenoh config, applied last, e.g. "
                        "transport/link/tls/connect_certificate=/etc/zfusion/certs/radar2d.pem "
                        "(a value that is not JSON5 is taken as a string); repeatable")


def fabric(p: argparse.ArgumentParser, per_process: bool = True) -> None:
    """How a process joins Zenoh (``--connect``, its mode and config), the key prefix, ``-v``."""
    g = p.add_argument_group("Zenoh fabric (default: peer-to-peer on loopback, no router)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="dial this Zenoh endpoint (router or peer), e.g. tcp/127.0.0.1:7447; repeatable "
                        "(with --zenoh-config: replaces the file's connect endpoints)")
    if per_process:  # one process, one identity: its mode and its own certificate
        g.add_argument("--zenoh-mode", choices=("peer", "client"),
                       help="Zenoh mode (default: the config file's, else peer); a client talks only to its router")
        zenoh_file_and_overrides(g)
    else:
        g.add_argument("--zenoh-config", metavar="FILE",
                       help="a Zenoh JSON5 config file for every process (see deploy/zenoh/)")
    g.add_argument("--deployment", default=DEFAULT_DEPLOYMENT, help="key prefix zf/<deployment>/ (default: %(default)s)")
    verbose(p)


def verbose(p: argparse.ArgumentParser, tracebacks: bool = False) -> None:
    p.add_argument("-v", "--verbose", action="store_true",
                   help="log at debug level; tracebacks for errors" if tracebacks else "log at debug level")


def site_or_scenario(p: argparse.ArgumentParser, required: bool = True) -> None:
    """``--scenario`` (a scenario run) or ``--site`` (a live session: UTC time,
    open-ended, until SIGINT/SIGTERM), and the live session's clock check."""
    g = p.add_mutually_exclusive_group(required=required)
    g.add_argument("--scenario", help="built-in scenario name or path to a .toml file (a scenario run)")
    g.add_argument("--site", help="site file, or a scenario taken as its site: a live session on UTC time, "
                                  "until SIGINT/SIGTERM (docs/live.md)")
    p.add_argument("--max-skew", type=seconds, default=5.0, metavar="S",
                   help="live: refuse stamps more than S seconds ahead of this host's clock (default %(default)s)")


def scenario(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", required=True, help="built-in scenario name or path to a .toml file")


def seed_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=seed, help="replace the scenario's seed (a non-negative integer)")


def method(p: argparse.ArgumentParser, help: str = "estimation method (default: the scenario's)") -> None:
    p.add_argument("--method", help=help)


def fusion_rule(p: argparse.ArgumentParser, help: str = "track-to-track fusion rule of a track-fusion method") -> None:
    p.add_argument("--fusion-rule", choices=FUSION_RULES, help=help)


def fuser(p: argparse.ArgumentParser, help: str = "the fuser whose tracks to take (default: %(default)s)",
          every: bool = False) -> None:
    """``--fuser ID``: which fuser's output a process takes (``every``: ``*`` may name them all)."""
    p.add_argument("--fuser", type=(lambda t: t if t == "*" else key_id(t)) if every else key_id,
                   default=DEFAULT_FUSER, metavar="ID", help=help)


def topology(p: argparse.ArgumentParser) -> None:
    p.add_argument("--topology", choices=LAYOUTS, help="process layout (default: the method's; regional: a "
                   "centralised many-target method as regional fusers under a system fuser, docs/regional.md)")


def tracker_options(p: argparse.ArgumentParser, duration: bool = True) -> None:
    """``--set KEY=VALUE`` (repeatable) and, for scenario runs, ``--duration-s``."""
    p.add_argument("--set", dest="settings", action="append", type=setting, default=[], metavar="KEY=VALUE",
                   help="override a [tracker] key for every method (value in TOML, e.g. q=0.05 or motion='cv'); "
                        "repeatable")
    if duration:
        duration_option(p)


def duration_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration-s", type=seconds, metavar="N", help="override the scenario's duration (s)")


def overrides(args) -> dict:
    """The command line's overrides of ``[tracker]``: ``--fusion-rule``, then ``--set``."""
    out = {"fusion_rule": args.fusion_rule} if getattr(args, "fusion_rule", None) else {}
    out.update(dict(getattr(args, "settings", None) or []))
    return out


def writable_file(path: str | Path, option: str) -> None:
    """``path`` may be written: its directory made if needed and the file opened for
    appending once (removed again if that made it), or a :class:`UserError` saying why
    not. Run before anything starts, so a long run never ends on an output it cannot write."""
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        existed = p.exists()
        with open(p, "ab"):
            pass
        if not existed:
            p.unlink()
    except OSError as e:
        raise UserError(f"{option} {path}: cannot write there ({e.strerror or e}); choose a path you may "
                        f"write to") from None


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
