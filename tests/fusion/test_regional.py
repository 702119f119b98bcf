"""Regional fusers under a system fuser (fusion.regional): a handover keeps its system
id, a shared sensor's common information is not counted twice (CI consistent where the
naive product is not), and one region covering everything is the centralised tracker."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from fusion.methods import make_method, method_config
from fusion.metrics import chi2_bounds
from fusion.motion import ConstantAcceleration, ConstantTurn, ConstantVelocity
from fusion.regional import (SCREEN_SLACK_M, RegionalFrame, RegionalFuser, RegionalMethod, SystemFuser, SystemTrack,
                             _ci_pairs, _Rows, _transitions)
from fusion.regions import Region, box_polygon
from fusion.track_fusion import fuse_ci
from fusion.tracking.hypotheses import gate_threshold, track_distance2
from fusion.types import Estimate, Identity
from sensors_sim import load_scenario, truth_trajectory
from services.evaluation import merged_measurements, run_method
from conftest import ROOT

TWO_REGIONS = ROOT / "tests" / "data" / "two-regions.toml"


def scenario(tmp_path, duration, pos, vel, name="two.toml"):
    """tests/data/two-regions.toml with the aircraft's start, velocity and the duration replaced."""
    text = TWO_REGIONS.read_text()
    for key, value in (("duration_s", duration), ("pos_km", pos), ("vel_mps", vel)):
        text, n = re.subn(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.M)
        assert n == 1
    p = tmp_path / name
    p.write_text(text)
    return load_scenario(p)


def run_regional(sc, run=0, rule="ci", regions=None):
    method = RegionalMethod.from_config("SS", regions or sc.regions, method_config(sc.tracker, "SS"), make_method,
                                        rule)
    out, members, t_prev = [], [], None
    for m in merged_measurements(sc, run):
        if t_prev is not None and m.t > t_prev:
            out += method.advance(t_prev)
        out += method.process(m)
        t_prev = m.t
        members.append({s.id: dict(s.members) for s in method.system.tracks.values()})
    return out + method.finish(), members


def test_a_crossing_keeps_one_system_track_id(tmp_path):
    """One aircraft from 25 km west to 25 km east at 200 m/s: the west region holds it
    up to 8 km east, the east region from 8 km west; its system track is T1 throughout,
    held by the west track, then both, then the east track, and never two system tracks."""
    sc = scenario(tmp_path, 250.0, "[-25.0, 5.0, 6.0]", "[200.0, 0.0, 0.0]")
    out, members = run_regional(sc)
    assert out and {e.track for e in out} == {"T1"}
    held = [tuple(sorted(m["T1"])) for m in members if "T1" in m]
    seen = list(dict.fromkeys(held))  # in order of first appearance
    assert seen == [("west",), ("east", "west"), ("east",)]
    assert max(len(m) for m in members) == 1  # never a second system track
    # the system track follows the aircraft throughout
    traj = truth_trajectory(sc, "A", 0)
    err = [np.linalg.norm(e.x[:3] - traj.position(e.t)) for e in out if e.t > 20.0]
    assert max(err) < 150.0


class _Systems:
    """Stands for :class:`RegionalMethod`'s system fuser: each regional frame, in the
    order the method releases them, goes to several system fusers, each fed the frames of
    its own regions (a system fuser's picture is a function of the frames it is fed in
    that order alone, and a regional fuser's frames do not depend on the other regions)."""

    def __init__(self, systems):
        self.systems = systems  # key -> (SystemFuser, the regions whose frames it is fed)
        self.out = {key: [] for key in systems}

    def frame(self, f):
        for key, (system, regions) in self.systems.items():
            if f.region in regions:
                self.out[key] += system.frame(f)
        return []


