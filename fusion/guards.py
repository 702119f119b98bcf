r"""What every estimator guarantees of the estimates it emits, on any valid input.

A live fuser may see any sequence of valid measurements: a replay dated a year back and
then live data, a station alone for an hour and then a second one. Two rules keep what
it emits a valid estimate (one the wire carries: :mod:`schemas.messages`).

**A track is started afresh** — re-initialised from the measurements at hand, exactly
as at its first scan or epoch — instead of predicted and updated when

* the time since its state (its last update or coast) exceeds ``max_gap_s``, a
  ``[tracker]`` key of every method (default :data:`MAX_GAP_S` = 600 s), or
* after an update its covariance is not positive definite (:func:`positive_definite`).

A prediction over a gap ``Δt`` adds the process noise ``Q(Δt)``; with constant
acceleration its position variance grows as ``q Δt⁵/20``, which at ``q = 0.01`` is
(2 km)² after 100 s, (200 km)² after 10 min and (5·10⁷ km)² after a day: the prediction is
worth nothing, and ``F P Fᵀ`` in float64 loses positive definiteness (a track predicted
across a day, then updated, had a negative variance; its next update raised). The
initialiser's priors are what a track that old should start from. Ten minutes is far
beyond any revisit of the built-in scenarios (the longest, a moving observer's bearings
every 300 s) and far below where the numbers break.

**An epoch's NIS** sums the normalised innovation squares of at most
:data:`NIS_MAX_DOF` = 64 degrees of freedom, its latest terms (:func:`epoch_nis`): for a
consistent filter a χ² variable of that many dof, and never more than the wire carries
(an estimate's ``nis_dof`` is at most 64). A DF filter starting up from hundreds of held
bearings still reports a valid statistic.

docs/reliability.md ("The fuser never dies on data") lists these with their tests.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from . import linalg

#: default ``max_gap_s`` (s): a track not updated for longer is started afresh
MAX_GAP_S = 600.0
#: the most degrees of freedom an estimate's NIS sums (the wire's limit on ``nis_dof``)
NIS_MAX_DOF = 64


def positive_definite(P: np.ndarray) -> bool:
    """Whether the symmetric covariance ``P`` is finite and positive definite to working
    precision: a positive diagonal and a Cholesky factor of ``D^-1/2 P D^-1/2`` (``D`` its
    diagonal; the test the track-fusion rules' inverses apply)."""
    P = np.asarray(P, dtype=float)
    d = np.diagonal(P)
    if not np.isfinite(P).all() or not (d > 0.0).all():
        return False
    s = 1.0 / np.sqrt(d)
    try:
        linalg.cholesky(P * s[:, None] * s[None, :])
    except np.linalg.LinAlgError:
        return False
    return True


def gap_too_long(gap: float, max_gap: float) -> bool:
    """Whether a track whose state is ``gap`` seconds older than the new data must be
    started afresh rather than predicted (module docstring)."""
    return gap > max_gap


def epoch_nis(terms: Iterable[tuple[float, int]]) -> tuple[float | None, int | None]:
    """``(NIS, dof)`` of an epoch from its ``(nis, dof)`` terms in processing order: the
    sum over the latest terms whose dofs total at most :data:`NIS_MAX_DOF`; ``(None,
    None)`` without a term. Below the limit, the plain sum in order."""
    kept: list[tuple[float, int]] = []
    dof = 0
    for nis, k in reversed(list(terms)):
        if dof + k > NIS_MAX_DOF:
            break
        kept.append((nis, k))
        dof += k
    if not kept:
        return None, None
    return float(sum(nis for nis, _ in reversed(kept))), dof
