"""The local nodes and centre of the distributed topologies (fusion/network.py) and their
wire form (schemas/links.py): initialisation handshake, feedback ordering, running alone
when the downlink is lost."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fusion.links import (Drop, DropTrack, Feedback, Init, InitRequest, LocalReport, MeasurementReport, PredictionReport)
from fusion.methods import split
from fusion.network import NetworkMethod, TrackCentre, TrackNode
from fusion.types import Estimate, Measurement
from fusion.patent import TrackerConfig
from fusion.topology import SCHEMES
from schemas import decode
from schemas.links import downlink, encode_downlink, encode_uplink, uplink
from services.evaluation import merged_measurements
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
    assert all(isinstance(u, InitRequest) for u in ups)  # no prior yet: the first measurement goes up
    for u in sorted(ups, key=lambda u: u.order_key):
        assert centre.process(u) == []
    nodes["angle"].offer(a[1])
    assert nodes["angle"].waiting_for == "init" and nodes["angle"].step() == []
    # The node promises only up to just before what it holds, which lets the first scan close.
    assert nodes["angle"].upstream_watermark(np.inf) < a[1].t
    (init,) = centre.advance(nodes["angle"].upstream_watermark(np.inf))
    downs = centre.take_downlinks()
    assert sorted(d.node for d in downs) == ["angle", "radar2d"] and all(isinstance(d, Init) for d in downs)
    for d in downs:
        nodes[d.node].receive(d)
    # Initialised, and the centre's horizon covers every scan before t1: the update may go.
    nodes["angle"].set_horizon(centre.horizon)
    (u,) = nodes["angle"].step()
    assert isinstance(u, LocalReport) and u.feedback_t == init.t and u.estimate.nis is not None
    assert u.estimate.extra == {}  # the link terms are the report's, not the estimate's
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
    assert isinstance(req, InitRequest)
    for m in a[1:4]:
        node.offer(m)
    assert node.step() == [] and node.waiting_for == "init"
    out = node.step(alone=True)  # no centre: start from its own measurement, then update
    assert node.tracker.initialised and len(out) == 2 and all(u.estimate.nis is not None for u in out)
    assert not node.pending


def _same(g, e, what="message"):
    """Bit for bit: the same type, and field by field the same times, ids, arrays
    (values and dtype), estimates and measurements."""
    assert type(g) is type(e), what
    if isinstance(e, np.ndarray):
        assert g.dtype == e.dtype == np.float64 and g.shape == e.shape and g.tobytes() == e.tobytes(), what
    elif isinstance(e, Measurement):
        assert g == e, what
    elif dataclasses.is_dataclass(e):
        for f in dataclasses.fields(e):
            _same(getattr(g, f.name), getattr(e, f.name), f"{what}.{f.name}")
    elif isinstance(e, dict):
        assert set(g) == set(e), what
        for k in e:
            _same(g[k], e[k], f"{what}[{k}]")
    else:
        assert g == e, what


_IMM = {"motion": "imm", "fusion_rule": "info"}  # local IMMs' per-model terms up, the centre's down


@pytest.mark.parametrize("name,config", [("HNV", {"fusion_rule": "bar-shalom-campo"}),
                                         ("PHHNV", {"fusion_rule": "bar-shalom-campo"}),
                                         ("DDHNV", {"fusion_rule": "bar-shalom-campo"}),
                                         ("PHHNV", _IMM), ("DDHNV", _IMM), ("KF+TR", {})])
def test_uplinks_and_downlinks_survive_the_wire(stream, name, config):
    """Every message up and down of a run, through the wire and back, is the same bit
    for bit (its ``seq`` becomes the message's, and a measurement's with it)."""
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
    kinds = {type(u) for u in sent}
    assert kinds == ({MeasurementReport} if name == "KF+TR" else
                     {InitRequest, PredictionReport} if name == "DDHNV" else {InitRequest, LocalReport})
    for k, u in enumerate(sent):
        back = uplink(decode(encode_uplink(u, "trk-" + u.node, k)))
        want = dataclasses.replace(u, seq=k)
        if hasattr(u, "measurement"):  # the measurement's seq is the message's too
            want = dataclasses.replace(want, measurement=dataclasses.replace(u.measurement, seq=k))
        _same(back, want)
    reports = [u for u in sent if isinstance(u, (LocalReport, PredictionReport))]
    assert all((u.models is not None) == (config is _IMM) for u in reports)
    assert any(u.feedback_t is not None for u in reports) or name == "KF+TR"
    assert any(u.feedback_t is None for u in reports) == (name == "HNV")  # fed back: every report follows a restart
    assert bool(down) == (name != "KF+TR")
    feedback = [d for d in down if isinstance(d, Feedback)]
    assert bool(feedback) == (name in ("PHHNV", "DDHNV")) and all(isinstance(d, (Init, Feedback)) for d in down)
    assert all((d.update is not None) == (name == "DDHNV") for d in feedback)
    assert all((d.models is not None) == (config is _IMM) for d in feedback)
    for k, d in enumerate(down):
        _same(downlink(d.node, decode(encode_downlink(d, "fuser", k))), d)


def test_a_deletion_notice_and_order_survive_the_wire():
    """Many targets: a node's ``drop`` of its local track and the centre's ``drop_track``."""
    u = Drop(4.0, "radar2d", 2, "L3")
    _same(uplink(decode(encode_uplink(u, "trk-radar2d", 2))), u)
    d = DropTrack("radar2d", 5.0, "L3")
    _same(downlink("radar2d", decode(encode_downlink(d, "fuser", 5))), d)


def test_link_messages_refuse_what_the_wire_cannot_say():
    """An extra a link does not carry, a measurement or estimate stamped off its
    message's time, or a prediction with a NIS is an error at the sender, not a silent loss."""
    e = Estimate(1.0, np.zeros(2), np.eye(2), "HNV", "angle", "T1", extra={"omega": np.ones(2)})
    with pytest.raises(ValueError, match="omega"):
        encode_downlink(Init("angle", dataclasses.replace(e, node="centre")), "fuser", 1)
    plain = dataclasses.replace(e, extra={})
    m = Measurement(1.5, "angle", "azel", np.array([1.0, 0.1]), np.array([1e-3, 1e-3]), np.zeros(3))
    with pytest.raises(ValueError, match="measurement at t = 1.5"):
        encode_uplink(InitRequest(1.0, "angle", 1, m), "trk-angle", 1)
    with pytest.raises(ValueError, match="estimate of node 'angle' at t = 1.0"):
        PredictionReport(2.0, "angle", 1, plain, m)
    with pytest.raises(ValueError, match="no NIS"):
        encode_uplink(PredictionReport(1.0, "angle", 1, dataclasses.replace(plain, nis=1.0, nis_dof=2),
                                       dataclasses.replace(m, t=1.0)), "trk-angle", 1)