def _last_nees(sc, runs, systems):
    """For each of ``systems`` (key -> (rule, regions)), the mean over runs of the NEES of
    each run's last estimate of the system track: per run, one pass of the regional
    trackers of every region used, their frames fed to every system fuser — what
    :func:`run_regional` with that rule and those regions gives each."""
    nees = {key: [] for key in systems}
    config = method_config(sc.tracker, "SS")
    used = {name: g for name, g in sc.regions.items() if any(name in regions for _, regions in systems.values())}
    for r in range(runs):
        tee = _Systems({key: (RegionalMethod.system_fuser("SS", config, regions, rule), set(regions))
                        for key, (rule, regions) in systems.items()})
        method = RegionalMethod("SS", [RegionalFuser(g, make_method("SS", config)) for g in used.values()], tee)
        run_method(sc, "SS", None, r, method=method)  # the frames go to ``tee``
        for key, out in tee.out.items():
            last = out[-1]
            err = last.x - truth_trajectory(sc, "A", r).state(last.t)[: last.x.size]
            nees[key].append(float(err @ np.linalg.solve(last.P, err)))
    return {key: float(np.mean(v)) for key, v in nees.items()}


def test_shared_sensor_information_is_counted_once_by_ci():
    """Two regional estimates of one state (6 components), each from its own sensor and a
    shared one whose information dominates: ``P₁ = (I_a + I_s)⁻¹``, ``P₂ = (I_b + I_s)⁻¹``,
    ``Cov(e₁, e₂) = P₁ I_s P₂``. Through the system fuser, 300 draws: CI's ANEES lies in
    the two-sided 95 % χ² interval, the naive product's (the shared information counted
    twice) above it."""
    n, runs = 6, 300
    I_s = np.diag([9.0, 8.0, 10.0, 4.0, 5.0, 6.0])
    I_a, I_b = np.diag([1.0, 2.0, 1.0, 0.5, 1.0, 0.7]), np.diag([2.0, 1.0, 1.5, 1.0, 0.4, 0.6])
    P1, P2 = np.linalg.inv(I_a + I_s), np.linalg.inv(I_b + I_s)
    P12 = P1 @ I_s @ P2
    joint = np.block([[P1, P12], [P12.T, P2]])
    rng = np.random.default_rng(11)
    lo, hi = chi2_bounds(n, runs)
    for rule, inside in (("ci", True), ("naive", False)):
        nees = []
        for e in rng.multivariate_normal(np.zeros(2 * n), joint, runs):
            system = SystemFuser("SS", ConstantVelocity(1.0), 0.999, rule)
            system.frame(RegionalFrame("west", 0.0, (Estimate(0.0, e[:n], P1, "SS", "west", "west.T1"),)))
            fused = system.frame(RegionalFrame("east", 0.0, (Estimate(0.0, e[n:], P2, "SS", "east", "east.T1"),)))
            assert [f.track for f in fused] == ["T1"]
            nees.append(float(fused[0].x @ np.linalg.solve(fused[0].P, fused[0].x)))
        anees = float(np.mean(nees))
        assert (lo <= anees <= hi) is inside, (rule, anees, lo, hi)
        if not inside:
            assert anees > hi


@pytest.fixture(scope="module")
def overlap(tmp_path_factory):
    """An aircraft flying north 2 km east of the boundary: in both regions throughout,
    each fed by its own radar and the shared, more accurate one (s)."""
    return scenario(tmp_path_factory.mktemp("overlap"), 60.0, "[2.0, -5.0, 6.0]", "[0.0, 150.0, 0.0]")


def test_trackers_sharing_a_sensor_fused_by_ci_are_as_consistent_as_one_region(overlap):
    """The same through the trackers, 30 runs: the regional trackers are themselves
    conservative here (one region's ANEES about 2.9 of 6: the EKF's prior and
    linearisation), so the reference is one region's own ANEES on the same runs: CI's
    system track stays within 10 % of it; the naive product doubles it."""
    runs = 30
    anees = _last_nees(overlap, runs, {"one": ("ci", {"west": overlap.regions["west"]}),
                                       "ci": ("ci", overlap.regions), "naive": ("naive", overlap.regions)})
    one, ci, naive = anees["one"], anees["ci"], anees["naive"]
    assert ci <= 1.1 * one, (ci, one)
    assert naive >= 1.6 * one, (naive, one)


