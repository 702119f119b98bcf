"""services.scoring.truth_function: each true state computed once per run and time,
equal to the trajectory's, read-only, and forgotten when another run is asked."""

from __future__ import annotations

import numpy as np
import pytest

from sensors_sim import load_scenario, truth_trajectory
from services import scoring


def test_states_equal_the_trajectory_and_are_shared_read_only(monkeypatch):
    sc = load_scenario("patent-3d")
    truth = scoring.truth_function(sc)
    for run in (0, 1, 0):
        for t in (0.0, 1.0, 17.0, 30.0):
            x = truth(run, "T1", t)
            assert np.array_equal(x, truth_trajectory(sc, "T1", run).state(t))
            assert truth(run, "T1", t) is x  # computed once
            with pytest.raises(ValueError):
                x[0] = 0.0
    monkeypatch.setattr(scoring, "TRUTH_STATES_KEPT", 3)
    truth = scoring.truth_function(sc)
    kept = [truth(0, "T1", float(t)) for t in range(5)]
    assert truth(0, "T1", 4.0) is kept[4] and truth(0, "T1", 0.0) is not kept[0]  # bounded
    assert np.array_equal(truth(0, "T1", 0.0), kept[0])
