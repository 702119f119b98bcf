"""Live sessions without Zenoh: site files, the clock guard, the bounded wait for a
lagging source, and out-of-sequence measurements re-filtered to the in-order estimate."""

from __future__ import annotations

import dataclasses
import math
import textwrap

import numpy as np
import pytest

from fusion.methods import make_method, method_config
from schemas import KeySpace, encode, encode_measurement
from sensors_sim import Scenario, ScenarioError, SiteSpec, load_scenario, load_site
from services.evaluation import merged_measurements, run_method
from services.fuser import FuserCore, MeasurementIntake
from services.live import ClockGuard, LiveOptions
from services.node import RejectLog
from services.ordering import WatermarkMerger

KEYS = KeySpace("unit")
EPOCH = 1_796_000_000.0  # a UTC time base (2026)

SITE = """\
description = "two stations"
[origin]
lat_deg = 21.0
lon_deg = 105.8
alt_m = 10.0
[defaults]
topology = "centralised"
method = "SS"
[tracker]
motion = "ca"
[sensors.radar2d]
kind = "radar2d"
lat_deg = 21.001
lon_deg = 105.8
alt_m = 10.0
period_s = 1.0
std_az_deg = 1.0
std_range_m = 20.0
[sensors.angle]
kind = "angle"
site = "messages"
period_s = 0.5
std_az_deg = 0.05
std_el_deg = 0.05
"""


def _write(tmp_path, text: str):
    p = tmp_path / "site.toml"
    p.write_text(textwrap.dedent(text))
    return p


# --- site files ---------------------------------------------------------------------------


def test_site_file_loads_fixed_geodetic_and_mobile_stations(tmp_path):
    site = load_site(_write(tmp_path, SITE))
    assert type(site) is SiteSpec and site.name == "site"
    assert site.sensors["angle"].site is None  # from the messages
    radar = site.sensors["radar2d"]
    # 0.001° of latitude north of the origin, same height: ~110.6 m north
    np.testing.assert_allclose(radar.site.points[0], [0.0, 110.6, 0.0], atol=0.2)
    assert radar.std[0] == pytest.approx(math.radians(1.0)) and radar.std[1] == 20.0
    assert site.sensors["angle"].period == 0.5 and site.defaults["method"] == "SS"


def test_any_scenario_is_a_site():
    sc = load_site("patent-3d")
    assert isinstance(sc, Scenario) and isinstance(sc, SiteSpec)
    assert list(sc.sensors) == list(load_scenario("patent-3d").sensors)


@pytest.mark.parametrize("edit, where", [
    (('site = "messages"', 'site = "moving"'), "sensors.angle.site: must be 'messages'"),
    (('site = "messages"', 'site = "messages"\npos_m = [0, 0, 0]'), "sensors.angle.site: a mobile station"),
    (('period_s = 0.5', 'period_s = 0.5\ntargets = ["T1"]'), "sensors.angle.targets: unknown key"),
    (('period_s = 0.5', 'period_s = 0.5\nlatency_s = 1.0'), "sensors.angle.latency_s: unknown key"),
    (('std_range_m = 20.0', 'std_range_m = -20.0'), "sensors.radar2d.std_range_m: must be > 0"),
])
def test_site_errors_name_file_line_and_field(tmp_path, edit, where):
    text = SITE.replace(*edit)
    path = _write(tmp_path, text)
    with pytest.raises(ScenarioError) as e:
        load_site(path)
    msg = str(e.value)
    assert where in msg, msg
    file, line, _ = msg.split(":", 2)
    assert file == str(path)
    key = where.split(":")[0].rsplit(".", 1)[-1]
    assert key in text.splitlines()[int(line) - 1] or "[sensors" in text.splitlines()[int(line) - 1], msg


def test_scenario_sensors_need_a_position(tmp_path):
    text = load_scenario("patent-3d").source
    src = (tmp_path / "s.toml")
    from importlib import resources
    body = resources.files("sensors_sim").joinpath("scenarios", text).read_text()
    src.write_text(body.replace('pos_m = [0.0, 0.0, 0.0]    # co-located', 'site = "messages"  # co-located'))
    with pytest.raises(ScenarioError, match=r"s\.toml:\d+: sensors\.radar2d\.site: a scenario's sensors need"):
        load_scenario(src)


def test_latency_is_a_scenario_key(tmp_path):
    from importlib import resources
    body = resources.files("sensors_sim").joinpath("scenarios", "patent-3d.toml").read_text()
    p = tmp_path / "lat.toml"
    p.write_text(body.replace("std_el_deg = 0.05", "std_el_deg = 0.05\nlatency_s = 2.5"))
    sc = load_scenario(p)
    assert sc.sensors["angle"].latency == 2.5 and sc.sensors["radar2d"].latency == 0.0
    p.write_text(body.replace("std_el_deg = 0.05", "std_el_deg = 0.05\nlatency_s = -1"))
    with pytest.raises(ScenarioError, match=r"lat\.toml:\d+: sensors\.angle\.latency_s: must be >= 0"):
        load_scenario(p)


