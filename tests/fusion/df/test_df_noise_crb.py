"""Bearing-noise samplers and the Cramér–Rao bound."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.df.crb import crb, crb_rmse, crb_rmse_series, fisher_information
from fusion.df.models import bearing
from fusion.df.noise import contaminated, gaussian, mixture_variance, snr_db

N = 200_000


def test_gaussian_has_one_std_per_site_and_is_reproducible():
    sig = np.array([0.01, 0.02, 0.05])
    n = gaussian(np.random.default_rng(1), sig, (N, 3))
    np.testing.assert_allclose(n.std(axis=0), sig, rtol=0.01)
    np.testing.assert_array_equal(n, gaussian(np.random.default_rng(1), sig, (N, 3)))


@pytest.mark.parametrize("law", ["laplacian", "uniform"])
def test_contaminated_noise_mixes_the_right_laws(law):
    s1, s2, p = 0.0175, 0.25, 0.3
    n, mask = contaminated(np.random.default_rng(2), s1, s2, p, N, law=law, return_mask=True)
    assert abs(mask.mean() - p) < 4 * np.sqrt(p * (1 - p) / N)
    out, clean = n[mask], n[~mask]
    assert out.std() == pytest.approx(s2, rel=0.02)
    assert clean.std() == pytest.approx(s1, rel=0.01)
    assert n.var() == pytest.approx(mixture_variance(s1, s2, p), rel=0.03)
    kurt = np.mean(out ** 4) / np.mean(out ** 2) ** 2
    if law == "uniform":
        assert np.abs(out).max() <= np.sqrt(3) * s2 and kurt == pytest.approx(1.8, rel=0.02)
    else:
        assert kurt == pytest.approx(6.0, rel=0.1)


def test_contaminated_rejects_bad_parameters():
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="law"):
        contaminated(rng, 0.01, 0.2, 0.1, 10, law="cauchy")
    with pytest.raises(ValueError, match="p must be"):
        contaminated(rng, 0.01, 0.2, 1.5, 10)


def test_snr_definition():
    assert snr_db(0.0175, 0.25, 0.0) == pytest.approx(-10 * np.log10(0.0175 ** 2))
    assert snr_db(0.0175, 0.25, 0.3) == pytest.approx(10 * np.log10(1 / (0.7 * 0.0175 ** 2 + 0.3 * 0.0625)))


def test_fisher_information_by_finite_differences_fixed_and_moving():
    p = np.array([141e3, 141e3])
    k = np.arange(9)
    moving = np.column_stack([130e3 + 30e3 * k, 11e3 + 30e3 * k])
    fixed = np.repeat(np.array([[0.0, 0.0], [20e3, 0.0], [30e3, 0.0]]), 5, axis=0)
    for sites in (moving, fixed):
        sig = np.linspace(0.01, 0.03, len(sites))
        h = 1.0
        g = np.column_stack([(bearing(p + d, sites) - bearing(p - d, sites)) / (2 * h) for d in np.eye(2) * h])
        J = (g / sig[:, None] ** 2).T @ g
        np.testing.assert_allclose(fisher_information(p, sites, sig), J, rtol=1e-6)
        assert crb_rmse(p, sites, sig) == pytest.approx(np.sqrt(np.trace(np.linalg.inv(J))), rel=1e-6)


def test_crb_two_orthogonal_bearings_closed_form():
    # a site due west and one due south, at ranges r1, r2: the bound is diag((σ r2)², (σ r1)²)
    p = np.array([0.0, 0.0])
    sites = np.array([[-3e3, 0.0], [0.0, -4e3]])
    C = crb(p, sites, 0.01)
    np.testing.assert_allclose(C, np.diag([(0.01 * 4e3) ** 2, (0.01 * 3e3) ** 2]), rtol=1e-12)


def test_crb_is_undefined_from_one_site_and_series_is_inf_until_observable():
    p = np.array([1e3, 2e3])
    one = np.zeros((5, 2))
    with pytest.raises(ValueError, match="singular"):
        crb(p, one, 0.01)
    s = crb_rmse_series(p, [(np.zeros((1, 2)), 0.01), (np.array([[5e3, 0.0]]), 0.01)])
    assert np.isinf(s[0]) and np.isfinite(s[1])
