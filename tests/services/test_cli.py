"""Command-line contract: listing, and clear errors for bad arguments."""

from __future__ import annotations

import subprocess
import sys


def zf(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True, timeout=60)


def test_scenarios_lists_each_builtin_on_one_line():
    from sensors_sim import list_scenarios

    p = zf("scenarios")
    assert p.returncode == 0
    lines = p.stdout.strip().splitlines()
    names = [n for n, _ in list_scenarios()]
    assert len(lines) == len(names)
    assert any(line.split()[0] == "patent-3d" and len(line.split()) > 2 for line in lines)
    for required in ["patent-3d", "thesis-fixed-c1", "thesis-fixed-c6", "thesis-moving-2", "thesis-moving-9",
                     "jammed-df"]:
        assert required in names


def test_bad_arguments_are_refused_clearly():
    p = zf("run", "--scenario", "patent-3d", "--speed", "-3")
    assert p.returncode != 0 and "--speed" in p.stderr
    p = zf("run", "--scenario", "no-such-scenario", "--speed", "max")
    assert p.returncode != 0 and "no-such-scenario" in p.stderr
    p = zf("run", "--scenario", "patent-3d", "--method", "NOPE", "--speed", "max")
    assert p.returncode != 0 and "NOPE" in p.stderr
    p = zf("view", "/nonexistent.rrd")
    assert p.returncode != 0 and "no such recording" in p.stderr
    p = zf("eval", "--scenario", "thesis-fixed-c3", "--runs", "1", "--fusion-rule", "info")
    assert p.returncode != 0 and "track-fusion methods" in p.stderr


def test_every_option_of_every_command_says_what_it_does():
    import argparse

    from services.cli import build_parser

    silent = []

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, [*path, name])
            elif action.option_strings and not action.help and action.dest != "help":
                silent.append(f"zfusion {' '.join(path)} {action.option_strings[0]}")

    walk(build_parser(), [])
    assert not silent, silent


def test_the_command_line_offers_the_key_spaces_default():
    """The parser names the default deployment and fuser itself (the key space's module
    loads numpy)."""
    from schemas.keys import DEFAULT_DEPLOYMENT, DEFAULT_FUSER
    from services.commands import options

    assert (options.DEFAULT_DEPLOYMENT, options.DEFAULT_FUSER) == (DEFAULT_DEPLOYMENT, DEFAULT_FUSER)


def test_an_interrupt_that_a_library_turned_into_another_error_is_an_interrupt(monkeypatch):
    """Ctrl-C while numpy imports its C extension comes out as ``ImportError: numpy._core.
    umath failed to import`` (raised while handling the KeyboardInterrupt): the command
    ends with 130, as for any Ctrl-C, not 1 with a traceback (ci29, a run sent SIGINT
    0.3 s after it started)."""
    from services import cli
    from services.commands import scenarios
    from services.errors import INTERRUPTED

    def importing(_args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("numpy._core.umath failed to import") from None

    def bug(_args):
        raise ImportError("something else")

    monkeypatch.setattr(scenarios, "run", importing)
    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    for action in parser._subparsers._group_actions[0].choices.values():
        if action.get_default("main") is not None and action.prog.endswith(" scenarios"):
            action.set_defaults(main=importing)
    assert cli.main(["scenarios"]) == INTERRUPTED
    for action in parser._subparsers._group_actions[0].choices.values():
        if action.prog.endswith(" scenarios"):
            action.set_defaults(main=bug)
    try:
        cli.main(["scenarios"])
        raise AssertionError("a bug's ImportError was taken for an interrupt")
    except ImportError:
        pass
