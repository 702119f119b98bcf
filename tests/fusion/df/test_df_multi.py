"""Many emitters in a DF network (fusion/df/multi.py): ghost rejection, bearing
association, and the df-multi scenario in-process and through the real processes."""

from __future__ import annotations

import dataclasses
import json
import subprocess

import numpy as np
import pytest

from fusion.tracking.hypotheses import gate_threshold
from fusion.angles import math_to_compass, wrap_pi
from fusion.df.models import bearing, bearing_measurements
from fusion.df.multi import MultiEmitterMethod, bearing_d2, initiate
from fusion.methods import make_method
from fusion.mtt_metrics import score_tracks
from sensors_sim import load_scenario
from services.evaluation import run_method
from services.scoring import track_steps

SIGMA = 0.0175
G = gate_threshold(1, 0.999)
KM = 1000.0

# Two emitters, three stations (m). Closed form: the rays S1→A and S2→B meet at
# (0, 20) km, S1→B and S2→A at (0, 20/3) km — the two ghosts of S1 and S2. S3 lies on
# their line x = 0, so it sees both ghosts due north (β = π/2), while it sees A and B
# at atan2(20, ∓5), 14° either side: the third station rules both ghosts out.
A, B = np.array([-5.0, 10.0]) * KM, np.array([5.0, 10.0]) * KM
S1, S2, S3 = np.array([-10.0, 0.0]) * KM, np.array([10.0, 0.0]) * KM, np.array([0.0, -10.0]) * KM
GHOSTS = np.array([[0.0, 20.0], [0.0, 20.0 / 3.0]]) * KM


def _bearings(stations, emitters):
    """Noise-free bearings: station-major, emitter order within a station."""
    sites = np.array([s for s in stations for _ in emitters])
    betas = np.array([bearing(e, s) for s in stations for e in emitters])
    names = [f"df{k + 1}" for k, s in enumerate(stations) for _ in emitters]
    return sites, betas, names


def test_the_two_ghosts_of_two_stations_lie_where_the_closed_form_puts_them():
    from fusion.df.triangulation import intersect_bearings

    got = [intersect_bearings(S1, bearing(A, S1), S2, bearing(B, S2)),
           intersect_bearings(S1, bearing(B, S1), S2, bearing(A, S2))]
    np.testing.assert_allclose(got, GHOSTS, atol=1e-6)
    # the third station's bearings miss both ghosts by 14°, far outside the gate
    sites, betas, _ = _bearings([S3], [A, B])
    d2 = bearing_d2(GHOSTS, np.zeros((2, 2, 2)), sites, betas, SIGMA)
    np.testing.assert_allclose(np.sqrt(d2) * SIGMA, np.arctan2(5, 20), rtol=1e-9)
    assert d2.min() > 10 * G  # 14σ


def test_a_third_station_removes_the_ghosts():
    sites, betas, names = _bearings([S1, S2, S3], [A, B])  # indices: A = 0, 2, 4; B = 1, 3, 5
    groups = initiate(sites, betas, SIGMA, names, G, need=3)
    assert sorted(groups) == [[0, 2, 4], [1, 3, 5]]
    # A bearing of B missing at S3: A is still found, and B's two bearings left over do
    # not make an emitter (nor a ghost with A's) — two stations cannot tell.
    keep = [0, 1, 2, 3, 4]
    groups = initiate(sites[keep], betas[keep], SIGMA, [names[k] for k in keep], G, need=3)
    assert groups == [[0, 2, 4]]


def test_with_two_stations_every_crossing_is_a_candidate():
    """Why the third station is needed: two stations' four crossings all fit their two
    bearings exactly, and with nothing else the first groups may be ghosts."""
    sites, betas, names = _bearings([S1, S2], [A, B])
    groups = initiate(sites, betas, SIGMA, names, G, need=2)
    assert len(groups) == 2 and all(len(g) == 2 for g in groups)
    assert sorted(i for g in groups for i in g) == [0, 1, 2, 3]  # each bearing used once


