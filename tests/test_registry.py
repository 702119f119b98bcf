"""The method registry (fusion.methods): each record's facts agree with the method it
builds, and the command line, the launcher and the scenario loader read their choices
from it (scenario defaults by sensor kinds: tests/test_eval.py)."""

from __future__ import annotations

import argparse

import pytest

from fusion.methods import METHODS, TOPOLOGIES, TRACK_FUSION_METHODS, make_method, spec, split, topology_default
from fusion.network import MultiTrackCentre, TrackCentre, TrackNode
from fusion.topology import TOPOLOGIES as LEAF_TOPOLOGIES
from services.cli import build_parser
from services.launcher import topology_of

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
    assert centre.feedback == (s.topology in ("feedback", "two-stage"))
    assert isinstance(centre, TrackCentre) == s.fuses_tracks
    assert isinstance(split(name).centre(ASSOCIATION), MultiTrackCentre) == s.fuses_tracks
    node = split(name).node("radar", {})
    if isinstance(node, TrackNode):
        assert (node.mode == "predict") == (s.topology == "two-stage")


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
    assert tuple(run["topology"].choices) == TOPOLOGIES == LEAF_TOPOLOGIES


def test_the_launcher_reads_the_registry():
    assert [topology_of(n) for n in ("SS", "HNV", "PHHNV", "DDHNV", "KF+TR", "EKF")] == \
        ["centralised", "distributed", "feedback", "two-stage", "distributed", "centralised"]
    assert [topology_default(t, "3d") for t in TOPOLOGIES[1:]] == ["HNV", "PHHNV", "DDHNV"]
    assert [topology_default(t, "df") for t in TOPOLOGIES[1:]] == ["KF+TR", None, None]
