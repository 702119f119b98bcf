"""Processes that say what they do: a gateway started by hand says what it reads, warns
when the endpoint it dials does not answer (then says when it connects), ends a file or
stdin with a summary line, and with ``-v`` logs each reading; a file of past readings
replays on its own clock; a process on a terminal prints a status line a minute."""

from __future__ import annotations

import logging
import re
import subprocess
import sys
import threading
import time

import pytest

from _ingest_helpers import Capture, gateway, site_toml, stop
from conftest import ROOT, wait_for
from schemas import KeySpace
from services.launcher import free_port
from services.node import STATUS_LINE_S, Node, ZenohOptions, status_line

pytestmark = pytest.mark.slow

RADAR2D = ROOT / "tests" / "data" / "jsonl" / "radar2d.jsonl"  # docs/ingest.md's example: dated 2025-12-01
SUMMARY = re.compile(r"radar2d: end of (\S+): 10 lines, published (\d+), refused (\d+)(?: \(([^)]*)\))?, repeats 0$")


class Lines:
    """A process's stderr, line by line as it comes, each with when it came."""

    def __init__(self, stream):
        self.lines: list[tuple[float, str]] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream) -> None:
        for line in iter(stream.readline, ""):
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def first(self, text: str) -> tuple[float, str] | None:
        return next(((t, line) for t, line in list(self.lines) if text in line), None)

    def text(self) -> str:
        return "\n".join(line for _, line in self.lines)


def test_a_gateway_warns_within_5_s_when_its_endpoint_does_not_answer_then_says_when_it_connects(
        deployment, tmp_path):
    site = tmp_path / "site.toml"
    site.write_text(site_toml({"df1": {"pos_m": [0.0, 0.0, 0.0]}}))
    cap = Capture(deployment)  # its endpoint: a free port nobody listens on yet
    p = gateway("jsonl", "--id", "df1", "--site", str(site), "--input", f"tcp://127.0.0.1:{free_port()}", "-v",
                capture=cap)
    try:
        out = Lines(p.stderr)
        started, line = wait_for(lambda: out.first("reading JSON lines from tcp://"), "the gateway's first line")
        assert "publishing on zf/" in line
        warned, line = wait_for(lambda: out.first("cannot reach"), "a warning that the endpoint does not answer")
        assert cap.endpoint in line and "WARNING" in line
        assert warned - started < 5.0 + 1.5, out.text()  # 5 s after the session opened (and its first line)
        with cap:  # now something listens there: Zenoh keeps dialling, and the gateway says so
            _, line = wait_for(lambda: out.first("connected to"), "a line once connected", timeout=60)
            assert cap.endpoint in line
            p.send_signal(2)
            assert p.wait(15) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert "Traceback" not in out.text()


@pytest.mark.parametrize("how", ["--input", "stdin-file"])
def test_a_year_old_file_replays_in_full_and_ends_with_a_summary(deployment, how):
    """docs/ingest.md's example, as written: a file (or stdin from one) is read on its own
    clock. Before, all 10 readings were refused as stale (and, within --max-age, late)."""
    with Capture(deployment) as cap:
        args = ["jsonl", "--id", "radar2d", "--site", "patent-3d", "-v"]
        if how == "--input":
            p = gateway(*args, "--input", str(RADAR2D), capture=cap, stdin=subprocess.DEVNULL)
            _, err = p.communicate(timeout=120)
        else:
            with RADAR2D.open("rb") as f:
                p = gateway(*args, capture=cap, stdin=f)
                _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-2000:]
        last = err.strip().splitlines()[-1]
        m = SUMMARY.search(last)
        assert m and m.group(2, 3) == ("10", "0"), err[-2000:]
        assert cap.wait(lambda: len(cap.of("range_az")) == 10), len(cap.of("range_az"))
        # -v: one line per reading published, its time in UTC
        published = [line for line in err.splitlines() if "radar2d: published range_az of 2025-12-01T18:00:0" in line]
        assert len(published) == 10, err[-2000:]


def test_a_pipe_of_past_readings_is_refused_and_told_how_to_replay(deployment):
    with Capture(deployment) as cap:
        p = gateway("jsonl", "--id", "radar2d", "--site", "patent-3d", capture=cap, stdin=subprocess.PIPE)
        _, err = p.communicate(RADAR2D.read_text(), timeout=120)
    assert p.returncode == 0, err[-2000:]
    assert "replays on its own clock with --input FILE" in err, err
    m = SUMMARY.search(err.strip().splitlines()[-1])
    assert m and m.group(1) == "stdin" and m.group(2, 3, 4) == ("0", "10", "stale 10"), err[-2000:]


def test_a_live_stdin_reading_is_logged_with_v_and_counted_in_the_summary(deployment):
    line = '{"t": %.3f, "kind": "range_az", "az_deg": 36.87, "range_m": 10198.0}\n'
    with Capture(deployment) as cap:
        p = gateway("jsonl", "--id", "radar2d", "--site", "patent-3d", "-v", capture=cap, stdin=subprocess.PIPE)
        out = Lines(p.stderr)
        wait_for(lambda: out.first("reading JSON lines from stdin"), "the gateway's first line")
        t = time.time()  # fresh: within the heartbeat lag
        p.stdin.write(line % t + "not json\n" + line % (t + 0.01))
        p.stdin.close()
        assert p.wait(60) == 0, out.text()
        wait_for(lambda: out.first("end of stdin"), "the summary line")
        err = out.text()
    assert err.count("radar2d: published range_az of ") == 2, err
    assert err.strip().splitlines()[-1].endswith("end of stdin: 3 lines, published 2, refused 1 (json 1), repeats 0")


def test_status_line_a_minute_on_a_terminal_or_with_v(deployment, caplog, monkeypatch):
    assert status_line("running", {"received": 12, "published": 9, "rejected": 3, "rejected.late": 2,
                                   "rejected.stale": 1, "cpu_s": 0.4}) == \
        "running: received 12, published 9, rejected 3 (late 2, stale 1)"
    assert status_line("ready", {"rejected": 0}) == "ready: nothing yet"
    with Node("gw", "ingest", KeySpace(deployment), ZenohOptions()) as node:
        node.count("received", 5)
        with caplog.at_level(logging.INFO, logger="zfusion"):  # neither a terminal nor -v: quiet
            node._status_line_at -= STATUS_LINE_S
            node.publish_status("running")
            assert "received 5" not in caplog.text
        with caplog.at_level(logging.DEBUG, logger="zfusion"):  # -v
            node.publish_status("running")
            assert "gw: running: received 5" in caplog.text
            node.count("received", 2)
            node.publish_status("running")  # not a minute since the last line: none
            assert "received 7" not in caplog.text
            node._status_line_at -= STATUS_LINE_S
            node.publish_status("running")
            assert "gw: running: received 7" in caplog.text