def test_one_region_covering_everything_is_the_centralised_tracker():
    """air-picture, 60 s: the system picture of one region holding every sensor equals the
    centralised SS tracker's estimates to 1e-9 (and its ids)."""
    sc = dataclasses.replace(load_scenario("air-picture"), duration=60.0)
    everything = {"all": Region("all", box_polygon(-1e7, -1e7, 1e7, 1e7), 0.0, tuple(sc.sensors))}
    central = run_method(sc, "SS", None, 0, merged_measurements(sc, 0))
    regional, _ = run_regional(sc, 0, regions=everything)
    assert len(regional) == len(central) > 100
    for a, b in zip(central, regional):
        assert (a.t, a.track) == (b.t, b.track)
        np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.P, a.P, rtol=0, atol=1e-9)


def west_and_east() -> dict[str, Region]:
    """Two regions west and east of e = 0 with 8 km margins, a radar each (w, e)."""
    return {"west": Region("west", box_polygon(-60e3, -60e3, 0.0, 60e3), 8e3, ("w",)),
            "east": Region("east", box_polygon(0.0, -60e3, 60e3, 60e3), 8e3, ("e",))}


def aircraft(region: str, track: str, e: float, t: float = 0.0, moving: bool = True) -> Estimate:
    """A regional track's estimate of an aircraft flying east at 200 m/s, 6 km up: at e (m)
    at t = 0 (``moving``: at e + 200 t at t; else at e whatever t), σ 100 m and 10 m/s."""
    x = e + 200.0 * t if moving else e
    P = np.diag([100.0, 100.0, 100.0, 10.0, 10.0, 10.0]) ** 2
    return Estimate(t, np.array([x, 0.0, 6000.0, 200.0, 0.0, 0.0]), P, "SS", region, f"{region}.{track}")


def test_a_margin_track_waits_to_join_and_an_overlap_duplicate_waits():
    """A track in its region's margin (over the neighbour's polygon) starts no system track:
    it waits, and joins the neighbour's once that exists; a second west track on an
    aircraft that both regions hold waits too; a west track over west alone starts one."""
    regions = west_and_east()
    system = SystemFuser("SS", ConstantVelocity(1.0), 0.999, "ci", regions=regions)

    def est(region, track, e, t=0.0):
        return aircraft(region, track, e, t, moving=False)

    assert system.frame(RegionalFrame("east", 0.0, (est("east", "T1", -3000.0),))) == []  # over west: waits
    assert not system.tracks
    out = system.frame(RegionalFrame("west", 0.0, (est("west", "T1", -3050.0), est("west", "T2", -40e3))))
    assert [e.track for e in out] == ["T1", "T2"]
    out = system.frame(RegionalFrame("east", 1.0, (est("east", "T1", -2800.0, 1.0),)))
    assert [e.track for e in out] == ["T1"] and system.tracks["T1"].members == {"west": "west.T1", "east": "east.T1"}
    out = system.frame(RegionalFrame("west", 1.0, (est("west", "T1", -2850.0, 1.0), est("west", "T3", -2700.0, 1.0))))
    assert [e.track for e in out] == ["T1"] and "west.T3" not in system.owner and len(system.tracks) == 2


