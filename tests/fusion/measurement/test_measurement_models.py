"""fusion.measurement.models: stacking is generic over models and leaves the spherical
path as it was; the filters take any model of the protocol."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.ekf import TrackEKF
from fusion.filters import filter_factory
from fusion.measurement.kinds import model_for
from fusion.measurement.models import SphericalModel, StackedModel, stack
from fusion.motion import ConstantAcceleration

DEG = np.pi / 180.0
X = np.array([6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.5, 1.0, -0.05])


def _pair():
    return (model_for("azel", [100.0, 0.0, 0.0], (0.05 * DEG, 0.05 * DEG)),
            model_for("range_az", [0.0, -300.0, 5.0], (1.0 * DEG, 20.0)))


def test_stacking_spherical_models_is_the_spherical_stack():
    a, r = _pair()
    s = stack([a, r])
    assert type(s) is SphericalModel and s is SphericalModel.stack([a, r])  # the cached spherical stack
    assert stack([a]) is a
    with pytest.raises(ValueError, match="zero"):
        stack([])
    with pytest.raises(ValueError, match="state lengths"):
        stack([a, model_for("range_az", np.zeros(3), (0.01, 5.0), 6)])


def test_a_stacked_model_equals_the_spherical_stack_of_the_same_rows():
    a, r = _pair()
    ref = SphericalModel.stack([a, r])
    s = StackedModel([a, r])
    z = ref.h(X) + np.array([2e-4, -1e-4, 3e-3, 15.0])
    assert s.components == ref.components and s.n_z == 4 and s.n_x == 9
    np.testing.assert_array_equal(s.R, ref.R)
    np.testing.assert_array_equal(s.angles, ref.angles)
    np.testing.assert_array_equal(s.h(X), ref.h(X))
    np.testing.assert_array_equal(s.h(np.stack([X, X + 1.0])), ref.h(np.stack([X, X + 1.0])))
    np.testing.assert_array_equal(s.jacobian(X), ref.jacobian(X))
    for got, want in zip(s.innovation_and_jacobian(z, X), ref.innovation_and_jacobian(z, X)):
        np.testing.assert_array_equal(got, want)
    # an azimuth across north wraps in the residual, a range does not
    np.testing.assert_allclose(s.residual(np.array([0.001, 0.0, 6.28, 5.0]), np.array([6.28, 0.0, 0.001, 1.0])),
                               [0.001 - 6.28 + 2 * np.pi, 0.0, 6.28 - 0.001 - 2 * np.pi, 4.0], rtol=0, atol=1e-12)


class _Linear:
    """A model outside the spherical family: ``z = A x[:3]``, for the stacking and filter tests."""

    def __init__(self, A, std, n_x=9):
        self.A = np.asarray(A, float)
        self.n_z, self.n_x = self.A.shape[0], n_x
        self.components = tuple(f"l{i}" for i in range(self.n_z))
        self.R = np.diag(np.asarray(std, float) ** 2)
        self.angles = np.zeros(self.n_z, bool)

    def h(self, x):
        return np.asarray(x)[..., :3] @ self.A.T

    def jacobian(self, x):
        return np.hstack([self.A, np.zeros((self.n_z, self.n_x - 3))])

    def residual(self, z, z_hat):
        return np.asarray(z, float) - z_hat

    def innovation_and_jacobian(self, z, x):
        return self.residual(z, self.h(x)), self.jacobian(x)


def test_mixed_stacks_merge_neighbouring_spherical_rows():
    a, r = _pair()
    lin = _Linear([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]], [3.0, 4.0])
    s = stack([a, r, lin, a])
    assert isinstance(s, StackedModel) and len(s.blocks) == 3
    assert s.blocks[0] is SphericalModel.stack([a, r]) and s.blocks[1] is lin and s.blocks[2] is a
    assert s.components == (*a.components, *r.components, *lin.components, *a.components)
    R = s.R
    assert R.shape == (8, 8) and np.count_nonzero(R - np.diag(np.diag(R))) == 0
    np.testing.assert_array_equal(np.diag(R)[4:6], [9.0, 16.0])
    np.testing.assert_array_equal(s.h(X), np.concatenate([a.h(X), r.h(X), lin.h(X), a.h(X)]))
    np.testing.assert_array_equal(s.angles, [True, True, True, False, False, False, True, True])


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_a_filter_updates_with_a_stacked_model_as_with_its_blocks_in_turn(name):
    """Independent blocks: one stacked update equals sequential updates with each block
    for a linear model (the Kalman update's associativity), so the stacking is right."""
    motion = ConstantAcceleration(0.01)
    P = np.diag([100.0, 100.0, 100.0, 25.0, 25.0, 25.0, 1.0, 1.0, 1.0])
    l1, l2 = _Linear([[1.0, 0.0, 0.0]], [5.0]), _Linear([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [7.0, 2.0])
    z1, z2 = l1.h(X) + 3.0, l2.h(X) - 2.0
    one = filter_factory(name, motion)(X, P, 0.0)
    one.update(stack([l1, l2]), np.concatenate([z1, z2]))
    two = filter_factory(name, motion)(X, P, 0.0)
    two.update(l1, z1)
    two.update(l2, z2)
    np.testing.assert_allclose(one.x, two.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(one.P, two.P, rtol=1e-9, atol=1e-9)
    assert isinstance(filter_factory("ekf", motion)(X, P, 0.0), TrackEKF)
