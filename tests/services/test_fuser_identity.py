"""Fuser identity: each fuser publishes on ``fused/<fuser>`` and answers on
``picture/<fuser>``, so fusers run side by side on one deployment and each consumer
takes the one it names (``--fuser``). Two fusers of one scenario, with different
methods, each give exactly their in-process result; ``zfusion picture --fuser '*'``
prints every fuser's picture."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import zenoh

from fusion.types import Estimate
from schemas import KeySpace, encode, encode_estimate
from services.launcher import free_port
from services.node import ZenohOptions
from sensors_sim import load_scenario

from _multihost import Watcher, behind_a_router
from _runs import in_process, same_series

FUSERS = {"north": "SS", "south": "LCDD"}


@pytest.mark.slow
def test_two_fusers_side_by_side_each_equal_in_process(deployment):
    scenario = load_scenario("patent-3d")
    keys = KeySpace(deployment)
    with behind_a_router(deployment, scenario.name) as (children, watcher, common):
        for fuser, method in FUSERS.items():
            children.start(fuser, ["fuser", *common, "--method", method, "--id", fuser])
        for s in scenario.sensors:
            children.start(s, ["sensor", *common, "--id", s, "--speed", "max",
                               "--wait-for", ",".join([*FUSERS, Watcher.NAME])])
        watcher.announce()
        for name in [*FUSERS, *scenario.sensors]:
            assert children.wait(name, 90.0) == 0, name
        refs = {f: in_process("patent-3d", m) for f, m in FUSERS.items()}
        for fuser in FUSERS:
            watcher.wait_fused(refs[fuser]["n_updates"], fuser=fuser)
        got = {f: watcher.summary(scenario, fuser=f) for f in FUSERS}
        senders = {(k, m.src) for k, data in watcher.samples if "/fused" in k for m in [watcher.decode(data)]}
    assert senders == {(keys.fused(f), f) for f in FUSERS}  # each on its own key, nothing on another
    for fuser in FUSERS:
        same_series(got[fuser], refs[fuser])
    assert got["north"]["series"]["rmse_pos"] != got["south"]["series"]["rmse_pos"]  # two methods, two outputs


def _track(x: float, track: str, src: str, seq: int) -> bytes:
    return encode_estimate(Estimate(5.0, np.array([x, 0.0, 1000.0, 0, 0, 0]), np.eye(6), "SS", "centre", track),
                           src, seq)


def test_picture_asks_one_fuser_or_every_fuser(deployment):
    """From outside: ``zfusion picture`` takes the default fuser's picture, ``--fuser ID``
    another's, ``--fuser '*'`` one line per fuser."""
    keys = KeySpace(deployment)
    ep = f"tcp/127.0.0.1:{free_port()}"
    hub = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    queryables = []
    try:
        for k, fuser in enumerate(("fuser", "north", "south")):
            def on_query(q, fuser=fuser, k=k) -> None:
                q.reply(keys.picture(fuser), _track(1000.0 * k, "T1", fuser, 1))
                q.reply(keys.picture(fuser), encode("watermark", fuser, 0, 5.0, final=False))
            queryables.append(hub.declare_queryable(keys.picture(fuser), on_query))

        def picture(*extra: str) -> list[dict]:
            out = subprocess.run([sys.executable, "-m", "services.cli", "picture", "--connect", ep,
                                  "--deployment", deployment, "--timeout", "20", *extra],
                                 capture_output=True, text=True, timeout=60)
            assert out.returncode == 0, out.stderr
            return [json.loads(line) for line in out.stdout.splitlines()]

        default, south, every = picture(), picture("--fuser", "south"), picture("--fuser", "*")
    finally:
        for q in queryables:
            q.undeclare()
        hub.close()
    assert [(d["fuser"], d["tracks"][0]["x"][0]) for d in default] == [("fuser", 0.0)]
    assert [(d["fuser"], d["tracks"][0]["x"][0]) for d in south] == [("south", 2000.0)]
    assert [d["fuser"] for d in every] == ["fuser", "north", "south"]


def test_a_fuser_id_that_names_no_key_is_a_users_mistake():
    out = subprocess.run([sys.executable, "-m", "services.cli", "picture", "--fuser", "a/b"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "--fuser" in out.stderr
