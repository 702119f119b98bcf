"""The local nodes and centre of the distributed topologies (fusion/network.py) and their
wire form (schemas/links.py): initialisation handshake, feedback ordering, running alone
when the downlink is lost."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.methods import split
from fusion.network import Downlink, NetworkMethod, TrackCentre, TrackNode, Uplink
from fusion.patent import TrackerConfig
from fusion.topology import SCHEMES
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
    nodes = {s: TrackNode(s, cfg, "PHHNV", SCHEMES["feedback"]) for s in ("angle", "radar2d")}
    centre = TrackCentre("PHHNV", cfg, SCHEMES["feedback"])
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
    node = TrackNode("angle", TrackerConfig.from_dict({}), "PHHNV", SCHEMES["feedback"])
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


def _same_estimate(g, e):
    """Bit for bit: times, ids, arrays (values and dtype) and every extra."""
    assert (g.t, g.method, g.node, g.track, g.nis, g.nis_dof) == (e.t, e.method, e.node, e.track, e.nis, e.nis_dof)
    assert set(g.extra) == set(e.extra)
    for k in ("x", "P"):
        a, b = getattr(g, k), getattr(e, k)
        assert a.dtype == b.dtype == np.float64 and a.tobytes() == b.tobytes(), k
    for k, v in e.extra.items():
        if isinstance(v, np.ndarray):
            assert g.extra[k].dtype == np.float64 and g.extra[k].tobytes() == v.tobytes(), k
        else:
            assert type(g.extra[k]) is type(v) and g.extra[k] == v, k


_IMM = {"motion": "imm", "fusion_rule": "info"}  # local IMMs' per-model terms up, the centre's down


@pytest.mark.parametrize("name,config", [("HNV", {"fusion_rule": "bar-shalom-campo"}),
                                         ("PHHNV", {"fusion_rule": "bar-shalom-campo"}),
                                         ("DDHNV", {"fusion_rule": "bar-shalom-campo"}),
                                         ("PHHNV", _IMM), ("DDHNV", _IMM), ("KF+TR", {})])
def test_uplinks_and_downlinks_survive_the_wire(stream, name, config):
    """Every uplink and downlink of a run, through the wire and back, is the same bit
    for bit (a measurement's ``seq`` becomes the message's)."""
    method = NetworkMethod(split(name), config)
    sent, down = [], []
    if name != "KF+TR":
        for node in ("angle", "radar2d"):
            method._node(node)
    orig, take = method.centre.process, method.centre.take_downlinks

    def spy(u):
        sent.append(u)
        return orig(u)

    def spy_down():
        out = take()
        down.extend(out)
        return out

    method.centre.process, method.centre.take_downlinks = spy, spy_down
    bearings = [dataclasses.replace(m, kind="bearing", z=m.z[:1], std=m.std[:1]) for m in _of(stream, "angle")]
    for m in stream if name != "KF+TR" else bearings:
        method.process(m)
    method.finish()
    assert any(u.estimate is not None for u in sent) or name == "KF+TR"
    assert any(u.init_request for u in sent)
    for k, u in enumerate(sent):
        back = uplink(decode(encode_uplink(u, "trk-" + u.node, k)))
        assert (back.t, back.node, back.seq, back.drop) == (u.t, u.node, k, u.drop)
        assert (back.estimate is None) == (u.estimate is None) and (back.measurement is None) == (u.measurement is None)
        if u.estimate is not None:
            _same_estimate(back.estimate, u.estimate)
        if u.measurement is not None:
            assert back.measurement == dataclasses.replace(u.measurement, seq=k)
    assert bool(down) == (name != "KF+TR")
    assert any(not d.init for d in down) == (name in ("PHHNV", "DDHNV"))  # feedback
    if name == "DDHNV":
        assert any("sensor_x" in d.estimate.extra for d in down)
    if config is _IMM:
        assert all("imm_loglik" in u.estimate.extra for u in sent if u.report)
        assert any("imm_mu" in d.estimate.extra for d in down)
    for k, d in enumerate([*down, Downlink("angle", _fused(method), True)] if down else []):
        back = downlink(d.node, decode(encode_downlink(d, "fuser", k)))
        assert (back.node, back.init, back.drop) == (d.node, d.init, d.drop)
        _same_estimate(back.estimate, d.estimate)


def test_a_deletion_notice_survives_the_wire():
    """Many targets: a node's ``drop`` of its local track (an estimate without a local
    report's fields) and the centre's ``drop`` downlink."""
    from fusion.types import Estimate

    e = Estimate(4.0, np.arange(6.0), np.eye(6) * 3.0, "PHHNV", "radar2d", "L3")
    back = uplink(decode(encode_uplink(Uplink(4.0, "radar2d", 2, e, drop=True), "trk-radar2d", 2)))
    assert back.drop and not back.report and back.estimate.extra == {}
    _same_estimate(back.estimate, e)
    d = Downlink("radar2d", dataclasses.replace(e, node="centre"), False, drop=True)
    back = downlink("radar2d", decode(encode_downlink(d, "fuser", 5)))
    assert back.drop and not back.init
    _same_estimate(back.estimate, d.estimate)


def test_link_messages_refuse_what_the_wire_cannot_say():
    """An extra a link does not carry, or an estimate stamped off its uplink's time, is
    an error at the sender, not a silent loss."""
    from fusion.types import Estimate

    e = Estimate(1.0, np.zeros(2), np.eye(2), "HNV", "angle", "T1", extra={"omega": np.ones(2)})
    with pytest.raises(ValueError, match="omega"):
        encode_uplink(Uplink(1.0, "angle", 1, e), "trk-angle", 1)
    with pytest.raises(ValueError, match="omega"):
        encode_downlink(Downlink("angle", dataclasses.replace(e, node="centre"), False), "fuser", 1)
    with pytest.raises(ValueError, match="t = 2"):
        encode_uplink(Uplink(2.0, "angle", 1, dataclasses.replace(e, extra={})), "trk-angle", 1)


def _fused(method):
    from fusion.types import Estimate

    f = method.centre.fuser
    return Estimate(f.t, f.x, f.P, method.name, "centre", "T1")