def test_a_four_station_ghost_does_not_take_the_bearings_of_two_emitters():
    """df-multi's run 37 in closed form: stations at the corners of a 40 km square, X
    near the df1–df3 diagonal, Y near the df2–df4 one. df1's and df3's bearings of X and
    df2's and df4's of Y all point at one point near the crossing of the diagonals,
    (19.6, 21.7) km: they are 0.5–1σ off X and Y, as noise could make them. That point
    is a 4-station candidate that fits exactly, better than X or Y. Picked first, as a greedy search
    does, it leaves X and Y two stations each: no emitter. The grouping holds both."""
    sites4 = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]]) * KM
    X, Y, ghost = np.array([23.0, 25.0]) * KM, np.array([30.0, 11.0]) * KM, np.array([19.6, 21.7]) * KM
    toward = {("X", 0): ghost, ("X", 2): ghost, ("Y", 1): ghost, ("Y", 3): ghost}
    rows = [(s, e, bearing(toward.get((e, s), X if e == "X" else Y), sites4[s])) for s in range(4) for e in "XY"]
    sites = np.array([sites4[s] for s, _, _ in rows])
    betas = np.array([b for *_, b in rows])
    names = [f"df{s + 1}" for s, _, _ in rows]
    off = [abs(b - bearing(X if e == "X" else Y, sites4[s])) / SIGMA for s, e, b in rows]
    assert 0.4 < min(o for o in off if o > 0) and max(off) < 1.1
    groups = initiate(sites, betas, SIGMA, names, G, need=3)
    assert sorted(sorted(rows[i][1] for i in g) for g in groups) == [["X"] * 4, ["Y"] * 4]


def _stream(epochs: int, outlier_at: int | None = None, shuffle_seed: int = 0):
    """Noise-free bearings of A and B at S1..S3, one epoch a second; within each
    station's scan the emitters come in random order (nothing tells which is which).
    ``outlier_at``: in that epoch S2's bearing on A is 0.3 rad off (a jamming outlier)."""
    rng = np.random.default_rng(shuffle_seed)
    sites = np.array([S1, S2, S3])
    out = []
    for k in range(epochs):
        beta = np.array([[bearing(e, s) for s in sites] for e in (A, B)])  # (emitter, station)
        if outlier_at == k:
            beta[0, 1] += 0.3
        order = [rng.permutation(2) for _ in sites]
        for s in range(3):
            for e in order[s]:
                m = bearing_measurements([k + 1.0], [f"df{s + 1}"], sites[s:s + 1], beta[e:e + 1, s:s + 1], SIGMA)[0]
                out.append(dataclasses.replace(m, seq=len(out)))
    return out


def _run(method, stream):
    out = []
    for m in stream:
        out += method.advance(m.t - 0.5) + method.process(m)
    return out + method.finish()


def test_bearings_go_to_their_emitters_and_outliers_to_none():
    config = {"association": "gnn", "sigma": SIGMA, "q22": 0.0}
    method = make_method("EKF", config)
    assert isinstance(method, MultiEmitterMethod) and method.name == "EKF"
    out = _run(method, _stream(6, outlier_at=4))
    # confirmed after 3 epochs of 3-station support (3 of 4), one fix per emitter and epoch
    assert sorted({e.t for e in out}) == [3.0, 4.0, 5.0, 6.0]
    last = {e.track: e for e in out if e.t == 6.0}
    assert sorted(last) == ["E1", "E2"]
    by_emitter = {("A" if np.linalg.norm(e.x - A) < 1.0 else "B" if np.linalg.norm(e.x - B) < 1.0 else None): e
                  for e in last.values()}
    assert set(by_emitter) == {"A", "B"}  # each track on one emitter, to < 1 m (noise-free)
    # every bearing of the 6 epochs went to its own emitter's filter, except the outlier
    assert by_emitter["B"].extra["n_bearings"] == 18
    assert by_emitter["A"].extra["n_bearings"] == 17
    # the ids stay with their tracks
    for k in ("E1", "E2"):
        xs = [e.x for e in out if e.track == k]
        assert max(np.linalg.norm(x - xs[-1]) for x in xs) < 1.0