def test_two_system_tracks_on_one_aircraft_merge_into_the_older():
    """A west duplicate born out of the gate of the aircraft's system track (held by west
    and east) starts its own; once the two stay in each other's gate for merge_frames
    looks at distinct times (two regions' frames of one time are one look) the younger
    is merged into the older and its west track waits, starting none; when the west
    tracker deletes its first track the waiting one joins the older system track, whose id
    the aircraft keeps. Two system tracks held by one region each are that region's
    tracker's to review: they are not merged."""
    regions = west_and_east()
    system = SystemFuser("SS", ConstantVelocity(1.0), 0.999, "ci", regions=regions, merge_frames=3)
    # west's second track 1.5 km off (d² ≈ 112: out of the gate) at t = 0, then 100 m off
    offsets = {0.0: 1500.0, 1.0: 100.0, 2.0: 100.0, 3.0: 100.0, 4.0: 100.0}
    seen = []
    for t, off in offsets.items():
        seen.append([e.track for e in system.frame(RegionalFrame(
            "west", t, (aircraft("west", "T1", -3000.0, t), aircraft("west", "T2", -3000.0 + off, t))))])
        seen.append([e.track for e in system.frame(RegionalFrame("east", t, (aircraft("east", "T1", -2950.0, t),)))])
        if t == 0.0:
            assert system.tracks["T1"].members == {"west": "west.T1", "east": "east.T1"}
            assert system.tracks["T2"].members == {"west": "west.T2"}
    # looks in the gate at t = 1, 2, 3: merged at t = 3, nothing of T2 after
    assert seen[:6] == [["T1", "T2"], ["T1"], ["T1", "T2"], ["T1"], ["T1", "T2"], ["T1"]]
    assert seen[6:] == [["T1"], ["T1"], ["T1"], ["T1"]]
    assert list(system.tracks) == ["T1"] and "west.T2" in system.absorbed
    out = system.frame(RegionalFrame("west", 5.0, (aircraft("west", "T2", -2900.0, 5.0),), dropped=("west.T1",)))
    assert [e.track for e in out] == ["T1"]
    assert system.tracks["T1"].members == {"west": "west.T2", "east": "east.T1"}

    alone = SystemFuser("SS", ConstantVelocity(1.0), 0.999, "ci", regions=regions, merge_frames=3)
    for t, off in offsets.items():
        out = alone.frame(RegionalFrame("west", t, (aircraft("west", "T1", -40e3, t),
                                                    aircraft("west", "T2", -40e3 + off, t))))
        assert [e.track for e in out] == ["T1", "T2"]


def test_two_regions_tracks_of_one_aircraft_the_join_missed_merge():
    """An east track born 1.5 km off the west track of the same aircraft (out of the gate:
    it starts its own system track, over east) and then 100 m off: the two system tracks,
    held by one region each but different ones, are merged after merge_frames looks, the
    east track joining the older; two tracks of one region are not (its tracker's)."""
    regions = west_and_east()
    system = SystemFuser("SS", ConstantVelocity(1.0), 0.999, "ci", regions=regions, merge_frames=3)
    for t, off in {0.0: 1500.0, 1.0: 100.0, 2.0: 100.0, 3.0: 100.0, 4.0: 100.0}.items():
        system.frame(RegionalFrame("west", t, (aircraft("west", "T1", -1000.0, t),)))
        system.frame(RegionalFrame("east", t, (aircraft("east", "T1", -1000.0 + off, t),)))
        if t == 0.0:
            assert {k: s.members for k, s in system.tracks.items()} == {"T1": {"west": "west.T1"},
                                                                         "T2": {"east": "east.T1"}}
    assert {k: s.members for k, s in system.tracks.items()} == {"T1": {"west": "west.T1", "east": "east.T1"}}


