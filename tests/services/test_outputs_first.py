"""Every output path is checked before any process starts: a path that cannot be written
is one line on stderr and exit 2, at once, never a traceback from a child, nor (live) a
summary lost at the end of a long session."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from conftest import ROOT

UNWRITABLE = "/proc/zfusion-x"  # /proc exists and takes no new file, even as root


def zf(*args: str, timeout: float = 60) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True,
                       timeout=timeout, stdin=subprocess.DEVNULL, cwd=ROOT)
    return p, time.monotonic() - t0


CASES = {
    "run-rrd": (["run", "--scenario", "patent-3d", "--speed", "max", "--rrd", f"{UNWRITABLE}.rrd"], "--rrd"),
    "run-json": (["run", "--scenario", "patent-3d", "--speed", "max", "--json", f"{UNWRITABLE}.json"], "--json"),
    "run-live-json": (["run", "--scenario", "patent-3d", "--live", "--for", "30", "--json", f"{UNWRITABLE}.json"],
                      "--json"),
    "run-rotated-rrd": (["run", "--scenario", "patent-3d", "--speed", "max", "--rotate-s", "10", "--rrd",
                         f"{UNWRITABLE}/r.rrd"], "--rrd"),
    "run-geojson": (["run", "--scenario", "patent-3d", "--speed", "max", "--geojson", f"{UNWRITABLE}.geojson"],
                    "--geojson"),
    "record-rrd": (["record", "--rrd", f"{UNWRITABLE}.rrd"], "--rrd"),
    "record-rotated-rrd": (["record", "--rrd", f"{UNWRITABLE}.rrd", "--rotate-s", "60"], "--rrd"),
    "export-geojson": (["export", "geojson", "--file", f"{UNWRITABLE}.geojson", "--scenario", "patent-3d"],
                       "--file"),
    "fuser-json": (["fuser", "--scenario", "patent-3d", "--json", f"{UNWRITABLE}.json"], "--json"),
    "eval-json": (["eval", "--scenario", "patent-3d", "--runs", "1", "--json", f"{UNWRITABLE}.json"], "--json"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_an_unwritable_output_is_one_line_before_anything_starts(case):
    argv, option = CASES[case]
    p, took = zf(*argv)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert "Traceback" not in p.stderr, p.stderr[-3000:]
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith(f"zfusion {argv[0]}") and option in lines[0] \
        and "cannot write" in lines[0], p.stderr
    assert took < 3.0 or os.getloadavg()[0] > 4, took  # no process was started (a run takes seconds to start)


def test_the_check_leaves_no_file_behind(tmp_path):
    """The check writes where the output goes; a refused run leaves nothing there."""
    out = tmp_path / "sub" / "x.json"
    p, _ = zf("run", "--scenario", "patent-3d", "--method", "NOPE", "--json", str(out))
    assert p.returncode == 2 and not out.exists()


def test_checks_load_nothing_heavy():
    """The checks run before the launcher is imported: no numpy, no Zenoh, no Rerun."""
    code = ("import sys; from services.cli import main; rc = main(sys.argv[1:]); "
            "print(rc, sorted(m for m in ('numpy', 'zenoh', 'rerun') if m in sys.modules))")
    p = subprocess.run([sys.executable, "-c", code, "run", "--scenario", "patent-3d", "--rrd", f"{UNWRITABLE}.rrd"],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.stdout.split(None, 1) == ["2", "[]\n"], (p.stdout, p.stderr)
