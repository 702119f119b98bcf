"""Many targets through the real processes of the distributed, feedback and two-stage
topologies: one ``zfusion tracker`` per sensor (frames, local tracks ``L<n>``,
initialisation requests) and the fuser's many-target centre (track-to-track
association, inits, drops, the horizon), over Zenoh."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from services.evaluation import run_method
from services.scoring import score_tracks_of
from services.summary import tracks_summary

from conftest import CROSSING
from _runs import run_cmd


@pytest.mark.slow
@pytest.mark.parametrize("method, topology", [("HNV", "distributed"), ("PHHNV", "feedback"), ("DDHNV", "two-stage")])
def test_many_targets_through_the_processes_equal_in_process(crossing, tmp_path, deployment, method, topology):
    """Three crossing aircraft in clutter: the fused air picture of the tracker and fuser
    processes is the in-process network's, step by step — ids included (breaks and
    purity depend on them), so the local ids, inits and drops crossed the wire intact
    and every frame was processed after the centre's answers, as in-process."""
    path = CROSSING
    p = subprocess.run(run_cmd(tmp_path, str(path), deployment, "--topology", topology, "--speed", "max"),
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "running alone" not in p.stderr, p.stderr[-3000:]  # a node that ran alone would be timing-dependent
    doc = json.loads((tmp_path / "out.json").read_text())
    assert doc["topology"] == topology
    got = doc["methods"][method]
    ref = tracks_summary([score_tracks_of(crossing, run_method(crossing, method))])
    assert got["series"]["t"] == ref["series"]["t"]
    np.testing.assert_allclose(got["series"]["gospa"], ref["series"]["gospa"], rtol=0, atol=1e-9)
    for key in ("held", "breaks", "purity", "tracks", "false_tracks", "n_updates"):
        assert got[key] == ref[key], key
    assert got["tracks"] >= 3 and got["held"] > 0.8  # a real air picture, not two empty ones
