"""How the fuser's cost and latency grow with the number of sensors (1 → 64) and of
tracks (1 → 1,000), over Zenoh with real processes (see ``_rig.py``).

    python benchmarks/bench_scaling.py [--rate 1000] [--seconds 4] [--repeats 1] [--search]

Each point runs at a fixed offered rate (measurements/s, all sensors together) and
reports latency p50/p99 (end to end, and the fuser's own, without the ordering wait) and
the fuser process's CPU time per measurement (all its threads, from the first publish
to the last fused track). ``--search`` also runs the throughput search of
``bench_fuser.py`` at each point (slow).

Sensors: the real ``zfusion fuser`` (method RADAR3D, one track). Tracks: the fuser
harness with a multi-track method (``_rig.MultiTrack``): 4 sensors, each scan has one
measurement per track, the tracks of a scan are updated together by ``fusion.batch``;
``--ekf single`` loops the single-track path instead (a comparison row at 1,000 tracks
is always included).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics

import _common as C

import _rig
from bench_fuser import search


def point(args, **kw) -> dict:
    rs = []
    # every track is measured at least 4 times by every sensor (one scan of S·N measurements
    # per sensor period S·N/rate)
    seconds = max(args.seconds, 4.0 * kw.get("sensors", 4) * kw.get("tracks", 1) / args.rate)
    for _ in range(args.repeats):
        r = _rig.run_trial(_rig.Trial(rate=args.rate, seconds=seconds, **kw))
        print("  " + _rig.brief(r), flush=True)
        rs.append(r)
    med = lambda k: statistics.median([r.get(k, math.nan) for r in rs])  # noqa: E731
    out = {k: med(k) for k in ("publish_rate", "lat_p50_ms", "lat_p99_ms", "fuser_lat_p50_ms", "fuser_lat_p99_ms",
                               "fuser_cpu_pct")}
    out["cpu_us_per_meas"] = statistics.median([r["fuser_cpu_s"] / r["sent"] * 1e6 for r in rs])
    out["seconds"] = seconds
    out["kept_up"] = all(r["kept_up"] for r in rs)
    if args.search:
        ns = argparse.Namespace(seconds=args.seconds, sensors=kw.get("sensors", 4), start_rate=args.rate,
                                max_rate=64000.0, bisect=2)
        best, _ = search_with(ns, kw)
        out["sustained"] = best
    return out


def search_with(ns, kw):
    import bench_fuser

    orig = bench_fuser.trial

    def trial(rate, a, **extra):
        seconds = max(a.seconds, 4.0 * kw.get("sensors", 4) * kw.get("tracks", 1) / rate)
        r = _rig.run_trial(_rig.Trial(rate=rate, seconds=seconds, **{**kw, **extra}))
        print("    " + _rig.brief(r), flush=True)
        return r

    bench_fuser.trial = trial
    try:
        return search(ns)
    finally:
        bench_fuser.trial = orig


def row(label, r) -> list:
    return [label, f"{r['publish_rate']:,.0f}", f"{r['seconds']:g}", f"{r['lat_p50_ms']:.2f}", f"{r['lat_p99_ms']:.2f}",
            f"{r['fuser_lat_p50_ms']:.2f}", f"{r['fuser_lat_p99_ms']:.2f}", f"{r['fuser_cpu_pct']:.0f}",
            f"{r['cpu_us_per_meas']:.0f}", f"{r['sustained']:,.0f}" if "sustained" in r else "—",
            "yes" if r["kept_up"] else "no"]


HEAD = ["point", "published /s", "run s", "p50 ms", "p99 ms", "fuser p50 ms", "fuser p99 ms", "fuser CPU %",
        "fuser CPU µs/meas", "sustained /s (search)", "kept up"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=1000.0, help="offered measurements/s at every point")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--sensors", type=int, nargs="+", default=[1, 4, 16, 64])
    ap.add_argument("--tracks", type=int, nargs="+", default=[1, 10, 100, 1000])
    ap.add_argument("--ekf", choices=("batch", "single"), default="batch")
    ap.add_argument("--search", action="store_true", help="also search the sustained rate at every point")
    ap.add_argument("--json")
    args = ap.parse_args()
    print(f"# Fuser scaling over Zenoh — {C.machine_line()}")
    print(f"offered {args.rate:,.0f} measurements/s, {args.seconds:g} s per point, {args.repeats} run(s) each\n")

    res_s = {}
    print("Sensors (1 track, zfusion fuser, RADAR3D):")
    for s in args.sensors:
        res_s[s] = point(args, sensors=s, tracks=1)
    res_t = {}
    print("\nTracks (4 sensors, fuser harness with a multi-track method):")
    for n in args.tracks:
        res_t[n] = point(args, sensors=4, tracks=n, ekf=args.ekf, harness=True)
    other = "single" if args.ekf == "batch" else "batch"
    n_max = max(args.tracks)
    print(f"\nTracks {n_max} with the {other} EKF path, for comparison:")
    res_cmp = point(args, sensors=4, tracks=n_max, ekf=other, harness=True)

    print(f"\n## Sensors (1 track; load now {C.load_now():.1f})\n")
    print(C.table(HEAD, [row(f"{s} sensors", r) for s, r in res_s.items()]))
    print("\n## Tracks (4 sensors)\n")
    print(C.table(HEAD, [row(f"{n} tracks ({args.ekf})", r) for n, r in res_t.items()]
                  + [row(f"{n_max} tracks ({other})", res_cmp)]))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": C.machine_line(), "sensors": res_s, "tracks": res_t,
                       f"tracks_{n_max}_{other}": res_cmp}, fh, indent=1, default=float)


if __name__ == "__main__":
    main()
