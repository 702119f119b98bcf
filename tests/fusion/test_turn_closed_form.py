"""The coordinated-turn model's closed forms (fusion/motion.py, ``CoordinatedTurn``): ``F₁(u)``,
``∂F₁/∂u`` and ``Q₁(u)`` against the Van Loan matrix exponentials they replaced (kept here as
the reference) over turn rates from 0 to 0.2 rad/s and steps from 1e-4 to 60 s, both sides of
the series / sin-cos threshold included; ``∂F₁/∂u`` against a central difference of ``F₁`` in
``u``; ``Q₁`` symmetric positive definite; ``u = 0`` the constant-acceleration model; and the
two branches agreeing where both are accurate."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

import fusion.motion as motion
from fusion.motion import ConstantAcceleration, CoordinatedTurn

X0 = motion._TURN_SERIES_X
U_MAX = 0.2**2
# u = ω² from 0 through the rates a filter meets, (0.2 rad/s)² at most; dt from 1e-4 s to 60 s
US = [0.0, 1e-12, 1e-10, 1e-8, 1e-6, 1e-5, 1e-4, 1e-3, 4e-3, 1e-2, 2e-2, U_MAX]
DTS = [1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0, 2.0, 4.0, 7.0, 10.0, 20.0, 30.0, 60.0]
# x = u dt² around the branch threshold, on both sides, at three steps
NEAR = [X0 * (1.0 + r) for r in (-0.5, -0.1, -1e-3, -1e-9, -1e-15, 0.0, 1e-15, 1e-9, 1e-3, 0.1, 0.5)]
GRID = ([(u, dt) for u in US for dt in DTS]
        + [(x / dt**2, dt) for dt in (7.5, 10.0, 60.0) for x in NEAR if x / dt**2 <= U_MAX])


def van_loan(u: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference: ``F₁``, ``∂F₁/∂u`` (upper-right block of ``exp([[A₁, ∂A₁/∂u], [0, A₁]] dt)``)
    and ``Q₁`` for ``q = 1`` (Van Loan's ``exp([[−A₁, e₃e₃ᵀ], [0, A₁ᵀ]] dt)``), as the model
    computed them with scipy's ``expm`` before its closed forms."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -u, 0.0]])
    M = np.zeros((6, 6))
    M[:3, :3] = M[3:, 3:] = A
    M[2, 4] = -1.0
    E = expm(M * dt)
    F1, dF1 = E[:3, :3], E[:3, 3:]
    M = np.zeros((6, 6))
    M[:3, :3] = -A
    M[2, 5] = 1.0
    M[3:, 3:] = A.T
    E = expm(M * dt)
    Q1 = E[3:, 3:].T @ E[:3, 3:]
    return F1, dF1, 0.5 * (Q1 + Q1.T)


def scaled(u: float, dt: float, F1, dF1, Q1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The three blocks with the powers of ``dt`` divided out (``D = diag(dt², dt, 1)``:
    ``D⁻¹ F₁ D``, ``D⁻¹ ∂F₁/∂u D / dt²``, ``D⁻¹ Q₁ D⁻¹ / dt``), every entry a function of
    ``x = u dt²`` of order one, so that a Frobenius comparison weighs the small entries
    (``Q₁[0, 0] = dt⁵/20`` at ``u = 0``) as much as the large."""
    d = np.array([dt * dt, dt, 1.0])
    Dl, Dr = 1.0 / d[:, None], d[None, :]
    return F1 * Dl * Dr, dF1 * Dl * Dr / dt**2, Q1 * Dl / Dr / dt


def rel_err(a: np.ndarray, b: np.ndarray, floor: float = 1e-300) -> float:
    """``‖a − b‖ / ‖b‖`` (Frobenius), or the absolute error where ``‖b‖`` is below ``floor``."""
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), floor))


def closed(u: float, dt: float, q: float = 1.0):
    return CoordinatedTurn(q)._axis(u, dt)


def test_closed_forms_equal_the_van_loan_exponentials():
    """Within 1e-9 of the reference per matrix (Frobenius, relative), both as they are and
    with the powers of dt divided out; at dt = 0 exactly ``I``, 0, 0."""
    worst = np.zeros(6)
    for u, dt in GRID:
        got, ref = closed(u, dt), van_loan(u, dt)
        errs = [rel_err(a, b) for a, b in zip(got, ref)]
        errs += [rel_err(a, b) for a, b in zip(scaled(u, dt, *got), scaled(u, dt, *ref))]
        assert max(errs) <= 1e-9, (u, dt, errs)
        worst = np.maximum(worst, errs)
    print("worst relative errors (F₁, ∂F₁/∂u, Q₁; then dt-scaled):", worst)
    F1, dF1, Q1 = closed(0.01, 0.0)
    np.testing.assert_array_equal(F1, np.eye(3))
    np.testing.assert_array_equal(dF1, 0.0)
    np.testing.assert_array_equal(Q1, 0.0)
    # q scales Q₁ only
    for u, dt in [(0.0, 3.0), (1e-3, 3.0), (U_MAX, 30.0)]:
        F1, dF1, Q1 = closed(u, dt, q=2.5)
        np.testing.assert_array_equal(F1, closed(u, dt)[0])
        np.testing.assert_allclose(Q1, 2.5 * closed(u, dt)[2], rtol=1e-15)


