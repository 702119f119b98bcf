"""Single-track EKF kernels the benchmark compares with the project's path (not used by
the project): a lean numpy step hand-specialised to one 3D radar (3 × 3 innovation
covariance inverted in closed form, no positive-definiteness check), a lower bound for
any numpy formulation, and, when numba is installed, the same step compiled.

All compute one predict + update of the 9-state CA model with one spherical
measurement ``[az, el, range]`` from one site, Joseph form, NIS — the maths of
:func:`fusion.ekf.ekf_predict` + :func:`~fusion.ekf.ekf_update`. The
benchmark checks each against the project's path before timing it.
"""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi
_I9 = np.eye(9)


def lean_step(x, P, F, Q, site, r_diag, z):
    """The single-track step with ~25 numpy calls, specialised to this one case.

    Beyond what the project's path does (the geometry in Python floats, one numpy
    Cholesky), it uses the position-only Jacobian as a 3 × 3 block and inverts the 3 × 3
    innovation covariance in closed form, without the checks (positive definite,
    singular geometry) and without the general ``n_z``/``n_x`` of the shared core.
    """
    xp = F @ x
    Pp = F @ P @ F.T + Q
    Pp = 0.5 * (Pp + Pp.T)
    de, dn, du = (xp[0] - site[0], xp[1] - site[1], xp[2] - site[2])
    rho2 = de * de + dn * dn
    rho = math.sqrt(rho2)
    r2 = rho2 + du * du
    r = math.sqrt(r2)
    az = math.atan2(de, dn) % TWO_PI
    el = math.atan2(du, rho)
    n0 = (z[0] - az + math.pi) % TWO_PI - math.pi
    nu = np.array([n0 if n0 != -math.pi else math.pi, z[1] - el, z[2] - r])
    Hp = np.array([[dn / rho2, -de / rho2, 0.0],
                   [-de * du / (rho * r2), -dn * du / (rho * r2), rho / r2],
                   [de / r, dn / r, du / r]])
    HP = Hp @ Pp[:3]  # H P (3 × 9)
    S = HP[:, :3] @ Hp.T
    S[0, 0] += r_diag[0]
    S[1, 1] += r_diag[1]
    S[2, 2] += r_diag[2]
    (a, b, c), (_, e, f), (_, _, i) = S.tolist()  # symmetric: closed-form inverse
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * A + b * B + c * C
    Si = np.array([[A, B, C], [B, a * i - c * c, b * c - a * f], [C, b * c - a * f, a * e - b * b]]) / det
    KT = Si @ HP
    K = KT.T
    x_new = xp + K @ nu
    IKH = _I9.copy()
    IKH[:, :3] -= K @ Hp
    P_new = IKH @ Pp @ IKH.T + (K * r_diag) @ KT
    P_new = 0.5 * (P_new + P_new.T)
    nis = float(nu @ Si @ nu)
    return x_new, P_new, nis


