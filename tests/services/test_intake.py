"""The ordered intake every consumer calls (services/intake.py): key, decode, route
(kind and sender), time, repeats; each refusal counted by its cause, in that order."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from fusion.types import Estimate, Measurement
from schemas import KeySpace, encode, encode_estimate, encode_measurement
from services.fuser import FuserCore
from services.intake import HORIZON_SLACK_S, ROUTES, STREAMS_MAX, Intake
from services.live import ClockGuard
from services.node import RejectLog

KEYS = KeySpace("intake")


def meas(sensor: str = "radar2d", t: float = 1.0, seq: int = 0, src: str | None = None) -> bytes:
    m = Measurement(t, sensor, "range_az", np.array([0.5, 1e4]), np.array([0.01, 20.0]), np.zeros(3), seq)
    return encode_measurement(m, src or sensor)


def est(t: float = 1.0, seq: int = 1, src: str = "fuser") -> bytes:
    return encode_estimate(Estimate(t, np.zeros(9), np.eye(9), "SS", "centre", "T1"), src, seq)


def intake(*families: str, **kw) -> tuple[Intake, RejectLog]:
    reject = RejectLog("test")
    return Intake(KEYS, reject, families or ROUTES, **kw), reject


def test_what_passes_comes_with_its_family_and_id():
    it, reject = intake("meas")
    s = it.offer(KEYS.meas("radar2d"), meas())
    assert (s.family, s.ident, s.msg.kind, s.msg.src) == ("meas", "radar2d", "range_az", "radar2d")
    assert reject.total == 0


@pytest.mark.parametrize("key,data,cause", [
    ("zf/other/meas/radar2d", meas(), "key"),  # another deployment
    (KEYS.fused("fuser"), est(), "key"),  # a family this consumer does not take
    (KEYS.meas("radar2d"), b"\xc1", "malformed"),
    (KEYS.meas("radar2d"), est(), "kind"),  # an estimate never travels on meas/
    (KEYS.meas("radar2d"), meas(src="angle"), "spoofed-src"),  # sent by another process
    (KEYS.meas("radar2d"), meas(sensor="angle", src="radar2d"), "spoofed-src"),  # of another sensor
    (KEYS.meas("radar2d"), meas(t=31.0 + HORIZON_SLACK_S), "future"),
    (KEYS.meas("radar2d"), meas(t=-1.0), "past"),
])
def test_each_refusal_is_counted_by_its_cause(key, data, cause):
    it, reject = intake("meas", horizon=30.0 + HORIZON_SLACK_S, earliest=0.0)
    assert it.offer(key, data) is None
    assert dict(reject.by_cause) == {cause: 1}


def test_the_checks_run_in_their_order():
    """A message wrong in several ways is refused for the first: kind, then sender, then time."""
    it, reject = intake("meas", horizon=10.0, earliest=0.0, dedup=True)
    assert it.offer(KEYS.meas("radar2d"), est(t=99.0, src="angle")) is None  # kind, sender and time wrong
    assert it.offer(KEYS.meas("radar2d"), meas(t=99.0, src="angle")) is None  # sender and time wrong
    assert it.offer(KEYS.meas("radar2d"), meas(t=99.0)) is None
    assert dict(reject.by_cause) == {"kind": 1, "spoofed-src": 1, "future": 1}


def test_statuses_are_not_judged_by_time_and_a_watermark_may_be_just_below_zero():
    it, reject = intake("status", "local", horizon=10.0, earliest=0.0)
    status = encode("status", "fuser", 1, 1e9, state="running", role="fuser", counters={}, events=[], sources={})
    assert it.offer(KEYS.status("fuser"), status) is not None
    assert it.offer(KEYS.local("trk-a"), encode("watermark", "trk-a", 1, -5e-324, final=False)) is not None
    assert reject.total == 0


def test_a_truth_names_its_target_and_feedback_comes_from_its_fuser():
    it, reject = intake("truth", "feedback", senders={"feedback": "fuser"})
    truth = encode("truth", "truth", 1, 1.0, target="T2", x=[0.0] * 9)
    assert it.offer(KEYS.truth("T1"), truth) is None and it.offer(KEYS.truth("T2"), truth) is not None
    mark = encode("watermark", "mallory", 1, 1.0, final=False)
    assert it.offer(KEYS.feedback("trk-a"), mark) is None
    assert it.offer(KEYS.feedback("trk-a"), encode("watermark", "fuser", 1, 1.0, final=False)) is not None
    assert reject.by_cause["spoofed-src"] == 2


def test_a_repeat_is_dropped_but_a_restarted_sender_is_heard_again():
    """The same bytes with the same seq are a repeat; a restarted process numbers from 1
    again, and its seq 1 with other bytes is a new message."""
    it, reject = intake("fused", dedup=True)
    assert it.offer(KEYS.fused("fuser"), est(t=1.0, seq=1)) is not None
    assert it.offer(KEYS.fused("fuser"), est(t=1.0, seq=1)) is None
    assert it.offer(KEYS.fused("fuser"), est(t=5.0, seq=1)) is not None
    assert dict(reject.by_cause) == {"duplicate": 1}
    plain, _ = intake("fused")
    assert plain.offer(KEYS.fused("fuser"), est(t=1.0, seq=1)) is not None and plain.offer(KEYS.fused("fuser"), est()) is not None


def test_repeats_are_remembered_for_a_bounded_number_of_streams():
    it, _ = intake("meas", dedup=True)
    for i in range(STREAMS_MAX + 10):
        it.offer(KEYS.meas(f"s{i}"), meas(sensor=f"s{i}"))
    assert len(it._seen) == STREAMS_MAX
    it.forget("meas", f"s{STREAMS_MAX + 9}")
    assert len(it._seen) == STREAMS_MAX - 1


def test_live_a_stamp_ahead_of_the_clock_is_future():
    it, reject = intake("meas", clock=ClockGuard(max_skew=5.0))
    assert it.offer(KEYS.meas("radar2d"), meas(t=1000.0), utc=990.0) is None
    assert it.offer(KEYS.meas("radar2d"), meas(t=1000.0, seq=1), utc=996.0) is not None
    assert dict(reject.by_cause) == {"future": 1} and it.events  # and the source's clock is said to be ahead


def test_of_scenario_bounds_a_run_and_not_a_live_session():
    run = Intake.of_scenario(KEYS, RejectLog("x"), ["meas"], 30.0)
    assert (run.horizon, run.earliest) == (30.0 + HORIZON_SLACK_S, 0.0)
    live = Intake.of_scenario(KEYS, RejectLog("x"), ["meas"], None)
    assert (live.horizon, live.earliest) == (math.inf, -math.inf)


class _Method:
    def __init__(self):
        self.seen = []

    def process(self, m):
        self.seen.append(m.t)
        return []

    def advance(self, t):
        return []

    def finish(self):
        return []


def test_the_fuser_takes_its_input_through_the_intake():
    """A watermark beyond the end would make the source's real data look stale; a
    measurement before time 0 would be fused before anything real: the fuser's intake
    refuses both, and what follows is fused as if they never came."""
    method = _Method()
    reject = RejectLog("fuser")
    core = FuserCore(method, ["radar2d"], KEYS, reject, timeout=10.0, horizon=11.0)
    core.offer(KEYS.meas("radar2d"), meas(t=-1e300, seq=0), 0.0)
    core.offer(KEYS.meas("radar2d"), encode("watermark", "radar2d", 1, 1e300, final=False), 0.0)
    core.offer(KEYS.meas("radar2d"), meas(t=1.0, seq=1), 0.0)
    core.offer(KEYS.meas("radar2d"), encode("watermark", "radar2d", 2, 10.0, final=True), 0.0)
    core.step(0.0)
    assert method.seen == [1.0]
    assert dict(reject.by_cause) == {"past": 1, "future": 1}
    garbage = msgpack.packb({"v": 1})
    assert core.offer(KEYS.meas("radar2d"), garbage, 0.0) is None and reject.total == 3


def test_a_fusers_tracks_come_only_from_that_fuser():
    """``fused/<fuser>`` names its sender: another fuser's tracks on it are forged."""
    it, reject = intake("fused")
    assert it.offer(KEYS.fused("north"), est(src="north")) is not None
    assert it.offer(KEYS.fused("north"), est(src="south", seq=2)) is None
    assert dict(reject.by_cause) == {"spoofed-src": 1}


def test_a_consumer_of_one_fuser_passes_over_another_fusers_tracks_uncounted():
    """Fusers publish side by side: what a consumer does not follow is no error."""
    it, reject = intake("fused", only={"fused": "north"})
    assert it.offer(KEYS.fused("south"), est(src="south")) is None
    assert it.offer(KEYS.fused("north"), est(src="north")) is not None
    assert (it.passed, reject.total) == (1, 0)
