"""fusion.tracking.hypotheses: χ² gating of plots against tracks, sequential gating."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from fusion.measurement.kinds import model_for
from fusion.tracking.hypotheses import gate_threshold, gating_update, mahalanobis2

ALPHA = 0.01


@pytest.mark.parametrize("dof, prob", [(1, 0.99), (2, 0.999), (4, 0.95)])
def test_gate_threshold_is_the_chi2_quantile(dof, prob):
    G = gate_threshold(dof, prob)
    assert stats.chi2.cdf(G, dof) == pytest.approx(prob, abs=1e-12)
    if dof == 2:  # closed form: P(χ²₂ ≤ G) = 1 − e^{−G/2}
        assert G == pytest.approx(-2.0 * math.log(1.0 - prob))


def test_mahalanobis_distance_is_the_closed_form_and_wraps_azimuth():
    """A target due north of the site with only a north-south position variance: the
    azimuth row sees none of it (∂az/∂p_n = 0), so d² = ν_az²/σ_az² + ν_r²/(σ_n² + σ_r²);
    an azimuth measured just below 2π is a small innovation of a target at 0."""
    sa, sr, sn = 0.01, 20.0, 100.0
    model = model_for("range_az", [0.0, 0.0, 0.0], [sa, sr], 9)
    x = np.zeros(9)
    x[:3] = [0.0, 10_000.0, 0.0]
    P = np.zeros((9, 9))
    P[1, 1] = sn**2
    z = np.array([[2 * math.pi - 0.015, 10_050.0], [0.005, 9_990.0]])
    want = [(0.015 / sa) ** 2 + 50.0**2 / (sn**2 + sr**2), (0.005 / sa) ** 2 + 10.0**2 / (sn**2 + sr**2)]
    np.testing.assert_allclose(mahalanobis2(model, x, P, z), want, rtol=1e-9)


def test_sequential_gating_is_the_scalar_kalman_recursion():
    """Two plots of a 2D radar of a target due north with only a north-south position
    variance: the range is then a scalar linear problem. After the first plot the gating
    state is the scalar Kalman update (m₁ = n₀ + σ_n²/(σ_n² + σ_r²)(r₁ − n₀),
    v₁ = σ_n²σ_r²/(σ_n² + σ_r²)), the second plot's d² is (r₂ − m₁)²/(v₁ + σ_r²) plus its
    azimuth term, and the two d² add up to the joint d² of both ranges stacked."""
    sa, sr, sn = 0.01, 20.0, 300.0
    model = model_for("range_az", [0.0, 0.0, 0.0], [sa, sr], 9)
    x = np.zeros(9)
    x[:3] = [0.0, 10_000.0, 0.0]
    P = np.diag([0.0, sn**2, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    z1, z2 = np.array([0.0, 10_200.0]), np.array([0.004, 10_150.0])
    x1, P1 = gating_update(model, x, P, z1)
    m1 = 10_000.0 + sn**2 / (sn**2 + sr**2) * 200.0
    v1 = sn**2 * sr**2 / (sn**2 + sr**2)
    np.testing.assert_allclose([x1[1], P1[1, 1]], [m1, v1], rtol=1e-12)
    d2_second = float(mahalanobis2(model, x1, P1, z2[None, :])[0])
    np.testing.assert_allclose(d2_second, (0.004 / sa) ** 2 + (10_150.0 - m1) ** 2 / (v1 + sr**2), rtol=1e-9)
    nu = np.array([200.0, 150.0])
    joint = nu @ np.linalg.solve(sn**2 * np.ones((2, 2)) + sr**2 * np.eye(2), nu)
    d2_first = float(mahalanobis2(model, x, P, z1[None, :])[0])
    np.testing.assert_allclose(d2_first + d2_second, joint + (0.004 / sa) ** 2, rtol=1e-9)


def test_true_measurements_fall_in_the_gate_with_the_gate_probability():
    """Truth drawn from the track's N(x, P), measurement from N(h(truth), R): with a
    covariance small enough for h to be linear, d² is χ²(2), so a 99 % gate keeps
    99 % of the true plots (binomial test at 1 %, 20 000 draws)."""
    rng = np.random.default_rng(5)
    model = model_for("azel", [100.0, -200.0, 0.0], [1e-3, 1e-3], 6)
    x = np.array([8000.0, 6000.0, 3000.0, 100.0, 0.0, 0.0])
    A = rng.normal(size=(6, 6))
    P = A @ A.T * 10.0 + np.eye(6) * 100.0
    n = 20_000
    truths = rng.multivariate_normal(x, P, size=n)
    z = model.h(truths) + rng.normal(size=(n, 2)) * 1e-3
    d2 = mahalanobis2(model, x, P, z)
    G = gate_threshold(2, 0.99)
    assert stats.binomtest(int(np.sum(d2 <= G)), n, 0.99).pvalue > ALPHA
    assert stats.kstest(d2, stats.chi2(2).cdf).pvalue > ALPHA
