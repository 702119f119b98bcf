"""Publish measurements to zfusion from your own code: zenoh + msgpack, nothing else.

    python docs/examples/publish_measurements.py --connect tcp/127.0.0.1:7447 --id radar7 \
        --site-m 0 0 0

Each measurement is a msgpack map on ``zf/<deployment>/meas/<id>``: the envelope
(``v`` schema version 1, ``kind``, ``src`` = the sensor id, ``seq`` counting
measurements, ``t`` UTC POSIX seconds as a float), then ``sensor``, ``site`` (ENU
metres in the site's frame, three floats) and per component its value and stated std
in SI units (``az``/``std_az`` radians clockwise from north in [0, 2π), ``range``/
``std_range`` metres, ``el``/``std_el`` radians). After the measurements of a time, a
``watermark`` (its own ``seq``) promises that nothing older will follow. The stds must be
those of the sensor's entry in the site file; every field must be a float (not an int).
"""

import argparse
import json
import math
import time

import msgpack
import zenoh


def measurement(sensor: str, seq: int, t: float, az_rad: float, range_m: float, site_m) -> bytes:
    return msgpack.packb({
        "v": 1, "kind": "range_az", "src": sensor, "seq": seq, "t": float(t),
        "sensor": sensor, "site": [float(x) for x in site_m],
        "az": float(az_rad) % (2 * math.pi), "std_az": math.radians(1.0),
        "range": float(range_m), "std_range": 20.0,
    })


def watermark(sensor: str, seq: int, t: float) -> bytes:
    return msgpack.packb({"v": 1, "kind": "watermark", "src": sensor, "seq": seq, "t": float(t), "final": False})


def main(connect: str, deployment: str, sensor: str, site_m, count: int, period_s: float) -> None:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    key = f"zf/{deployment}/meas/{sensor}"
    with zenoh.open(conf) as session:
        with session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                       reliability=zenoh.Reliability.RELIABLE) as pub:
            time.sleep(1.0)  # let the session find its peers before the first put
            for k in range(count):
                t = time.time()
                pub.put(measurement(sensor, k + 1, t, math.radians(30.0 + k), 10_000.0 - 50.0 * k, site_m))
                pub.put(watermark(sensor, k + 1, math.nextafter(t, -math.inf)))
                time.sleep(period_s)


if __name__ == "__main__":
    zenoh.init_log_from_env_or("error")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447")
    ap.add_argument("--deployment", default="default")
    ap.add_argument("--id", default="radar7")
    ap.add_argument("--site-m", type=float, nargs=3, default=[0.0, 0.0, 0.0])
    ap.add_argument("--count", type=int, default=5)
    ap.add_argument("--period-s", type=float, default=1.0)
    a = ap.parse_args()
    main(a.connect, a.deployment, a.id, a.site_m, a.count, a.period_s)