def test_association_wraps_df_methods_for_many_emitters_and_3d_methods_for_many_targets():
    # the DF methods keep their names under association; a 3D method still gets the 3D wrapper
    assert make_method("TORRIERI", {"association": "gnn"}).name == "TORRIERI"
    with pytest.raises(ValueError, match="apply to 3D tracks"):
        make_method("EKF", {"association": "gnn", "merge_frames": 5})
    assert type(make_method("SS", {"association": "gnn"})).__name__ == "MultiTargetMethod"


def test_a_station_is_gated_with_an_estimate_that_leaves_it_out():
    """A track pulled 1 km off A by a wrong bearing of S3: the estimate it gates S3 with
    comes from its S1 and S2 bearings alone (one Torrieri step), back within metres of
    A (one linearised step from 1 km off: within 100 m), so S3's true bearing of A is
    in that gate and the wrong one is not; with one
    other station there is no such estimate and the track's own is used."""
    from fusion.tracking.table import ManagementRule, TrackLogic
    from fusion.df.multi import Bearings, _Emitter
    from fusion.types import Estimate

    x_off = A + np.array([1000.0, 0.0])
    tr = _Emitter(None, Estimate(0.0, x_off, np.eye(2) * 100.0**2, "EKF", "centre"), window=3,
                  logic=TrackLogic(ManagementRule()))
    for _ in range(3):  # noise-free bearings of A from S1, S2; S3's is of B
        tr.taken.append(Bearings(np.array([S1, S2, S3]), np.array([bearing(A, S1), bearing(A, S2), bearing(B, S3)]),
                                 np.full(3, SIGMA), ["df1", "df2", "df3"], [], 0.0))
    x, P = tr.without("df3")
    assert np.linalg.norm(x - A) < 100.0 and np.all(np.linalg.eigvalsh(P) > 0)
    d2 = bearing_d2(x, P, np.array([S3, S3]), np.array([bearing(A, S3), bearing(B, S3)]), np.full(2, SIGMA))
    assert d2[0] < 1.0 and d2[1] > G
    tr.taken.clear()
    tr.taken.append(Bearings(np.array([S1, S3]), np.array([bearing(A, S1), bearing(B, S3)]), np.full(2, SIGMA),
                             ["df1", "df3"], [], 0.0))
    x, P = tr.without("df3")
    assert x is tr.last.x and P is tr.last.P


def test_a_swap_ghost_pair_is_exchanged_into_the_two_emitters():
    """Emitters P and Q near the diagonal of four stations at the corners of a 40 km
    square: tracks g and h hold, for 5 epochs, df1's and df3's bearings of P with df2's
    and df4's of Q, and the reverse — two ghosts whose static fits cost 68 (χ², noise-
    free bearings) against 0 for the real pairing. Exchanging df2's and df4's bearings
    between them makes each a real emitter: both tracks end on P and Q, within metres,
    every bearing of each from one emitter."""
    from fusion.tracking.table import CONFIRMED, ManagementRule, TrackLogic
    from fusion.df.multi import _Emitter

    sites = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 40.0], [0.0, 40.0]]) * KM
    P, Q = np.array([14.0, 17.0]) * KM, np.array([26.0, 23.0]) * KM
    method = make_method("EKF", {"association": "gnn", "sigma": SIGMA, "q22": 0.0})

    def ghost(first, second):  # df1, df3 see `first`, df2, df4 `second`
        tr = None
        for k in range(5):
            ms = [dataclasses.replace(bearing_measurements(
                [k + 1.0], [f"df{s + 1}"], sites[s:s + 1], [[bearing(first if s in (0, 2) else second, sites[s])]],
                SIGMA)[0], seq=s) for s in range(4)]
            if tr is None:
                emitter = method._make_emitter()
                tr = _Emitter(emitter, method._localise(emitter, ms, k + 1.0), 5, TrackLogic(ManagementRule(1, 1)))
            else:
                tr.last = method._localise(tr.method, ms, k + 1.0)
            tr.taken.append(method._bearings(ms, k + 1.0))
        assert tr.logic.status == CONFIRMED
        return tr

    g, h = ghost(P, Q), ghost(Q, P)
    method._resolve_swaps([g, h])
    ends = sorted([g, h], key=lambda tr: tr.last.x[0])
    for tr, emitter in zip(ends, (P, Q)):
        assert np.linalg.norm(tr.last.x - emitter) < 10.0, (tr.last.x, emitter)
        for sites_e, betas, *_ in tr.taken:
            np.testing.assert_allclose(betas, [bearing(emitter, s) for s in sites_e], atol=1e-9)
    # a real pair is left alone
    before = [tr.last.x.copy() for tr in (g, h)]
    method._resolve_swaps([g, h])
    assert all(np.array_equal(b, tr.last.x) for b, tr in zip(before, (g, h)))


