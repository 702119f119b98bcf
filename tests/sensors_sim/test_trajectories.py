"""Truth trajectories: segment closed forms, the white-noise-jerk law, determinism."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest
from scipy import stats

from fusion.angles import wrap_pi
from sensors_sim import load_scenario, truth_events, truth_trajectory
from sensors_sim.segments import ConstantAcceleration, ConstantVelocity, CoordinatedTurn, Orbit, Static, Waypoints
from sensors_sim.trajectories import Trajectory, sample_times
from sensors_sim.spec import TargetSpec

ALPHA = 0.01  # significance of every statistical test in this file


def jerk_transition(dt):
    """Per-axis CA transition F₁ (the brief's closed form, an oracle independent of the code)."""
    return np.array([[1.0, dt, dt * dt / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])


def jerk_covariance(q, dt):
    """Per-axis white-noise-jerk covariance q·Q₁(dt)."""
    return q * np.array([[dt**5 / 20, dt**4 / 8, dt**3 / 6], [dt**4 / 8, dt**3 / 3, dt**2 / 2],
                         [dt**3 / 6, dt**2 / 2, dt]])


def make_target(x0, *segments, jerk_psd=0.0) -> TargetSpec:
    return TargetSpec("T", np.asarray(x0, dtype=float), tuple(segments), jerk_psd)


def scenario_file(tmp_path, targets: str, duration=100.0, truth_dt=0.5, period=1.0, seed=7):
    text = textwrap.dedent(f"""\
        description = "trajectory test"
        seed = {seed}
        duration_s = {duration}
        truth_dt_s = {truth_dt}
        [origin]
        lat_deg = 0.0
        lon_deg = 0.0
        alt_m = 0.0
        [defaults]
        topology = "centralised"
        method = "SS"
        [sensors.r]
        kind = "radar3d"
        pos_m = [-50000.0, -50000.0, 0.0]
        period_s = {period}
        std_az_deg = 1.0
        std_el_deg = 1.0
        std_range_m = 20.0
    """) + textwrap.dedent(targets)
    path = tmp_path / "traj.toml"
    path.write_text(text)
    return load_scenario(path)


# --- segments ---------------------------------------------------------------------------

X0 = [6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.5, 1.0, -0.05]


def test_constant_acceleration_closed_form():
    traj = Trajectory(make_target(X0, ConstantAcceleration()))
    p0, v0, a = np.array(X0[:3]), np.array(X0[3:6]), np.array(X0[6:])
    for t in (0.0, 1.0, 17.3, 60.0):
        np.testing.assert_allclose(traj.state(t), np.concatenate([p0 + v0 * t + a * t * t / 2, v0 + a * t, a]),
                                   rtol=1e-12, atol=1e-9)


def test_constant_velocity_and_static_segments_chain():
    # 10 s CV at a new velocity, then static: position continuous, v = a = 0 after
    traj = Trajectory(make_target(X0, ConstantVelocity(10.0, np.array([10.0, 0.0, 0.0])), Static()))
    np.testing.assert_allclose(traj.state(5.0), [6050.0, 8000.0, 2000.0, 10, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(traj.state(10.0), [6100.0, 8000.0, 2000.0, 0, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(traj.state(500.0), traj.state(10.0))


def test_coordinated_turn_right_turn_keeps_speed_and_turns_clockwise():
    omega = math.radians(3.0)  # 3°/s to the right
    v0 = np.array([0.0, 200.0, 2.0])  # heading north, climbing
    traj = Trajectory(make_target([0, 0, 1000, *v0, 0, 0, 0], CoordinatedTurn(omega)))
    period = 2 * math.pi / omega
    for t in np.linspace(0.0, period, 13):
        x = traj.state(t)
        v = x[3:6]
        assert math.hypot(v[0], v[1]) == pytest.approx(200.0, rel=1e-12)
        heading = math.atan2(v[0], v[1]) % (2 * math.pi)  # compass
        assert wrap_pi(heading - omega * t) == pytest.approx(0.0, abs=1e-9)
        # centripetal: |a| = v·ω, perpendicular to v, pointing right of the heading
        a = x[6:9]
        assert np.linalg.norm(a) == pytest.approx(200.0 * omega, rel=1e-12)
        assert float(a[:2] @ v[:2]) == pytest.approx(0.0, abs=1e-9)
        assert float(v[0] * a[1] - v[1] * a[0]) < 0  # clockwise
        assert x[2] == pytest.approx(1000.0 + 2.0 * t)
    # a full circle comes back; the centre is the radius to the right (east)
    np.testing.assert_allclose(traj.state(period)[:2], [0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(traj.state(period / 2)[:2], [2 * 200.0 / omega, 0.0], atol=1e-6)


def test_waypoints_fly_straight_legs_at_constant_speed():
    pts = np.array([[1000.0, 0.0, 0.0], [1000.0, 2000.0, 0.0]])
    traj = Trajectory(make_target([0, 0, 0, 0, 0, 0, 0, 0, 0], Waypoints(pts, 50.0)))
    np.testing.assert_allclose(traj.state(20.0), [1000, 0, 0, 0, 50, 0, 0, 0, 0])  # leg 2 starts at 20 s
    np.testing.assert_allclose(traj.state(10.0)[:6], [500, 0, 0, 50, 0, 0])
    np.testing.assert_allclose(traj.state(60.0)[:3], [1000, 2000, 0])
    np.testing.assert_allclose(traj.state(70.0)[:6], [1000, 2500, 0, 0, 50, 0])  # flies on


def test_segment_boundaries_keep_position_continuous():
    segs = (ConstantAcceleration(5.0), CoordinatedTurn(0.05, 10.0), ConstantVelocity(5.0),
            Waypoints(np.array([[0.0, 0.0, 0.0]]), 300.0), Static())
    traj = Trajectory(make_target(X0, *segs))
    for t in (5.0, 15.0, 20.0):
        np.testing.assert_allclose(traj.state(t - 1e-7)[:3], traj.state(t)[:3], atol=1e-4)


def test_negative_time_is_rejected():
    with pytest.raises(ValueError, match="t = -1"):
        Trajectory(make_target(X0, Static())).state(-1.0)


def test_sample_times_are_inclusive_and_drift_free():
    t = sample_times(1.0, 0.1, 1000.0)
    assert len(t) == 9991 and t[0] == 1.0 and t[-1] == pytest.approx(1000.0)
    assert len(sample_times(0.0, 1.0, 30.0)) == 31
    assert len(sample_times(50.0, 1.0, 30.0)) == 0


# --- process noise ----------------------------------------------------------------------

CA_TARGET = """
    [targets.T1]
    pos_m = [6000.0, 8000.0, 2000.0]
    vel_mps = [-120.0, -60.0, 5.0]
    acc_mps2 = [0.5, 1.0, -0.05]
    jerk_psd = 0.01
"""


def _deviation_states(traj: Trajectory, times) -> np.ndarray:
    return np.array([traj.state(t) - traj.nominal(t) for t in times])


@pytest.mark.parametrize("stride", [1, 4])
def test_jerk_increments_follow_the_exact_discretisation(tmp_path, stride):
    """On the grid (stride 1) and sub-sampled at 4·dt, e_{k+1} − F e_k ~ N(0, q·Q₁(Δ)):
    whitened per axis by the Cholesky factor, the components are i.i.d. N(0, 1)."""
    dt, q = 0.5, 0.01
    sc = scenario_file(tmp_path, CA_TARGET, duration=2000.0, truth_dt=dt)
    traj = truth_trajectory(sc, "T1")
    step = stride * dt
    times = np.arange(0.0, 2000.0 + 1e-9, step)
    e = _deviation_states(traj, times).reshape(len(times), 3, 3)  # [k, (p,v,a), axis]
    F, L = jerk_transition(step), np.linalg.cholesky(jerk_covariance(q, step))
    w = e[1:] - np.einsum("ij,kja->kia", F, e[:-1])
    white = np.linalg.solve(L, w.transpose(1, 0, 2).reshape(3, -1)).ravel()
    n = white.size
    assert abs(white.mean()) * math.sqrt(n) < stats.norm.ppf(1 - ALPHA / 2)
    chi2 = float(white @ white)
    assert stats.chi2.ppf(ALPHA / 2, n) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, n)
    assert stats.kstest(white, "norm").pvalue > ALPHA


def test_truth_starts_at_x0_and_between_nodes_carries_the_deviation(tmp_path):
    sc = scenario_file(tmp_path, CA_TARGET, duration=20.0, truth_dt=0.5)
    traj = truth_trajectory(sc, "T1")
    np.testing.assert_array_equal(traj.state(0.0), sc.targets["T1"].x0)
    e_node = traj.state(3.0) - traj.nominal(3.0)
    expected = (jerk_transition(0.2) @ e_node.reshape(3, 3)).reshape(9)
    np.testing.assert_allclose(traj.state(3.2) - traj.nominal(3.2), expected, atol=1e-12)


def test_truth_is_a_deterministic_function_of_scenario_and_run(tmp_path):
    sc = scenario_file(tmp_path, CA_TARGET, duration=30.0)
    again = load_scenario(sc.source)  # another process loading the same file
    times = sample_times(0.0, 1.0, 30.0)
    a = truth_trajectory(sc, "T1", run=0).states(times)
    np.testing.assert_array_equal(a, truth_trajectory(again, "T1", run=0).states(times))
    assert not np.array_equal(a, truth_trajectory(sc, "T1", run=1).states(times))
    other_seed = scenario_file(tmp_path, CA_TARGET, duration=30.0, seed=8)
    assert not np.array_equal(a, truth_trajectory(other_seed, "T1").states(times))


def test_a_noiseless_target_draws_nothing_from_the_truth_stream(tmp_path):
    sc = scenario_file(tmp_path, CA_TARGET, duration=30.0)
    with_emitter = scenario_file(tmp_path, """
        [targets.E0]
        pos_km = [1.0, 2.0]
        segments = [{ type = "static" }]
    """ + CA_TARGET, duration=30.0)
    times = sample_times(0.0, 1.0, 30.0)
    np.testing.assert_array_equal(truth_trajectory(sc, "T1").states(times),
                                  truth_trajectory(with_emitter, "T1").states(times))
    np.testing.assert_array_equal(truth_trajectory(with_emitter, "E0").state(12.0),
                                  [1000.0, 2000.0, 0, 0, 0, 0, 0, 0, 0])


def test_truth_events_default_to_the_fastest_sensor_period(tmp_path):
    sc = scenario_file(tmp_path, CA_TARGET + """
    [targets.T2]
    pos_km = [1.0, 2.0, 3.0]
    """, duration=10.0, period=0.5)
    events = list(truth_events(sc))
    assert [e.t for e in events[:4]] == [0.0, 0.0, 0.5, 0.5]
    assert [e.target for e in events[:4]] == ["T1", "T2", "T1", "T2"]
    assert len(events) == 2 * 21
    traj = truth_trajectory(sc, "T1")
    np.testing.assert_array_equal(events[-2].x, traj.state(10.0))
    assert len(list(truth_events(sc, period=2.0))) == 2 * 6


def test_unknown_target_is_a_clear_error(tmp_path):
    sc = scenario_file(tmp_path, CA_TARGET, duration=10.0)
    with pytest.raises(KeyError, match="no target 'T9'"):
        truth_trajectory(sc, "T9")


# --- endless trajectories -----------------------------------------------------------------


def test_orbit_is_smooth_periodic_and_its_own_derivative():
    """Velocity and acceleration are the derivatives of position (central differences,
    independent of the closed forms), the ellipse's semi-axes and lap are as given,
    and the state at t and t + k·lap is the same for any k: defined for every t."""
    seg = Orbit(10_000.0, 5_000.0, 600.0, math.radians(90.0), left=True)
    traj = Trajectory(make_target([0.0, 5000.0, 2000.0, 0, 0, 0, 0, 0, 0], seg))
    h = 1e-3
    for t in np.linspace(h, 1800.0, 97):
        x, xp, xm = traj.state(t), traj.state(t + h), traj.state(t - h)
        np.testing.assert_allclose((xp[:3] - xm[:3]) / (2 * h), x[3:6], atol=1e-4)
        np.testing.assert_allclose((xp[3:6] - xm[3:6]) / (2 * h), x[6:9], atol=1e-6)
        np.testing.assert_allclose(traj.state(t + 600.0 * 12), x, atol=1e-6)  # 12 laps later
        np.testing.assert_allclose(traj.state(t + 3600.0 * 24 * 3), x, atol=1e-4)  # three days later
        assert x[2] == 2000.0 and x[5] == 0.0
    centre = np.array([0.0, 10_000.0])
    pts = traj.states(np.linspace(0.0, 600.0, 2401))[:, :2] - centre
    np.testing.assert_allclose((pts[:, 0] / 10_000.0) ** 2 + (pts[:, 1] / 5_000.0) ** 2, 1.0, atol=1e-12)
    assert pts[:, 0].max() == pytest.approx(10_000.0) and pts[:, 1].max() == pytest.approx(5_000.0)
    # starts at the middle of the southern side heading east, counter-clockwise
    np.testing.assert_allclose(traj.state(0.0)[:6], [0, 5000, 2000, 2 * math.pi / 600 * 10_000, 0, 0], atol=1e-9)
    assert traj.state(150.0)[0] == pytest.approx(10_000.0)


def test_orbit_turning_right_mirrors_left():
    x0 = [0.0, 0.0, 1000.0, 0, 0, 0, 0, 0, 0]
    left = Trajectory(make_target(x0, Orbit(4000.0, 1000.0, 300.0, 0.0, left=True)))  # long axis north
    right = Trajectory(make_target(x0, Orbit(4000.0, 1000.0, 300.0, 0.0, left=False)))
    for t in (10.0, 75.0, 200.0):
        a, b = left.state(t), right.state(t)
        np.testing.assert_allclose([-a[0], a[1], -a[3], a[4], -a[6], a[7]], [b[0], b[1], b[3], b[4], b[6], b[7]],
                                   atol=1e-9)
    assert left.state(75.0)[0] < 0 < right.state(75.0)[0]  # the centre is west (left) of a northbound start


def test_patent_3d_orbit_scenario():
    sc = load_scenario("patent-3d-orbit")
    assert sc.duration == 600.0 and set(sc.sensors) == {"radar2d", "angle"}
    assert set(sc.sensors) == set(load_scenario("patent-3d").sensors)
    traj = truth_trajectory(sc, "T1")
    ranges = [np.linalg.norm(traj.position(t)) for t in np.linspace(0, 600, 601)]
    assert 4_000 < min(ranges) and max(ranges) < 20_000  # always in the sensors' view
    np.testing.assert_allclose(traj.state(7200.0), traj.state(0.0), atol=1e-6)  # 12 laps: back at the start


def test_orbit_axes_are_checked(tmp_path):
    from sensors_sim import ScenarioError

    from sensors_sim.loader import _builtin_dir

    src = ((_builtin_dir() / "patent-3d-orbit.toml").read_text()
           .replace("axes_m = [10000.0, 5000.0]", "axes_m = [1000.0, 5000.0]"))
    path = tmp_path / "bad.toml"
    path.write_text(src)
    with pytest.raises(ScenarioError, match="axes_m"):
        load_scenario(str(path))


def test_iter_times_is_sample_times_lazily_and_may_be_endless():
    """The sources' lazy scan and truth times: the same floats as :func:`sample_times`
    (bit for bit: a scenario run's measurements are unchanged), and an infinite end."""
    import itertools

    from sensors_sim.trajectories import iter_times, sample_times

    for args in [(0.0, 1.0, 30.0), (0.5, 0.1, 600.0), (0.25, 1 / 3, 10.0), (5.0, 1.0, 4.0), (0.0, 0.1, 100.0),
                 (0.3, 0.7, 0.3)]:
        assert list(iter_times(*args)) == sample_times(*args).tolist(), args
    assert list(itertools.islice(iter_times(2.0, 0.5, float("inf")), 10**5))[-1] == 2.0 + 0.5 * (10**5 - 1)
