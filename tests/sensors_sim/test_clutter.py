"""False alarms in the sensor emulators: Poisson count law, uniform spread over the
coverage, no truth in the stream, determinism, and validation of ``clutter_rate``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from sensors_sim import ScenarioError, sensor_events
from _scenarios import write_scenario

ALPHA = 0.01
N_SCANS = 3000
RATE = 2.5

RADAR = f"""
    [sensors.radar]
    kind = "radar2d"
    pos_m = [0.0, 0.0, 0.0]
    period_s = 1.0
    std_az_deg = 1.0
    std_range_m = 20.0
    max_range_km = 40.0
    clutter_rate = {RATE}

    [sensors.angle]
    kind = "angle"
    pos_m = [0.0, 0.0, 0.0]
    period_s = 1.0
    std_az_deg = 0.05
    std_el_deg = 0.05
    fov_az_deg = [300.0, 60.0]
    fov_el_deg = [5.0, 45.0]
    clutter_rate = {RATE}
"""
TARGET = """
    [targets.T1]
    pos_m = [3000.0, 8000.0, 3000.0]
    segments = [{ type = "static" }]
"""


@pytest.fixture(scope="module")
def cluttered(tmp_path_factory):
    return write_scenario(tmp_path_factory.mktemp("clutter"), RADAR, TARGET, duration=N_SCANS - 1.0)


def scans(scenario, sensor_id, run=0):
    """The sensor's events grouped by scan time."""
    out: dict[float, list] = {}
    for ev in sensor_events(scenario, sensor_id, run):
        out.setdefault(ev.t, []).append(ev)
    return list(out.values())


@pytest.mark.parametrize("sensor_id", ["radar", "angle"])
def test_false_alarm_count_per_scan_is_poisson(cluttered, sensor_id):
    """Mean (z-test), dispersion (variance = mean: Σ(n − n̄)²/n̄ ~ χ²(N−1)) and the whole
    law (χ² goodness of fit on the counts 0…7, ≥ 8 pooled), each at 1 %."""
    counts = np.array([sum(ev.clutter for ev in scan) for scan in scans(cluttered, sensor_id)])
    assert len(counts) == N_SCANS
    n = len(counts)
    assert abs(counts.mean() - RATE) / math.sqrt(RATE / n) < stats.norm.ppf(1 - ALPHA / 2)
    dispersion = float(np.sum((counts - counts.mean()) ** 2) / counts.mean())
    assert stats.chi2.ppf(ALPHA / 2, n - 1) < dispersion < stats.chi2.ppf(1 - ALPHA / 2, n - 1)
    observed = np.array([np.sum(counts == k) for k in range(8)] + [np.sum(counts >= 8)])
    p = np.append(stats.poisson.pmf(np.arange(8), RATE), stats.poisson.sf(7, RATE))
    assert stats.chisquare(observed, n * p).pvalue > ALPHA


def test_false_alarms_are_uniform_over_the_coverage(cluttered):
    """Each component, normalised to its coverage interval, is U(0, 1) (KS at 1 %):
    radar azimuth over 360° and range over [0, max_range]; the angle sensor's azimuth
    over its sector through north and elevation between its limits."""
    def plots(sensor_id):
        return np.array([ev.measurement.z for scan in scans(cluttered, sensor_id) for ev in scan if ev.clutter])

    radar = plots("radar")
    angle = plots("angle")
    first, width = math.radians(300.0), math.radians(120.0)
    lo, hi = math.radians(5.0), math.radians(45.0)
    for u in (radar[:, 0] / (2 * math.pi), radar[:, 1] / 40_000.0,
              np.mod(angle[:, 0] - first, 2 * math.pi) / width, (angle[:, 1] - lo) / (hi - lo)):
        assert np.all((u >= 0) & (u <= 1))
        assert stats.kstest(u, "uniform").pvalue > ALPHA


def test_stream_carries_no_truth_and_keeps_the_order_contract(cluttered):
    """Plots of a scan share its time and take seq 0, 1, … in publication order; the
    target's plot is not singled out by its place: it comes first with probability
    E[1/(N+1)] = (1 − e^{−λ})/λ, N ~ Poisson(λ) false alarms (binomial test, 1 %)."""
    all_scans = scans(cluttered, "radar")
    seq = [ev.measurement.seq for scan in all_scans for ev in scan if ev.measurement is not None]
    assert seq == list(range(len(seq)))
    keys = [ev.measurement.order_key for scan in all_scans for ev in scan if ev.measurement is not None]
    assert keys == sorted(keys)
    first = [scan[0].target == "T1" for scan in all_scans]
    assert all(any(ev.target == "T1" for ev in scan) for scan in all_scans)  # P_D = 1
    expected = (1 - math.exp(-RATE)) / RATE
    assert stats.binomtest(sum(first), len(first), expected).pvalue > ALPHA
    ev = next(ev for scan in all_scans for ev in scan if ev.clutter)
    assert ev.target == "" and ev.detected and not ev.jammed
    assert ev.measurement.kind == "range_az" and ev.measurement.sensor == "radar"


def test_clutter_is_deterministic_and_rate_zero_draws_nothing(tmp_path, cluttered):
    again = write_scenario(tmp_path, RADAR, TARGET, duration=N_SCANS - 1.0)
    a = [ev.measurement.z for ev in sensor_events(cluttered, "radar", 3) if ev.measurement is not None]
    b = [ev.measurement.z for ev in sensor_events(again, "radar", 3) if ev.measurement is not None]
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    # an explicit rate of 0 is the clutter-free stream, bit for bit
    zero = write_scenario(tmp_path, RADAR.replace(f"clutter_rate = {RATE}", "clutter_rate = 0.0"), TARGET,
                          duration=200.0, name="zero.toml")
    none = write_scenario(tmp_path, RADAR.replace(f"clutter_rate = {RATE}", ""), TARGET, duration=200.0,
                          name="none.toml")
    for sid in ("radar", "angle"):
        za = [ev.measurement.z.tobytes() for ev in sensor_events(zero, sid) if ev.measurement is not None]
        zb = [ev.measurement.z.tobytes() for ev in sensor_events(none, sid) if ev.measurement is not None]
        assert za == zb and len(za) == 201


@pytest.mark.parametrize("edit, field, why", [
    (("max_range_km = 40.0", ""), "sensors.radar.clutter_rate", "finite coverage"),
    (("clutter_rate = 2.5", "clutter_rate = -1.0"), "sensors.radar.clutter_rate", ">= 0"),
    (("clutter_rate = 2.5", 'clutter_rate = "many"'), "sensors.radar.clutter_rate", ""),
])
def test_bad_clutter_rate_names_file_line_and_field(tmp_path, edit, field, why):
    text = RADAR.replace(*edit, 1)
    with pytest.raises(ScenarioError) as e:
        write_scenario(tmp_path, text, TARGET, duration=10.0)
    path = tmp_path / "emu.toml"
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1) if t.strip().startswith("clutter_rate"))
    assert str(e.value).startswith(f"{path}:{line}: {field}: ") and why in str(e.value)
