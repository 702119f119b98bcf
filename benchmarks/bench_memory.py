"""Memory of the fuser (and the recorder) over a long run at a steady rate: resident set
size sampled every second, the fuser's held-measurement queue and the recorder's backlog
from their status messages. Flat means no growth in queues or recordings held in memory.

    python benchmarks/bench_memory.py --minutes 10 [--rate 1000] [--sensors 4] [--no-recorder]

The default (``--minutes 1``) is a short check; the figure the README quotes says how
long it ran. The rate should be one the fuser keeps up with (``bench_fuser.py``): above
it the backlog, and so memory, grows by design until the run ends.
"""

from __future__ import annotations

import argparse
import json

import _common as C
import numpy as np

import _rig


def slope_mb_per_min(t: np.ndarray, rss: np.ndarray) -> float:
    if len(t) < 3:
        return float("nan")
    return float(np.polyfit(t / 60.0, rss, 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--sensors", type=int, default=4)
    ap.add_argument("--tracks", type=int, default=1)
    ap.add_argument("--no-recorder", action="store_true", help="leave the recorder out")
    ap.add_argument("--json")
    args = ap.parse_args()
    seconds = args.minutes * 60.0
    n = args.rate * seconds
    print(f"# Memory over {args.minutes:g} min — {C.machine_line()}")
    print(f"{args.sensors} sensors, {args.tracks} track(s), {args.rate:,.0f} measurements/s, "
          f"recorder {'off' if args.no_recorder else 'on'}\n", flush=True)
    r = _rig.run_trial(_rig.Trial(rate=args.rate, seconds=seconds, sensors=args.sensors, tracks=args.tracks,
                                  recorder=not args.no_recorder, keep_every=max(1, int(n // 100_000)),
                                  sample_period=1.0, drain_s=120.0))
    print(_rig.brief(r) + "\n")
    rows = []
    summary = {}
    for name in ("fuser", "recorder"):
        m = r.get(f"{name}_rss_mb")
        if not m:
            continue
        t, rss = np.array(m["t"]), np.array(m["rss"])
        run = (t >= 0) & (t <= seconds)
        warm = run & (t >= min(30.0, 0.2 * seconds))  # after imports, caches and the first allocations
        tw, rw = t[warm], rss[warm]
        if len(tw) < 3:
            continue
        s = slope_mb_per_min(tw, rw)
        summary[name] = {"rss_start_mb": float(rw[0]), "rss_end_mb": float(rw[-1]), "rss_max_mb": float(rss[run].max()),
                         "slope_mb_per_min": s, "cpu_pct": r.get(f"{name}_cpu_pct")}
        rows.append([name, f"{rw[0]:.1f}", f"{rw[-1]:.1f}", f"{rss[run].max():.1f}", f"{s:+.2f}",
                     f"{r.get(f'{name}_cpu_pct', float('nan')):.0f}"])
    print(C.table(["process", "RSS after warm-up MB", "RSS at end MB", "max MB", "trend MB/min", "CPU %"], rows))
    queues = []
    for src, key in (("fuser", "held"), ("recorder", "backlog"), ("recorder", "dropped")):
        vals = [c.get(key) for _, c in r["status"].get(src, []) if c.get(key) is not None]
        if vals:
            queues.append([f"{src}.{key}", f"{np.median(vals):.0f}", f"{max(vals):.0f}", f"{vals[-1]:.0f}"])
            summary[f"{src}.{key}"] = {"median": float(np.median(vals)), "max": float(max(vals)), "last": vals[-1]}
    if queues:
        print("\nQueues, from the status messages (items):\n")
        print(C.table(["counter", "median", "max", "last"], queues))
    print(f"\nlatency over the run: p50 {r.get('lat_p50_ms', float('nan')):.2f} ms, p99 "
          f"{r.get('lat_p99_ms', float('nan')):.2f} ms; fused {r['fused']}/{r['sent']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": C.machine_line(), "args": vars(args), "summary": summary,
                       "fuser_rss": r.get("fuser_rss_mb"), "recorder_rss": r.get("recorder_rss_mb"),
                       "latency": {k: r.get(k) for k in ("lat_p50_ms", "lat_p99_ms", "lat_max_ms")}},
                      fh, indent=1, default=float)


if __name__ == "__main__":
    main()
