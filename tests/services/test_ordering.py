"""Watermark ordering: the released stream is time-ordered, independent of arrival
interleaving, and unaffected by rejected input; dead sources are skipped and rejoin."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from services.ordering import WatermarkMerger


def _streams(n_src: int, n_scans: int, rng: np.random.Generator) -> dict[str, list[tuple[str, float, int]]]:
    """Per source: a list of ('m', t, seq) measurements and ('w', t, _) watermarks, in source order."""
    out = {}
    for i in range(n_src):
        src = f"s{i}"
        period = rng.choice([0.5, 1.0, 2.0])
        ev, seq = [], 0
        for k in range(n_scans):
            t = round(k * period + rng.uniform(0, 0.3), 3)
            if rng.uniform() < 0.8:
                ev.append(("m", t, seq))
                seq += 1
            ev.append(("w", t, -1))
        out[src] = ev
    return out


def _feed(merger: WatermarkMerger, streams, order: list[str]) -> list[tuple]:
    pos = {s: 0 for s in streams}
    released = []
    ev: list[str] = []
    for src in order:
        kind, t, seq = streams[src][pos[src]]
        pos[src] += 1
        final = pos[src] == len(streams[src])
        if kind == "m":
            assert merger.add(src, t, seq, (t, src, seq), 0.0, ev) is None
        else:
            assert merger.watermark(src, t, final, 0.0, ev) is None
        released.extend(merger.release()[0])
    return released


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_release_order_is_independent_of_interleaving(seed):
    rng = np.random.default_rng(seed)
    streams = _streams(3, 12, rng)
    expected = sorted((t, s, q) for s, ev in streams.items() for k, t, q in ev if k == "m")
    for _ in range(3):
        order = [s for s, ev in streams.items() for _ in ev]
        rng.shuffle(order)
        got = _feed(WatermarkMerger(list(streams), timeout=10), streams, order)
        assert got == expected


def test_nothing_released_before_every_live_watermark_passes():
    m = WatermarkMerger(["a", "b"], timeout=10)
    ev: list[str] = []
    m.add("a", 1.0, 0, "a1", 0.0, ev)
    m.watermark("a", 1.0, False, 0.0, ev)
    assert m.release()[0] == []
    m.watermark("b", 0.5, False, 0.0, ev)
    assert m.release() == ([], 0.5)
    m.watermark("b", 1.0, False, 0.0, ev)
    assert m.release() == (["a1"], 1.0)


def test_every_kind_of_bad_input_is_rejected_with_its_cause():
    ev: list[str] = []
    clean = WatermarkMerger(["a", "b"], timeout=10)
    dirty = WatermarkMerger(["a", "b"], timeout=10)
    causes = []
    for t in range(1, 6):
        for mg, noisy in ((clean, False), (dirty, True)):
            for src in ("a", "b"):
                assert mg.add(src, float(t), t, (t, src), 0.0, ev) is None
                if noisy:
                    causes += [mg.add(src, float(t), t, "dup", 0.0, ev).cause,  # same seq again
                               mg.add("mallory", float(t), t, "spoof", 0.0, ev).cause]
                mg.watermark(src, float(t), t == 5, 0.0, ev)
                if noisy and t > 1:
                    causes.append(mg.add(src, float(t - 1), t + 200, "old", 0.0, ev).cause)
    assert clean.release()[0] == dirty.release()[0] != []
    assert {"duplicate", "unknown-source", "out-of-order"} <= set(causes)  # a time out of the session: the intake's


def test_rejected_input_leaves_output_identical():
    ev: list[str] = []

    def run(noisy: bool) -> list:
        mg = WatermarkMerger(["a", "b"], timeout=10)
        out = []
        for t in range(1, 8):
            for src in ("a", "b"):
                mg.add(src, t + 0.1 * (src == "b"), t, (t, src), 0.0, ev)
                if noisy:
                    mg.add(src, t + 0.1, t, "dup", 0.0, ev)
                    mg.add("zed", t, t, "unknown", 0.0, ev)
                mg.watermark(src, t + 0.1 * (src == "b"), t == 7, 0.0, ev)
                if noisy:
                    mg.add(src, t - 0.5, 20_000 + t, "behind", 0.0, ev)
                out.extend(mg.release()[0])
        return out

    assert run(True) == run(False)
    assert len(run(False)) == 14


def test_dead_source_is_skipped_then_rejoins():
    ev: list[str] = []
    m = WatermarkMerger(["a", "b"], timeout=2.0, start_grace=0.0, now=0.0)
    m.add("a", 1.0, 0, "a1", 0.0, ev)
    m.watermark("a", 1.0, False, 0.0, ev)
    m.watermark("b", 0.0, False, 0.0, ev)
    assert m.release()[0] == []
    m.check_timeouts(1.0, ev)
    assert not m.sources["b"].dead
    m.check_timeouts(2.5, ev)
    assert m.sources["b"].dead and any("b declared dead" in e for e in ev)
    assert m.release()[0] == ["a1"]  # no longer waiting for b
    # b comes back: its stale data is late, its fresh data is merged again
    rej = m.add("b", 0.5, 0, "b-stale", 3.0, ev)
    assert rej.cause == "late" and not m.sources["b"].dead and any("rejoined" in e for e in ev)
    m.add("b", 2.0, 1, "b2", 3.0, ev)
    m.add("a", 2.0, 1, "a2", 3.0, ev)
    m.watermark("a", 2.0, True, 3.0, ev)
    assert m.release()[0] == []  # waits for b again
    m.watermark("b", 2.0, True, 3.0, ev)
    assert m.release()[0] == ["a2", "b2"]
    assert m.sources["b"].dead_intervals == [[0.0, 1.0]]
    assert m.done


def test_merged_watermark_is_infinite_when_all_final():
    ev: list[str] = []
    m = WatermarkMerger(["a"], timeout=1)
    m.watermark("a", 3.0, True, 0.0, ev)
    assert math.isinf(m.merged_watermark) and m.release() == ([], 3.0) and m.done


def test_a_forged_huge_seq_does_not_silence_the_real_source():
    """Duplicates are judged among held seqs, not against a high-water mark: a forged
    message with the largest seq (accepted if it is otherwise plausible) must not make the
    real source's later messages look like duplicates."""
    ev: list[str] = []
    m = WatermarkMerger(["a"], timeout=10)
    released = []
    for t in range(10):
        assert m.add("a", float(t), t, ("a", t), 0.0, ev) is None
        if t == 3:
            assert m.add("a", 3.5, 2**63 - 1, "forged", 0.0, ev) is None  # plausible: only authentication stops it
        m.watermark("a", float(t), t == 9, 0.0, ev)
        released.extend(m.release()[0])
    assert [r for r in released if r != "forged"] == [("a", t) for t in range(10)]