def test_a_system_track_says_its_members_identity_and_existence():
    """The system picture carries what its regional tracks say of the target, as a
    centralised fuser's does: a track of one member its identity and existence; of
    several, the identity of the most certain member that has one and the largest
    existence (without them CoT and CAT062 lost every callsign in the regional topology)."""
    regions = west_and_east()
    system = SystemFuser("SS", ConstantVelocity(1.0), 0.999, "ci", regions=regions)
    afr, dlh = Identity("39856a", "AFR1234"), Identity("3c6444", "DLH5KP")

    def said(region, track, t, identity, existence, sigma=1.0):
        e = aircraft(region, track, -3000.0, t, moving=False)
        return dataclasses.replace(e, P=e.P * sigma ** 2, identity=identity, existence=existence)

    (out,) = system.frame(RegionalFrame("west", 0.0, (said("west", "T1", 0.0, afr, 0.93),)))
    assert (out.track, out.identity, out.existence) == ("T1", afr, 0.93)
    (out,) = system.frame(RegionalFrame("east", 1.0, (said("east", "T1", 1.0, None, 0.99, sigma=0.5),)))
    assert system.tracks["T1"].members == {"west": "west.T1", "east": "east.T1"}
    assert (out.identity, out.existence) == (afr, 0.99)  # the only one that says who it is; the larger existence
    (out,) = system.frame(RegionalFrame("east", 2.0, (said("east", "T1", 2.0, dlh, 0.5, sigma=0.5),)))
    assert (out.identity, out.existence) == (dlh, 0.93)  # the more certain member's
    (out,) = system.frame(RegionalFrame("west", 2.0, (said("west", "T1", 2.0, None, None, sigma=0.25),)))
    assert (out.identity, out.existence) == (dlh, 0.5)


