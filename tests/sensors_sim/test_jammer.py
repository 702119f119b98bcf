"""Jammers: schedule, barrage/spot reach, the jamming law, and what it does to streams."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
from scipy import stats

from fusion.angles import wrap_pi
from sensors_sim import jam_effect, jam_events, jam_state, load_scenario, sensor_events, truth_trajectory
from sensors_sim.geometry import observe
from sensors_sim.jammer import jam_to_signal
from sensors_sim.noise import outlier_cdf

ALPHA = 0.01  # significance of every statistical test in this file
SIGMA1, SIGMA2 = 0.0175, 0.25  # the IMM thesis's clean and outlier bearing stds (rad)


def write_scenario(tmp_path, sensors: str, jammers: str = "", duration=999.0, name="jam.toml"):
    text = textwrap.dedent(f"""\
        description = "jammer test"
        seed = 3
        duration_s = {duration}
        [origin]
        lat_deg = 13.7
        lon_deg = 100.5
        alt_m = 0.0
        [defaults]
        topology = "centralised"
        method = "IMM"
        [targets.E1]
        pos_km = [15.0, 15.0]
        segments = [{{ type = "static" }}]
    """) + textwrap.dedent(sensors) + textwrap.dedent(jammers)
    path = tmp_path / name
    path.write_text(text)
    return load_scenario(path)


def df(sid: str, x_km: float, band: str | None = None, extra: str = "") -> str:
    band_line = f'band = "{band}"' if band else ""
    return f"""
        [sensors.{sid}]
        kind = "df"
        pos_km = [{x_km}, 0.0]
        period_s = 1.0
        std_az_rad = {SIGMA1}
        {band_line}
        {extra}
    """


def bearing_errors(scenario, sensor_id, events=None):
    """(times, wrapped bearing errors, outlier flags, jammed flags) of detected scans."""
    traj = truth_trajectory(scenario, "E1")
    events = events if events is not None else list(sensor_events(scenario, sensor_id))
    rows = [(e.t, float(wrap_pi(e.measurement.z[0] - observe("bearing", traj.position(e.t), e.measurement.site)[0])),
             e.outlier, e.jammed) for e in events if e.measurement is not None]
    t, err, out, jam = (np.array(c) for c in zip(*rows))
    return t, err, out.astype(bool), jam.astype(bool)


# --- the IMM thesis's fixed-p mixture ---------------------------------------------------


@pytest.mark.parametrize("law", ["laplacian", "uniform"])
def test_fixed_p_mixture_rate_and_laws(tmp_path, law):
    """10k bearings under a barrage jammer with p = 0.3: the outlier count is
    Binomial(n, 0.3); outliers follow the law with std σ₂; the rest N(0, σ₁²)."""
    sc = write_scenario(tmp_path, df("df1", 0.0), f"""
        [jammers.jammer]
        pos_km = [15.0, 40.0]
        mode = "barrage"
        p_outlier = 0.3
        outlier_law = "{law}"
        outlier_std_rad = {SIGMA2}
    """, duration=9999.0)
    _, err, out, jam = bearing_errors(sc, "df1")
    n = len(err)
    assert n == 10_000 and jam.all()
    assert stats.binomtest(int(out.sum()), n, 0.3).pvalue > ALPHA
    assert stats.kstest(err[out], lambda x: outlier_cdf(x, SIGMA2, law)).pvalue > ALPHA
    clean = err[~out]
    assert stats.kstest(clean / SIGMA1, "norm").pvalue > ALPHA
    chi2 = float(clean @ clean) / SIGMA1**2
    assert stats.chi2.ppf(ALPHA / 2, len(clean)) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, len(clean))
    if law == "uniform":
        assert np.abs(err[out]).max() <= math.sqrt(3) * SIGMA2


# --- the J/S law ------------------------------------------------------------------------


def test_js_law_closed_form_for_passive_and_active_sensors(tmp_path):
    sc = write_scenario(tmp_path, df("df1", 0.0) + """
        [sensors.radar]
        kind = "radar2d"
        pos_km = [0.0, 0.0, 0.0]
        period_s = 1.0
        std_az_deg = 1.0
        std_range_m = 20.0
        signal_power_w = 4.0
    """, """
        [jammers.j]
        pos_km = [0.0, 20.0]
        mode = "barrage"
        power_w = 2.0
        outlier_std_deg = 5.0
    """)
    j = sc.jammers["j"]
    # ρ = (P_j/P_s)·(d_t/1 km)^k / (d_j/1 km)²
    assert jam_to_signal(j, sc.sensors["df1"], 20e3, 10e3) == pytest.approx(2.0 * 10**2 / 20**2)
    assert jam_to_signal(j, sc.sensors["radar"], 20e3, 10e3) == pytest.approx(2.0 / 4.0 * 10**4 / 20**2)
    eff = jam_effect(sc, "df1", 0.0, np.array([10e3, 0.0, 0.0]))
    assert eff.variance_gain == pytest.approx(1.5)
    assert eff.p_outlier == pytest.approx(1 - math.exp(-0.5))


def test_js_law_outlier_rate_and_raised_noise(tmp_path):
    """E1 at 21.2 km, jammer at 30 km, P_j/P_s = 2: ρ = 2·(21.21/30)² = 1.0, so
    p = 1 − e⁻¹ and the Gaussian std is σ·√2 (binomial and χ² tests at 1 %)."""
    sc = write_scenario(tmp_path, df("df1", 0.0), """
        [jammers.j]
        pos_km = [0.0, 30.0]
        mode = "barrage"
        power_w = 2.0
        outlier_std_rad = 0.25
    """, duration=9999.0)
    rho = 2.0 * (math.hypot(15, 15) / 30.0) ** 2
    assert rho == pytest.approx(1.0)
    events = list(sensor_events(sc, "df1"))
    assert all(e.measurement.std.tolist() == [SIGMA1] for e in events)  # trackers see the stated σ
    _, err, out, _ = bearing_errors(sc, "df1", events)
    assert stats.binomtest(int(out.sum()), len(out), 1 - math.exp(-rho)).pvalue > ALPHA
    clean, sigma_j = err[~out], SIGMA1 * math.sqrt(1 + rho)
    chi2 = float(clean @ clean) / sigma_j**2
    assert stats.chi2.ppf(ALPHA / 2, len(clean)) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, len(clean))


def test_independent_jammers_combine(tmp_path):
    sc = write_scenario(tmp_path, df("df1", 0.0), """
        [jammers.a]
        pos_km = [0.0, 30.0]
        mode = "barrage"
        p_outlier = 0.3
        outlier_law = "uniform"
        outlier_std_rad = 0.1
        [jammers.b]
        pos_km = [30.0, 30.0]
        mode = "barrage"
        p_outlier = 0.5
        outlier_std_rad = 0.2
    """)
    eff = jam_effect(sc, "df1", 5.0, np.array([15e3, 15e3, 0.0]))
    assert eff.p_outlier == pytest.approx(1 - 0.7 * 0.5)
    assert (eff.outlier_law, eff.outlier_std, eff.jammers) == ("laplacian", 0.2, ("a", "b"))
    assert eff.variance_gain == 1.0  # fixed-p jammers do not raise the Gaussian noise


# --- switching on mid-run: who is touched -----------------------------------------------

SPOT = """
    [jammers.jammer]
    pos_km = [0.0, 30.0]
    mode = "spot"
    band = "X"
    search_delay_s = 100.0
    schedule_s = [[300.0, inf]]
    range_km = 50.0
    power_w = 2.0
    outlier_std_rad = 0.25
