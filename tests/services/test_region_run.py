"""``region-400`` as processes: ``zfusion run --speed max`` (30 sensor processes, the
fuser with the sweep tracker, the recorder) gives the summary of its in-process
evaluation (``zfusion eval``), key by key, the GOSPA series step by step to 1e-9.

30 s of scenario: two and a half turns of the slowest radars (12 s), six of the
approach radars, ten of the angle sensors; about 6,000 fused updates on nearly 400
tracks, with tracks started, confirmed and tentative ones deleted. The run's cost is
mostly its 32 processes' start and the recorder, so a longer run would add coverage
of confirmed tracks' deletion (3 missed looks of 12 s) at the price of the suite's time.

Thirty source processes started together take long to come up on a loaded host (at load
24 one was first heard more than the fuser's start grace and source timeout, 45 s, after
the fuser started, and was declared dead: the run then differed). A never-heard source's
grace now runs from the first source heard (:class:`services.ordering.WatermarkMerger`).
"""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest

from services.evaluation import evaluate, variants_for
from services.ordering import WatermarkMerger
from services.scenario import load

from _runs import run_cmd

DURATION_S = 30.0
EVAL_ONLY = {"crossings"}  # the regions' hand-overs: an in-process figure of a regional scenario


def same_summary(got: dict, ref: dict, path: str = "") -> None:
    """Every key of ``ref`` in ``got`` with the same value (numbers to 1e-9)."""
    if isinstance(ref, dict):
        assert isinstance(got, dict), path
        for key, value in ref.items():
            if key not in EVAL_ONLY:
                assert key in got, f"{path}/{key} missing"
                same_summary(got[key], value, f"{path}/{key}")
    elif isinstance(ref, list):
        assert isinstance(got, list) and len(got) == len(ref), (path, len(got), len(ref))
        for i, (a, b) in enumerate(zip(got, ref)):
            same_summary(a, b, f"{path}[{i}]")
    elif isinstance(ref, float) and isinstance(got, (int, float)):
        assert (math.isnan(ref) and math.isnan(got)) or abs(got - ref) <= 1e-9, (path, got, ref)
    else:
        assert got == ref, (path, got, ref)


@pytest.mark.slow
def test_region_400_run_equals_its_in_process_evaluation(tmp_path, deployment):
    sc = load("region-400", None, DURATION_S)  # as `zfusion eval --duration-s` loads it
    ref = evaluate(sc, variants_for(["SS"]), 1, crb=False)["methods"]["SS"]
    out = subprocess.run(run_cmd(tmp_path, "region-400", deployment, "--speed", "max", "--duration-s",
                                 f"{DURATION_S:g}"), capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    assert set(doc["exit_codes"]) >= {"fuser", "recorder", *sc.sensors}
    got = doc["methods"]["SS"]
    assert got["n_updates"] > 3000 and got["tracks"] > 300 and len(got["series"]["t"]) == 31  # a real picture
    assert got["series"]["t"] == ref["series"]["t"]
    np.testing.assert_allclose(got["series"]["gospa"], ref["series"]["gospa"], rtol=0, atol=1e-9)
    same_summary(got, ref)


def test_a_never_heard_source_gets_its_grace_from_the_first_source_heard():
    """Start grace 30 s, timeout 15 s; the fuser up at 0, the first source heard at 40
    (the consumers and the sources took that long to start): a source not yet heard is
    dead 40 + 30 + 15 s in, not 45 s; with no source heard at all, 45 s as before."""
    ev: list[str] = []
    m = WatermarkMerger(["a", "b"], timeout=15.0, start_grace=30.0, now=0.0)
    m.check_timeouts(46.0, ev)
    assert m.sources["a"].dead and m.sources["b"].dead  # nothing heard: the grace from the start
    ev = []
    m = WatermarkMerger(["a", "b"], timeout=15.0, start_grace=30.0, now=0.0)
    m.watermark("a", 1.0, False, 40.0, ev)
    m.check_timeouts(84.0, ev)
    assert not m.sources["b"].dead
    assert ev == ["source a declared dead (silent for more than 15 s)"]  # a itself: silent since 40
    m.check_timeouts(85.5, ev)
    assert m.sources["b"].dead and ev[1:] == ["source b declared dead (silent for more than 15 s)"]
