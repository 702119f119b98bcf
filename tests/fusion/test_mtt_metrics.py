"""The streaming many-target score (fusion.mtt_metrics.TrackScorer) against the batch
(score_tracks, every step kept) and closed forms: the same totals, a binned series, and
memory bounded by the live targets and tracks however long the stream."""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pytest

from fusion.mtt_metrics import Step, TrackScorer, score_tracks

C = 100.0  # GOSPA cut-off of these streams (m)


def traffic(n_steps: int, life: int = 40, every: int = 5, seed: int = 0):
    """Steps of endless traffic: a target born every ``every`` steps lives ``life`` steps,
    followed by its own track (an id never reused) that is born two steps late, drops it
    for 3 steps mid-life (a break; the target is then held by a second track), and a
    clutter track now and then lives 4 steps on nothing."""
    rng = np.random.default_rng(seed)
    for k in range(n_steps):
        truths, tracks = {}, {}
        for b in range(max(0, (k - life) // every + 1), k // every + 1):
            age = k - b * every
            if not 0 <= age < life:
                continue
            x = np.array([50.0 * age, 1000.0 * b, 0.0])
            truths[f"A{b}"] = x
            if 2 <= age < 20:
                tracks[f"T{b}"] = x + rng.normal(0.0, 5.0, 3)
            elif age >= 23:
                tracks[f"U{b}"] = x + rng.normal(0.0, 5.0, 3)
        if k % 7 < 4:
            tracks[f"G{k // 7}"] = np.array([-5000.0, 0.0, 0.0])
        yield Step(float(k), truths, tracks)


def test_streaming_is_the_batch_with_forgetting_and_binning():
    """Forgetting what is 3 steps gone and binning to 8 points: every total is the batch's,
    the least hold fraction too, the mean GOSPA to rounding; each point is the mean of
    its ``bin`` steps of the batch's series (the last one of what is left)."""
    steps = list(traffic(300))
    ref = score_tracks(steps, C)
    s = TrackScorer(C, forget_after=3, series_max=8)
    for step in steps:
        s.add(step)
    got = s.score()
    for k in ("truth_steps", "held_steps", "breaks", "break_chances", "track_steps", "dominant_steps",
              "false_tracks", "false_track_steps", "n_tracks", "steps", "missed_steps", "assigned_sq"):
        assert getattr(got, k) == getattr(ref, k), k
    assert ref.breaks > 0 and ref.false_tracks > 0 and ref.n_tracks > 100  # the stream exercises them
    assert got.worst_hold == ref.worst_hold < 1.0 and got.found_at_end == ref.found_at_end
    assert got.longest_ghost == ref.longest_ghost == [4]
    assert got.mean_gospa == pytest.approx(ref.mean_gospa, rel=1e-12)
    assert got.bin == 64 and len(got.t) == 5  # 300 steps: 4 points of 64, one of 44
    k = got.bin
    assert got.t == [ref.t[min(i + k, 300) - 1] for i in range(0, 300, k)]
    np.testing.assert_allclose(got.gospa, [np.mean(ref.gospa[i:i + k]) for i in range(0, 300, k)], rtol=1e-12)
    assert got.n_missed == [sum(ref.n_missed[i:i + k]) for i in range(0, 300, k)]
    assert not got.assignments
    # what is held: the targets and tracks of the last 3 steps
    assert len(s.on_counts) <= 3 * 12 and len(s.found) <= 3 * 9 and len(s.binned) <= 8


def test_batch_is_the_fold_without_forgetting():
    """No ``forget_after``, no ``series_max``: the scorer is the batch, series and
    assignments included; scoring goes on after :meth:`score`."""
    steps = list(traffic(60))
    s = TrackScorer(C)
    for step in steps[:30]:
        s.add(step)
    assert s.score() == score_tracks(steps[:30], C)
    for step in steps[30:]:
        s.add(step)
    assert s.score() == score_tracks(steps, C)
    assert len(s.score().assignments) == 60


def _growth(forget_after: int | None, at: tuple[int, int]) -> int:
    """Traced heap a scorer gains from step ``at[0]`` to step ``at[1]`` of traffic (made
    lazily; 4 targets at once)."""
    tracemalloc.start()
    try:
        s = TrackScorer(C, forget_after=forget_after, series_max=64)
        for k, step in enumerate(traffic(at[1], every=10), 1):
            s.add(step)
            if k == at[0]:
                base = tracemalloc.get_traced_memory()[0]
        return tracemalloc.get_traced_memory()[0] - base
    finally:
        tracemalloc.stop()


def test_memory_is_bounded_by_the_live_targets_and_tracks():
    """From step 400 to step 2,000 the scorer's heap stays the same (the live targets'
    and tracks' state and 64 points), where keeping the gone ones' state grows with the
    stream (about 0.14 kB a step)."""
    assert _growth(10, (400, 2_000)) < 8_000
    assert _growth(None, (400, 1_000)) > 40_000


def test_held_after_init_breaks_and_false_tracks_of_a_hand_built_run():
    """Two targets over six steps, counted by hand: A held by T1 from step 1, dropped at
    step 4, taken up by T2 at step 5 (one break in A's 3 chances: a target not held
    cannot break); B held by T3 from step 3 (2 chances, no break); a ghost G on nothing
    for 3 steps (the one false track). A settles at step 2, B at step 3: of their 7
    settled truth-steps 6 are held (12 truth-steps, 7 held in all)."""
    A, B, G = np.zeros(3), np.array([1000.0, 0.0, 0.0]), np.array([-5000.0, 0.0, 0.0])
    near = np.array([3.0, 4.0, 0.0])  # 5 m off
    plan = [  # (tracks, settled)
        ({"G": G}, set()),
        ({"T1": A + near, "G": G}, set()),
        ({"T1": A + near, "G": G}, {"A"}),
        ({"T1": A - near, "T3": B + near}, {"A", "B"}),
        ({"T3": B + near}, {"A", "B"}),
        ({"T2": A + near, "T3": B - near}, {"A", "B"}),
    ]
    steps = [Step(float(k), {"A": A, "B": B}, tracks, frozenset(s)) for k, (tracks, s) in enumerate(plan)]
    score = score_tracks(steps, C)
    assert (score.truth_steps, score.held_steps) == (12, 7) and score.held == 7 / 12
    assert (score.settled_steps, score.settled_held) == (7, 6) and score.held_after_init == 6 / 7
    assert (score.breaks, score.break_chances) == (1, 5) and score.break_rate == 0.2
    assert (score.false_tracks, score.n_tracks) == (1, 4)
    merged = type(score).merged([score, score])
    assert merged.held_after_init == 6 / 7 and merged.break_rate == 0.2 and merged.false_tracks == 2
    unsaid = score_tracks([dataclasses.replace(s, settled=None) for s in steps], C)
    assert np.isnan(unsaid.held_after_init) and unsaid.held == 7 / 12


def test_rmse_pos_assigned_is_over_the_gospa_pairs_of_a_hand_built_run():
    """Step 0: A at 0, B at 10 m, tracks X at 4 m and Y at −5 m on one line. The nearest
    pair first would put X on A (4 m) and Y on B (15 m); GOSPA's assignment (least Σd²)
    puts Y on A (5 m) and X on B (6 m): 25 + 36. Step 1: X 12 m from A, and a track
    150 m from B, beyond the cut-off: not a pair. RMSE √((25 + 36 + 144)/3)."""
    A, B = np.zeros(3), np.array([10.0, 0.0, 0.0])
    steps = [Step(0.0, {"A": A, "B": B}, {"X": np.array([4.0, 0, 0]), "Y": np.array([-5.0, 0, 0])}),
             Step(1.0, {"A": A, "B": B}, {"X": np.array([0, 12.0, 0]), "Z": B + [0, 150.0, 0]})]
    score = score_tracks(steps, C)
    assert score.held_steps == 3 and score.assignments[0] == {"A": "Y", "B": "X"}
    assert score.rmse_pos_assigned == pytest.approx(np.sqrt((25 + 36 + 144) / 3), rel=1e-12)
    assert score.summary()["rmse_pos_assigned"] == score.rmse_pos_assigned
    assert type(score).merged([score, score_tracks(steps[:1], C)]).rmse_pos_assigned == pytest.approx(
        np.sqrt((2 * 61 + 144) / 5), rel=1e-12)
    assert np.isnan(score_tracks(steps[1:], C / 20).rmse_pos_assigned)  # nothing assigned


@pytest.mark.parametrize("seed", range(6))
def test_a_large_step_is_matched_sparsely_as_densely(seed, monkeypatch):
    """Random crowded steps (targets 300 m apart, tracks 0-3 km off, missed targets and
    clutter tracks): the sparse matching of a large step gives the dense assignment, the
    same GOSPA (and its counts) and OSPA, to rounding."""
    from fusion import mtt_metrics

    rng = np.random.default_rng(seed)
    n = int(rng.integers(120, 180))
    X = rng.uniform(-3000.0, 3000.0, (n, 3))
    Y = np.vstack([X[: n - 15] + rng.normal(0.0, rng.uniform(50.0, 1000.0), (n - 15, 3)),
                   rng.uniform(-3000.0, 3000.0, (int(rng.integers(0, 40)), 3))])
    truths = {f"A{i}": X[i] for i in range(n)}
    tracks = {f"T{i}": Y[i] for i in rng.permutation(len(Y))}
    dense = mtt_metrics.match(truths, tracks, 1000.0)
    assert len(truths) * len(tracks) <= mtt_metrics.DENSE_MAX
    monkeypatch.setattr(mtt_metrics, "DENSE_MAX", 0)
    sparse = mtt_metrics.match(truths, tracks, 1000.0)
    assert sparse[0] == dense[0] and len(dense[0]) > n // 3
    assert sparse[1].distance == pytest.approx(dense[1].distance, rel=1e-12)
    assert sparse[1][4:] == dense[1][4:]
    assert sparse[2] == pytest.approx(dense[2], rel=1e-12)