"""
BARRAGE = SPOT.replace('mode = "spot"', 'mode = "barrage"').replace('band = "X"\n', "") \
    .replace("search_delay_s = 100.0\n", "")
# near: in reach, on the jammer's band; other: in reach, another band; far: out of reach
NETWORK = df("near", 0.0, "X") + df("other", 5.0, "Y") + df("far", 100.0, "X")


def _streams(sc, sid):
    events = list(sensor_events(sc, sid))
    return events, np.array([e.measurement.z for e in events])


@pytest.mark.parametrize("jammer, touched", [(SPOT, {"near"}), (BARRAGE, {"near", "other"})])
def test_jammer_switched_on_mid_run_touches_only_sensors_in_reach_and_band(tmp_path, jammer, touched):
    clean = write_scenario(tmp_path, NETWORK, name="clean.toml")
    jammed = write_scenario(tmp_path, NETWORK, jammer, name="jammed.toml")
    t_found = 400.0 if "spot" in jammer else 300.0  # spot: switch-on + search delay
    for sid in ("near", "other", "far"):
        ev_clean, z_clean = _streams(clean, sid)
        ev_jam, z_jam = _streams(jammed, sid)
        before = np.array([e.t < t_found for e in ev_jam])
        # the stream before the jammer acts is literally the same
        np.testing.assert_array_equal(z_jam[before], z_clean[before])
        if sid not in touched:
            np.testing.assert_array_equal(z_jam, z_clean)  # bit-identical, whole run
            assert not any(e.jammed or e.outlier for e in ev_jam)
            continue
        assert all(e.jammed == (e.t >= t_found) for e in ev_jam)
        _, err, out, _ = bearing_errors(jammed, sid, ev_jam)
        # error variance after switch-on (outliers included) ≫ before: one-sided F-test
        after = err[~before]
        f = after.var(ddof=1) / err[before].var(ddof=1)
        assert f > stats.f.ppf(1 - ALPHA, len(after) - 1, before.sum() - 1)
        assert out[~before].any() and not out[before].any()


def test_spot_jammer_state_searches_then_jams_its_band(tmp_path):
    sc = write_scenario(tmp_path, NETWORK, SPOT)
    off, searching, jamming = (jam_state(sc, "jammer", t) for t in (299.0, 300.0, 400.0))
    assert not off.on and off.affects == () and not off.searching
    assert searching.on and searching.searching and searching.affects == ()
    assert jamming.on and not jamming.searching and jamming.affects == ("near",)
    assert (jamming.mode, jamming.band, jamming.reach) == ("spot", "X", 50e3)
    np.testing.assert_array_equal(jamming.pos, [0.0, 30e3, 0.0])


def test_jam_events_cover_the_run_at_the_jammer_period(tmp_path):
    sc = write_scenario(tmp_path, NETWORK, BARRAGE.replace("range_km = 50.0", "range_km = 50.0\nperiod_s = 10.0"),
                        duration=999.0)
    events = list(jam_events(sc, "jammer"))
    assert [e.t for e in events[:3]] == [0.0, 10.0, 20.0] and len(events) == 100
    assert [e.on for e in events] == [e.t >= 300.0 for e in events]
    assert all(e.affects == ("near", "other") for e in events if e.on)


def test_df_reports_bearings_on_the_jammer_while_it_transmits(tmp_path):
    sc = write_scenario(tmp_path, df("df1", 0.0, extra='targets = ["E1", "jammer"]'), """
        [jammers.jammer]
        pos_km = [10.0, 10.0]
        mode = "barrage"
        schedule_s = [[10.0, 20.0]]
        p_outlier = 1.0
        outlier_std_rad = 0.25
    """, duration=30.0)
    on_jammer = [e for e in sensor_events(sc, "df1") if e.target == "jammer"]
    assert [e.measurement is not None for e in on_jammer] == [10 <= e.t < 20 for e in on_jammer]
    for e in on_jammer:
        assert not e.jammed and not e.outlier  # its own signal is not contamination
        if e.measurement is not None:
            assert abs(wrap_pi(e.measurement.z[0] - math.pi / 4)) < 5 * SIGMA1
    on_emitter = [e for e in sensor_events(sc, "df1") if e.target == "E1"]
    assert [e.outlier for e in on_emitter] == [10 <= e.t < 20 for e in on_emitter]  # p = 1 while on
