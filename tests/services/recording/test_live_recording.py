"""A live session's recording read back with the Rerun SDK: its ``utc`` timeline starts
at the session, not in 1970."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest

from conftest import zfusion
from _recording import row_times, verify

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """patent-3d live for 12 s: (the wall time just before it started, the recording, the summary)."""
    tmp = tmp_path_factory.mktemp("live")
    t0 = time.time()
    p = zfusion("run", "--scenario", "patent-3d", "--live", "--for", "12", "--rrd", str(tmp / "live.rrd"),
                "--json", str(tmp / "live.json"), "--deployment", f"live{int(t0 * 1000) % 10**9}",
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = p.communicate(timeout=240)
    assert p.returncode == 0, err[-3000:]
    verify(tmp / "live.rrd")
    return t0, tmp / "live.rrd", json.loads((tmp / "live.json").read_text())


def test_no_row_of_a_live_recording_is_before_the_session(live):
    t0, rrd, doc = live
    rows = row_times(rrd, "utc")
    assert rows, "no row on the utc timeline"
    early = {path: times[0] for path, times in rows.items() if times[0] < t0}
    assert not early, early  # status events were stamped 1970-01-01 (t = 0)
    last = max(times[-1] for times in rows.values())
    assert last <= time.time() and last - t0 < 600
    assert doc["epoch_utc"] > t0
