"""fusion.measurement.kinds: the kind table agrees with its models, and the facts others
read from it (families, pairing rules, wire fields, scenario keys) come out of it."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.measurement.components import COMPONENTS
from fusion.measurement.kinds import KINDS, POINT, RAY, SPHERE, kind, kinds_of, model_for, model_of, partners
from fusion.types import Measurement
from schemas import MEASUREMENT_KINDS, decode, encode_measurement
from sensors_sim.spec import SENSOR_KINDS

X = np.array([6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.5, 1.0, -0.05])


def test_every_kind_is_made_of_known_components():
    for k in KINDS.values():
        assert all(COMPONENTS[c.name] is c for c in k.components), k.name
        assert len(set(k.names)) == k.n_z
    assert len({c.std_field for c in COMPONENTS.values()}) == len(COMPONENTS)
    assert not {c.std_field for c in COMPONENTS.values()} & set(COMPONENTS)


@pytest.mark.parametrize("name", sorted(kinds_of("3d")))
def test_a_3d_kind_s_model_has_the_kind_s_rows(name):
    k = KINDS[name]
    std = np.linspace(0.01, 0.03, k.n_z)
    model = model_for(name, [10.0, -20.0, 3.0], std, 9)
    assert model.components == k.names and model.n_z == k.n_z and model.n_x == 9
    np.testing.assert_array_equal(model.angles, k.angles)
    np.testing.assert_array_equal(model.R, np.diag(std**2))
    assert model.h(X).shape == (k.n_z,) and model.jacobian(X).shape == (k.n_z, 9)


def test_families_and_what_a_report_starts_a_track_from():
    assert kinds_of("3d") == {"azel", "range_az", "az_el_range", "position"}
    assert kinds_of("df") == {"bearing"}
    assert [KINDS[k].start for k in ("bearing", "azel", "range_az", "az_el_range")] == [RAY, RAY, SPHERE, POINT]
    assert KINDS["bearing"].model is None
    assert [KINDS[k].fixes_range for k in ("azel", "range_az", "az_el_range")] == [False, True, True]


def test_a_ray_pairs_with_a_sphere_of_its_family():
    assert partners("azel") == {"range_az"} and partners("range_az") == {"azel"}
    assert partners("az_el_range") == frozenset()
    assert partners("bearing") == frozenset()  # the DF family has no sphere
    with pytest.raises(ValueError, match="unknown measurement kind 'radar'"):
        kind("radar")


def test_model_of_refuses_what_is_not_a_3d_report():
    site = np.zeros(3)
    with pytest.raises(ValueError, match="not a 3D sensor kind"):
        model_of(Measurement(0.0, "df1", "bearing", np.array([0.3]), np.array([0.01]), site))
    with pytest.raises(ValueError, match="a1"):
        model_of(Measurement(0.0, "a1", "azel", np.array([0.3, np.nan]), np.array([0.01, 0.01]), site))
    with pytest.raises(ValueError, match="3-vector site"):
        model_of(Measurement(0.0, "a1", "azel", np.array([0.3, 0.1]), np.array([0.01, 0.01]), np.zeros(2)))


def test_the_wire_carries_each_kind_s_components_and_their_std_fields():
    assert MEASUREMENT_KINDS == tuple(KINDS)
    for k in KINDS.values():
        z = np.array([{"az": 0.5, "el": 0.1, "range": 1234.0, "east": -5.0, "north": 7.0, "up": 900.0}[c]
                      for c in k.names])
        m = Measurement(2.0, "s1", k.name, z, np.full(k.n_z, 0.01), np.array([1.0, 2.0, 3.0]), 7)
        msg = decode(encode_measurement(m, "s1"))
        assert set(msg.body) == {"sensor", "site", *k.names, *(c.std_field for c in k.components)}


def test_every_sensor_kind_reports_a_known_kind_with_a_std_key_per_component():
    for s in SENSOR_KINDS.values():
        k = KINDS[s.measures]
        assert len(s.std_keys_of()) == k.n_z and all(s.std_keys_of()), s.name
