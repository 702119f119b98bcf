"""fusion.tracking.manager: the frame loop over injected parts, the track table's order
and ids, GNN's priority of confirmed tracks, the spatial-gating seam, and what a
weighted associator hands the updater."""

from __future__ import annotations

import numpy as np

from fusion.ekf import ekf_update_weighted
from fusion.methods import make_method
from fusion.measurement.models import SphericalModel
from fusion.tracking.associators import GNN, Assignment, Weights
from fusion.tracking.hypotheses import Hypotheses, PlotHypothesiser, gating_update, mahalanobis2
from fusion.tracking.manager import MultiTargetTracker
from fusion.tracking.table import CONFIRMED, DELETED, ManagementRule, Track, TrackLogic, TrackTable
from fusion.types import Estimate, Measurement
from services.evaluation import merged_measurements, run_method


# The table ---------------------------------------------------------------------------------
def _track(status: str) -> Track:
    logic = TrackLogic(ManagementRule(2, 3))
    logic.status = status
    return Track(None, Estimate(0.0, np.zeros(2), np.eye(2), "M", "centre"), logic)


def test_ids_are_issued_at_confirmation_in_table_order_and_the_order_is_restored():
    """Births b1..b5; b2 and b4 confirmed in frame 1 (ids T1, T2 in table order); in
    frame 2 b1 is deleted and b5 and b3 are confirmed: T3 goes to b3, which comes first
    in the table (birth order), T4 to b5. The order is then confirmed by id, tentative
    by birth."""
    table = TrackTable(lambda: TrackLogic(ManagementRule(2, 3)))
    tracks = [table.add(_track("tentative")) for _ in range(5)]
    tracks[1].logic.status = tracks[3].logic.status = CONFIRMED
    assert [tr.birth for tr in table.close_frame()] == [2, 4]
    assert [(tr.birth, tr.id) for tr in table.tracks] == [(2, "T1"), (4, "T2"), (1, None), (3, None), (5, None)]
    tracks[0].logic.status = DELETED
    tracks[4].logic.status = tracks[2].logic.status = CONFIRMED
    assert [tr.id for tr in table.close_frame()] == ["T1", "T2", "T3", "T4"]
    assert [(tr.birth, tr.id) for tr in table.tracks] == [(2, "T1"), (4, "T2"), (3, "T3"), (5, "T4")]
    assert table.add(_track("tentative")).birth == 6  # births are never reused either


# GNN's priority -----------------------------------------------------------------------------
def test_a_tentative_track_cannot_take_a_plot_a_confirmed_one_gates():
    """One plot, which fits the tentative row far better (d² 0.1 against 5): assigned
    all at once, the tentative row takes it (0.1 + G against 5 + G); confirmed first,
    the confirmed row does."""
    hyp = Hypotheses([0], range(2), np.array([[5.0], [0.1]]), np.full(2, 9.0), np.array([True, False]))
    assert GNN(confirmed_first=True).associate(hyp).pairs == ((0, 0),)
    assert GNN(confirmed_first=False).associate(hyp).pairs == ((1, 0),)


def test_a_row_misses_at_its_own_gate():
    """Per-row gates (track-to-track costs of different ranks): a pair is taken when
    inside its own row's gate, whatever the other rows' gates."""
    hyp = Hypotheses([0, 1], range(2), np.array([[3.0, np.inf], [np.inf, 3.0]]), np.array([2.0, 4.0]),
                     np.ones(2, dtype=bool))
    assert GNN().associate(hyp).pairs == ((1, 1),)


# The spatial-gating seam -----------------------------------------------------------------------
class _Oracle(PlotHypothesiser):
    """A "spatial index" that leaves out exactly the pairs outside the gate (``drop_best``:
    and, wrongly, each track's best pair inside it)."""

    drop_best = False

    def candidates(self, model, gate, states, Z):
        for r, (x, P) in enumerate(states):
            d2 = mahalanobis2(model, x, P, Z)
            keep = d2 <= gate
            if self.drop_best and keep.any():
                keep[int(np.argmin(d2))] = False
            yield r, np.flatnonzero(keep)


def _run_with(crossing, hypothesiser_class):
    method = make_method("SS", dict(crossing.tracker))
    method.tracker.hypothesiser = hypothesiser_class(method.n_x, method.config.gate_prob)
    return _stream(method, merged_measurements(crossing, 0))


def _stream(method, stream):
    out, t_prev = [], None
    for m in stream:
        if t_prev is not None and m.t > t_prev:
            out += method.advance(t_prev)
        out += method.process(m)
        t_prev = m.t
    return out + method.finish()


