"""Live sessions from outside: ``zfusion run --live`` as real processes on UTC time, a
slow link whose late data is applied as out-of-sequence measurements, and the command
line's live and override options (user mistakes are one line, exit 2)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from services.evaluation import run_method
from services.scoring import truth_function
from services.summary import method_summary
from sensors_sim import load_scenario

from conftest import DATA, ROOT, zfusion
from _recording import rerun_exe
from _runs import FusedWatch

DATA = DATA


def _live(tmp_path: Path, name: str, scenario: str, deployment: str, *extra: str) -> subprocess.Popen:
    return zfusion("run", "--scenario", scenario, "--live", "--for", "20", "--deployment", f"{deployment}{name}",
                   "--json", str(tmp_path / f"{name}.json"), "--rrd", str(tmp_path / f"{name}.rrd"), *extra,
                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(p: subprocess.Popen, tmp_path: Path, name: str) -> dict:
    out, err = p.communicate(timeout=150)
    assert p.returncode == 0, err[-3000:]
    return json.loads((tmp_path / f"{name}.json").read_text())


@pytest.mark.slow
def test_live_run_on_utc_time_and_a_slow_link_applied_out_of_sequence(tmp_path, deployment):
    """patent-3d live for 20 s: UTC epoch and series, >= 10 fused updates, a verifiable
    recording on a timestamp timeline. The same with the angle sensor 2.5 s late and
    --max-delay 0.5: nothing of it rejected, its late scans counted as out of sequence,
    and SS within 1.5x of the on-time run."""
    t0 = time.time()
    runs = {"plain": _live(tmp_path, "plain", "patent-3d", deployment),
            "slow": _live(tmp_path, "slow", str(DATA / "patent-3d-latency.toml"), deployment, "--max-delay", "0.5")}
    docs = {name: _finish(p, tmp_path, name) for name, p in runs.items()}
    for name, doc in docs.items():
        epoch = doc["epoch_utc"]
        assert t0 < epoch < time.time()
        ss = doc["methods"]["SS"]
        assert ss["n_updates"] >= 10
        ts = ss["series"]["t"]
        assert ts == sorted(ts) and epoch - 1e-6 <= ts[0] and ts[-1] <= epoch + 21.0, (epoch, ts[:3], ts[-3:])
        np.testing.assert_allclose(np.diff(ts), 1.0, atol=1e-5)  # one fused update per 1 s scan, on UTC
        v = subprocess.run([rerun_exe(), "rrd", "verify", str(tmp_path / f"{name}.rrd")], capture_output=True, text=True)
        assert v.returncode == 0, v.stderr
        assert _timelines(tmp_path / f"{name}.rrd") == {"utc": "timestamp"}
    angle = docs["slow"]["sources"]["angle"]
    assert angle["rejected"] == 0 and angle["stale"] == 0, angle
    # ~17 of its scans arrive after the radar's were released on a quiet machine; under
    # load the sources start late and their first scans arrive together, in order
    assert angle["oosm"] >= 1, angle
    assert angle["lag_s"] == pytest.approx(2.5, abs=0.5)
    assert docs["plain"]["sources"]["angle"]["oosm"] == 0
    plain, slow = docs["plain"]["methods"]["SS"]["rmse_pos"], docs["slow"]["methods"]["SS"]["rmse_pos"]
    assert slow <= 1.5 * plain, (slow, plain)
    # and the slow link is not free: had its scans been dropped, SS would be the radar alone
    radar_alone = method_summary([run_method(load_scenario("patent-3d"), "RADAR2D")],
                                 truth_function(load_scenario("patent-3d")))["rmse_pos"]
    assert slow < 0.5 * radar_alone, (slow, radar_alone)


def _timelines(path: Path) -> dict[str, str]:
    """Timeline name -> kind ('timestamp' or 'duration') of the recording's rows."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    out = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        for name in chunk.timeline_names:
            kind = rb.schema.field(name).type
            out[name] = "timestamp" if pa.types.is_timestamp(kind) else "duration"
    return out


