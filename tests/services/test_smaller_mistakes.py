"""The smaller things a newcomer met: an option misspelt is refused by its command with
the option it may mean; Zenoh's errors read as sentences; a site file is called one;
exports never print -0.0; a first eval --report prints nothing of matplotlib's."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import numpy as np
import pytest

from fusion.geodetic import LocalFrame
from services.export import cot, geojson


def zf(*args: str, timeout: float = 120, **env) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL, env={**os.environ, **env})


def one_line(p: subprocess.CompletedProcess, code: int = 2) -> str:
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == code and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    return lines[0]


@pytest.mark.parametrize("argv, says", [
    (["run", "--scenario", "patent-3d", "--topolgy", "centralised"],
     "zfusion run: unrecognized argument --topolgy; did you mean --topology?"),
    (["run", "--scenaro", "patent-3d"], "zfusion run: unrecognized argument --scenaro; did you mean --scenario?"),
    (["run", "--scenario", "patent-3d", "stray"], "zfusion run: unrecognized arguments: stray"),
    (["ingest", "jsonl", "--id", "x", "--site", "s.toml", "--max-ages", "5"],
     "zfusion ingest jsonl: unrecognized argument --max-ages; did you mean --max-age?"),
])
def test_a_misspelt_option_is_refused_by_its_command_with_the_one_it_may_mean(argv, says):
    assert one_line(zf(*argv)).startswith(says)


def test_an_endpoint_zenoh_refuses_reads_as_a_sentence():
    line = one_line(zf("picture", "--connect", "nonsense"))
    assert "Endpoints must be of the form <protocol>/<address>" in line and ": nonsense" in line, line
    assert "Json5Err" not in line and "Message {" not in line and "location" not in line, line


@pytest.mark.slow
def test_a_busy_listen_port_is_one_balanced_line():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        line = one_line(zf("run", "--scenario", "patent-3d", "--speed", "max", "--listen", f"tcp/127.0.0.1:{port}"))
    assert "Address already in use" in line and line.count("[") == line.count("]"), line


def test_a_missing_site_file_is_called_a_site_file(tmp_path):
    line = one_line(zf("fuser", "--site", str(tmp_path / "missing.toml")))
    assert "cannot read site file" in line and "scenario" not in line, line


def test_exports_never_print_minus_zero():
    frame = LocalFrame(0.0, 0.0, 0.0)  # the equator at the prime meridian: every coordinate near 0
    enu = np.array([-1e-7, -1e-7, -1e-4])  # rounds to zero from below
    feature = geojson.sensor_feature("s1", "df", enu, frame)
    assert feature["geometry"]["coordinates"] == [0.0, 0.0, 0.0]
    assert "-0.0" not in json.dumps(feature)
    event = cot.sensor_event("s1", "df", enu, frame, "uid", cot.Types(), 1.7e9, 60.0).decode()
    assert 'lat="0.0000000" lon="0.0000000" hae="0.0"' in event and "-0.0" not in event, event


@pytest.mark.slow
def test_the_first_eval_report_prints_nothing_of_matplotlib(tmp_path):
    pytest.importorskip("matplotlib")
    p = zf("eval", "--scenario", "patent-3d", "--runs", "1", "--methods", "SS", "--duration-s", "10", "--report",
           str(tmp_path / "report"), MPLCONFIGDIR=str(tmp_path / "mpl"))  # no font cache yet: the first run
    assert p.returncode == 0, p.stderr[-2000:]
    assert "font" not in p.stderr.lower(), p.stderr  # "generated new fontManager", "building the font cache"
