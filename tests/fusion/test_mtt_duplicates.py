"""``duplicates`` and ``id_changes`` of the many-target score (fusion.mtt_metrics),
counted by hand on a built run, and the same through the streaming scorer."""

from __future__ import annotations

import numpy as np

from fusion.mtt_metrics import Step, TrackScorer, score_tracks

C = 100.0


def test_duplicates_and_id_changes_of_a_hand_built_run():
    """A held by T1 (steps 0-2), by nobody (3), by T2 (4-5): one id change, though two
    breaks' worth of steps (held -> none -> another); at step 1 D sits 20 m from A
    (one duplicate), at step 2 D and E both do (still one aircraft with a second track),
    at step 5 F is 150 m off (beyond the cut-off: no duplicate). B is held by T3 throughout,
    and at step 4 by T4 instead (a second id change) while T3 sits on B too (a duplicate)."""
    A, B = np.zeros(3), np.array([1000.0, 0.0, 0.0])
    off = np.array([3.0, 4.0, 0.0])
    plan = [
        {"T1": A + off, "T3": B},
        {"T1": A + off, "D": A + [20.0, 0, 0], "T3": B},
        {"T1": A + off, "D": A + [20.0, 0, 0], "E": A - [0, 25.0, 0], "T3": B},
        {"T3": B},
        {"T2": A, "T4": B + off, "T3": B + [0, 30.0, 0]},
        {"T2": A, "F": A + [150.0, 0, 0], "T4": B},
    ]
    steps = [Step(float(k), {"A": A, "B": B}, tracks) for k, tracks in enumerate(plan)]
    score = score_tracks(steps, C)
    assert score.duplicates == 1 + 1 + 1
    assert score.id_changes == 2
    assert score.summary()["duplicates"] == 3 and score.summary()["id_changes"] == 2
    streamed = TrackScorer(C, forget_after=2, series_max=4)
    for s in steps:
        streamed.add(s)
    assert (streamed.score().duplicates, streamed.score().id_changes) == (3, 2)
    merged = type(score).merged([score, score])
    assert (merged.duplicates, merged.id_changes) == (6, 4)