# --- the clock guard ----------------------------------------------------------------------


def test_clock_guard_refuses_the_future_and_reports_skewed_sources():
    g = ClockGuard(max_skew=5.0)
    events: list[str] = []
    assert g.check("a", EPOCH + 4.9, EPOCH, events) is None  # within the bound
    rej = g.check("a", EPOCH + 5.1, EPOCH, events)
    assert rej is not None and rej.cause == "future"
    assert g.report("a")["clock"] == "ahead" and "clock looks skewed" in events[-1]
    assert g.check("a", EPOCH + 1.0, EPOCH + 1.5, events) is None
    assert g.report("a") == {"lag_s": 0.5, "clock": "ok"} and "clock ok" in events[-1]
    # a watermark may look ahead by the source's period, and is not a lag sample
    assert g.check("a", EPOCH + 9.0, EPOCH + 1.5, events, lookahead=3.0) is None
    assert g.check("a", EPOCH + 9.6, EPOCH + 1.5, events, lookahead=3.0) is not None
    # a source whose freshest stamps stay older than the bound looks behind
    for k in range(40):
        g.check("b", EPOCH + k - 8.0, EPOCH + k, events)
    assert g.report("b") == {"lag_s": 8.0, "clock": "behind"}
    assert any("source b: clock looks skewed (behind" in e for e in events)


# --- bounded wait and out-of-sequence data in the merger -----------------------------------


def test_merger_waits_at_most_max_delay_for_a_lagging_source():
    m = WatermarkMerger(["fast", "slow"], timeout=100.0, max_delay=0.5, oosm_window=10.0)
    ev: list[str] = []
    m.watermark("slow", EPOCH - 1.0, False, 0.0, ev)
    assert m.add("fast", EPOCH, 0, "f0", 0.0, ev) is None
    m.watermark("fast", EPOCH + 0.99, False, 0.0, ev)
    assert m.release(0.4) == ([], EPOCH - 1.0)  # still waiting for the slow source
    items, wm = m.release(0.5)  # max_delay after the fast source's watermark
    assert items == ["f0"] and wm == EPOCH + 0.99
    # the slow source's data for that time is out of sequence, not late
    assert m.add("slow", EPOCH, 0, "s0", 0.6, ev) is None
    assert m.sources["slow"].oosm == 1 and m.take_oosm() == ["s0"] and m.take_oosm() == []
    # a repeat of it is a duplicate until the source's watermark passes it, then out of order
    assert m.add("slow", EPOCH, 0, "s0", 0.6, ev).cause == "duplicate"
    m.watermark("slow", EPOCH + 0.5, False, 0.7, ev)
    assert m.add("slow", EPOCH, 0, "s0", 0.8, ev).cause == "out-of-order"
    # a later measurement of the laggard for a released time: out of sequence too
    assert m.add("slow", EPOCH + 0.9, 1, "s1", 0.8, ev) is None and m.take_oosm() == ["s1"]
    # older than the window: stale
    m2 = WatermarkMerger(["a", "b"], timeout=100.0, max_delay=0.0, oosm_window=10.0)
    m2.add("a", EPOCH + 20, 0, "a0", 0.0, ev)
    m2.watermark("a", EPOCH + 20, False, 0.0, ev)
    assert m2.release(0.0)[0] == ["a0"]
    rej = m2.add("b", EPOCH + 9.9, 0, "b0", 0.1, ev)
    assert rej.cause == "stale" and m2.sources["b"].stale == 1


