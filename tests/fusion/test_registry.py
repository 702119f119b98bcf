"""The method registry (fusion.methods): each record's facts agree with the method it
builds, and the command line, the launcher and the scenario loader read their choices
from it (scenario defaults by sensor kinds: tests/services/test_eval.py)."""

from __future__ import annotations

import argparse

import pytest

from fusion.methods import METHODS, TOPOLOGIES, TRACK_FUSION_METHODS, make_method, spec, split, topology_default
from fusion.network import MultiTrackCentre, TrackCentre, TrackNode
from fusion.topology import LAYOUTS, TOPOLOGIES as LEAF_TOPOLOGIES
from fusion.topology import SCHEMES, Scheme, scheme_of
from services.cli import build_parser
from services.request import topology_of

ASSOCIATION = {"association": "gnn"}


@pytest.mark.parametrize("name", METHODS)
def test_every_record_builds_its_method(name):
    s = METHODS[name]
    assert make_method(name, {}).name == name
    assert make_method(name, ASSOCIATION).name == name  # many targets, same name
    assert s.family in ("3d", "df") and s.topology in TOPOLOGIES


@pytest.mark.parametrize("name", [n for n, s in METHODS.items() if s.split is not None])
def test_a_split_method_s_topology_is_what_its_nodes_and_centre_do(name):
    s = METHODS[name]
    centre = split(name).centre({})
    assert isinstance(centre, TrackCentre) == s.fuses_tracks
    if s.fuses_tracks:
        assert centre.scheme == scheme_of(s.topology)
        assert centre.scheme.feeds_back == (s.topology in ("feedback", "two-stage"))
        assert split(name).centre(ASSOCIATION).scheme == centre.scheme
    assert isinstance(split(name).centre(ASSOCIATION), MultiTrackCentre) == s.fuses_tracks
    node = split(name).node("radar", {})
    if isinstance(node, TrackNode):
        assert node.scheme == scheme_of(s.topology) and node.scheme.predicts == (s.topology == "two-stage")
        assert split(name).node("radar", ASSOCIATION).scheme == node.scheme


def test_track_fusion_methods_are_those_whose_centre_fuses_tracks():
    assert TRACK_FUSION_METHODS == tuple(n for n, s in METHODS.items()
                                         if s.split is not None and isinstance(s.split.centre({}), TrackCentre))
    assert set(TRACK_FUSION_METHODS) == {"HNV", "PHHNV", "DDHNV"}


def test_centralised_methods_have_no_split():
    for name, s in METHODS.items():
        if s.topology == "centralised":
            with pytest.raises(ValueError, match="not a distributed method"):
                split(name)
    with pytest.raises(ValueError, match="unknown method 'KALMAN'"):
        spec("KALMAN")


def test_the_command_line_reads_the_registry():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    run = {a.dest: a for a in sub.choices["run"]._actions}
    assert TOPOLOGIES == LEAF_TOPOLOGIES
    assert tuple(run["topology"].choices) == (*TOPOLOGIES, "regional") == LAYOUTS  # and the regional layout


def test_the_launcher_reads_the_registry():
    assert [topology_of(n) for n in ("SS", "HNV", "PHHNV", "DDHNV", "KF+TR", "EKF")] == \
        ["centralised", "distributed", "feedback", "two-stage", "distributed", "centralised"]
    assert [topology_default(t, "3d") for t in TOPOLOGIES[1:]] == ["HNV", "PHHNV", "DDHNV"]
    assert [topology_default(t, "df") for t in TOPOLOGIES[1:]] == ["KF+TR", None, None]

def test_a_scheme_is_what_its_topology_says():
    """Only the split topologies have a scheme; a node that only predicts needs feedback."""
    assert {t: (s.predicts, s.feeds_back) for t, s in SCHEMES.items()} == {
        "distributed": (False, False), "feedback": (False, True), "two-stage": (True, True)}
    assert set(SCHEMES) == set(LEAF_TOPOLOGIES) - {"centralised"}
    with pytest.raises(ValueError, match="centralised"):
        scheme_of("centralised")
    with pytest.raises(ValueError, match="fed back"):
        Scheme(predicts=True)
