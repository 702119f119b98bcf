"""The local nodes and centre of the distributed topologies (fusion/network.py) and their
wire form (schemas/links.py): initialisation handshake, feedback ordering, running alone
when the downlink is lost."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.methods import make_method
from fusion.network import Downlink, TrackCentre, TrackNode
from fusion.patent import TrackerConfig
from schemas import decode
from schemas.links import downlink, encode_downlink, encode_uplink, uplink
from sim3d import ANGLE, RADAR2D, simulate


@pytest.fixture(scope="module")
def stream():
    return simulate(1, seed=11, duration=6.0, sensors=(ANGLE, RADAR2D)).measurements[0]


def _of(stream, sensor):
    return [m for m in stream if m.sensor == sensor]


def test_initialisation_handshake_and_feedback_order(stream):
    cfg = TrackerConfig.from_dict({})
    nodes = {s: TrackNode(s, cfg, "PHHNV", "feedback") for s in ("angle", "radar2d")}
    centre = TrackCentre("PHHNV", cfg, "feedback")
    a, r = _of(stream, "angle"), _of(stream, "radar2d")
    ups = []
    for s, m in (("angle", a[0]), ("radar2d", r[0])):
        nodes[s].offer(m)
        ups += nodes[s].step()
    assert all(u.init_request for u in ups)  # no prior yet: the first measurement goes up
    for u in sorted(ups, key=lambda u: u.order_key):
        assert centre.process(u) == []
    nodes["angle"].offer(a[1])
    assert nodes["angle"].waiting_for == "init" and nodes["angle"].step() == []
    # The node promises only up to just before what it holds, which lets the first scan close.
    assert nodes["angle"].upstream_watermark(np.inf) < a[1].t
    (init,) = centre.advance(nodes["angle"].upstream_watermark(np.inf))
    downs = centre.take_downlinks()
    assert sorted(d.node for d in downs) == ["angle", "radar2d"] and all(d.init for d in downs)
    for d in downs:
        nodes[d.node].receive(d)
    # Initialised, and the centre's horizon covers every scan before t1: the update may go.
    nodes["angle"].set_horizon(centre.horizon)
    (u,) = nodes["angle"].step()
    assert u.estimate.extra["feedback_t"] == init.t and u.estimate.nis is not None
    # Next measurement: must wait for the fusion of the scan at t1 (horizon still before it).
    nodes["angle"].offer(a[2])
    assert nodes["angle"].waiting_for == "feedback"
    nodes["radar2d"].offer(r[1])
    nodes["radar2d"].set_horizon(centre.horizon)
    (v,) = nodes["radar2d"].step()
    centre.process(u)
    (fused,) = centre.process(v)  # the scan holds every node: it closes at once
    assert fused.node == "centre" and fused.t == a[1].t
    assert {d.node for d in centre.take_downlinks()} == {"angle", "radar2d"}
    nodes["angle"].set_horizon(centre.horizon)
    assert nodes["angle"].waiting_for == "feedback"  # the centre has not heard past t1 yet
    # The radar's sensor is complete up to t1 only: a radar scan could still come before t2.
    centre.advance(min(nodes["angle"].upstream_watermark(np.inf), nodes["radar2d"].upstream_watermark(r[1].t)))
    nodes["angle"].set_horizon(centre.horizon)
    assert nodes["angle"].waiting_for == "feedback"
    # Once the radar is complete up to t2, no scan can come between: the update may go.
    centre.advance(min(nodes["angle"].upstream_watermark(np.inf), nodes["radar2d"].upstream_watermark(r[2].t)))
    nodes["angle"].set_horizon(centre.horizon)
    assert nodes["angle"].waiting_for is None


def test_lost_downlink_runs_alone(stream):
    node = TrackNode("angle", TrackerConfig.from_dict({}), "PHHNV", "feedback")
    a = _of(stream, "angle")
    node.offer(a[0])
    (req,) = node.step()
    assert req.init_request
    for m in a[1:4]:
        node.offer(m)
    assert node.step() == [] and node.waiting_for == "init"
    out = node.step(alone=True)  # no centre: start from its own measurement, then update
    assert node.tracker.initialised and len(out) == 2 and all(u.estimate.nis is not None for u in out)
    assert not node.pending


@pytest.mark.parametrize("name", ["HNV", "PHHNV", "DDHNV"])
def test_uplinks_and_downlinks_survive_the_wire(stream, name):
    """Everything the centre reads off a local report, and a downlink, round-trips exactly."""
    method = make_method(name, {"fusion_rule": "bar-shalom-campo"})
    sent = []
    for node in ("angle", "radar2d"):
        method._node(node)
    orig = method.centre.process

    def spy(u):
        sent.append(u)
        return orig(u)

    method.centre.process = spy
    for m in stream:
        method.process(m)
    method.finish()
    assert any(u.estimate is not None for u in sent) and any(u.init_request for u in sent)
    for u in sent:
        msgs = [decode(b) for b in encode_uplink(u, "trk-" + u.node, 7)]
        back = uplink(u.node, *msgs)
        assert (back.t, back.node) == (u.t, u.node)
        if u.estimate is not None:
            e, g = u.estimate, back.estimate
            assert g.extra["feedback_t"] == e.extra["feedback_t"] and g.extra["prediction"] == e.extra["prediction"]
            for k in ("prior_x", "prior_P", "KH"):
                np.testing.assert_array_equal(g.extra[k], e.extra[k])
            np.testing.assert_array_equal(g.x, e.x)
            np.testing.assert_array_equal(g.P, e.P)
        if u.measurement is not None:
            np.testing.assert_array_equal(back.measurement.z, u.measurement.z)
            assert back.measurement.kind == u.measurement.kind
    for init in (True, False):
        d = Downlink("angle", _fused(method), init)
        back = downlink("angle", decode(encode_downlink(d, "fuser", 3)))
        assert back.init is init
        np.testing.assert_array_equal(back.estimate.x, d.estimate.x)
        np.testing.assert_array_equal(back.estimate.P, d.estimate.P)


def _fused(method):
    from fusion.types import Estimate

    f = method.centre.fuser
    return Estimate(f.t, f.x, f.P, method.name, "centre", "T1")
