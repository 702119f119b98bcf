r"""Kinematic motion models for 3D targets.

State layout (docs/design.md, Conventions): ``[px py pz vx vy vz ax ay az]`` for constant acceleration
(CA), its first six for constant velocity (CV). The layout is *derivative-major*: index
``3·d + axis`` holds the d-th derivative on ``axis`` (0 = east, 1 = north, 2 = up).
Each axis follows the same independent 1D model, so with a per-axis block ``F₁``,
``Q₁`` (size ``m × m``, m = 2 for CV, 3 for CA)::

    F(dt) = F₁(dt) ⊗ I₃,        Q(dt) = Q₁(dt) ⊗ I₃

Per-axis transition (Taylor series of the m-th order integrator)::

    CV: F₁ = [[1, dt], [0, 1]]
    CA: F₁ = [[1, dt, dt²/2], [0, 1, dt], [0, 0, 1]]

Process noise, two standard families (Bar-Shalom, Li & Kirubarajan 2001, §6.2–6.3):

``noise="continuous"`` — continuous-time white noise on the highest derivative with
power spectral density ``q`` (white-noise acceleration for CV, q in m²/s³; white-noise
jerk for CA, q in m²/s⁵), integrated exactly over dt::

    CV: Q₁ = q [[dt³/3, dt²/2], [dt²/2, dt]]
    CA: Q₁ = q [[dt⁵/20, dt⁴/8, dt³/6], [dt⁴/8, dt³/3, dt²/2], [dt³/6, dt²/2, dt]]

``noise="discrete"`` — discrete white noise (DWNA for CV) / discrete Wiener-process
acceleration (DWPA for CA): a piecewise-constant random increment per step with
variance ``q`` enters through Γ::

    CV: Γ = [dt²/2, dt]ᵀ,  CA: Γ = [dt²/2, dt, 1]ᵀ,   Q₁ = q Γ Γᵀ

Here ``q`` is a per-step variance (m²/s⁴), not a spectral density, and Q₁ has rank
one, so Q is singular (PSD) — that is the model, not a defect.

:meth:`sample` draws the next true state from the very same ``F`` and ``Q``, so a
simulated truth and the filter's model are matched by construction.

``q_up`` (CV and CA; None: ``q``) is the up axis's own ``q``, for targets that hold
their level most of the time (aircraft) while they turn: ``Q(dt) = Q₁(dt) ⊗ diag(1,
1, q_up/q)``, the up axis's block that of ``q_up`` (``q > 0``).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
from scipy.linalg import expm

NOISE_FORMS = ("continuous", "discrete")


_I3 = np.eye(3)


def _kron_i3(A: np.ndarray) -> np.ndarray:
    """``A ⊗ I₃``: ``np.kron(A, np.eye(3))``'s products, element for element, in one
    broadcast multiply (``np.kron``'s argument handling costs ten times the arithmetic
    of a 9 × 9 result, and a filter predicts over a new interval at every plot of a
    rotating radar)."""
    m = A.shape[0]
    return (A[:, None, :, None] * _I3[None, :, None, :]).reshape(3 * m, 3 * A.shape[1])


class KinematicModel:
    """Shared core of :class:`ConstantVelocity` and :class:`ConstantAcceleration`.

    Subclasses set ``order`` (number of per-axis derivatives kept, m) and ``name``.
    """

    order: int
    name: str

    def __init__(self, q: float, noise: str = "continuous", q_up: float | None = None):
        q = float(q)
        if not np.isfinite(q) or q < 0.0:
            raise ValueError(f"process noise q must be finite and >= 0, got {q!r}")
        if noise not in NOISE_FORMS:
            raise ValueError(f"process noise form must be one of {NOISE_FORMS}, got {noise!r}")
        if q_up is not None and not (np.isfinite(q_up) and q_up >= 0.0 and q > 0.0):
            raise ValueError(f"process noise q_up must be finite and >= 0, with q > 0, got {q_up!r} (q={q!r})")
        self.q = q
        self.noise = noise
        self.q_up = None if q_up is None else float(q_up)
        #: the per-axis scale of ``Q₁`` (module docstring): None, or ``[1, 1, q_up/q]``
        self.axis_scale = None if q_up is None else np.array([1.0, 1.0, self.q_up / q])
        self.n_x = 3 * self.order
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}  # dt -> (F, Q), read-only

    def __repr__(self) -> str:
        up = "" if self.q_up is None else f", q_up={self.q_up!r}"
        return f"{type(self).__name__}(q={self.q!r}, noise={self.noise!r}{up})"

    @staticmethod
    def _check_dt(dt: float) -> float:
        dt = float(dt)
        if not np.isfinite(dt) or dt < 0.0:
            raise ValueError(f"time step dt must be finite and >= 0, got {dt!r}")
        return dt

    # Per-axis blocks -------------------------------------------------------------
    def F_axis(self, dt: float) -> np.ndarray:
        """Per-axis transition ``F₁(dt)`` (m × m): ``F₁[i, j] = dt^(j−i)/(j−i)!``."""
        dt = self._check_dt(dt)
        m = self.order
        F1 = np.eye(m)
        term = 1.0
        for k in range(1, m):
            term = term * dt / k  # dt^k / k!
            F1 += term * np.eye(m, k=k)
        return F1

    def noise_gain_axis(self, dt: float) -> np.ndarray | None:
        """Γ for the discrete form (m × 1); ``None`` for the continuous form."""
        if self.noise != "discrete":
            return None
        dt = self._check_dt(dt)
        if self.order == 2:
            return np.array([[0.5 * dt * dt], [dt]])
        return np.array([[0.5 * dt * dt], [dt], [1.0]])

    def Q_axis(self, dt: float) -> np.ndarray:
        """Per-axis process-noise covariance ``Q₁(dt)`` (m × m): ``q Γ Γᵀ`` in the
        discrete form, else :meth:`continuous_Q_axis`."""
        dt = self._check_dt(dt)
        G = self.noise_gain_axis(dt)
        if G is not None:
            return self.q * (G @ G.T)
        return self.continuous_Q_axis(dt)

    def continuous_Q_axis(self, dt: float) -> np.ndarray:
        """``Q₁(dt)`` of continuous white noise of PSD ``q`` on the last derivative."""
        # Continuous white noise on derivative m−1: Q₁[i, j] = q dt^(p_i+p_j+1) /
        # ((p_i+p_j+1) p_i! p_j!) with p = m−1−i the power of dt in F₁'s last column.
        m = self.order
        p = (m - 1) - np.arange(m)
        fact = np.array([1.0, 1.0, 2.0])[p]
        s = p[:, None] + p[None, :] + 1
        return self.q * dt ** s / (s * fact[:, None] * fact[None, :])

    # Full 3D model ---------------------------------------------------------------
    def _FQ(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        # Filters predict over the same few intervals again and again: cache them
        # (bounded; the arrays are read-only so a cached matrix cannot be altered).
        FQ = self._cache.get(dt)
        if FQ is None:
            F = _kron_i3(self.F_axis(dt))
            Q = _kron_i3(self.Q_axis(dt)) if self.axis_scale is None else np.kron(self.Q_axis(dt),
                                                                                   np.diag(self.axis_scale))
            F.setflags(write=False)
            Q.setflags(write=False)
            if len(self._cache) >= 64:
                self._cache.clear()
            FQ = self._cache[float(dt)] = (F, Q)
        return FQ

    def F(self, dt: float) -> np.ndarray:
        """State transition ``F(dt) = F₁(dt) ⊗ I₃`` (n_x × n_x), read-only."""
        return self._FQ(dt)[0]

    def Q(self, dt: float) -> np.ndarray:
        """Process-noise covariance ``Q(dt) = Q₁(dt) ⊗ I₃`` (n_x × n_x; with ``q_up``,
        ``Q₁(dt) ⊗ diag(1, 1, q_up/q)``), read-only."""
        return self._FQ(dt)[1]

    def check_state(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if x.shape[-1] != self.n_x:
            raise ValueError(f"{self.name} state must have {self.n_x} components, got shape {x.shape}")
        return x

    def sample(self, x: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
        """Draw the next true state ``F x + w``, ``w ~ N(0, Q(dt))``.

        ``x`` may be one state (n_x,) or a batch (..., n_x) — e.g. all Monte Carlo runs
        at once; each row gets independent noise from ``rng``.
        """
        x = self.check_state(x)
        F1 = self.F_axis(dt)
        G = self.noise_gain_axis(dt)
        if G is None:
            # Cholesky of the per-axis block, padded for dt = 0 (Q = 0).
            Q1 = self.Q_axis(dt)
            L1 = np.linalg.cholesky(Q1) if dt > 0.0 and self.q > 0.0 else np.zeros_like(Q1)
        else:
            L1 = np.sqrt(self.q) * G
        batch = x.shape[:-1]
        m = self.order
        # Rows of x reshaped to (..., m derivatives, 3 axes): F acts on the derivative index.
        X = x.reshape(*batch, m, 3)
        noise = rng.standard_normal((*batch, L1.shape[1], 3))
        if self.axis_scale is not None:
            noise = noise * np.sqrt(self.axis_scale)
        Xn = np.einsum("ij,...jk->...ik", F1, X) + np.einsum("ij,...jk->...ik", L1, noise)
        return Xn.reshape(*batch, self.n_x)


class ConstantVelocity(KinematicModel):
    """3D constant velocity, state ``[px py pz vx vy vz]``: per axis
    ``F₁ = [[1, dt], [0, 1]]``, process noise white acceleration (``q`` in m²/s³) or
    discrete white-noise acceleration (``q`` in m²/s⁴)."""

    order = 2
    name = "cv"


class ConstantAcceleration(KinematicModel):
    """3D constant acceleration, state ``[px py pz vx vy vz ax ay az]``: per axis
    ``F₁ = [[1, dt, dt²/2], [0, 1, dt], [0, 0, 1]]``, process noise white jerk (``q`` in
    m²/s⁵) or the discrete Wiener-process acceleration (``q`` in m²/s⁴)."""

    order = 3
    name = "ca"


class PaddedConstantVelocity(KinematicModel):
    """Constant velocity on the CA state ``[p v a]`` (an IMM's common state): per axis
    ``F₁ = [[1, dt, 0], [0, 1, 0], [0, 0, 0]]``, so the acceleration is zero after any
    step, and ``Q₁`` is :class:`ConstantVelocity`'s padded with a zero acceleration
    row and column (white acceleration, ``q`` in m²/s³, or ``Γ = [dt²/2, dt, 0]ᵀ`` with
    ``q`` in m²/s⁴)."""

    order = 3
    name = "cv"

    def F_axis(self, dt: float) -> np.ndarray:
        F1 = np.zeros((3, 3))
        F1[:2, :2] = [[1.0, self._check_dt(dt)], [0.0, 1.0]]
        return F1

    def noise_gain_axis(self, dt: float) -> np.ndarray | None:
        if self.noise != "discrete":
            return None
        dt = self._check_dt(dt)
        return np.array([[0.5 * dt * dt], [dt], [0.0]])

    def continuous_Q_axis(self, dt: float) -> np.ndarray:
        Q1 = np.zeros((3, 3))
        Q1[:2, :2] = self.q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
        return Q1


class ConstantTurn(KinematicModel):
    r"""Constant turn at a known rate ω on the CA state ``[p v a]`` (3D, any turn plane).

    A constant-speed turn at rate ω about an axis perpendicular to the velocity has
    ``a = ω × v`` and so ``ȧ = ω × a = −ω² v``: with ``ṗ = v``, ``v̇ = a`` every axis
    follows the same linear system ``A₁ = [[0, 1, 0], [0, 0, 1], [0, −ω², 0]]``
    whatever the turn's direction or plane (the direction is in ``a``)::

        F₁ = exp(A₁ dt) = [[1, sin ωdt / ω, (1 − cos ωdt) / ω²],
                           [0, cos ωdt,     sin ωdt / ω       ],
                           [0, −ω sin ωdt,  cos ωdt           ]]

    ``ω → 0`` is :class:`ConstantAcceleration`. Process noise on ``ȧ``: white jerk of
    PSD ``q`` (m²/s⁵), ``Q₁ = ∫₀^dt e^{A₁s} [0 0 1]ᵀ q [0 0 1] e^{A₁ᵀs} ds`` (Van Loan's
    matrix exponential), or the discrete form with CA's ``Γ = [dt²/2, dt, 1]ᵀ``.
    """

    order = 3
    name = "ct"

    def __init__(self, q: float, turn_rate: float, noise: str = "continuous"):
        turn_rate = float(turn_rate)
        if not np.isfinite(turn_rate) or turn_rate <= 0.0:
            raise ValueError(f"turn rate must be finite and > 0 rad/s, got {turn_rate!r}")
        self.turn_rate = turn_rate
        super().__init__(q, noise)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(q={self.q!r}, turn_rate={self.turn_rate!r}, noise={self.noise!r})"

    def A_axis(self) -> np.ndarray:
        """The per-axis system matrix ``A₁`` (``ẋ = A₁ x`` per axis)."""
        return np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, -self.turn_rate**2, 0.0]])

    def F_axis(self, dt: float) -> np.ndarray:
        dt = self._check_dt(dt)
        w = self.turn_rate
        s, c = np.sin(w * dt), np.cos(w * dt)
        return np.array([[1.0, s / w, (1.0 - c) / w**2], [0.0, c, s / w], [0.0, -w * s, c]])

    def continuous_Q_axis(self, dt: float) -> np.ndarray:
        A = self.A_axis()
        M = np.zeros((6, 6))
        M[:3, :3] = -A
        M[:3, 3:] = np.diag([0.0, 0.0, self.q])
        M[3:, 3:] = A.T
        E = expm(M * dt)
        Q1 = E[3:, 3:].T @ E[:3, 3:]  # Van Loan: F₁ · (upper-right block)
        return 0.5 * (Q1 + Q1.T)


# CoordinatedTurn's per-axis blocks in closed form ------------------------------------
#
# With x = u dt² and θ = √x = ω dt, every entry of F₁, ∂F₁/∂u and Q₁ is a power of dt times
# a product of eight entire functions of x (CoordinatedTurn's docstring). Near x = 0 their
# sin/cos forms cancel catastrophically (relative error ~ε/x, ~ε/x² for h₀₀ and e₂′: 2e-13
# at x = 0.1, 1e-11 at x = 0.01), so below _TURN_SERIES_X they are summed from their Taylor
# series instead, whose truncation error grows with x. Measured against 50-digit
# values on 201 points of x ∈ [0.1, 10], as the largest Frobenius error of F₁, ∂F₁/∂u, Q₁
# relative to its norm at dt = 1 and 10 s: the 12-term series ≤ 4e-16 up to x = 2, 6e-16 to
# 4e-15 on [2, 3), 2e-13 on [3, 4); the closed forms 1e-14 on [0.5, 1), ≤ 2e-15 on [1, 2)
# and ≤ 1e-15 from x = 2 on. The threshold is where they cross.
_TURN_SERIES_X = 2.0
_TURN_SERIES_TERMS = 12


def _turn_series(terms: int) -> np.ndarray:
    """Taylor coefficients of :func:`_turn_primitives`' eight functions in powers of ``−x``
    (8 × terms), from ``eₙ(x) = Σₖ (−x)ᵏ / (2k + n)!``, each computed exactly and rounded once."""
    def a(n, k):
        return Fraction(1, math.factorial(2 * k + n))

    def e(n):  # eₙ
        return [a(n, k) for k in range(terms)]

    def de(n):  # deₙ/dx
        return [-(k + 1) * a(n, k + 1) for k in range(terms)]

    def h(ni, nj):  # ∫₀¹ σ^(ni+nj) e_ni(xσ²) e_nj(xσ²) dσ, the product's series integrated
        return [sum(a(ni, p) * a(nj, k - p) for p in range(k + 1)) / (2 * k + ni + nj + 1)
                for k in range(terms)]

    rows = (e(0), e(1), e(2), de(1), de(2), h(2, 2), h(2, 0), h(1, 1))
    return np.array([[float(c) for c in row] for row in rows])


_TURN_SERIES = _turn_series(_TURN_SERIES_TERMS)
_TURN_POWERS = np.arange(_TURN_SERIES_TERMS)


def _turn_primitives(x: float) -> list[float]:
    """``[e₀, e₁, e₂, e₁′, e₂′, h₀₀, h₀₂, h₁₁]`` at ``x = u dt² ≥ 0`` (CoordinatedTurn's
    docstring): Taylor series below ``_TURN_SERIES_X``, sin/cos of ``θ = √x`` above."""
    if x < _TURN_SERIES_X:
        return (_TURN_SERIES @ np.power(-x, _TURN_POWERS)).tolist()
    t = math.sqrt(x)
    s, c = math.sin(t), math.cos(t)
    e1 = s / t
    one_c = 2.0 * math.sin(0.5 * t) ** 2  # 1 − cos θ, to its last digit also near θ = 2πk
    h11 = (t - s * c) / (2.0 * t * x)
    return [c, e1, one_c / x,
            (t * c - s) / (2.0 * t * x), (t * s - 2.0 * one_c) / (2.0 * x * x),
            (1.5 - 2.0 * e1 + 0.5 * e1 * c) / (x * x), e1 * one_c / x - h11, h11]


def _turn_axis(u: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``F₁(u)``, ``∂F₁/∂u`` and ``Q₁(u)`` for ``q = 1`` over ``dt`` (CoordinatedTurn's docstring)."""
    e0, e1, e2, de1, de2, h00, h02, h11 = _turn_primitives(u * dt * dt)
    t2 = dt * dt
    t3, t4, t5 = t2 * dt, t2 * t2, t2 * t2 * dt
    F1 = np.array([[1.0, dt * e1, t2 * e2],
                   [0.0, e0, dt * e1],
                   [0.0, -u * dt * e1, e0]])
    dF1 = np.array([[0.0, t3 * de1, t4 * de2],
                    [0.0, -0.5 * t2 * e1, t3 * de1],
                    [0.0, -0.5 * dt * (e0 + e1), -0.5 * t2 * e1]])
    q01, q12 = 0.5 * t4 * e2 * e2, 0.5 * t2 * e1 * e1
    Q1 = np.array([[t5 * h00, q01, t3 * h02],
                   [q01, t3 * h11, q12],
                   [t3 * h02, q12, 0.5 * dt * (1.0 + e0 * e1)]])
    return F1, dF1, Q1


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` of two 3-vectors, as ``np.cross`` computes it (which spends ~15 µs a call
    on broadcasting, most of a turn model's step)."""
    a0, a1, a2 = a.tolist()
    b0, b1, b2 = b.tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


class CoordinatedTurn(KinematicModel):
    r"""Coordinated turn at the rate the state itself implies, on the CA state ``[p v a]``.

    A coordinated turn (constant speed, acceleration across the velocity) turns at the rate
    vector ``ω = v × a / |v|²``, and its acceleration rotates with it, ``ȧ = ω × a = −ω² v``.
    Taking the squared rate from the state, ``u(x) = |v × a|² / |v|⁴``, every axis follows
    :class:`ConstantTurn`'s system at that rate, ``A₁(u) = [[0, 1, 0], [0, 0, 1], [0, −u, 0]]``::

        f(x) = (F₁(u(x)) ⊗ I₃) x,        F₁(u) = exp(A₁(u) dt)

    exact for a coordinated turn at any rate and in any plane; at ``a = 0`` (``u = 0``) it is
    :class:`ConstantAcceleration`, i.e. straight flight, with no rate to choose. ``F₁`` is an
    even function of ω, so of ``u``, and ``u`` is smooth wherever ``v ≠ 0`` (quadratic in
    ``a``): the Jacobian exists everywhere, also on straight flight where ``∂u/∂x = 0``::

        ∂f/∂x = F₁(u) ⊗ I₃ + vec(∂F₁/∂u · X) (∂u/∂x)ᵀ,    X = x as (derivative × axis)
        ∂u/∂v = 2 (a × c) / |v|⁴ − 4 |c|² v / |v|⁶,    ∂u/∂a = 2 (c × v) / |v|⁴,    c = v × a

    Process noise: white jerk of PSD ``q`` (m²/s⁵) through ``A₁(u)``,
    ``Q₁ = q ∫₀^dt g(s) g(s)ᵀ ds`` with ``g(s) = e^{A₁s} [0 0 1]ᵀ = [(1 − cos ωs)/ω², sin ωs / ω,
    cos ωs]ᵀ`` (:class:`ConstantTurn`'s integral at the state's rate), or the discrete form
    with CA's ``Γ``. :meth:`F` and :meth:`Q` without a state are the straight-flight ones
    (``u = 0``); a filter predicts with :meth:`transition`.

    All three are closed forms. With ``x = u dt²``, ``θ = √x = ω dt`` and the entire functions
    ``eₙ(x) = Σₖ (−x)ᵏ / (2k + n)!`` (``e₀ = cos θ``, ``e₁ = sin θ / θ``, ``e₂ = (1 − cos θ)/θ²``,
    so ``g(s) = [s² e₂, s e₁, e₀](u s²)``) and their derivatives ``eₙ′ = deₙ/dx``
    (``e₁′ = (θ cos θ − sin θ)/(2θ³)``, ``e₂′ = (θ sin θ − 2(1 − cos θ))/(2θ⁴)``)::

        F₁ = [[1, dt e₁, dt² e₂], [0, e₀, dt e₁], [0, −u dt e₁, e₀]]
        ∂F₁/∂u = [[0, dt³ e₁′, dt⁴ e₂′], [0, −dt² e₁/2, dt³ e₁′], [0, −dt (e₀ + e₁)/2, −dt² e₁/2]]
        Q₁ / q = [[dt⁵ h₀₀, dt⁴ e₂²/2, dt³ h₀₂], [·, dt³ h₁₁, dt² e₁²/2], [·, ·, dt (1 + e₀ e₁)/2]]
        h₀₀ = (3/2 − 2 e₁ + e₀ e₁ / 2)/θ⁴,   h₁₁ = (θ − sin θ cos θ)/(2θ³),   h₀₂ = e₁ e₂ − h₁₁

    (``∂/∂u = dt² d/dx``, and ``2 eₙ′ = n eₙ₊₂ − eₙ₊₁`` gives ``e₀′ = −e₁/2`` and
    ``d(x e₁)/dx = (e₀ + e₁)/2``; in ``Q₁``, ``g₀′ = g₁`` and ``g₁′ = g₂`` make
    ``∫ g₀ g₁ = g₀(dt)²/2``, ``∫ g₁ g₂ = g₁(dt)²/2`` and ``∫ g₀ g₂ = g₀ g₁ − ∫ g₁²``). The sin/cos
    forms of ``e₂, e₁′, e₂′, h₀₀, h₀₂, h₁₁`` lose ``~1/x`` to ``~1/x²`` of their digits to
    cancellation as ``x → 0`` (1e-11 relative at ``x = 0.01``), so below ``x = 2`` all eight
    are summed from their Taylor series in ``x`` instead (12 terms; ``h₀₀``, ``h₀₂``, ``h₁₁``
    are ``g``'s products' series integrated), each branch where it is the more accurate: F₁,
    ∂F₁/∂u and Q₁ are within ~1e-15 of their norm for every ``u ≥ 0`` and ``dt`` (scipy's
    ``expm`` of the Van Loan matrices, used before, was off by up to 1e-11 at ``x`` ~ 36),
    and ``u = 0`` gives :class:`ConstantAcceleration`'s ``F₁`` and ``Q₁`` to rounding.
    """

    order = 3
    name = "turn"

    @staticmethod
    def rate2(x: np.ndarray) -> float:
        """``u = |v × a|² / |v|⁴``, the squared turn rate of a coordinated turn through ``x``."""
        v, a = x[3:6], x[6:9]
        c = _cross(v, a)
        vv = float(v @ v)
        return float(c @ c) / (vv * vv) if vv > 0.0 else 0.0

    @staticmethod
    def rate2_gradient(x: np.ndarray) -> np.ndarray:
        """``∂u/∂x`` (9,), zero on the position block."""
        v, a = x[3:6], x[6:9]
        c = _cross(v, a)
        vv = float(v @ v)
        g = np.zeros(9)
        if vv > 0.0:
            g[3:6] = 2.0 * _cross(a, c) / vv**2 - 4.0 * float(c @ c) * v / vv**3
            g[6:9] = 2.0 * _cross(c, v) / vv**2
        return g

    def _axis(self, u: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``F₁(u)``, ``∂F₁/∂u`` and this model's ``Q₁(u)`` over ``dt``."""
        F1, dF1, Q1 = _turn_axis(u, dt)
        G = self.noise_gain_axis(dt)
        return F1, dF1, self.q * (Q1 if G is None else G @ G.T)

    def F_axis(self, dt: float) -> np.ndarray:
        return _turn_axis(0.0, self._check_dt(dt))[0]

    def continuous_Q_axis(self, dt: float) -> np.ndarray:
        return self.q * _turn_axis(0.0, dt)[2]

    def transition(self, x: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(f(x), ∂f/∂x, Q)`` over ``dt`` at the state's own rate (class docstring)."""
        x = self.check_state(x)
        dt = self._check_dt(dt)
        u = self.rate2(x)
        F1, dF1, Q1 = self._axis(u, dt)
        X = x.reshape(3, 3)
        J = _kron_i3(F1) + np.outer((dF1 @ X).reshape(9), self.rate2_gradient(x))
        return (F1 @ X).reshape(9), J, _kron_i3(Q1)


MOTION_MODELS = {"cv": ConstantVelocity, "ca": ConstantAcceleration}


def make_motion(name: str, q: float, noise: str = "continuous", q_up: float | None = None) -> KinematicModel:
    """Build a motion model by name (``"ca"`` or ``"cv"``)."""
    try:
        cls = MOTION_MODELS[name]
    except KeyError:
        raise ValueError(f"motion model must be one of {sorted(MOTION_MODELS)}, got {name!r}") from None
    return cls(q, noise, q_up)
