"""ASTERIX: CAT048 decoding and the whole gateway path, per record, and the CPU share of
the gateway core fed 2,000 plots/s in real time (the goal: at most 10 % of one core).

    python benchmarks/bench_asterix.py [--repeats 9] [--rate 2000] [--seconds 10]

Candidates, timed round-robin on the same datagrams (20 Mode S plots of three radars
in a data block, about 35 octets each, with a sector crossing): ``decode`` (bytes to
typed records, :func:`schemas.asterix.decode`), ``gateway`` (bytes to published
measurement and watermark messages: decode, turn into the site frame, check, msgpack;
:class:`services.ingest.asterix.AsterixIngest`), libasterix's decoder when installed (the
test-only reference), and CAT062 encoding of system tracks. Then the paced run: datagrams
handed to the gateway core at ``--rate`` records/s for ``--seconds``, CPU time of this
process over wall time.
"""

from __future__ import annotations

import argparse
import math
import time

import _common as C
import numpy as np

from fusion.geodetic import LocalFrame
from schemas import KeySpace
from schemas import asterix as ax
from services.ingest.asterix import AsterixFeed, AsterixIngest, Radar
from services.ingest.gateway import Gateway, SensorSite

PER_BLOCK = 20
MIDNIGHT = 1_764_633_600.0


def rig():
    frame = LocalFrame(52.0, 4.0, 0.0, deg=True)
    sites = {"r1": np.array([0.0, 0.0, 30.0]), "r2": np.array([80e3, 20e3, 30.0]), "r3": np.array([-50e3, 90e3, 30.0])}
    radars = {(25, k + 1): Radar.at(sid, (25, k + 1), "range_az", pos, frame) for k, (sid, pos) in
              enumerate(sites.items())}
    std = np.array([math.radians(0.1), 50.0])
    sensors = {sid: SensorSite(sid, "range_az", std, pos) for sid, pos in sites.items()}
    rejected = []
    gw = Gateway(sensors, frame, KeySpace("bench"), lambda *a: rejected.append(a), max_age=1e9, lag=0.0)
    return AsterixIngest(AsterixFeed(radars, sector_lag=1), gw, lambda *a: rejected.append(a)), rejected


def datagrams(n: int, tod0: float = 3600.0) -> list[bytes]:
    """``n`` datagrams, each one block of PER_BLOCK plots (times increasing) and a crossing."""
    rng = np.random.default_rng(1)
    out = []
    for k in range(n):
        recs = []
        for j in range(PER_BLOCK):
            i = k * PER_BLOCK + j
            recs.append(ax.TargetReport(
                sac=25, sic=1 + i % 3, tod=tod0 + i * 1e-3, typ=5, rho=float(rng.uniform(5e3, 300e3)),
                theta=float(rng.uniform(0, 2 * math.pi)), mode3a=int(rng.integers(4096)),
                flight_level=float(rng.integers(0, 1600)) / 4, address=int(rng.integers(1 << 24)),
                callsign="KLM1234", track_number=i % 4096, track_status=ax.cat048.TrackStatus(rad=2)))
        recs.append(ax.ServiceMessage(sac=25, sic=1 + k % 3, message_type=ax.SECTOR_CROSSING,
                                      tod=tod0 + (k + 1) * PER_BLOCK * 1e-3))
        out.extend(ax.encode(recs))
    return out


def tracks(n: int) -> list[ax.SystemTrack]:
    P = np.diag([40.0, 50.0, 60.0, 5.0, 5.0, 2.0]) ** 2
    acc = ax.Accuracy.from_covariance(P, lat=52.0)
    return [ax.SystemTrack(sac=25, sic=100, track_number=k, tod=3600.0 + k * 1e-3, lat=52.0 + k * 1e-4, lon=4.0,
                           x=1000.0 * k, y=-500.0 * k, vx=200.0, vy=-20.0, altitude=10_000.0, address=0x400000 + k,
                           callsign="BAW12", accuracy=acc) for k in range(n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=9, help="round-robin repeats (default %(default)s)")
    ap.add_argument("--rate", type=float, default=2000.0, help="records/s of the paced run (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=10.0, help="length of the paced run (default %(default)s)")
    args = ap.parse_args()
    print(f"# ASTERIX\n\n{C.machine_line()}\n")

    data = datagrams(50)
    ingest, rejected = rig()
    now = MIDNIGHT + 3600.0 + 60.0
    state = {"k": 0}

    def gateway_one():  # one datagram through the whole core, the gateway's state moving on
        k = state["k"]
        state["k"] += 1
        if k % len(data) == 0:  # a fresh gateway per pass, so that no plot is late
            state["ingest"] = rig()[0]
        state["ingest"].receive(data[k % len(data)], now)

    cands = {"decode": lambda: ax.decode(data[0]), "gateway": gateway_one}
    try:
        import asterix.generated as lib
        from asterix.base import Bits, RawDatablock

        def libasterix():
            for db in RawDatablock.parse(Bits.from_bytes(data[0])):
                if db.get_category() == 48:
                    lib.Cat_048_1_32.cv_uap.parse(db.get_raw_records())
        cands["libasterix decode"] = libasterix
    except ImportError:
        pass
    out62 = tracks(PER_BLOCK)
    cands["CAT062 encode"] = lambda: ax.encode(out62, max_octets=1400)
    res = C.interleaved(cands, args.repeats)
    rows = []
    peer = res.get("libasterix decode")  # the ratio against the peer timed in this same run
    for name, r in res.items():
        per = r["cpu_median_us"] / PER_BLOCK
        ratio = "" if peer is None else f"{peer['cpu_median_us'] / r['cpu_median_us']:.1f}×"
        rows.append([name, C.fmt_us(per), f"{1e6 / per:,.0f}", f"{per * 2000 / 1e4:.1f} %", ratio])
    print("## Per record (CPU time, median of the repeats)\n")
    print(C.table(["path", "µs per record", "records/s on one core", "CPU at 2,000/s", "speed vs libasterix decode"],
                  rows))

    # the paced run: datagrams at --rate records/s, in real time
    n = max(1, int(args.rate * args.seconds / PER_BLOCK))
    paced = datagrams(n, tod0=3600.0)
    ingest, rejected = rig()
    published = 0
    period = PER_BLOCK / args.rate
    c0, t0 = time.process_time(), time.perf_counter()
    for k, d in enumerate(paced):
        published += len(ingest.receive(d, now))
        delay = t0 + (k + 1) * period - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    recs = n * PER_BLOCK
    print(f"\n## Paced: {recs:,} plots at {args.rate:,.0f}/s\n")
    print(C.table(["plots", "wall s", "CPU s", "CPU share of one core", "messages published", "refused"],
                  [[f"{recs:,}", f"{wall:.2f}", f"{cpu:.2f}", f"{100 * cpu / wall:.1f} %", f"{published:,}",
                    len(rejected)]]))


if __name__ == "__main__":
    main()
