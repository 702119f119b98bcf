"""How every ``zfusion`` process speaks on stderr: one logger, ``zfusion``, whose lines
are ``HH:MM:SS LEVEL text`` (``-v``: debug too, and tracebacks of a user's errors).

Light on purpose (the standard library only): the command line sets it up before it
knows which command runs, so an argument error never loads numpy or Zenoh.
"""

from __future__ import annotations

import datetime
import logging
import sys

log = logging.getLogger("zfusion")


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    # A library's chatter is not ours: matplotlib's "building the font cache" on the first
    # eval --report, its font lookups with -v.
    logging.getLogger("matplotlib").setLevel(logging.ERROR)


def chatty() -> bool:
    """Whether a process says how it is doing as it runs (connected, a status line a
    minute): on a terminal, or with ``-v``. A launched child's stderr is a pipe, so a
    ``zfusion run`` stays quiet."""
    return sys.stderr.isatty() or log.isEnabledFor(logging.DEBUG)


def utc_text(t: float) -> str:
    """UTC POSIX seconds as ISO 8601 to the millisecond: ``2026-12-04T15:54:23.000Z``."""
    try:
        when = datetime.datetime.fromtimestamp(t, datetime.timezone.utc)
    except (OverflowError, OSError, ValueError):
        return f"t = {t!r}"
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"