@pytest.mark.parametrize("name", ["PHHNV", "DDHNV"])
def test_a_node_is_named_apart_from_its_sensor(crossing, name):
    """Many targets, with every sensor's node named ``trk-<sensor>`` instead of after
    the sensor: the centre sends its inits, feedback and drops to the node that sent the
    requests (not to a measurement's sensor), and every estimate is the same bit for bit,
    but for the local reports' ``node``."""
    ms = [m for m in merged_measurements(crossing, 0) if m.t <= 25.0]
    same = NetworkMethod(split(name), dict(crossing.tracker))
    apart = NetworkMethod(split(name), dict(crossing.tracker), node_of=lambda sensor: "trk-" + sensor)
    runs = []
    for method in (same, apart):
        out = []
        for m in ms:
            out += method.process(m)
        runs.append(out + method.finish())
    assert sorted(apart.nodes) == ["trk-" + s for s in sorted(same.nodes)]
    a, b = runs
    assert len(a) == len(b) and sum(e.node == "centre" for e in a) > 20
    for e, g in zip(a, b):
        assert g.node == (e.node if e.node == "centre" else "trk-" + e.node)
        _same(dataclasses.replace(g, node=e.node), e)


@pytest.mark.parametrize("name", ["PHHNV", "DDHNV"])
def test_a_node_that_joins_later_is_merged_in_order(crossing, name):
    """Many targets, the radar's node from 8 s and the angle sensor's from 9 s (the
    nodes of a restarted fuser, joining at different scans): at 9 s both nodes' uplinks
    reach the centre in key order (t, node, seq), as the fuser merges them, whichever
    node was created first — the same estimates as with the nodes named so that their
    creation order is their key order. (Pumped in creation order, the radar's uplink of
    9 s went first and the centre refused the angle's as out of order.)"""
    start = {"radar": 8.0, "angle": 9.0}
    ms = [m for m in merged_measurements(crossing, 0) if start[m.sensor] <= m.t <= 25.0]
    runs = []
    for node_of in (lambda sensor: sensor, {"radar": "a-radar", "angle": "b-angle"}.get):
        method = NetworkMethod(split(name), dict(crossing.tracker), node_of=node_of)
        out = []
        for m in ms:
            out += method.process(m)
        runs.append([e for e in out + method.finish() if e.node == "centre"])
    a, b = runs
    assert len(a) == len(b) and len(a) > 20
    for e, g in zip(a, b):
        _same(g, e)


