"""The ``zfusion`` command line (contract: docs/design.md, "Command line").

It only assembles the commands of :mod:`services.commands` (each registers its own
sub-parser and runs itself) and runs the one asked for: a user's mistake is one line on
stderr and an exit code (:mod:`services.errors`), anything else a traceback. Building
the parser loads no numpy, Zenoh or Rerun, so ``--help`` and an argument error answer
at once; a command's modules load when it runs.
"""

from __future__ import annotations

import argparse
import difflib
import sys
from pathlib import Path

from .commands import eval as eval_command
from .commands import (export, fuser, ingest, picture, plan, record, router, run, scenarios, sensor, tracker,
                       view)
from .commands.options import Parser
from .errors import INTERRUPTED, UserError, interrupted, one_line
from .logs import setup_logging

# In the order of `zfusion --help`: a user's commands, then the processes of a deployment.
COMMANDS = (run, eval_command, scenarios, plan, view, router, sensor, fuser, tracker, picture, record, ingest,
            export)


def build_parser() -> Parser:
    ap = Parser(prog="zfusion", description="Real-time multi-sensor fusion over Zenoh.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.register(sub)
    return ap


def command_parser(ap: argparse.ArgumentParser, argv: list[str]) -> argparse.ArgumentParser:
    """The parser of the command ``argv`` names (``run``; ``ingest jsonl``), else ``ap``."""
    p = ap
    for token in argv:
        if token.startswith("-"):
            continue
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or token not in subs[0].choices:
            break
        p = subs[0].choices[token]
    return p


def check_options(p: argparse.ArgumentParser, argv: list[str]) -> None:
    """An option the command does not take is refused by the command, with the option it
    may mean (argparse says only that a required one is missing, or leaves the unknown
    one to the top-level parser, which names no command)."""
    known = [o for o in p._option_string_actions if o.startswith("--")]
    for token in argv:
        if token == "--":
            return
        name = token.split("=", 1)[0]
        if not name.startswith("--") or name in known or any(o.startswith(name) for o in known):
            continue  # argparse takes an unambiguous prefix of an option (and says if it is ambiguous)
        close = difflib.get_close_matches(name, known, n=1)
        p.error(f"unrecognized argument {name}" + (f"; did you mean {close[0]}?" if close else ""))


def main(argv: list[str] | None = None) -> int:
    """Run one command; a user's error is one line on stderr (services/errors.py)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = build_parser()
    command = command_parser(ap, argv)
    if command is not ap:
        check_options(command, argv)
    args, extra = ap.parse_known_args(argv)
    if extra:
        command.error(f"unrecognized arguments: {' '.join(extra)}")
    setup_logging(getattr(args, "verbose", False))
    try:
        config = getattr(args, "zenoh_config", None)
        if config and not Path(config).is_file():
            raise UserError(f"--zenoh-config {config}: no such file; give a Zenoh JSON5 config file "
                            f"(see deploy/zenoh/)")
        return args.main(args)
    except KeyboardInterrupt:
        return INTERRUPTED
    except Exception as exc:
        if interrupted(exc):  # a Ctrl-C while a library was importing
            return INTERRUPTED
        said = one_line(exc)
        if said is None or getattr(args, "verbose", False):
            raise
        text, code = said
        print(text if text.startswith("zfusion ") else f"zfusion {_name(args)}: {text}", file=sys.stderr)
        return code


def _name(args) -> str:
    return " ".join(filter(None, (args.command, getattr(args, "exporter", None), getattr(args, "gateway", None))))


if __name__ == "__main__":
    sys.exit(main())
