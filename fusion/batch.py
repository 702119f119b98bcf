r"""The EKF step of :mod:`fusion.ekf` over many tracks at once (vectorised numpy).

Same maths as :func:`fusion.ekf.ekf_predict` / :func:`~fusion.ekf.ekf_update`
(:mod:`fusion.kalman`: angle-wrapped innovation, Joseph form, symmetrised, NIS), on a
stack of ``N`` tracks: ``x`` is ``(N, n_x)``, ``P`` is ``(N, n_x, n_x)``. One call
replaces ``N`` calls of the single-track path and equals it to round-off. Typical use:
many tracks updated at one scan, or every Monte Carlo run of a scenario advanced together.

Predict with one ``F``, ``Q`` for the whole stack, ``(F P) Fᵀ`` as one BLAS product of the
stacked rows. A spherical measurement depends on position only, ``H = [H_p  0]``, so
``H P = H_p P[:3, :]`` and ``S = (H P)[:, :3] H_pᵀ + R``, and the Joseph product is two
rank-``n_z`` corrections (still the Joseph form, not the "optimal gain" shortcut)::

    Kᵀ = S⁻¹ (H P)
    B  = (I − K H) P  = P − K (H P)
    P⁺ = B (I − K H)ᵀ + K R Kᵀ = B + (K R − B[:, :3] H_pᵀ) Kᵀ

``S⁻¹`` comes from a Cholesky factorisation written over the stack (one vector operation
per row of ``S`` over all tracks), every product has contiguous operands, and the large
temporaries are reused work arrays (:func:`_scratch`); ``benchmarks/README.md`` has the
figures. Singular geometry (a target straight above a site for an angle row, or at a
site for a range row) raises ``ValueError`` naming the first offending track; an
innovation covariance that is not positive definite raises ``LinAlgError``.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import numpy as np

from .angles import TWO_PI, wrap_pi
from .measurement.models import MIN_HORIZONTAL_RANGE, MIN_RANGE, SphericalModel

__all__ = ["BatchUpdate", "predict", "ekf_predict", "spherical", "innovation", "update", "ekf_update",
           "ekf_step"]


class BatchUpdate(NamedTuple):
    """Per-track results of :func:`update`: :class:`fusion.kalman.UpdateResult`, stacked."""

    x: np.ndarray  # (N, n_x)
    P: np.ndarray  # (N, n_x, n_x)
    nu: np.ndarray  # (N, n_z)
    S: np.ndarray  # (N, n_z, n_z)
    nis: np.ndarray  # (N,)
    K: np.ndarray  # (N, n_x, n_z)


# Helpers -----------------------------------------------------------------------------
_SCRATCH = threading.local()
_SCRATCH_MAX_BYTES = 16 << 20  # larger stacks allocate per call (and are not held on to)


def _scratch(slot: str, shape: tuple[int, ...]) -> np.ndarray:
    """A reusable work array (one per slot and thread) for a large temporary of one call.

    glibc hands a freed block of a few hundred kB back to the system (heap trimming), so
    a fresh (N, n, n) temporary each call would come back page by page. The contents
    never outlive the call that fills them.
    """
    store = getattr(_SCRATCH, "arrays", None)
    if store is None:
        store = _SCRATCH.arrays = {}
    a = store.get(slot)
    if a is None or a.shape != shape:
        a = np.empty(shape)
        if a.nbytes <= _SCRATCH_MAX_BYTES:
            store[slot] = a
    return a


def _symmetrise(P: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``(P + Pᵀ) / 2`` for every matrix of a stack."""
    out = np.add(P, P.swapaxes(-1, -2), out=out)
    out *= 0.5
    return out


def _T(A: np.ndarray) -> np.ndarray:
    """Contiguous transpose of every matrix of a stack (for fast stacked products)."""
    return np.ascontiguousarray(A.swapaxes(-1, -2))


