"""Losing a region, live: how long a killed regional fuser's aircraft are absent from the
system picture, with and without a hot standby per region (issue 28).

Runs ``zfusion run --scenario S --topology regional --live --duration-s D [--standby]``
(a session of its own dialled by the run's processes, following ``fused/fuser``), kills
the primary fuser of ``--region`` with SIGKILL once the system output is ``--kill-after``
seconds old, and lets the run end. Then, for the aircraft inside that region's polygon
and beyond every other region's margin at the kill (its region's alone) that a system
estimate within ``--near`` m held before it (truth at the estimate's time): the longest
wall-time gap between arrivals of system estimates near each in the 30 s before the kill
(the undisturbed revisits), the gap across the kill (from the last arrival before it to
the first after; none after: to 45 s after it) and the longest in the 45 s after it,
against the region's radar periods (the gap across the kill is
:func:`fusion.absence.absences`' absence, on wall-time arrivals); how many ended on another
system id than the one they had at the kill; and whether the machine kept up (the system
output's lag, arrival UTC minus estimate time; each process's CPU from the summary). The
run's own summary says, in the killed fuser's outage, the absences on its scored steps
(scenario time: ``aircraft``, ``longest_absence_s``, ``absent_over_2_periods``,
``not_back``, ``period_s``; docs/regional.md, "Losing a region"), printed at the end.
``--analyse`` reads a run kept in ``--keep DIR`` again.

    python benchmarks/bench_region_loss.py --scenario region-400 --region nw --duration-s 120 [--standby]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import zenoh

from _common import machine_line  # puts the repository on sys.path

from fusion import absence
from schemas import KeySpace, decode
from sensors_sim import load_scenario
from sensors_sim.traffic import population
from services.launcher import free_port
from services.node import ZenohOptions

BEFORE, AFTER = 30.0, 45.0  # s of wall time around the kill over which absences are measured


def run(args, out: Path) -> tuple[list[tuple[float, float, str, np.ndarray]], float, dict]:
    """The run: the system output as (arrival UTC, t, track, east-north), the kill's UTC
    time, the summary."""
    deployment = f"loss{os.getpid()}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(ZenohOptions(listen=[endpoint]).to_config())
    got: list[tuple[float, float, str, np.ndarray]] = []
    lock = threading.Lock()

    def on_fused(sample) -> None:
        msg = decode(sample.payload.to_bytes())
        if msg.kind == "track":
            with lock:
                got.append((time.time(), msg.t, msg.body["track"], np.asarray(msg.body["x"][:2], dtype=float)))

    sub = session.declare_subscriber(KeySpace(deployment).fused("fuser"), on_fused)
    cmd = [sys.executable, "-m", "services.cli", "run", "--scenario", args.scenario, "--topology", "regional",
           "--live", "--duration-s", str(args.duration_s), "--deployment", deployment, "--connect", endpoint,
           "--rrd", str(out / "run.rrd"), "--json", str(out / "run.json"), *(["--standby"] if args.standby else [])]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=(out / "run.log").open("w"))
    killed = None
    try:
        deadline = time.monotonic() + args.duration_s + 600
        while killed is None and time.monotonic() < deadline and proc.poll() is None:
            with lock:
                span = got[-1][1] - got[0][1] if got else 0.0
            if span >= args.kill_after:
                victim = next(c for c in psutil.Process(proc.pid).children(recursive=True)
                              if "--region" in (argv := c.cmdline()) and argv[argv.index("--region") + 1] == args.region
                              and "--standby" not in argv)  # the primary, not its standby
                victim.kill()
                killed = time.time()
            time.sleep(0.05)
        proc.wait(args.duration_s + 600)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(60)
        sub.undeclare()
        session.close()
    if killed is None:
        sys.exit(f"no kill: the system output never spanned {args.kill_after} s (see {out / 'run.log'})")
    return got, killed, json.loads((out / "run.json").read_text())


def absences(sc, got, killed: float, region: str, epoch: float,
             near: float) -> list[tuple[str, float, float, float, bool]]:
    """Per aircraft of ``region`` alone held at the kill: (id, its longest wall-time gap
    between system estimates near it in the ``BEFORE`` s before the kill, the gap across
    the kill, the longest in the ``AFTER`` s after it, whether its nearest system id at
    the end differs from the kill's)."""
    reg = sc.regions[region]
    others = [r for name, r in sc.regions.items() if name != region]
    traffic = population(sc, 0)
    window = [g for g in got if killed - BEFORE <= g[0] <= killed + AFTER]
    at_kill = traffic.fleet(killed - epoch)
    pos = at_kill.positions(killed - epoch)[:, :2]
    mine = reg.inside(pos) & ~np.any([o.holds(pos) for o in others], axis=0)
    ids = [i for i, m in zip(at_kill.ids, mine) if m]
    seen: dict[str, list[tuple[float, str]]] = {i: [] for i in ids}  # aircraft -> (arrival, track) near it
    by_t: dict[float, list] = {}
    for g in window:
        by_t.setdefault(g[1], []).append(g)
    for t in sorted(by_t):
        fleet = traffic.fleet(t - epoch)
        where = dict(zip(fleet.ids, fleet.positions(t - epoch)[:, :2]))
        for arrival, _, track, xy in by_t[t]:
            for i in ids:
                if i in where and np.hypot(*(where[i] - xy)) <= near:
                    seen[i].append((arrival, track))
    gone = absence.absences({i: [a for a, _ in seen[i]] for i in ids}, killed, killed + AFTER, since=killed - BEFORE)
    out = []
    for i, g in gone.items():  # held before the kill
        arrivals = sorted(seen[i])
        a = np.array([at for at, _ in arrivals])
        gaps, starts, ends = np.diff(a), a[:-1], a[1:]
        before = [tr for at, tr in arrivals if at <= killed]
        out.append((i, float(max(gaps[ends <= killed], default=0.0)), g.s,
                    float(max(gaps[starts > killed], default=0.0)), g.back is None or arrivals[-1][1] != before[-1]))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="region-400")
    p.add_argument("--region", default="nw")
    p.add_argument("--duration-s", type=float, default=120.0)
    p.add_argument("--kill-after", type=float, default=60.0, help="s of system output before the kill")
    p.add_argument("--near", type=float, default=2000.0, help="m: a system estimate this close holds the aircraft")
    p.add_argument("--standby", action="store_true")
    p.add_argument("--keep", metavar="DIR", help="keep the run's files here")
    p.add_argument("--analyse", action="store_true", help="no run: analyse the one kept in --keep DIR again")
    args = p.parse_args(argv)
    out = Path(args.keep or tempfile.mkdtemp(prefix="region-loss-"))
    out.mkdir(parents=True, exist_ok=True)
    if args.analyse:
        saved = np.load(out / "fused.npz")
        got = [(a, t, tr, xy) for a, t, tr, xy in zip(saved["arrival"], saved["t"], saved["track"], saved["xy"])]
        killed, doc = float(saved["killed"]), json.loads((out / "run.json").read_text())
    else:
        got, killed, doc = run(args, out)
        np.savez(out / "fused.npz", arrival=[g[0] for g in got], t=[g[1] for g in got], track=[g[2] for g in got],
                 xy=np.array([g[3] for g in got]), killed=killed)
    sc = load_scenario(args.scenario)
    reg = sc.regions[args.region]
    periods = sorted({sc.sensors[s].period for s in reg.sensors if sc.sensors[s].kind.startswith("radar")})
    rows = absences(sc, got, killed, args.region, doc["epoch_utc"], args.near)
    lag = np.array([a - t for a, t, _, _ in got])
    print(f"# Losing region {args.region} of {args.scenario}, live {args.duration_s:g} s, "
          f"{'with' if args.standby else 'without'} a standby per region; {machine_line()}")
    print(f"killed at {killed - doc['epoch_utc']:.1f} s of scenario time; the region's radar periods "
          f"{periods[0]:g}-{periods[-1]:g} s")
    print(f"system output lag (arrival - estimate time): median {np.median(lag):.2f} s, p99 "
          f"{np.percentile(lag, 99):.2f} s, max {lag.max():.2f} s over {len(got)} estimates")
    arrival = np.array([g[0] for g in got])
    print("system output around the kill, by 4 s of wall time: estimates, lag median / max (s)")
    for lo in range(-12, 40, 4):
        m = (arrival >= killed + lo) & (arrival < killed + lo + 4)
        print(f"  {lo:+3d} to {lo + 4:+3d} s: {int(m.sum()):5d}" +
              (f", {np.median(lag[m]):.2f} / {lag[m].max():.2f}" if m.any() else ""))
    if rows:
        print(f"{len(rows)} aircraft of {args.region} alone, held at the kill; the longest gap between system "
              f"estimates near one (s, and in the region's fastest / slowest radar periods):")
        for name, col in (("before the kill", 1), ("across the kill", 2), ("after it", 3)):
            gaps = np.array([r[col] for r in rows])
            worst = max(rows, key=lambda r: r[col])
            print(f"  {name}: longest {gaps.max():.2f} s ({gaps.max() / periods[0]:.2f} / "
                  f"{gaps.max() / periods[-1]:.2f}; {worst[0]}), median {np.median(gaps):.2f} s, "
                  f"over 2 fastest / slowest periods: {int(np.sum(gaps > 2 * periods[0]))} / "
                  f"{int(np.sum(gaps > 2 * periods[-1]))}")
        print(f"  on another system id (or none) at the end: {sum(r[4] for r in rows)}")
    cpu = {n: u for n, u in doc.get("processes", {}).items()}
    busiest = sorted(cpu.items(), key=lambda kv: -(kv[1].get("cpu_s") or 0))[:8]
    print("busiest processes (cpu_s): " + ", ".join(f"{n} {u.get('cpu_s')}" for n, u in busiest))
    print(f"outages: {doc.get('outages')}; files in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
