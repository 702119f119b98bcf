"""The gateway core (services/ingest/gateway.py): what reaches the wire, and what not.

Every published message is decoded with the project's strict decoder (schemas.decode),
so what the tests read is what a fuser would accept.
"""

from __future__ import annotations

import math

import numpy as np
import pymap3d
import pytest

from fusion.geodetic import LocalFrame
from schemas import KeySpace, decode, to_measurement
from services.ingest.gateway import Gateway, Reading, SensorSite
from services.node import RejectLog

ORIGIN = (21.0285, 105.8542, 10.0)
NOW = 1764612000.0
STD = np.array([math.radians(2.0)])


def gateway(**kw) -> Gateway:
    sensors = {"fixed": SensorSite("fixed", "bearing", STD, np.array([100.0, 200.0, 0.0])),
               "mobile": SensorSite("mobile", "bearing", STD, None),
               "radar": SensorSite("radar", "range_az", np.array([math.radians(1.0), 20.0]), None)}
    return Gateway(sensors, LocalFrame(*ORIGIN, deg=True), KeySpace("t"), RejectLog("gw"), **kw)


def bearing(sensor="mobile", t=NOW - 1.0, az=1.0, geo=(21.05, 105.9, None), **kw) -> Reading:
    return Reading(sensor=sensor, t=t, kind="bearing", z=np.array([az]), geodetic=geo, **kw)


def decoded(out):
    return [(key, decode(data)) for key, data in out]


def test_a_reading_becomes_a_measurement_then_a_watermark_just_below_it():
    gw = gateway()
    (k1, m), (k2, w) = decoded(gw.offer(bearing(), NOW))
    assert k1 == k2 == "zf/t/meas/mobile"
    assert m.kind == "bearing" and m.src == "mobile" and m.seq == 1 and m.t == NOW - 1.0
    meas = to_measurement(m)
    assert meas.z[0] == 1.0 and meas.std[0] == STD[0]
    # Site: the message's lat/lon in the site's ENU frame, at the origin's altitude.
    e, n, u = pymap3d.geodetic2enu(21.05, 105.9, ORIGIN[2], *ORIGIN)
    assert np.allclose(meas.site, [e, n, u], atol=1e-6)
    assert w.kind == "watermark" and w.t == math.nextafter(NOW - 1.0, -math.inf) and not w.body["final"]


def test_a_pinned_site_wins_and_a_mobile_one_needs_a_position():
    gw = gateway()
    (_, m), _ = decoded(gw.offer(bearing("fixed"), NOW))
    assert to_measurement(m).site.tolist() == [100.0, 200.0, 0.0]
    assert gw.offer(bearing("mobile", geo=None), NOW) == []
    assert gw.reject.by_cause == {"no-position": 1}
    (_, m), _ = decoded(gw.offer(bearing("mobile", geo=None, site=np.array([1.0, 2.0, 3.0])), NOW))
    assert to_measurement(m).site.tolist() == [1.0, 2.0, 3.0]


def test_identical_repeats_are_not_republished_and_not_errors():
    gw = gateway()
    assert len(gw.offer(bearing(), NOW)) == 2
    assert gw.offer(bearing(), NOW + 1) == []
    assert gw.counters["repeats"] == 1 and gw.reject.total == 0
    # Another detection of the same scan (same t, other value) is published, seq 2.
    ((_, m),) = decoded(gw.offer(bearing(az=2.0), NOW))
    assert m.seq == 2


@pytest.mark.parametrize("reading, cause", [
    (bearing(t=NOW + 6.0), "future"),
    (bearing(t=NOW - 61.0), "stale"),
    (bearing(t=math.nan), "non-finite"),
    (bearing(sensor="nobody"), "unknown-sensor"),
    (Reading("radar", NOW, "bearing", np.array([1.0])), "kind-mismatch"),
    (bearing(std=np.array([math.radians(1.0)])), "std-mismatch"),
    (bearing(az=2 * math.pi), "range"),
    (bearing(az=-0.1), "range"),
    (bearing(geo=(91.0, 0.0, None)), "position"),
])
def test_refusals_are_counted_by_cause(reading, cause):
    gw = gateway()
    assert gw.offer(reading, NOW) == []
    assert dict(gw.reject.by_cause) == {cause: 1}
    assert gw.counters["published"] == 0


def test_a_stated_std_equal_to_the_site_files_is_accepted():
    gw = gateway()
    assert gw.offer(bearing(std=np.array([math.radians(2.0) * (1 + 1e-12)])), NOW)


def test_time_only_moves_forward():
    gw = gateway()
    gw.offer(bearing(t=NOW - 1.0), NOW)
    assert gw.offer(bearing(t=NOW - 2.0, az=0.5), NOW) == []
    assert gw.reject.by_cause == {"late": 1}


def test_heartbeat_watermarks_and_late_readings():
    gw = gateway(lag=2.0)
    out = decoded(gw.tick(NOW))
    assert sorted(k for k, _ in out) == ["zf/t/meas/fixed", "zf/t/meas/mobile", "zf/t/meas/radar"]
    assert all(m.kind == "watermark" and m.t == NOW - 2.0 for _, m in out)
    assert gw.tick(NOW) == []  # nothing new to promise
    # A reading of a time already promised is late ...
    assert gw.offer(bearing(t=NOW - 2.5), NOW) == []
    assert gw.reject.by_cause == {"late": 1}
    # ... a newer one is published; the watermark after it never goes back.
    out = decoded(gw.offer(bearing(t=NOW - 1.0), NOW))
    assert [m.kind for _, m in out] == ["bearing", "watermark"]
    assert not [k for k, _ in gw.tick(NOW + 0.5) if k.endswith("mobile")]  # NOW − 1.5 < the last promise
    ((_, w),) = [x for x in decoded(gw.tick(NOW + 2.0)) if x[0].endswith("mobile")]
    assert w.t == NOW


def test_flush_promises_each_sensors_last_time():
    gw = gateway()
    gw.offer(bearing(t=NOW - 1.0), NOW)
    (k, w), = decoded(gw.flush())
    assert k.endswith("mobile") and w.t == NOW - 1.0
    assert gw.flush() == []


def test_watermarks_are_valid_and_sequenced_per_sensor():
    gw = gateway(lag=0.5)
    seqs = []
    for i in range(5):
        for _, m in decoded(gw.offer(bearing(t=NOW + i, az=0.1 * i), NOW + i) + gw.tick(NOW + i + 0.6)):
            if m.kind == "watermark" and m.src == "mobile":
                seqs.append((m.seq, m.t))
    assert [s for s, _ in seqs] == list(range(1, len(seqs) + 1))
    assert all(a[1] < b[1] for a, b in zip(seqs, seqs[1:]))


def test_no_heartbeats_with_lag_zero():
    gw = gateway(lag=0.0)
    assert gw.tick(NOW) == []
    gw.offer(bearing(t=NOW - 30.0), NOW)
    assert len(gw.offer(bearing(t=NOW - 29.0), NOW + 20.0)) == 2  # old data, in order, all published