def test_the_screen_finds_the_pairs_of_the_test_over_every_pair():
    """The system fuser's screen (two k-d trees' candidates, over the rows unchanged since
    the big one was built and over those written since, then the test) finds exactly the
    pairs the test over every pair finds, among the rows asked for and not deleted:
    tracks spread over 60 km, spreads from 50 m to 3 km, times over 12 s, rows rewritten
    and deleted between builds, 200 random draws, a few thousand pairs in all."""
    rng = np.random.default_rng(3)
    gate, found = 22.46, 0

    def draw(n):
        out = []
        for _ in range(n):
            x = np.zeros(9)
            x[:2], x[3:5] = rng.uniform(-30e3, 30e3, 2), rng.normal(0.0, 200.0, 2)
            P = np.eye(9) * float(rng.choice([50.0, 300.0, 3000.0])) ** 2
            out.append(Estimate(float(rng.uniform(0.0, 12.0)), x, P, "SS", "n", "T1"))
        return out

    for _ in range(200):
        rows = _Rows(["west", "east"])
        tracks = [SystemTrack(f"T{k}", {"west": "w"}, e) for k, e in enumerate(draw(int(rng.integers(1, 60))))]
        for s in tracks:
            rows.put(s)
        if rng.uniform() < 0.7:
            rows._build()
        for s in rng.choice(tracks, len(tracks) // 3):  # rewritten since the build
            s.last = draw(1)[0]
            rows.put(s)
        for s in rng.choice(tracks, len(tracks) // 5):  # deleted
            rows.remove(s)
        a = draw(int(rng.integers(1, 30)))
        eligible = rng.uniform(size=len(rows.held)) < 0.8
        i, j = rows.near(a, gate, eligible)
        live = [k for k, s in enumerate(rows.tracks) if s is not None and s.id in rows.row and eligible[k]]
        if not live:
            assert len(i) == len(j) == 0
            continue
        b = [rows.tracks[k].last for k in live]
        t = np.maximum.outer([e.t for e in a], [e.t for e in b])
        pos = np.array([[e.x[:2] + e.x[3:5] * (t[i_, j_] - e.t) for j_ in range(len(b))] for i_, e in enumerate(a)])
        other = np.array([[f.x[:2] + f.x[3:5] * (t[i_, j_] - f.t) for j_, f in enumerate(b)] for i_ in range(len(a))])
        spread = np.add.outer([e.P[0, 0] + e.P[1, 1] for e in a], [f.P[0, 0] + f.P[1, 1] for f in b])
        every = np.linalg.norm(pos - other, axis=-1) <= np.sqrt(gate * spread) + SCREEN_SLACK_M
        ei, ej = np.nonzero(every.reshape(len(a), len(b)))
        np.testing.assert_array_equal(np.stack([i, j]), np.stack([ei, np.array(live, dtype=int)[ej]]))
        found += len(i)
    assert found > 1000


@pytest.mark.parametrize("motion", [ConstantVelocity(1.0), ConstantAcceleration(0.5),
                                    ConstantAcceleration(2.0, "discrete"), ConstantVelocity(3.0, "discrete", q_up=0.1),
                                    ConstantTurn(0.02, 1.0)])
def test_the_batched_transitions_are_the_models_own(motion):
    """F(dt), Q(dt) for many dt at once (the polynomial models' blocks evaluated together;
    any other model through its own F and Q) equal the model's F and Q, dt = 0 included."""
    dt = np.array([0.0, 0.37, 4.0, 12.5, 4.0])
    F, Q = _transitions(motion, dt)
    for k, d in enumerate(dt):
        np.testing.assert_allclose(F[k], motion.F(d), rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(Q[k], motion.Q(d), rtol=1e-13, atol=1e-13)


def _spd(rng, n, scale):
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + np.diag(scale ** 2)


def test_the_batched_track_distances_are_track_distance2():
    """The system fuser's d² of many pairs at once equals track_distance2 of each pair
    predicted (with the model's F, Q) to the later of its times on position and velocity,
    and is inf exactly where that is beyond the gate of its rank."""
    rng = np.random.default_rng(5)
    motion = ConstantAcceleration(0.5)
    system = SystemFuser("SS", motion, 0.999)
    scale = np.array([300.0, 300.0, 300.0, 20.0, 20.0, 20.0, 2.0, 2.0, 2.0])
    a, b = [], []
    for k in range(200):
        x = rng.normal(size=9) * scale
        a.append(Estimate(float(rng.uniform(0, 6)), x, _spd(rng, 9, scale), "SS", "w", "w.T1"))
        b.append(Estimate(float(rng.uniform(0, 6)), x + rng.normal(size=9) * scale * rng.uniform(0.5, 15.0),
                          _spd(rng, 9, scale), "SS", "e", "e.T1"))
    got = system._distances2(a, b)
    inside = 0
    for e, f, d in zip(a, b, got):
        t = max(e.t, f.t)
        FQ = [(motion.F(t - g.t), motion.Q(t - g.t)) for g in (e, f)]
        (xa, Pa), (xb, Pb) = ((g.x, g.P) if g.t == t else (F @ g.x, F @ g.P @ F.T + Q)
                              for g, (F, Q) in zip((e, f), FQ))
        d2, rank = track_distance2(xa, Pa, xb, Pb, dims=np.arange(6))
        if d2 <= gate_threshold(rank, 0.999):
            inside += 1
            assert d == pytest.approx(d2, rel=1e-9)
        else:
            assert d == np.inf
    assert 20 < inside < 180


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_the_batched_covariance_intersection_is_fuse_ci(criterion):
    """CI of many pairs at once (ω from the pencil's eigenvalues and Newton steps) equals
    fuse_ci pair by pair, ω inside (0, 1) and at its ends, and equal covariances."""
    rng = np.random.default_rng(7)
    scale = np.array([300.0, 300.0, 300.0, 20.0, 20.0, 20.0, 2.0, 2.0, 2.0])
    P1 = np.array([_spd(rng, 9, scale * rng.uniform(0.3, 3.0)) for _ in range(60)])
    P2 = np.array([_spd(rng, 9, scale * rng.uniform(0.3, 3.0)) for _ in range(60)])
    P2[:5] = P1[:5] * 100.0  # one far more certain: ω = 1
    P2[5] = P1[5]
    x1, x2 = rng.normal(size=(60, 9)) * scale, rng.normal(size=(60, 9)) * scale
    x, P = _ci_pairs(x1, P1, x2, P2, criterion)
    for k in range(60):
        xr, Pr, w = fuse_ci([x1[k], x2[k]], [P1[k], P2[k]], criterion)
        np.testing.assert_allclose(x[k], xr, rtol=1e-9, atol=1e-9 * np.max(np.abs(xr)))
        np.testing.assert_allclose(P[k], Pr, rtol=1e-9, atol=1e-9 * np.max(np.abs(Pr)))