def numba_kernels():
    """``(step, batch_step)`` compiled with numba, or ``None`` if numba is not installed."""
    try:
        import numba
    except ImportError:
        return None

    @numba.njit(cache=False, fastmath=False)
    def step_into(x, P, F, Q, site, r_diag, z, x_out, P_out):
        n = 9
        xp = np.zeros(n)
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += F[i, j] * x[j]
            xp[i] = s
        FP = np.zeros((n, n))
        for i in range(n):
            for k in range(n):
                f = F[i, k]
                if f != 0.0:
                    for j in range(n):
                        FP[i, j] += f * P[k, j]
        Pp = np.zeros((n, n))
        for i in range(n):
            for j in range(n):
                s = Q[i, j]
                for k in range(n):
                    s += FP[i, k] * F[j, k]
                Pp[i, j] = s
        for i in range(n):
            for j in range(i):
                v = 0.5 * (Pp[i, j] + Pp[j, i])
                Pp[i, j] = v
                Pp[j, i] = v
        de = xp[0] - site[0]
        dn = xp[1] - site[1]
        du = xp[2] - site[2]
        rho2 = de * de + dn * dn
        rho = math.sqrt(rho2)
        r2 = rho2 + du * du
        r = math.sqrt(r2)
        az = math.atan2(de, dn) % TWO_PI
        el = math.atan2(du, rho)
        nu = np.empty(3)
        n0 = (z[0] - az + math.pi) % TWO_PI - math.pi
        nu[0] = math.pi if n0 == -math.pi else n0
        nu[1] = z[1] - el
        nu[2] = z[2] - r
        Hp = np.empty((3, 3))
        Hp[0, 0] = dn / rho2
        Hp[0, 1] = -de / rho2
        Hp[0, 2] = 0.0
        Hp[1, 0] = -de * du / (rho * r2)
        Hp[1, 1] = -dn * du / (rho * r2)
        Hp[1, 2] = rho / r2
        Hp[2, 0] = de / r
        Hp[2, 1] = dn / r
        Hp[2, 2] = du / r
        HP = np.zeros((3, n))
        for a in range(3):
            for b in range(3):
                h = Hp[a, b]
                for j in range(n):
                    HP[a, j] += h * Pp[b, j]
        S = np.empty((3, 3))
        for a in range(3):
            for b in range(3):
                s = 0.0
                for c in range(3):
                    s += HP[a, c] * Hp[b, c]
                S[a, b] = s
        for a in range(3):
            S[a, a] += r_diag[a]
        for a in range(3):
            for b in range(a):
                v = 0.5 * (S[a, b] + S[b, a])
                S[a, b] = v
                S[b, a] = v
        a_, b_, c_, e_, f_, i_ = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
        A_, B_, C_ = e_ * i_ - f_ * f_, c_ * f_ - b_ * i_, b_ * f_ - c_ * e_
        det = a_ * A_ + b_ * B_ + c_ * C_
        if not det > 0.0:
            raise ValueError("innovation covariance is not positive definite")
        Si = np.empty((3, 3))
        Si[0, 0], Si[0, 1], Si[0, 2] = A_ / det, B_ / det, C_ / det
        Si[1, 0], Si[1, 1], Si[1, 2] = B_ / det, (a_ * i_ - c_ * c_) / det, (b_ * c_ - a_ * f_) / det
        Si[2, 0], Si[2, 1], Si[2, 2] = C_ / det, (b_ * c_ - a_ * f_) / det, (a_ * e_ - b_ * b_) / det
        KT = np.zeros((3, n))
        for a in range(3):
            for b in range(3):
                s_ = Si[a, b]
                for j in range(n):
                    KT[a, j] += s_ * HP[b, j]
        for i in range(n):
            s = xp[i]
            for a in range(3):
                s += KT[a, i] * nu[a]
            x_out[i] = s
        # Joseph: B = P − K (H P); P⁺ = B + (K R − B[:, :3] Hpᵀ) Kᵀ
        B = Pp.copy()
        for i in range(n):
            for a in range(3):
                k = KT[a, i]
                for j in range(n):
                    B[i, j] -= k * HP[a, j]
        M = np.empty((n, 3))
        for i in range(n):
            for a in range(3):
                s = KT[a, i] * r_diag[a]
                for c in range(3):
                    s -= B[i, c] * Hp[a, c]
                M[i, a] = s
        for i in range(n):
            for j in range(n):
                s = B[i, j]
                for a in range(3):
                    s += M[i, a] * KT[a, j]
                P_out[i, j] = s
        for i in range(n):
            for j in range(i):
                v = 0.5 * (P_out[i, j] + P_out[j, i])
                P_out[i, j] = v
                P_out[j, i] = v
        nis = 0.0
        for a in range(3):
            for b in range(3):
                nis += nu[a] * Si[a, b] * nu[b]
        return nis

    @numba.njit(cache=False)
    def step(x, P, F, Q, site, r_diag, z):
        x_out = np.empty(9)
        P_out = np.empty((9, 9))
        nis = step_into(x, P, F, Q, site, r_diag, z, x_out, P_out)
        return x_out, P_out, nis

    @numba.njit(cache=False)
    def batch_step(x, P, F, Q, site, r_diag, z):
        N = x.shape[0]
        x_out = np.empty_like(x)
        P_out = np.empty_like(P)
        nis = np.empty(N)
        for t in range(N):
            nis[t] = step_into(x[t], P[t], F, Q, site, r_diag, z[t], x_out[t], P_out[t])
        return x_out, P_out, nis

    return step, batch_step