def test_a_dropped_track_and_a_lost_request(stream):
    """The centre's ``DropTrack`` drops the node's track: its next measurement asks for an
    initial state again (the typed links once ignored it, so the node kept reporting a
    track the centre no longer counted as a member's). A node whose request went
    unanswered starts a track alone; it counts as having run alone once the centre's
    horizon has passed the request, not before, and not once an init has come."""
    cfg = TrackerConfig.from_dict({})
    node = TrackNode("angle", cfg, "PHHNV", SCHEMES["feedback"])
    a = _of(stream, "angle")
    node.offer(a[0])
    (req,) = node.step()
    node.receive(Init("angle", Estimate(a[0].t, np.r_[1000.0, 0, 0, 0, 0, 0, 1000, 0, 0], np.eye(9) * 1e4,
                                        "PHHNV", "centre", "T1")))
    assert node.tracker.initialised and not node.ran_alone
    node.receive(DropTrack("angle", a[0].t, "T1"))
    assert not node.tracker.initialised
    node.offer(a[1])
    (again,) = node.step()
    assert isinstance(again, InitRequest) and again.t == a[1].t
    for m in a[2:4]:
        node.offer(m)
    node.step(alone=True)  # no answer: a track of its own from a[2]
    assert node.tracker.initialised and not node.ran_alone  # the centre may still answer
    node.set_horizon(a[1].t)  # the centre is complete past the request, and did not answer
    assert node.ran_alone
    node.centre_restarted()
    node.offer(a[4])
    (third,) = node.step()
    assert isinstance(third, InitRequest) and not node.ran_alone


def test_a_node_woken_after_the_centre_went_on_drops_what_the_centre_passed(stream):
    """A node stopped (SIGSTOP) while the centre, which declared it dead, fused on without
    it: on waking it holds its sensor's measurements since, and the centre's feedback since
    comes in the same batch, applied before the measurements. With a prior at t5 and the
    measurements at t1..t4 pending, those four are dropped (counted in ``stale``: the
    centre refuses them as late, and the track cannot be predicted back to them) and t5 is
    an update from the prior. It raised 'cannot predict backwards' and the tracker died."""
    cfg = TrackerConfig.from_dict({})
    node = TrackNode("angle", cfg, "PHHNV", SCHEMES["feedback"])
    centre = TrackCentre("PHHNV", cfg, SCHEMES["feedback"])
    a = _of(stream, "angle")
    node.offer(a[0])
    (req,) = node.step()
    centre.process(req)
    centre.advance(np.nextafter(a[1].t, 0))  # the node's promise while it holds t1
    (init,) = centre.take_downlinks()
    node.receive(init)
    for m in a[1:7]:
        node.offer(m)
    e = init.estimate
    node.receive(Feedback("angle", Estimate(a[5].t, e.x, e.P, "PHHNV", "centre", "T1"), None, None))
    node.set_horizon(a[5].t)
    (u,) = node.step()
    assert node.stale == 4 and isinstance(u, LocalReport) and u.t == a[5].t and u.feedback_t == a[5].t
    assert node.waiting_for == "feedback" and [m.t for m in node.pending] == [a[6].t]


def test_a_many_target_node_woken_after_the_centre_went_on_drops_the_frames_it_passed(stream):
    """The same for a many-target node: a frame older than a prior its centre sent is
    dropped whole (its plots would start requests the centre refuses as late)."""
    node = split("PHHNV").node("angle", {"association": "gnn"})
    a = _of(stream, "angle")
    node.offer(a[0])
    node.set_watermark(np.nextafter(a[1].t, 0))
    node.set_horizon(a[0].t)
    (req,) = node.step()
    assert isinstance(req, InitRequest)
    centre = TrackCentre("PHHNV", TrackerConfig.from_dict({}), SCHEMES["feedback"])  # a state to start from
    centre.process(req)
    centre.advance(np.nextafter(a[1].t, 0))
    (init,) = centre.take_downlinks()
    node.receive(init)
    for m in a[1:6]:
        node.offer(m)
    node.set_watermark(np.nextafter(a[6].t, 0))
    node.receive(Feedback("angle", Estimate(a[4].t, init.estimate.x, init.estimate.P, "PHHNV", "centre", "T1"),
                          None, None))
    node.set_horizon(a[4].t)
    out = node.step()
    assert node.stale == 3  # the frames at t1..t3
    assert [u.t for u in out] == [a[4].t] and set(node.tracks) == {"T1"}  # the frame at t4 is taken
