"""Today's many-target tracker at a region's scale: ``zfusion eval`` time per simulated
second against the number of aircraft, stage by stage, with every point's CPU capped.

    python benchmarks/bench_region.py [--aircraft 20 50 100 200 400 1000 2000 4000]
        [--duration 60] [--cap 600] [--layout sync rotating] [--against CHECKOUT] [--json PATH]

Each point is ``region-4000`` (``sensors_sim/scenarios``) with its traffic scaled to N
aircraft (birth rate and ``max_alive`` times N/4,000), evaluated as ``zfusion eval
--methods SS --runs 1`` does it (``services.evaluation``: the merged stream, the method
fed plot by plot with a watermark at each new time, the run scored), in a child process
of its own. Two layouts:

* ``rotating``: the scenario as it is (26 rotating radars, 4 angle sensors);
* ``sync``: the same sensors as snapshot sensors scanning together every 8 s (the
  layout today's tracker was built for: a frame holds one scan of every sensor).

Stages, in thread CPU time, of the many-target tracker (``fusion/tracking``, configured by
``fusion.mtt``): stream generation (``merged_measurements``); gating (the hypothesiser:
predicted states, χ² distances, the sequential gating update; the sweep tracker's
screen and pair costs), assignment (GNN), initiation (the initiator's pairing and the
start of new tracks, with the distances it computes), update (the filters' scan updates
and coasts), track management (the table: hits and misses, duplicates, closing the
frame) and the frame loop's own Python (the rest); scoring (GOSPA, breaks, held after
initiation); and the wire a distributed run would add (encode, decode and ``to_measurement`` per plot,
``encode_estimate`` per estimate, timed on a sample). A stage is the outermost timed call
it is in (the initiator's distances are initiation). A point stops when its CPU passes
``--cap``: its figures are then per simulated second reached, and it says so.

``--against CHECKOUT`` runs every point a second time with another checkout's code (its
own ``benchmarks/bench_region.py``, in a process of its own, just before this one's),
and prints the two side by side with their ratio: a before and after measured in the
same run, under the same load.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager

import _common as C

STAGES = {  # stage -> (module, attribute path) of the calls timed for it, on today's trackers
    "gating": [("fusion.tracking.hypotheses", "PlotHypothesiser.predict"),
               ("fusion.tracking.hypotheses", "PlotHypothesiser.hypothesise"),
               ("fusion.tracking.hypotheses", "PlotHypothesiser.condition"),
               ("fusion.tracking.sweep", "near"), ("fusion.tracking.sweep", "pair_d2")],
    "assignment": [("fusion.tracking.associators", "GNN.associate")],
    "initiation": [("fusion.tracking.initiators", "Initiator.initiate"), ("fusion.mtt", "ScanUpdater.start"),
                   ("fusion.tracking.sweep", "SweepTracker.start")],
    "update": [("fusion.mtt", "ScanUpdater.update"), ("fusion.mtt", "ScanUpdater.scan")],
    "management": [("fusion.tracking.table", "TrackLogic.record"), ("fusion.tracking.table", "DuplicateWatch.review"),
                   ("fusion.tracking.table", "TrackTable.close_frame")],
}  # not SweepLogic.record: its clock would cost more than it does (every track, every frame)
SYNC_PERIOD = 8.0


class StageClock:
    """Thread CPU time per stage of the outermost timed call (module docstring)."""

    def __init__(self):
        self.seconds = {s: 0.0 for s in STAGES}
        self.missing: list[str] = []
        self._depth = 0
        self._undo = []

    def _wrap(self, stage, fn):
        clock = self

        def timed(*args, **kw):
            if clock._depth:
                return fn(*args, **kw)
            clock._depth += 1
            c0 = time.thread_time()
            try:
                return fn(*args, **kw)
            finally:
                clock.seconds[stage] += time.thread_time() - c0
                clock._depth -= 1
        return timed

    @contextmanager
    def installed(self):
        import importlib

        for stage, targets in STAGES.items():
            for module, path in targets:
                owner = importlib.import_module(module)
                *outer, name = path.split(".")
                for part in outer:
                    owner = getattr(owner, part, None)
                if owner is None or not hasattr(owner, name):
                    self.missing.append(f"{module}.{path}")
                    continue
                original = owner.__dict__[name] if name in vars(owner) else getattr(owner, name)
                self._undo.append((owner, name, original))
                setattr(owner, name, self._wrap(stage, original))
        try:
            yield self
        finally:
            for owner, name, original in reversed(self._undo):
                setattr(owner, name, original)
            self._undo.clear()


def scenario(n: int, layout: str, duration: float):
    from sensors_sim import load_scenario

    sc = load_scenario("region-4000")
    k = n / 4000.0
    traffic = dataclasses.replace(sc.traffic, rate=sc.traffic.rate * k, max_alive=max(1, round(sc.traffic.max_alive * k)))
    sensors = sc.sensors
    if layout == "sync":
        sensors = {i: dataclasses.replace(s, sectors=0, period=SYNC_PERIOD, start=0.0) for i, s in sensors.items()}
    return dataclasses.replace(sc, traffic=traffic, sensors=sensors, duration=duration, endless=False)


def _wire_per_item(measurements, estimates) -> tuple[float, float]:
    """CPU s per plot (encode, decode, to_measurement) and per estimate (encode_estimate)."""
    from schemas import decode, encode_estimate, encode_measurement, to_measurement

    sample = measurements[:: max(1, len(measurements) // 2000)][:2000]
    c0 = time.thread_time()
    for m in sample:
        to_measurement(decode(encode_measurement(m, m.sensor)))
    per_plot = (time.thread_time() - c0) / max(1, len(sample))
    sample = estimates[:: max(1, len(estimates) // 2000)][:2000]
    c0 = time.thread_time()
    for i, e in enumerate(sample):
        encode_estimate(e, "fuser", i + 1)
    per_estimate = (time.thread_time() - c0) / max(1, len(sample))
    return per_plot, per_estimate


def point(n: int, layout: str, duration: float, cap: float) -> dict:
    """One point (module docstring), in the calling process."""
    from fusion.methods import make_method, method_config
    from services.evaluation import merged_measurements
    from services.scoring import score_tracks_of

    sc = scenario(n, layout, duration)
    c0 = time.thread_time()
    stream = merged_measurements(sc)
    generation = time.thread_time() - c0
    method = make_method("SS", method_config(sc.tracker, "SS"))
    clock = StageClock()
    out, t_prev, reached, capped = [], None, 0.0, False
    c0 = time.thread_time()
    with clock.installed():
        for i, m in enumerate(stream):
            if t_prev is not None and m.t > t_prev:
                out += method.advance(t_prev)
                reached = t_prev
                if time.thread_time() - c0 > cap:  # checked as each new time begins
                    capped = True
                    break
            out += method.process(m)
            t_prev = m.t
        else:
            out += method.finish()
            reached = duration
    tracking = time.thread_time() - c0
    plots = sum(1 for m in stream if m.t <= reached)
    row = {"aircraft": n, "layout": layout, "simulated_s": reached, "capped": capped, "plots": plots,
           "estimates": len(out), "generation_s": generation * reached / duration, "tracking_s": tracking,
           "stages_s": dict(clock.seconds), "missing": clock.missing}
    row["stages_s"]["frame loop (the rest)"] = tracking - sum(clock.seconds.values())
    if not capped:
        c0 = time.thread_time()
        score = score_tracks_of(sc, out)
        row["scoring_s"] = time.thread_time() - c0
        row.update(held=score.held, held_after_init=score.held_after_init, false_tracks=score.false_tracks,
                   break_rate=score.break_rate,
                   tracks=score.n_tracks)
    per_plot, per_estimate = _wire_per_item(stream, out)
    row["wire_s"] = per_plot * plots + per_estimate * len(out)
    return row


def _child(q, *args):
    q.put(point(*args))


def run_point(n: int, layout: str, duration: float, cap: float) -> dict:
    """:func:`point` in a child process; one still running after 20 times the cap in wall
    time (a frame that never ends, or a very loaded machine) is stopped and reported so."""
    ctx = multiprocessing.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_child, args=(q, n, layout, duration, cap))
    p.start()
    deadline = time.monotonic() + 20.0 * cap
    row = None
    while row is None and time.monotonic() < deadline:
        try:
            row = q.get(timeout=5.0)
        except Exception:  # queue.Empty
            if not p.is_alive():
                break
    if row is None:
        p.terminate()
        p.join(5)
        if p.is_alive():
            p.kill()
        return {"aircraft": n, "layout": layout, "simulated_s": 0.0, "capped": True, "killed": True}
    p.join()
    return row


def other_point(checkout: str, n: int, layout: str, duration: float, cap: float) -> dict:
    """:func:`run_point` of another checkout (``--against``): its own script, in a process of its own."""
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "rows.json")
        subprocess.run([sys.executable, os.path.join(checkout, "benchmarks", "bench_region.py"), "--aircraft", str(n),
                        "--layout", layout, "--duration", str(duration), "--cap", str(cap), "--json", path],
                       check=True, stdout=subprocess.DEVNULL, cwd=checkout)
        with open(path) as f:
            return json.load(f)["rows"][0]


def per_second(row: dict, key: str) -> float:
    return row[key] / row["simulated_s"] if row.get("simulated_s") else float("nan")


def evaluation(row: dict, key: str) -> float:
    """CPU s per simulated s of the tracking (``key = "tracking"``) or of the whole
    evaluation (``"eval"``: generation, tracking and scoring)."""
    if key == "tracking":
        return per_second(row, "tracking_s")
    return sum(per_second(row, k) for k in ("generation_s", "tracking_s", "scoring_s") if k in row)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--aircraft", type=int, nargs="+", default=[20, 50, 100, 200, 400, 1000, 2000, 4000])
    ap.add_argument("--duration", type=float, default=60.0, help="simulated seconds per point")
    ap.add_argument("--cap", type=float, default=600.0, help="CPU seconds of tracking per point")
    ap.add_argument("--layout", nargs="+", default=["sync", "rotating"], choices=["sync", "rotating"])
    ap.add_argument("--against", metavar="CHECKOUT", help="also run every point with this checkout's code")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    print(f"# Today's tracker at region scale — {C.machine_line()}")
    print(f"region-4000's sensors and traffic scaled to N aircraft; {args.duration:g} s simulated per point, "
          f"tracking capped at {args.cap:g} s CPU\n")
    rows = []
    for layout in args.layout:
        for n in args.aircraft:
            if args.against:
                other = other_point(args.against, n, layout, args.duration, args.cap)
                other["checkout"] = args.against
                print(f"  {layout} {n} ({args.against}): {json.dumps(other)}", flush=True)
            t0 = time.monotonic()
            row = run_point(n, layout, args.duration, args.cap)
            row["wall_s"] = time.monotonic() - t0
            rows.append(row)
            print(f"  {layout} {n}: {json.dumps(row)}", flush=True)
            if args.against:
                row["against"] = other
    stage_names = [*STAGES, "frame loop (the rest)"]
    for layout in args.layout:
        mine = [r for r in rows if r["layout"] == layout and r.get("simulated_s")]
        if not mine:
            continue
        base = None
        table = []
        for r in mine:
            evald = evaluation(r, "eval")
            base = base or evald
            table.append([r["aircraft"], f"{r['simulated_s']:.0f}" + (" (capped)" if r["capped"] else ""),
                          f"{r['plots'] / r['simulated_s']:,.0f}", f"{evald:.3f}", f"{evald / base:.1f}",
                          f"{per_second(r, 'generation_s'):.3f}", f"{per_second(r, 'tracking_s'):.3f}",
                          f"{per_second(r, 'scoring_s'):.3f}" if "scoring_s" in r else "—",
                          f"{per_second(r, 'wire_s'):.3f}",
                          f"{r['held']:.3f}" if "held" in r else "—", r.get("false_tracks", "—")])
        print(f"\n## {layout}: CPU seconds per simulated second (× real time on one core)\n")
        print(C.table(["aircraft", "simulated s", "plots/s", "eval", "÷ first", "generation", "tracking",
                       "scoring", "wire (distributed)", "held", "false tracks"], table))
        print(f"\n## {layout}: the tracker's stages, share of its CPU\n")
        print(C.table(["aircraft", *stage_names, "tracking s per simulated s"],
                      [[r["aircraft"], *(f"{100 * r['stages_s'][s] / max(r['tracking_s'], 1e-12):.1f} %"
                                         for s in stage_names), f"{per_second(r, 'tracking_s'):.3f}"]
                       for r in mine]))
    if args.against:
        print(f"\n## Against {args.against}: CPU seconds per simulated second, the other checkout's ÷ this one's\n")
        table = []
        for r in rows:
            o = r["against"]
            cells = [r["aircraft"], r["layout"], f"{o.get('simulated_s', 0):.0f} / {r.get('simulated_s', 0):.0f}"]
            for key in ("tracking", "eval"):
                a, b = evaluation(o, key), evaluation(r, key)
                cells += [f"{a:.3f}", f"{b:.3f}", f"{a / b:.2f}"]
            for key in ("held", "held_after_init", "false_tracks", "break_rate"):
                cells.append(" / ".join(f"{v:.4f}" if isinstance(v, float) else str(v)
                                        for v in (o.get(key, "—"), r.get(key, "—"))))
            table.append(cells)
        print(C.table(["aircraft", "layout", "simulated s", "tracking, other", "tracking, this", "÷", "eval, other",
                       "eval, this", "÷", "held", "held after init", "false tracks", "break rate"], table))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"machine": C.machine_line(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