def test_a_late_message_does_not_advance_seq_bookkeeping():
    ev: list[str] = []
    m = WatermarkMerger(["a", "b"], timeout=1.0, start_grace=0.0)
    m.watermark("a", 5.0, False, 0.0, ev)
    m.watermark("b", 0.0, False, 0.0, ev)
    m.check_timeouts(2.0, ev)  # b is skipped; the stream moves on to a's watermark
    assert m.release() == ([], 5.0)
    assert m.add("b", 1.0, 10**9, "b-late", 2.0, ev).cause == "late"
    assert m.add("b", 6.0, 3, "b6", 2.0, ev) is None


def test_a_source_back_before_anything_was_released_was_dead_over_nothing():
    """Declared dead and heard again before the merger released anything (a restarted
    fuser's first seconds): its outage is [0, 0], not open ("dead until the end"), which
    the run summary's sources showed for a tracker that had come back at once."""
    ev: list[str] = []
    m = WatermarkMerger(["a", "b"], timeout=2.0, start_grace=0.0, now=0.0)
    m.check_timeouts(2.5, ev)
    assert m.sources["a"].dead and m.sources["b"].dead
    m.watermark("a", 1.0, False, 3.0, ev)
    assert m.sources["a"].dead_intervals == [[0.0, 0.0]] and m.sources["b"].dead_intervals == [[0.0, None]]
