"""Fuser throughput and latency over Zenoh: S asynchronous 3D radars in a load generator
process publishing to the real fuser process (``zfusion fuser``) on loopback.

    python benchmarks/bench_fuser.py [--sensors 4] [--seconds 4] [--repeats 3] [--json out.json]
    python benchmarks/bench_fuser.py --scenario region-4000 --duration-s 600 [--no-score] [--json out.json]

1. Sustained throughput: the offered rate is doubled from ``--start-rate`` until the
   fuser falls behind, then bisected. A level is *kept up* when every measurement came
   out as a fused track, no backlog built up (the median fuser latency over 65–85 % of
   the run is under 50 ms) and the fuser finished within 0.5 s of the last publish.
2. End-to-end latency (sensor ``put`` → fused track received by a subscriber) p50/p90/p99
   at 10 %, 50 % and 90 % of that rate and at 2,000 measurements/s, each the median of
   ``--repeats`` runs. "Fuser" latency leaves out the time-ordering wait: it counts from
   when the merged watermark let the fuser emit the estimate (``_rig.py``).
3. The sensors' watermarks look ahead, as ``services/source.py``'s do: after a scan at
   ``t`` each sensor promises "everything up to just before my next scan" (``t + T``
   less one ulp). The 10 % and 50 % levels run again with watermarks at the scan time
   ``t`` (how sensors published them before), to show the ordering wait that removes.

See ``_rig.py`` for the processes; every one is stopped at the end of each level.

``--scenario S --duration-s D`` instead feeds the real ``zfusion fuser --scenario S``
(its method, ``SS`` by default) S's own plots in real time for D seconds: every sensor's
batches (a rotating radar's sectors) from one feeder process, niced, as the sensor
processes would publish them (``_rig.run_feed``). It reports the plot-to-track latency
(a plot's batch ``put`` → the track it updated received), p50/p90/p99 overall and per
minute, the fuser's CPU, its RSS at 2 minutes, at its peak and at the end, and the
scale criteria: p99 ≤ 100 ms, peak RSS within 15 % of the 2-minute value.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics

import _common as C

import _rig


def trial(rate: float, args, **kw) -> dict:
    r = _rig.run_trial(_rig.Trial(rate=rate, seconds=args.seconds, sensors=args.sensors, **kw))
    print("  " + _rig.brief(r), flush=True)
    return r


def search(args) -> tuple[float, list[dict]]:
    """Largest rate kept up: doubling, then bisection."""
    tried = []
    lo, hi = 0.0, math.inf
    rate = args.start_rate
    while rate <= args.max_rate:
        r = trial(rate, args)
        tried.append(r)
        if r["kept_up"]:
            lo = rate
            if not math.isinf(hi):
                break
            rate *= 2
        else:
            hi = rate
            if lo > 0:
                break
            rate /= 2
            if rate < 100:
                return 0.0, tried
    if math.isinf(hi):
        return lo, tried
    for _ in range(args.bisect):
        mid = round((lo + hi) / 2, -1)
        r = trial(mid, args)
        tried.append(r)
        if r["kept_up"]:
            lo = mid
        else:
            hi = mid
    return lo, tried


def median_of(rs: list[dict], key: str) -> float:
    v = [r.get(key, math.nan) for r in rs]
    v = [x for x in v if x == x]
    return statistics.median(v) if v else math.nan


def fed(args) -> None:
    """``--scenario``: the real fuser fed a scenario in real time (module docstring)."""
    feed = _rig.Feed(scenario=args.scenario, duration=args.duration_s, method=args.method, score=not args.no_score)
    print(f"# {args.scenario} fed to `zfusion fuser --method {args.method}` in real time for "
          f"{args.duration_s:g} s — {C.machine_line()}\n", flush=True)
    r = _rig.run_feed(feed)
    print(C.table(["plots", "fused tracks", "at a plot's time", "feeder late (max s)", "p50 ms", "p90 ms", "p99 ms",
                   "max ms", "once its frame could close: p50 / p99 ms"],
                  [[f"{r['plots']:,}", f"{r['fused']:,}", f"{r['fused_at_a_plot']:,}", f"{r['feed_late_max_s']:.3f}",
                    f"{r.get('lat_p50_ms', math.nan):.1f}", f"{r.get('lat_p90_ms', math.nan):.1f}",
                    f"{r.get('lat_p99_ms', math.nan):.1f}", f"{r.get('lat_max_ms', math.nan):.1f}",
                    f"{r.get('lat_after_frame_p50_ms', math.nan):.1f} / {r.get('lat_after_frame_p99_ms', math.nan):.1f}"]]))
    print("\nPer minute (by the plot's publication):\n")
    print(C.table(["minute", "tracks", "p50 ms", "p99 ms", "fuser: most held for watermarks", "most in its inbox"],
                  [[m["minute"], f"{m['n']:,}", f"{m['p50_ms']:.1f}", f"{m['p99_ms']:.1f}", m["held_max"],
                    m["inbox_max"]] for m in r["per_minute"]]))
    print(f"\nfuser: CPU {r.get('fuser_cpu_pct', math.nan):.0f} % of a core over the feed "
          f"({r.get('fuser_cpu_s', math.nan):.0f} s in all; by thread {r.get('fuser_threads_pct')}), "
          f"RSS at 2 min {r.get('rss_2min_mb', math.nan):.1f} MB, peak {r.get('rss_peak_mb', math.nan):.1f} MB "
          f"(VmHWM {r.get('fuser_hwm_mb', math.nan):.1f}), end {r.get('rss_end_mb', math.nan):.1f} MB; "
          f"by minute {r.get('rss_by_minute_mb')}")
    print(f"fuser exit {r.get('fuser_exit')}; summary {r.get('summary')}; load now {C.load_now():.1f}")
    p99, rss2, peak = r.get("lat_p99_ms", math.inf), r.get("rss_2min_mb", math.nan), r.get("rss_peak_mb", math.inf)
    print("\n## Criteria\n")
    print(f"- p99 plot-to-track latency ≤ 100 ms: {p99:.1f} ms ({'met' if p99 <= 100 else 'NOT MET'})")
    if rss2 > 0:
        print(f"- peak RSS within 15 % of its value at 2 min: {peak:.1f} MB against {rss2:.1f} MB, "
              f"{100 * (peak / rss2 - 1):+.1f} % ({'met' if peak <= 1.15 * rss2 else 'NOT MET'})")
    else:
        print("- peak RSS within 15 % of its value at 2 min: the run is shorter than 2 min")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": C.machine_line(), **r}, fh, indent=1, default=float)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sensors", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=4.0, help="publishing time per level")
    ap.add_argument("--repeats", type=int, default=3, help="runs per latency level (medians reported)")
    ap.add_argument("--start-rate", type=float, default=1000.0)
    ap.add_argument("--max-rate", type=float, default=64000.0)
    ap.add_argument("--bisect", type=int, default=3)
    ap.add_argument("--scenario", help="feed this scenario's plots in real time instead (module docstring)")
    ap.add_argument("--duration-s", type=float, default=600.0, help="with --scenario: seconds fed")
    ap.add_argument("--method", default="SS", help="with --scenario: the fuser's method")
    ap.add_argument("--no-score", action="store_true",
                    help="with --scenario: the fuser without --json (its scorer keeps every estimate of a scenario run)")
    ap.add_argument("--json")
    args = ap.parse_args()
    if args.scenario:
        fed(args)
        return

    print(f"# Fuser over Zenoh — {C.machine_line()}")
    print(f"{args.sensors} sensors (3D radars, asynchronous), 1 track, method RADAR3D, {args.seconds:g} s per level\n")
    print("Throughput search:")
    best, tried = search(args)
    print(f"\nSustained: {best:,.0f} measurements/s\n")

    levels = {"10 %": 0.1 * best, "50 %": 0.5 * best, "90 %": 0.9 * best, "2,000/s": 2000.0}
    lat = {}
    print(f"Latency levels ({args.repeats} runs each):")
    for name, rate in levels.items():
        if rate <= 0:
            continue
        lat[name] = [trial(round(rate), args) for _ in range(args.repeats)]
    print("10 % and 50 % again, the sensors' watermarks at the scan time (no look-ahead, as before):")
    for name in ("10 %", "50 %"):
        if levels[name] > 0:
            lat[f"{name}, watermarks at scan time"] = [trial(round(levels[name]), args, lookahead=False)
                                                       for _ in range(args.repeats)]
    rows = []
    for name, rs in lat.items():
        rows.append([name, f"{rs[0]['trial']['rate']:,.0f}", f"{median_of(rs, 'publish_rate'):,.0f}",
                     f"{median_of(rs, 'lat_p50_ms'):.2f}", f"{median_of(rs, 'lat_p90_ms'):.2f}",
                     f"{median_of(rs, 'lat_p99_ms'):.2f}", f"{median_of(rs, 'fuser_lat_p50_ms'):.2f}",
                     f"{median_of(rs, 'fuser_lat_p99_ms'):.2f}", f"{median_of(rs, 'fuser_cpu_pct'):.0f}",
                     f"{sum(r['kept_up'] for r in rs)}/{len(rs)}"])
    print(f"\n## Latency, sensor put → fused track received (ms, medians of {args.repeats} runs; load now "
          f"{C.load_now():.1f})\n")
    print(C.table(["level", "offered /s", "published /s", "p50", "p90", "p99", "fuser p50", "fuser p99",
                   "fuser CPU %", "kept up"], rows))
    print("\n## Targets\n")
    print(f"- ≥ 20,000 measurements/s sustained: {best:,.0f}/s "
          f"({'met' if best >= 20000 else f'MISSED by {20000 / max(best, 1):.1f}×'})")
    if "2,000/s" in lat:
        p99 = median_of(lat["2,000/s"], "lat_p99_ms")
        print(f"- p99 latency < 5 ms at 2,000 measurements/s: {p99:.1f} ms ({'met' if p99 < 5 else 'MISSED'})")
    if args.json:
        slim = lambda r: {k: v for k, v in r.items() if not k.endswith("_rss_mb") and k != "status"}  # noqa: E731
        with open(args.json, "w") as fh:
            json.dump({"machine": C.machine_line(), "sustained": best, "search": [slim(r) for r in tried],
                       "latency": {k: [slim(r) for r in v] for k, v in lat.items()}}, fh, indent=1, default=float)


if __name__ == "__main__":
    main()
