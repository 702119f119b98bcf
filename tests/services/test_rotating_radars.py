"""Rotating radars through the real processes: the sensor process publishes each sector
of the in-process stream followed by its watermark, and a distributed run of
``tests/data/rotating.toml`` equals its in-process evaluation."""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest

from schemas import decode, to_measurement
from sensors_sim import load_scenario
from sensors_sim.emulators import sensor_batches

from _runs import in_process, run_cmd, same_series, sensor_stream
from conftest import DATA

pytestmark = pytest.mark.slow
ROTATING = DATA / "rotating.toml"


@pytest.mark.parametrize("sensor", ["radar3d", "angle"])
def test_the_sensor_process_publishes_the_sectors_each_with_its_watermark(deployment, sensor):
    """Message by message: each batch's measurements (equal to the in-process ones), then
    a watermark just before the next batch's start; the last one final, at the end. A
    rotating radar's batches are its sectors; the staring sensor's, its scans."""
    scenario = load_scenario(ROTATING)
    got = [decode(x) for x in sensor_stream(deployment, str(ROTATING), sensor)]
    want = []
    batches = list(sensor_batches(scenario, sensor))
    for b, after in zip(batches, [*batches[1:], None]):
        want += [("m", ev.measurement) for ev in b.events if ev.measurement is not None]
        want.append(("w", math.nextafter(after.t0, -math.inf) if after else scenario.duration))
    assert len(got) == len(want)
    for msg, (what, value) in zip(got, want):
        if what == "m":
            assert to_measurement(msg) == value
        else:
            assert msg.kind == "watermark" and msg.t == value
    assert got[-1].body["final"] is True
    if scenario.sensor(sensor).sectors:
        assert sum(w == "w" for w, _ in want) == len(batches) == math.ceil(38.5 / 6.0 * 32)  # 38.5 s of 6-s turns in 32 sectors


def test_distributed_run_equals_in_process(tmp_path, deployment):
    """The fuser's SS over the rotating radars' sectors and the staring sensor's scans,
    over Zenoh, estimate for estimate the in-process evaluation (1e-9)."""
    p = subprocess.run(run_cmd(tmp_path, str(ROTATING), deployment, "--speed", "max"), capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    got = json.loads((tmp_path / "out.json").read_text())["methods"]["SS"]
    ref = in_process(str(ROTATING), "SS")
    same_series(got, ref)
    assert got["n_updates"] > 40 and len(set(np.diff(got["series"]["t"]).round(9))) > 10  # plots at their own times
