"""How every ``zfusion`` process speaks on stderr: one logger, ``zfusion``, whose lines
are ``HH:MM:SS LEVEL text`` (``-v``: debug too, and tracebacks of a user's errors).

Light on purpose (the standard library only): the command line sets it up before it
knows which command runs, so an argument error never loads numpy or Zenoh.
"""

from __future__ import annotations

import logging
import sys

log = logging.getLogger("zfusion")


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