def test_data_of_a_dead_source_given_back_after_it_rejoins_is_recovered_and_applied():
    """A source cut off (declared dead) whose publisher gives back what it sent meanwhile:
    each such measurement (stamped up to ``recovery_until``, set as it is heard again) counts as
    ``recovered`` and is applied out of sequence, or refused as stale past the window;
    its data after that is neither."""
    m = WatermarkMerger(["a", "b"], timeout=2.0, max_delay=0.5, oosm_window=10.0)
    ev: list[str] = []
    for k in range(3):  # both flow, then b goes silent at EPOCH + 2
        for src in ("a", "b"):
            m.add(src, EPOCH + k, k, f"{src}{k}", float(k), ev)
            m.watermark(src, EPOCH + k + 0.99, False, float(k), ev)
        m.release(float(k))
    for k in range(3, 15):
        m.add("a", EPOCH + k, k, f"a{k}", float(k), ev)
        m.watermark("a", EPOCH + k + 0.99, False, float(k), ev)
        m.check_timeouts(float(k), ev)
        m.release(float(k))
    assert m.sources["b"].dead and m.released_until == EPOCH + 14.99
    m.sources["b"].recovery_until = EPOCH + 14.0  # the fuser's judgement as it hears b again
    for k in range(3, 15):  # b's cache, in order, on reconnection
        rej = m.add("b", EPOCH + k, k, f"b{k}", 14.0, ev)
        assert (rej is None) == (k >= 5), (k, rej)  # b3, b4: more than the window before the front
    st = m.sources["b"]
    assert not st.dead and st.recovered == 12 and st.oosm == 10 and st.stale == 2
    assert m.take_oosm() == [f"b{k}" for k in range(5, 15)]
    m.watermark("b", EPOCH + 15.99, False, 15.0, ev)
    assert m.add("b", EPOCH + 16, 16, "b16", 15.5, ev) is None and st.recovered == 12 and st.oosm == 10


def test_scenario_merger_is_unchanged_without_max_delay():
    m = WatermarkMerger(["fast", "slow"], timeout=100.0)
    ev: list[str] = []
    m.add("fast", 1.0, 0, "f0", 0.0, ev)
    m.watermark("fast", 1.5, False, 0.0, ev)
    assert m.release(1e6) == ([], -math.inf)  # waits for the slow source whatever the wall clock says
    m.declare_dead("slow", ev, "test")
    assert m.release(1e6)[0] == ["f0"]
    assert m.add("slow", 1.0, 0, "s0", 1e6, ev).cause == "late"


# --- the live fuser core, bytes in ------------------------------------------------------------


def _utc(m, dt=0.0):
    return dataclasses.replace(m, t=EPOCH + m.t + dt)


def test_live_core_applies_late_data_and_refuses_the_future():
    sc = load_scenario("patent-3d")
    method = make_method("SS", method_config(sc.tracker, "SS"))
    reject = RejectLog("test")
    core = FuserCore(method, list(sc.sensors), KEYS, reject, timeout=100.0, now=0.0,
                     intake=MeasurementIntake(sc.sensors), live=LiveOptions(max_delay=0.5),
                     periods={s: 1.0 for s in sc.sensors})
    ms = merged_measurements(sc, 0)
    out, fixed, received = [], [], []
    wm = {"radar2d": 0, "angle": 0}
    for k in range(31):
        now = float(k)  # wall clock = scenario time: a real-time run
        for m in (x for x in ms if x.t == k):
            if m.sensor == "radar2d":  # on time
                core.offer(KEYS.meas("radar2d"), encode_measurement(_utc(m), "radar2d"), now, EPOCH + now)
        wm["radar2d"] += 1
        core.offer(KEYS.meas("radar2d"), encode("watermark", "radar2d", wm["radar2d"], EPOCH + k + 0.999, final=False),
                   now, EPOCH + now)
        out.extend(core.step(now + 0.6))  # max_delay later: the radar's scan is released alone
        received += [m for m in ms if m.t == k and m.sensor == "radar2d"]
        for m in (x for x in ms if x.t == k - 2 and x.sensor == "angle"):  # 2 s late
            core.offer(KEYS.meas("angle"), encode_measurement(_utc(m), "angle"), now + 0.7, EPOCH + now + 0.7)
            received.append(m)
        before = core.republished
        step = core.step(now + 0.7)
        if core.republished > before:
            fixed.append((step[core.republished - before - 1], list(received)))
        out.extend(step)
    # far-future data is refused and counted, not fused
    far = _utc(ms[-1], dt=60.0)
    core.offer(KEYS.meas("radar2d"), encode_measurement(dataclasses.replace(far, seq=999), "radar2d"), 40.0,
               EPOCH + 31.0)
    rep = core.sources_report()
    assert rep["angle"]["oosm"] == 29 and rep["angle"]["rejected"] == 0 and rep["angle"]["stale"] == 0
    assert reject.by_cause["future"] == 1 and rep["radar2d"]["clock"] == "ahead"
    assert core.republished >= 29
    # each corrected estimate is the in-order result of what had been received by then
    assert len(fixed) >= 20
    for e, received in fixed[::5]:  # the in-order run on what was received, its centre estimate at e's time
        ref = {r.t: r for r in run_method(sc, "SS", measurements=sorted(received, key=lambda m: m.order_key))
               if r.node == "centre"}[round(e.t - EPOCH)]
        np.testing.assert_allclose(e.x, ref.x, rtol=0, atol=1e-6)  # UTC stamps: t is ~1e9 here
