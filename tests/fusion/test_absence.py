"""The absences across a process's loss (fusion/absence.py), against hand-computed ones:
an aircraft held throughout is absent one step, one lost before the loss or never held
is not counted, one not back is absent until it leaves or the watch ends."""

from __future__ import annotations

import numpy as np
from fusion.absence import Absence, LossWatch, absences, loss_counts


def test_the_absence_across_a_loss_runs_from_the_last_sighting_before_it_to_the_first_after():
    seen = {"held": [0, 1, 2, 3, 4, 5], "gap": [7, 0, 1, 2], "lost_before": [0, 1], "never": [], "later": [5, 6]}
    got = absences(seen, at=3.5, end=10.0)
    assert got == {"held": Absence(3.0, 4.0, 1.0), "gap": Absence(2.0, 7.0, 5.0),
                   "lost_before": Absence(1.0, None, 9.0)}
    assert set(absences(seen, at=3.5, end=10.0, since=2.0)) == {"held", "gap"}  # seen in [since, at] only
    assert absences({"gone": [1, 2]}, at=2.5, end={"gone": 4.0}) == {"gone": Absence(2.0, None, 2.0)}


def _steps(at: float):
    """Steps 0..10 s: who is present (x < 0: in the area) and held. held: throughout; gap:
    not held from 4 to 6 s; lost_before: not held from 2 to 4 s; just_lost: not held
    from 3 to 7 s; never: never held; outside: beyond the area; leaves: not held after
    3 s, gone after 5 s; not_back: not held after 3 s."""
    for t in range(11):
        truths = {a: np.array([-1.0e4, 0.0, 0.0])
                  for a in ("held", "gap", "lost_before", "just_lost", "never", "not_back")}
        truths["outside"] = np.array([1.0e4, 0.0, 0.0])
        if t <= 5:
            truths["leaves"] = np.array([-2.0e4, 0.0, 0.0])
        held = {"held", "outside"} | ({"gap"} if not 4 <= t <= 6 else set()) \
            | ({"lost_before"} if not 2 <= t <= 4 else set()) | ({"just_lost"} if not 3 <= t <= 7 else set()) \
            | ({"leaves", "not_back"} if t <= 3 else set())
        yield float(t), truths, held & truths.keys()


def test_a_loss_watch_follows_the_aircraft_of_its_area_held_in_the_period_before_the_loss():
    """Lost at 3.5 s, a period of 1.5 s: the aircraft held in the area at a step in
    [2, 3.5] s; lost_before (last held at 1 s) and never are not counted."""
    watch = LossWatch(3.5, lambda p: p[:, 0] < 0.0, since=2.0)
    for t, truths, held in _steps(3.5):
        watch.step(t, truths, held)
    got = watch.absences()
    assert got == {"held": Absence(3.0, 4.0, 1.0), "gap": Absence(3.0, 7.0, 4.0), "just_lost": Absence(2.0, 8.0, 6.0),
                   "leaves": Absence(3.0, None, 2.0), "not_back": Absence(3.0, None, 7.0)}
    assert loss_counts(got, period_s=1.5) == {"aircraft": 5, "longest_absence_s": 7.0, "absent_over_2_periods": 3,
                                             "not_back": 2, "period_s": 1.5}
    everyone = LossWatch(3.5)  # no area, since the run's start: lost_before too, from its last hold
    for t, truths, held in _steps(3.5):
        everyone.step(t, truths, held)
    assert set(everyone.absences()) == {"held", "gap", "lost_before", "just_lost", "leaves", "not_back", "outside"}
    assert everyone.absences()["lost_before"] == Absence(1.0, 5.0, 4.0)


def test_no_step_after_the_loss_no_absence():
    watch = LossWatch(20.0)
    for t, truths, held in _steps(20.0):
        watch.step(t, truths, held)
    assert watch.absences() == {}
    assert loss_counts({}, 1.0) == {"aircraft": 0, "longest_absence_s": None, "absent_over_2_periods": 0,
                                    "not_back": 0, "period_s": 1.0}