def test_rate_derivative_is_the_central_difference():
    """``∂F₁/∂u`` within 1e-7 (dt-scaled, Frobenius) of ``(F₁(u + h) − F₁(u − h)) / 2h`` with
    a step of 1e-4 of ``x = u dt²`` (or of 1 where x < 1; F₁ is analytic in u, also below 0)."""
    for u, dt in GRID:
        if dt == 0.0:
            continue
        h = 1e-4 * max(u, 1.0 / dt**2)
        fd = (closed(u + h, dt)[0] - closed(u - h, dt)[0]) / (2.0 * h)
        got = closed(u, dt)[1]
        err = rel_err(scaled(u, dt, got, got, got)[1], scaled(u, dt, fd, fd, fd)[1])
        assert err <= 1e-7, (u, dt, err)


def test_process_noise_is_symmetric_positive_definite():
    """``Q₁`` is exactly symmetric, and positive definite: with the powers of dt divided out
    (a Gram matrix of three independent functions) its least eigenvalue is positive, and
    the unscaled one is above −1e-15 of the largest."""
    for u, dt in GRID:
        Q1 = closed(u, dt)[2]
        np.testing.assert_array_equal(Q1, Q1.T)
        assert np.linalg.eigvalsh(scaled(u, dt, Q1, Q1, Q1)[2]).min() > 0.0, (u, dt)
        w = np.linalg.eigvalsh(Q1)
        assert w.min() >= -1e-15 * w.max(), (u, dt, w)


@pytest.mark.parametrize("dt", [0.0, 1e-4, 0.01, 0.5, 1.0, 3.0, 7.0, 60.0])
def test_straight_flight_is_constant_acceleration(dt):
    """At ``u = 0`` (:meth:`F_axis`, :meth:`Q_axis` and :meth:`transition` of a state with
    ``a = 0``) ``F₁`` and ``Q₁`` are :class:`ConstantAcceleration`'s to 1e-15, entry by entry,
    and ``∂F₁/∂u`` is its series' leading term ``[[0, −dt³/6, −dt⁴/24], [0, −dt²/2, −dt³/6],
    [0, −dt, −dt²/2]]``."""
    ct, ca = CoordinatedTurn(2.0), ConstantAcceleration(2.0)
    np.testing.assert_allclose(ct.F_axis(dt), ca.F_axis(dt), rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(ct.Q_axis(dt), ca.Q_axis(dt), rtol=1e-15, atol=0.0)
    x = np.array([10.0, -20.0, 3000.0, 180.0, -60.0, 2.0, 0.0, 0.0, 0.0])
    fx, J, Q = ct.transition(x, dt)
    np.testing.assert_allclose(J, ca.F(dt), rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(Q, ca.Q(dt), rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(fx, ca.F(dt) @ x, rtol=1e-15, atol=0.0)
    dF1 = closed(0.0, dt)[1]
    want = -np.array([[0.0, dt**3 / 6, dt**4 / 24], [0.0, dt**2 / 2, dt**3 / 6], [0.0, dt, dt**2 / 2]])
    np.testing.assert_allclose(dF1, want, rtol=1e-15, atol=0.0)


def test_series_and_sin_cos_branches_agree_around_the_threshold(monkeypatch):
    """Either side of the threshold, both branches are accurate: forced to one and then the
    other, the eight functions differ by less than 1e-14 of their size (1e-15 absolute where
    they cross zero) for x from X0/2 to 1.25 X0, and the model's own choice is one of them."""
    xs = np.linspace(0.5 * X0, 1.25 * X0, 31)
    for x in xs:
        monkeypatch.setattr(motion, "_TURN_SERIES_X", np.inf)
        series = np.array(motion._turn_primitives(x))
        monkeypatch.setattr(motion, "_TURN_SERIES_X", 0.0)
        sincos = np.array(motion._turn_primitives(x))
        monkeypatch.setattr(motion, "_TURN_SERIES_X", X0)
        np.testing.assert_allclose(sincos, series, rtol=1e-14, atol=1e-15, err_msg=f"x = {x}")
        chosen = np.array(motion._turn_primitives(x))
        np.testing.assert_array_equal(chosen, series if x < X0 else sincos)
