"""The run summary's ``processes``: every process's peak memory and CPU time, checked
against psutil's view of the same child processes from outside."""

from __future__ import annotations

import json
import subprocess
import threading
import time

import psutil
import pytest

from services.resources import ProcessUsage, own_usage

from _runs import run_cmd


def test_usage_over_incarnations():
    u = ProcessUsage()
    u.status(1, {"cpu_s": 1.0, "max_rss_mb": 50.0})
    u.status(2, {"cpu_s": 2.5, "max_rss_mb": 60.0})
    u.status(1, {"cpu_s": 0.5, "max_rss_mb": 55.0})  # restarted: seq from 1 again
    u.status(2, {"cpu_s": 0.75, "max_rss_mb": 58.0})
    u.status(3, {"rejected": 0})  # a status without usage (an older process) changes nothing
    assert u.report() == {"max_rss_mb": 60.0, "cpu_s": 3.25, "incarnations": 2}


def test_own_usage_is_the_kernels():
    me = psutil.Process()
    before = own_usage()
    rss_before = me.memory_info().rss / (1 << 20)  # may be below an earlier peak of this worker
    blob = bytearray(64 << 20)  # 64 MiB touched: the high-water mark must reach rss_before + 64
    for i in range(0, len(blob), 4096):
        blob[i] = 1
    rss = me.memory_info().rss / (1 << 20)
    after = own_usage()
    assert after["max_rss_mb"] >= rss - 1.0 and after["max_rss_mb"] >= rss_before + 60.0
    assert after["max_rss_mb"] >= before["max_rss_mb"]
    cpu = me.cpu_times()
    assert abs(after["cpu_s"] - (cpu.user + cpu.system)) < 0.1
    del blob


@pytest.mark.slow
def test_summary_processes_match_psutil(tmp_path, deployment):
    proc = subprocess.Popen(run_cmd(tmp_path, "patent-3d", deployment, "--speed", "10"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    seen: dict[str, dict] = {}  # psutil's view: peak RSS and latest CPU of each child, by --id

    def sample() -> None:
        launcher = psutil.Process(proc.pid)
        while proc.poll() is None:
            try:
                kids = launcher.children()
            except psutil.Error:
                break
            for c in kids:
                try:
                    cmd = c.cmdline()
                    name = cmd[cmd.index("--id") + 1] if "--id" in cmd else None
                    rss, cpu = c.memory_info().rss / (1 << 20), c.cpu_times()
                except (psutil.Error, ValueError):
                    continue
                if name:
                    s = seen.setdefault(name, {"rss": 0.0, "cpu": 0.0})
                    s["rss"] = max(s["rss"], rss)
                    s["cpu"] = max(s["cpu"], cpu.user + cpu.system)
            time.sleep(0.1)

    watcher = threading.Thread(target=sample)
    watcher.start()
    _, err = proc.communicate(timeout=120)
    watcher.join()
    assert proc.returncode == 0, err[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    procs = doc["processes"]
    assert set(procs) == {"fuser", "recorder", "radar2d", "angle", "truth", "launcher"}
    for name, p in procs.items():
        assert p["max_rss_mb"] > 20.0 and p["cpu_s"] > 0.1, (name, p)  # a Python with numpy and zenoh
    for name in ("fuser", "recorder", "radar2d"):
        ps = seen[name]
        # The peak is the kernel's high-water mark as of the last status: about every RSS psutil
        # saw (shutting down, after that status, adds a MB or so), and not far above it.
        assert 0.97 * ps["rss"] - 0.5 <= procs[name]["max_rss_mb"] <= ps["rss"] * 1.5 + 5, (name, procs[name], ps)
        # CPU: the process's last status (about a second before it exits) against psutil's last sample.
        assert ps["cpu"] - 1.5 <= procs[name]["cpu_s"] <= ps["cpu"] + 0.5, (name, procs[name], ps)


def test_a_long_runs_series_is_binned():
    """Beyond SERIES_MAX output times the series is binned; each bin is the RMSE (and
    mean NEES) of its estimates, computed here from the records by hand."""
    import math

    import numpy as np

    from services.summary import SERIES_MAX, aggregate

    rng = np.random.default_rng(3)
    n = 2 * SERIES_MAX + 1
    recs = [{"t": float(i), "n": 9, "pos2": float(rng.uniform(1, 100)), "vel2": 1.0, "acc2": 1.0,
             "nees": float(rng.uniform(1, 20)), "nis": None, "nis_dof": None, "eh": (0.0, 0.0)} for i in range(n)]
    s = aggregate([recs])["series"]
    assert s["bin"] == 3 and len(s["t"]) == math.ceil(n / 3) <= SERIES_MAX
    assert s["t"][:2] == [2.0, 5.0] and s["t"][-1] == float(n - 1) and s["n"][-1] == n % 3
    assert s["rmse_pos"][1] == pytest.approx(math.sqrt(sum(r["pos2"] for r in recs[3:6]) / 3))
    assert s["anees"][0] == pytest.approx(sum(r["nees"] for r in recs[:3]) / 3)
    short = aggregate([recs[:SERIES_MAX]])["series"]
    assert "bin" not in short and short["t"] == [r["t"] for r in recs[:SERIES_MAX]]