def test_a_station_of_the_distributed_kf_tr_smooths_each_emitter_apart():
    """KF+TR's station node with many emitters: S1 hears A and B 5σ apart, in a random
    order each scan, ±0.5σ of noise, and a jamming outlier in scan 2. Each emitter's
    bearings go to one bearing track: every smoothed bearing sent up is the one a lone
    smoother gives on that emitter's bearings so far (to 1e-12); the outlier starts a
    track of its own, which is deleted after ``delete_misses`` scans without a bearing."""
    from fusion.df.smoothing import BearingSmoother
    from fusion.mtt import AssociationConfig
    from fusion.df.stations import MultiStationNode

    association, rest = AssociationConfig.split({"association": "gnn", "delete_misses": 3, "sigma": SIGMA})
    node = MultiStationNode("df1", rest, False, association)
    truth = {"A": bearing(A, S1), "B": bearing(A, S1) + 5 * SIGMA}
    rng = np.random.default_rng(1)
    ref = {e: BearingSmoother(0.0, SIGMA) for e in truth}
    want, got = [], []
    for k in range(8):
        noisy = {e: b + (0.5 if k % 2 else -0.5) * SIGMA * (1 if e == "A" else -1) for e, b in truth.items()}
        scan = [(e, noisy[e]) for e in rng.permutation(sorted(noisy))]
        scan += [("outlier", truth["A"] + 0.4)] if k == 2 else []
        ms = [dataclasses.replace(bearing_measurements([k + 1.0], ["df1"], S1[None, :], [[b]], SIGMA)[0], seq=j)
              for j, (_, b) in enumerate(scan)]
        for (e, _), m in zip(scan, ms):
            node.offer(m)
            if e != "outlier":
                want.append((k + 1.0, float(ref[e].update(m).z[0])))
        node.set_watermark(k + 1.5)
        got += [(u.t, float(u.measurement.z[0])) for u in node.step() if u.measurement is not None]
        assert len(node.tracks) == (3 if 2 <= k < 2 + 3 else 2), k  # the outlier's track lives 3 more scans
    got_emitters = sorted(x for x in got if abs(x[1] - math_to_compass(truth["A"] + 0.4)) > 1e-6)
    assert len(got) == len(want) + 1
    np.testing.assert_allclose(got_emitters, sorted(want), rtol=0, atol=1e-12)


# df-multi, in-process ----------------------------------------------------------------
RUNS = [*range(10), 37]


def _score(sc, run):
    """The run scored as an air picture (GOSPA assignment, c = 1 km; horizontal fixes
    against the emitters' horizontal positions)."""
    est = run_method(sc, sc.defaults["method"], run=run)
    steps = track_steps(sc, est, run)
    return steps, score_tracks(steps, 1000.0)


@pytest.mark.parametrize("run", RUNS)
def test_df_multi_localises_every_emitter_and_ghosts_do_not_persist(run):
    """Measured on runs 0–49 (EKF, the scenario's tracker): at the last epoch every
    emitter had a confirmed track within 350 m in 50/50 runs (median run 161 m), and no
    track spent more than 3 consecutive epochs on no emitter. Without the gating of each
    station with an estimate that leaves that station out (module docstring, step 1),
    two tracks could swap one station's bearings for good; without the exchange test
    (step 4) a swap ghost pair (E1 and E5 lie near the df1–df3 diagonal) held for 23
    epochs: 6 of runs 0–29 failed without both (ghosts of 23–47 epochs; runs 2 and 9
    here). Run 37 fails when the groups are picked one at a time, best first (step 2): a
    ghost that fits four stations' bearings of E5 and E2 held for 32 epochs."""
    sc = load_scenario("df-multi")
    steps, score = _score(sc, run)
    last = steps[-1]
    err = [min((np.linalg.norm(x[:2] - p[:2]) for x in last.tracks.values()), default=np.inf)
           for p in last.truths.values()]
    assert max(err) <= 400.0, err
    assert score.longest_ghost[0] <= 10
    assert all(e.startswith("E") for st in steps for e in st.tracks)


