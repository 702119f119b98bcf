"""A user's mistake as one line: ``zfusion <command>: <what>, <how to fix>``.

Every command runs inside :func:`services.cli.main`, which turns the errors a user can
cause into one line on stderr and an exit code, and lets any other exception (a bug)
through as a traceback. ``-v`` shows the traceback of these too.

* :class:`UserError`: raised by the command line, the launcher and the processes for a
  request that cannot be carried out as given (exit 2, or 1 for a failure such as a
  refused connection); its text is the "what, how to fix" part. A scenario or site file
  that cannot be used is one (:mod:`services.scenario` says ``file:line: field: why``).
* A bad file given on the command line (``OSError`` with a file name), a Zenoh
  configuration or endpoint that Zenoh refuses (``zenoh.ZError``, its Rust source
  location dropped), and a missing optional dependency (``ImportError``) are mapped by
  :func:`one_line`.

Exit codes: 2 usage and input errors, 1 failures, 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import re

USAGE = 2
FAILURE = 1
INTERRUPTED = 130

_RUST_AT = re.compile(r"\s+at /\S+\.rs:\d+\.?")
_RUST_MSG = re.compile(r'msg: "((?:[^"\\]|\\.)*)"')


class UserError(Exception):
    """A request that cannot be carried out as given: ``what, how to fix`` and an exit code."""

    def __init__(self, text: str, code: int = USAGE):
        super().__init__(text)
        self.code = code


def zenoh_reason(exc: BaseException) -> str:
    """A Zenoh error's text on one line: the message of a Rust debug structure
    (``Json5Err(Message { msg: "..." })``), without source locations."""
    text = str(exc)
    m = _RUST_MSG.search(text)
    if m:
        text = m.group(1).replace('\\"', '"')
    text = re.sub(r"Single\((\S+?)\)", r"\1", _RUST_AT.sub("", text))
    return " ".join(text.split()).rstrip(".!")


def zenoh_text(exc: BaseException) -> tuple[str, int]:
    """A Zenoh error without its Rust source location, with what to check."""
    text = zenoh_reason(exc)
    if "Unable to connect" in text or "Timeout" in text:
        return (f"Zenoh: {text}: nothing answers there; start the router (zfusion router --listen EP) "
                f"or fix --connect"), FAILURE
    if "No such file" in text:
        return f"Zenoh: {text}: a file named in the Zenoh config (--zenoh-config, --zenoh-set) is missing", USAGE
    return f"Zenoh: {text}; check --listen/--connect endpoints (tcp/HOST:PORT) and the Zenoh config", USAGE


def interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` comes of a Ctrl-C: a KeyboardInterrupt, or an error raised while
    handling one (numpy turns an interrupt during its import into ``ImportError:
    numpy._core.umath failed to import``)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def one_line(exc: BaseException) -> tuple[str, int] | None:
    """The one line and exit code for an error a user can cause, else None (a bug)."""
    if isinstance(exc, UserError):
        return str(exc), exc.code
    if type(exc).__name__ == "ZError":
        return zenoh_text(exc)
    if isinstance(exc, ImportError) and exc.name:
        extra = " (pip install 'zfusion[report]')" if exc.name.split(".")[0] == "matplotlib" else ""
        return f"this needs the Python package {exc.name.split('.')[0]}, which is not installed{extra}", USAGE
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror or exc}; give a path that exists and that you may use", USAGE
    return None
