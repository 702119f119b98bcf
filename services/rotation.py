"""Recording rotation: a long session as a sequence of files, each complete on its own.

With ``--rotate-s N`` the recorder writes ``<stem>.<k>.rrd`` (k = 0, 1, ...) instead of
``<stem>.rrd``. File k holds what the recorder received while its clock was in one
window ``[a, a + N)`` of the session's time base (scenario seconds, or UTC seconds in a
live session), windows aligned to multiples of N (``a = N·⌊t/N⌋``: hourly files start on
the hour); a window without data makes no file. The clock is the time of the fused
output (:attr:`services.recording.recorder.Recorder.clock`): at ``--speed max`` the sources run
far ahead of it, and what they sent is recorded beside the picture of its time. When
the clock leaves the current window, the file is
closed — its queued rows before the boundary sent, flushed, its footer written, so that
``rerun rrd verify`` passes and it opens alone — and the next one opens with the same
blueprint, the same recording id (the viewer shows the files of one session as one
recording) and every static entity logged again, and the recorder draws the sensors'
sites again at the window's start.

What the recorder carries from one file to the next is what it holds anyway, each
bounded (docs/bounds.md): the static entities, the sites, each live track's and target's
path (``PATH_MAX`` points), the truth samples its scoring waits on, duplicate windows.
"""

from __future__ import annotations

import math
import re
from pathlib import Path


def rotated_path(path: str | Path, k: int) -> Path:
    """``<stem>.<k>.rrd`` beside ``path``."""
    p = Path(path)
    return p.with_name(f"{p.stem}.{k}{p.suffix or '.rrd'}")


def rotated_files(path: str | Path) -> list[Path]:
    """The files a rotating recorder wrote for ``path``, in order."""
    p = Path(path)
    pat = re.compile(re.escape(p.stem) + r"\.(\d+)" + re.escape(p.suffix or ".rrd") + "$")
    found = [(int(m.group(1)), f) for f in p.parent.glob(f"{p.stem}.*") if (m := pat.match(f.name))]
    return [f for _, f in sorted(found)]


class Rotation:
    """When to start the next file, and its name (module docstring)."""

    def __init__(self, path: str | Path, period: float):
        if not (period > 0 and math.isfinite(period)):
            raise ValueError(f"rotation period must be a positive number of seconds, not {period!r}")
        self.path = Path(path)
        self.period = float(period)
        self.k = 0
        self.end = math.inf  # end of the current file's window; inf until the first row's time is known

    def first(self) -> Path:
        return rotated_path(self.path, 0)

    def due(self, t: float) -> float | None:
        """Given the latest row time ``t``: the start of the next window if the current file
        must be closed, else None."""
        if not math.isfinite(t):
            return None
        start = self.period * math.floor(t / self.period)
        if self.end == math.inf:  # the first row fixes the first window
            self.end = start + self.period
            return None
        if t < self.end:
            return None
        self.end = start + self.period
        return start

    def next(self) -> Path:
        self.k += 1
        return rotated_path(self.path, self.k)
