"""What each process costs: its CPU time and peak resident memory, for the run summary.

Every process reports its own figures in every status (counters ``cpu_s``, user plus
system CPU seconds of all its threads, and ``max_rss_mb``, the kernel's high-water mark
of its resident set, in MiB), read from ``getrusage(RUSAGE_SELF)``: exact, and free of
any sampling by another process. The launcher keeps, per process id,
:class:`ProcessUsage`: the peak over every incarnation (a process the launcher restarted
is one id with several sessions) and the sum of their CPU times; a new incarnation is
told by its status ``seq`` starting again. A process killed with SIGKILL is counted up
to its last status (at most about a second old).
"""

from __future__ import annotations

import resource
import sys
from dataclasses import dataclass


def own_usage() -> dict[str, float]:
    """This process's ``cpu_s`` and ``max_rss_mb`` so far."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    per_mb = 1 << 20 if sys.platform == "darwin" else 1 << 10  # ru_maxrss: bytes on macOS, KiB on Linux
    return {"cpu_s": round(ru.ru_utime + ru.ru_stime, 3), "max_rss_mb": round(ru.ru_maxrss / per_mb, 2)}


@dataclass
class ProcessUsage:
    """One process id's usage over its incarnations (module docstring)."""

    max_rss_mb: float = 0.0
    cpu_s: float = 0.0  # incarnations that have ended
    incarnations: int = 0
    _seq: int = 0
    _cpu_now: float = 0.0  # the current incarnation's

    def status(self, seq: int, counters: dict) -> None:
        """A status of this process (its ``seq`` and counters)."""
        if "cpu_s" not in counters:
            return
        if seq <= self._seq or self.incarnations == 0:  # numbering starts again: a new incarnation
            self.cpu_s += self._cpu_now
            self._cpu_now = 0.0
            self.incarnations += 1
        self._seq = seq
        self._cpu_now = max(self._cpu_now, float(counters["cpu_s"]))
        self.max_rss_mb = max(self.max_rss_mb, float(counters.get("max_rss_mb", 0.0)))

    def report(self) -> dict:
        return {"max_rss_mb": self.max_rss_mb, "cpu_s": round(self.cpu_s + self._cpu_now, 3),
                "incarnations": self.incarnations}