def test_a_spatial_index_that_leaves_out_only_pairs_outside_the_gate_changes_nothing(crossing):
    """The crossing scenario, SS: candidates restricted to the pairs in the gate give
    every estimate bit for bit; a seam that also leaves out each track's best pair does
    not (the test can fail)."""
    plain = run_method(crossing, "SS")
    oracle = _run_with(crossing, _Oracle)
    assert len(oracle) == len(plain)
    for a, b in zip(plain, oracle):
        assert (a.t, a.track) == (b.t, b.track)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.P, b.P)

    class Broken(_Oracle):
        drop_best = True

    broken = _run_with(crossing, Broken)
    assert len(broken) != len(plain) or any(not np.array_equal(a.x, b.x) for a, b in zip(plain, broken))


# What a weighted associator hands the updater ------------------------------------------------
class _Spy:
    """A hypothesiser, initiator and updater that record what the tracker hands them."""

    def __init__(self):
        self.taken = {}
        self.left = []

    def predict(self, tracks, frame):
        return None

    def scans(self, frame):
        return [frame.plots[:2], frame.plots[2:]]

    def hypothesise(self, states, tracks, scan):
        n = len(tracks)
        return Hypotheses(scan, range(n), np.ones((n, len(scan))), np.full(n, 9.0), np.ones(n, dtype=bool))

    def condition(self, states, hyp, association):
        pass

    def unclaimed(self, hyp, columns):
        return [hyp.plots[c] for c in columns]

    def initiate(self, left, tracks, frame):
        self.left.append(left)
        return {}, ([left] if not tracks else [])

    def update(self, track, taken, frame):
        self.taken[track.birth] = taken
        return True

    def position_cov(self, track):
        return np.eye(3)

    def start(self, group, frame):
        return Track(None, Estimate(frame.t, np.zeros(3), np.eye(3), "M", "centre"))


class _Weighted:
    """The one track weights the first plot of each scan ¾ (β₀ ¼), which no new track
    may start from; the second plot of each scan is nobody's."""

    def associate(self, hyp):
        n = len(hyp.rows)
        beta = np.zeros(hyp.d2.shape)
        beta[:, 0] = 0.75
        return Weights(beta, np.full(n, 0.25), frozenset({0}) if n else frozenset())


def test_the_updater_gets_each_scan_s_weights_and_miss_weight():
    """Two scans of two plots: the updater gets, per scan, the plots of positive weight
    with their β and β₀; the initiator gets the plots nobody used."""
    spy = _Spy()
    tracker = MultiTargetTracker(spy, _Weighted(), spy, spy, TrackTable(lambda: TrackLogic(ManagementRule(1, 1))))
    plots = [_Plot(0.0, s) for s in ("a", "a", "b", "b")]
    tracker.frame(plots)  # no track yet: every plot left; one track starts from them
    assert [tr.birth for tr in tracker.tracks] == [1]
    spy.left = []
    tracker.frame(plots)
    first, second = spy.taken[1]
    assert (first.plots, first.beta, first.miss) == ((plots[0],), (0.75,), 0.25)
    assert (second.plots, second.beta, second.miss) == ((plots[2],), (0.75,), 0.25)
    assert spy.left == [[plots[1], plots[3]]]


class _Plot:
    def __init__(self, t, sensor):
        self.t, self.sensor = t, sensor

    def __repr__(self):
        return f"_Plot({self.t}, {self.sensor!r})"


def test_sequential_gating_on_weights_is_the_weighted_update():
    """A scan decided by weights conditions the gating state on the PDA mixture of its
    plots (the next sensor is gated against that); an assignment on the one plot taken."""
    model = SphericalModel(("az", "range"), [0.0, 0.0, 0.0], [1e-3, 20.0], 9)
    x = np.r_[0.0, 20e3, 3e3, np.zeros(6)]
    P = np.diag(np.r_[[200.0**2] * 3, [50.0**2] * 3, [1.0] * 3])
    plots = [Measurement(0.0, "r", "range_az", model.h(x) + d, np.array([1e-3, 20.0]), np.zeros(3), k)
             for k, d in enumerate(([2e-3, 30.0], [-1e-3, -40.0], [0.0, 300.0]))]
    hyp = PlotHypothesiser(9, 0.999).hypotheses([(x, P)], plots, [True])
    states = [(x, P)]
    PlotHypothesiser(9, 0.999).condition(states, hyp, Weights(np.array([[0.5, 0.3, 0.0]]), np.array([0.2])))
    want, _ = ekf_update_weighted(model, x, P, np.array([plots[0].z, plots[1].z]), [0.5, 0.3], 0.2)
    np.testing.assert_array_equal(states[0][0], want.x)
    np.testing.assert_array_equal(states[0][1], want.P)
    states = [(x, P)]
    PlotHypothesiser(9, 0.999).condition(states, hyp, Assignment(((0, 1),)))
    np.testing.assert_array_equal(states[0][0], gating_update(model, x, P, plots[1].z)[0])
