"""The ``zfusion`` command's entry point: SIGINT stops it, however it was started.

A job that a non-interactive shell starts in the background inherits SIGINT ignored,
and Python keeps an inherited "ignore": such a run heard SIGINT only once its own
handler was installed (``services.node.Node``), and one sent in its first second was
lost for good. The default handler is restored here, before the command line and the
libraries are imported; an interrupt while they are importing, or while the command
line is built, ends the command with 130, as a Ctrl-C later does, without a traceback."""

import signal
import sys

signal.signal(signal.SIGINT, signal.default_int_handler)

from services.errors import INTERRUPTED  # noqa: E402  (after the handler; it imports only re)

try:
    from services.cli import main as command  # noqa: E402  (light: the commands' modules load as they run)
except KeyboardInterrupt:
    sys.exit(INTERRUPTED)


def main() -> int:
    try:
        return command()  # which says 130 itself once it runs its command
    except KeyboardInterrupt:
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