def _check_stack(x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.ascontiguousarray(x, dtype=float)
    P = np.ascontiguousarray(P, dtype=float)
    if x.ndim != 2 or P.shape != (x.shape[0], x.shape[1], x.shape[1]):
        raise ValueError(f"expected x of shape (N, n) and P of shape (N, n, n), got {x.shape} and {P.shape}")
    return x, P


# Predict -----------------------------------------------------------------------------
def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (symmetrised) for every track.

    ``F``, ``Q`` are one ``(n, n)`` pair shared by the stack, or one per track ``(N, n, n)``.
    """
    x, P = _check_stack(x, P)
    F = np.asarray(F, dtype=float)
    Q = np.asarray(Q, dtype=float)
    N, n = x.shape
    FP = np.matmul(F, P, out=_scratch("a", P.shape))
    if F.ndim == 2:
        xp = x @ F.T
        # (F P) Fᵀ for all tracks at once: the stacked rows of F P times Fᵀ, one BLAS call.
        FPFt = np.matmul(FP.reshape(N * n, n), np.ascontiguousarray(F.T),
                         out=_scratch("b", P.shape).reshape(N * n, n)).reshape(N, n, n)
    else:
        xp = (F @ x[:, :, None])[:, :, 0]
        FPFt = np.matmul(FP, _T(F), out=_scratch("b", P.shape))
    FPFt += Q
    return xp, _symmetrise(FPFt, out=np.empty_like(P))


def ekf_predict(motion, x: np.ndarray, P: np.ndarray, dt) -> tuple[np.ndarray, np.ndarray]:
    """Time update of every track with a motion model (its ``F(dt)``, ``Q(dt)``).

    ``dt`` is one interval for all tracks, or one per track ``(N,)``: tracks are grouped
    by ``dt``, each group predicted with the model's own (cached) matrices — the very ones
    the single-track path uses. Tracks with ``dt == 0`` are returned untouched, as
    :func:`fusion.ekf.ekf_predict` does.
    """
    x, P = _check_stack(x, P)
    dt = np.asarray(dt, dtype=float)
    if dt.ndim == 0:
        if dt == 0.0:
            return x, P
        return predict(x, P, motion.F(float(dt)), motion.Q(float(dt)))
    if dt.shape != (x.shape[0],):
        raise ValueError(f"dt must be a scalar or one per track ({x.shape[0]},), got shape {dt.shape}")
    xp, Pp = x.copy(), P.copy()
    for d in np.unique(dt):
        if d == 0.0:
            continue
        sel = np.flatnonzero(dt == d)
        xp[sel], Pp[sel] = predict(x[sel], P[sel], motion.F(float(d)), motion.Q(float(d)))
    return xp, Pp


# Measurement model -------------------------------------------------------------------
def spherical(model: SphericalModel, x: np.ndarray, sites: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Predicted measurements ``h(x)`` (N, n_z) and position gradients ``H_p`` (N, n_z, 3).

    The rows are the model's components (az/el/range, formulas of
    :mod:`fusion.measurement.models`); ``sites`` (N, n_z, 3) replaces the model's sites per track
    (e.g. one model shared by tracks seen from different places). The full Jacobian is
    ``[H_p  0]``.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 2 or x.shape[1] != model.n_x:
        raise ValueError(f"expected states of shape (N, {model.n_x}), got {x.shape}")
    N, n_z = x.shape[0], model.n_z
    s = model.sites if sites is None else np.asarray(sites, dtype=float)
    if s.shape not in ((n_z, 3), (N, n_z, 3)):
        raise ValueError(f"sites must be ({n_z}, 3) or ({N}, {n_z}, 3), got {s.shape}")
    per_track = s.ndim == 3
    pe, pn, pu = x[:, 0], x[:, 1], x[:, 2]
    zp = np.empty((N, n_z))
    Hp = np.zeros((N, n_z, 3))
    for i, code in enumerate(model.codes.tolist()):  # a few rows: loop over rows, vectorise over tracks
        si = s[:, i] if per_track else s[i]
        de = pe - si[..., 0]
        dn = pn - si[..., 1]
        du = pu - si[..., 2]
        rho = np.hypot(de, dn)
        if code == 2:  # range
            r = np.hypot(rho, du)
            _check_geometry(r, MIN_RANGE, "target at a sensor site (zero range < {} m): range gradient undefined")
            zp[:, i] = r
            Hp[:, i, 0] = de / r
            Hp[:, i, 1] = dn / r
            Hp[:, i, 2] = du / r
            continue
        _check_geometry(rho, MIN_HORIZONTAL_RANGE, "target straight above/below a sensor site (horizontal range "
                        "< {} m): azimuth/elevation undefined")
        if code == 0:  # azimuth
            az = np.mod(np.arctan2(de, dn), TWO_PI)
            zp[:, i] = np.where(az >= TWO_PI, 0.0, az)
            rho2 = rho * rho
            Hp[:, i, 0] = dn / rho2
            Hp[:, i, 1] = -de / rho2
        else:  # elevation
            r = np.hypot(rho, du)
            zp[:, i] = np.arctan2(du, rho)
            rr = rho * (r * r)
            Hp[:, i, 0] = -de * du / rr
            Hp[:, i, 1] = -dn * du / rr
            Hp[:, i, 2] = rho / (r * r)
    return zp, Hp


def _check_geometry(v: np.ndarray, limit: float, why: str) -> None:
    if v.min() < limit:
        raise ValueError(f"track {int(np.flatnonzero(v < limit)[0])}: " + why.format(limit))


def innovation(model: SphericalModel, z: np.ndarray, zp: np.ndarray) -> np.ndarray:
    """``z − h(x)`` per track, the model's angular rows wrapped to (−π, π]."""
    z = np.asarray(z, dtype=float)
    if z.shape != zp.shape:
        raise ValueError(f"measurements must have shape {zp.shape} for {model.components}, got {z.shape}")
    nu = z - zp
    for i in np.flatnonzero(model.angles).tolist():
        nu[:, i] = wrap_pi(nu[:, i])
    return nu


# Update ------------------------------------------------------------------------------
def _spd_inverse(S: np.ndarray) -> np.ndarray:
    """Inverse of every SPD ``S`` (N, m, m) through its Cholesky factor ``L``, vectorised over
    the stack: ``S⁻¹ = L⁻ᵀ L⁻¹``. Raises ``LinAlgError`` if some ``S`` is not positive definite."""
    N, m, _ = S.shape
    if m > 8:  # not the small case this is written for
        np.linalg.cholesky(S)  # the positive-definiteness check
        return np.linalg.inv(S)
    s = S.transpose(1, 2, 0)  # s[i, j] is the (N,) vector of S[:, i, j]
    L = [[None] * m for _ in range(m)]
    for j in range(m):
        d = s[j, j].copy()
        for k in range(j):
            d -= L[j][k] * L[j][k]
        if not np.all(d > 0.0):
            raise np.linalg.LinAlgError(f"track {int(np.flatnonzero(~(d > 0.0))[0])}: innovation covariance "
                                        "is not positive definite")
        L[j][j] = np.sqrt(d)
        inv = 1.0 / L[j][j]
        for i in range(j + 1, m):
            v = s[i, j].copy()
            for k in range(j):
                v -= L[i][k] * L[j][k]
            L[i][j] = v * inv
    W = [[None] * m for _ in range(m)]  # W = L⁻¹, lower triangular
    for i in range(m):
        W[i][i] = 1.0 / L[i][i]
        for j in range(i):
            acc = L[i][j] * W[j][j]
            for k in range(j + 1, i):
                acc = acc + L[i][k] * W[k][j]
            W[i][j] = -acc * W[i][i]
    out = np.empty((N, m, m))
    for i in range(m):  # S⁻¹ = Wᵀ W
        for j in range(i + 1):
            acc = W[i][i] * W[i][j]
            for k in range(i + 1, m):
                acc = acc + W[k][i] * W[k][j]
            out[:, i, j] = acc
            out[:, j, i] = acc
    return out


def update(x: np.ndarray, P: np.ndarray, nu: np.ndarray, Hp: np.ndarray, R: np.ndarray) -> BatchUpdate:
    """Measurement update of every track given innovations ``nu`` (N, n_z), already wrapped,
    and position gradients ``Hp`` (N, n_z, 3), i.e. ``H = [Hp 0]``; Joseph form, NIS.

    ``R`` is one ``(n_z, n_z)`` for all tracks or one per track ``(N, n_z, n_z)``.
    """
    x, P = _check_stack(x, P)
    nu = np.asarray(nu, dtype=float)
    Hp = np.asarray(Hp, dtype=float)
    R = np.asarray(R, dtype=float)
    N, n = x.shape
    if P.shape[0] == 0:
        raise ValueError("empty stack of tracks")
    n_z = nu.shape[-1]
    if nu.shape != (N, n_z) or Hp.shape != (N, n_z, 3) or R.shape[-2:] != (n_z, n_z) or n < 3:
        raise ValueError(f"shapes do not agree: x {x.shape}, nu {nu.shape}, Hp {Hp.shape}, R {R.shape}")
    HpT = _T(Hp)  # (N, 3, n_z)
    HP = Hp @ P[:, :3, :]  # H P = (P Hᵀ)ᵀ, (N, n_z, n)
    S = _symmetrise(HP[:, :, :3] @ HpT + R)
    Si = _spd_inverse(S)
    KT = Si @ HP  # Kᵀ = S⁻¹ H P (the single path: cho_solve(S, (P Hᵀ)ᵀ))
    K = _T(KT)  # (N, n, n_z)
    nis = np.sum(nu * (Si @ nu[:, :, None])[:, :, 0], axis=1)
    x_new = x + (K @ nu[:, :, None])[:, :, 0]
    B = np.matmul(K, HP, out=_scratch("a", P.shape))
    np.subtract(P, B, out=B)  # B = (I − K H) P
    if R.ndim == 2 and np.count_nonzero(R) == np.count_nonzero(np.diagonal(R)):
        KR = K * np.diagonal(R)  # independent rows (diagonal R): K R without a product
    else:
        KR = K @ R
    KR -= B[:, :, :3] @ HpT  # K R − (B Hᵀ)
    B += np.matmul(KR, KT, out=_scratch("b", P.shape))  # B (I − K H)ᵀ + K R Kᵀ
    P_new = _symmetrise(B, out=np.empty_like(P))
    return BatchUpdate(x_new, P_new, nu, S, nis, K)


def ekf_update(model: SphericalModel, x: np.ndarray, P: np.ndarray, z: np.ndarray,
               sites: np.ndarray | None = None, R: np.ndarray | None = None) -> BatchUpdate:
    """EKF update of every track with one measurement each (``z`` (N, n_z)), linearised at
    each track's ``x``: the batched :func:`fusion.ekf.ekf_update`.

    All tracks share the model's components; ``sites`` (N, n_z, 3) and ``R`` (N, n_z, n_z)
    optionally replace its sites and noise per track.
    """
    x, P = _check_stack(x, P)
    zp, Hp = spherical(model, x, sites)
    return update(x, P, innovation(model, z, zp), Hp, model.R if R is None else R)


CHUNK = 1024  # tracks per pass of ekf_step: its work arrays then stay in a core's cache


def ekf_step(motion, model: SphericalModel, x: np.ndarray, P: np.ndarray, dt, z: np.ndarray,
             sites: np.ndarray | None = None, R: np.ndarray | None = None) -> BatchUpdate:
    """:func:`ekf_predict` over ``dt`` then :func:`ekf_update` with ``z``: one EKF cycle per track.

    Large stacks go through in passes of :data:`CHUNK` tracks (same results; beyond a few
    thousand tracks one pass would spill the work arrays out of cache).
    """
    x, P = _check_stack(x, P)
    N = x.shape[0]
    if N <= CHUNK:
        xp, Pp = ekf_predict(motion, x, P, dt)
        return ekf_update(model, xp, Pp, z, sites, R)
    z = np.asarray(z, dtype=float)
    dt = np.asarray(dt, dtype=float)
    sites = None if sites is None else np.asarray(sites, dtype=float)
    R = None if R is None else np.asarray(R, dtype=float)
    parts = []
    for a in range(0, N, CHUNK):
        sl = slice(a, min(a + CHUNK, N))
        xp, Pp = ekf_predict(motion, x[sl], P[sl], dt if dt.ndim == 0 else dt[sl])
        parts.append(ekf_update(model, xp, Pp, z[sl], sites if sites is None or sites.ndim == 2 else sites[sl],
                                R if R is None or R.ndim == 2 else R[sl]))
    return BatchUpdate(*(np.concatenate(f) for f in zip(*parts)))