@pytest.mark.parametrize("argv, says", [
    (["run", "--scenario", "patent-3d", "--live", "--speed", "max"], "zfusion run: --live runs in real time"),
    (["run", "--scenario", "patent-3d", "--for", "5"], "zfusion run: --for is for live runs"),
    (["run", "--scenario", "patent-3d", "--set", "foo=1"], "zfusion run: unknown tracker config key 'foo'"),
    (["eval", "--scenario", "patent-3d", "--runs", "1", "--methods", "SS", "--set", "q='high'"],
     "zfusion eval: tracker config 'q' must be a finite number"),
    (["eval", "--scenario", "patent-3d", "--runs", "1", "--methods", "SS", "--set", "association='jipda'",
      "--set", "jpda_star=1"], "zfusion eval: tracker config 'jpda_star' must be true or false"),
    (["fuser", "--site", "no-such-site.toml"], "zfusion fuser: no-such-site.toml: cannot read"),
    (["fuser", "--site", "patent-3d", "--max-delay", "-1"], "--max-delay: expected a non-negative number"),
])
def test_user_mistakes_are_one_line_and_exit_2(argv, says):
    p = subprocess.run([sys.executable, "-m", "services.cli", *argv], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2, (p.returncode, p.stderr)
    # (argparse's own errors come after its usage lines)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip() and not ln.startswith(("usage:", " "))]
    assert len(lines) == 1 and says in lines[0], p.stderr


def test_eval_duration_and_tracker_overrides(tmp_path):
    """--duration-s shortens the scenario (11 scans at 0..10 s); --set q=0.05 is the
    in-process method run with that q, not the scenario's."""
    js = tmp_path / "e.json"
    p = subprocess.run([sys.executable, "-m", "services.cli", "eval", "--scenario", "patent-3d", "--runs", "1",
                        "--methods", "SS", "--duration-s", "10", "--set", "q=0.05", "--json", str(js)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    got = json.loads(js.read_text())["methods"]["SS"]
    import dataclasses
    sc = dataclasses.replace(load_scenario("patent-3d"), duration=10.0)
    ref = method_summary([run_method(sc, "SS", {"q": 0.05})], truth_function(sc))
    default = method_summary([run_method(sc, "SS")], truth_function(sc))
    assert got["n_updates"] == ref["n_updates"] == 11
    assert got["rmse_pos"] == pytest.approx(ref["rmse_pos"], abs=1e-9)
    assert abs(got["rmse_pos"] - default["rmse_pos"]) > 1e-6


@pytest.mark.slow
def test_live_run_of_an_endless_scenario_goes_on_past_its_duration_until_stopped(tmp_path, deployment):
    """`run --live` without --for on a scenario marked endless (patent-3d-orbit, here with
    duration_s = 4): the sources go on past the duration until Ctrl-C, then the run stops
    in order and writes its summary, its fused updates one a second up to the stop."""
    import signal

    text = (ROOT / "sensors_sim/scenarios/patent-3d-orbit.toml").read_text()
    assert "duration_s = 600.0\nendless = true" in text
    (tmp_path / "orbit.toml").write_text(text.replace("duration_s = 600.0", "duration_s = 4.0"))
    watch = FusedWatch(deployment)
    p = zfusion("run", "--scenario", str(tmp_path / "orbit.toml"), "--live", "--deployment", deployment,
                "--connect", watch.endpoint, "--json", str(tmp_path / "e.json"), "--rrd", str(tmp_path / "e.rrd"),
                stdout=subprocess.DEVNULL, stderr=(tmp_path / "e.err").open("w"))
    try:
        watch.wait_until(1e9, p, timeout=120)  # fusing (a UTC time)
        watch.wait_until(watch.t + 8.0, p)  # twice the duration past the first fused update
        assert p.poll() is None, "the run ended by itself"
        p.send_signal(signal.SIGINT)
        p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
        watch.close()
    err = (tmp_path / "e.err").read_text()
    assert p.returncode == 0, err[-3000:]
    doc = json.loads((tmp_path / "e.json").read_text())
    t = np.array(doc["methods"]["SS"]["series"]["t"]) - doc["epoch_utc"]
    assert t[-1] >= 8.0 and np.all(np.diff(t) <= 1.0 + 1e-6), t
