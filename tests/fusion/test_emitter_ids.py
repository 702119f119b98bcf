"""An emitter fix is called E1 whichever way it is made: one emitter (a site's, a
scenario's, every DF method) or the first of many (the many-emitter tracker)."""

from __future__ import annotations

import pytest

from sensors_sim import load_scenario
from services.evaluation import run_method


@pytest.mark.parametrize("method", ["EKF", "MEKF1", "IMM", "TORRIERI", "KF+TR"])
def test_one_emitters_fixes_are_e1(method):
    estimates = run_method(load_scenario("thesis-fixed-c1"), method)
    assert estimates and {e.track for e in estimates} == {"E1"}


def test_many_emitters_fixes_are_e1_e2_and_so_on():
    estimates = run_method(load_scenario("df-multi"), "EKF")
    ids = {e.track for e in estimates}
    assert "E1" in ids and all(i[0] == "E" and i[1:].isdigit() for i in ids), ids