@pytest.mark.parametrize("method, run", [("MEKF1", 0), ("MEKF4", 12)])
def test_the_cross_fed_filters_misses_are_their_estimates_not_the_association(monkeypatch, method, run):
    """MEKF#1 and MEKF#4 miss the df-multi criteria (docs/results/df-multi.md) with
    bearings as well associated as the EKF's: over runs 0–49, 98.75 % (MEKF#1) and
    98.77 % (MEKF#4) of the bearings their confirmed tracks took were of the track's
    main emitter, against 98.77 % for the EKF (the rest: jamming outliers). Here, in a
    run each misses: every track holds ≥ 95 % bearings of one emitter, yet a track
    ends more than 1 km off the emitter it holds."""
    from fusion.df.models import bearing_of
    from fusion.df.multi import MultiEmitterMethod
    from sensors_sim import truth_trajectory

    sc = load_scenario("df-multi")
    emitters = {k: truth_trajectory(sc, k, run).position(0.0)[:2] for k in sc.targets}
    taken: dict[str, list[str]] = {}
    update = MultiEmitterMethod._update

    def spy(self, tr, mine, enough):
        update(self, tr, mine, enough)
        for m in mine[4] if tr.id is not None else ():
            site, beta = bearing_of(m)
            off = {k: abs(wrap_pi(beta - bearing(p, site))) for k, p in emitters.items()}
            taken.setdefault(tr.id, []).append(min(off, key=off.get))

    monkeypatch.setattr(MultiEmitterMethod, "_update", spy)
    est = run_method(sc, method, run=run)
    last = {e.track: e.x[:2] for e in est if e.t == max(e.t for e in est)}
    worst = 0.0
    for track, labels in taken.items():
        main = max(set(labels), key=labels.count)
        assert labels.count(main) >= 0.95 * len(labels), (track, labels)
        if track in last:
            worst = max(worst, float(np.linalg.norm(last[track] - emitters[main])))
    assert worst > 1000.0


# Through the processes -------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("method, topology", [("EKF", "centralised"), ("KF+TR", "distributed")])
def test_df_multi_over_zenoh_equals_in_process(tmp_path, deployment, method, topology, request):
    """The fuser's association of raw bearings (EKF, the scenario's default: the shared
    run), and the distributed KF+TR: one tracker process per station tracks its bearings
    (a smoother per bearing track) and sends the smoothed ones up; the fuser associates
    them into emitters."""
    from _runs import run_cmd
    from services.scoring import score_tracks_of
    from services.summary import tracks_summary

    if (method, topology) == ("EKF", "centralised"):
        doc = request.getfixturevalue("df_multi_run")[0]
        assert (doc["topology"], list(doc["methods"])) == (topology, [method])
    else:
        p = subprocess.run(run_cmd(tmp_path, "df-multi", deployment, "--speed", "max", "--topology", topology,
                                   "--method", method), capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr[-3000:]
        doc = json.loads((tmp_path / "out.json").read_text())
    got = doc["methods"][method]
    sc = load_scenario("df-multi")
    ref = tracks_summary([score_tracks_of(sc, run_method(sc, method))])
    assert ref["all_found_runs"] == 1 and ref["tracks"] >= 6
    assert got["series"]["t"] == ref["series"]["t"]
    np.testing.assert_allclose(got["series"]["gospa"], ref["series"]["gospa"], rtol=0, atol=1e-9)
    for key in ("held", "breaks", "purity", "tracks", "false_tracks", "n_updates"):
        assert got[key] == ref[key], key
