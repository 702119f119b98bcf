r"""Associators: which plots each track took, from one scan's :class:`~fusion.tracking.hypotheses.Hypotheses`.

An :class:`Associator` answers with an :class:`Assignment` (each track takes at most
one plot, each plot goes to at most one track) or with :class:`Weights` (each track's
association probabilities ``βⱼ`` over the plots in its gate and ``β₀`` that it made none
of them, for a PDA update): both say, per track, ``(columns, β, β₀)``, and which plots
are *used* (no new track starts from them).

(JIPDA, the weighted one with track existence: :class:`fusion.tracking.jipda.JIPDA`.)

*Global nearest neighbour* (:class:`GNN`, :func:`gnn`): the least-cost assignment with
one "miss" column of cost ``G`` per track, ``linear_sum_assignment`` on ``[D | diag(G)]``,
pairs outside the gate forbidden. Confirmed tracks are assigned first, then tentative
ones over the plots left, so a young track's broad gate cannot take a plot from an
established one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Protocol

import numpy as np
from scipy.optimize import linear_sum_assignment

from .hypotheses import Hypotheses

#: ``(row, columns, β, β₀)``: what one track took from one scan
RowTaken = tuple[int, tuple[int, ...], tuple[float, ...], float]


@dataclass(frozen=True)
class Assignment:
    """A hard association of one scan: ``pairs`` of (row, column), each row and each
    column at most once. Every pair has ``β = 1`` and ``β₀ = 0``."""

    pairs: tuple[tuple[int, int], ...] = ()

    existence = None  # an assignment updates no existence (see Weights.existence)

    @property
    def used(self) -> frozenset[int]:
        return frozenset(c for _, c in self.pairs)

    def per_row(self) -> Iterator[RowTaken]:
        for r, c in self.pairs:
            yield r, (c,), (1.0,), 0.0


@dataclass(frozen=True)
class Weights:
    """A probabilistic association of one scan (PDA, JPDA, JIPDA).

    Attributes:
        beta: ``(rows, plots)`` ``βⱼ``: the probability that the row's target made plot
            ``j`` (0 outside its gate).
        miss: ``(rows,)`` ``β₀``: the probability that it made none of them (missed or
            absent); ``beta[r].sum() + miss[r] = 1``.
        used: the plots no new track may start from.
        existence: ``(rows,)`` each row's probability that its target exists after the
            scan, from an associator that updates it (JIPDA), else None; the tracker
            hands it to the rows' track logic.
        claimed: ``(plots,)`` the probability that some row's target made each plot,
            from an associator that weighs existence (JIPDA), else None: a new track
            started from plot ``j`` exists with its birth existence times ``1 − claimedⱼ``.
    """

    beta: np.ndarray
    miss: np.ndarray
    used: frozenset[int] = frozenset()
    existence: np.ndarray | None = None
    claimed: np.ndarray | None = None

    def per_row(self) -> Iterator[RowTaken]:
        """Rows with a plot of positive weight."""
        for r in range(len(self.miss)):
            cols = np.flatnonzero(self.beta[r] > 0.0)
            if len(cols):
                yield r, tuple(int(c) for c in cols), tuple(float(b) for b in self.beta[r, cols]), float(self.miss[r])


class Associator(Protocol):
    """Decides one scan from its hypotheses: an :class:`Assignment` or :class:`Weights`."""

    def associate(self, hyp: Hypotheses) -> Assignment | Weights: ...


@dataclass(frozen=True)
class GNN:
    """Global nearest neighbour (module docstring).

    Args:
        confirmed_first: assign the confirmed rows first, then the others over the
            plots left (else all rows at once).
    """

    confirmed_first: bool = True

    def associate(self, hyp: Hypotheses) -> Assignment:
        n, m = hyp.d2.shape
        tiers = [r for r in range(n)], []
        if self.confirmed_first:
            tiers = [r for r in range(n) if hyp.confirmed[r]], [r for r in range(n) if not hyp.confirmed[r]]
        free = list(range(m))
        pairs: list[tuple[int, int]] = []
        for rows in tiers:
            if not rows or not free:
                continue
            found = gnn(hyp.d2[np.ix_(rows, free)], hyp.gate[rows])
            pairs += [(rows[r], free[c]) for r, c in found]
            used = {free[c] for _, c in found}
            free = [j for j in free if j not in used]
        return Assignment(tuple(pairs))


def gnn(d2: np.ndarray, gate) -> list[tuple[int, int]]:
    """Least-cost assignment of tracks (rows) to plots (columns) from their ``d²``: each
    track takes at most one plot and each plot goes to at most one track, a track left
    without a plot costs its ``gate`` (one for all rows, or one per row), and pairs
    outside it are forbidden.

    Returns the assigned ``(row, column)`` pairs in row order; a row not listed is a
    missed track, a column not listed a plot no track takes.
    """
    d2 = np.atleast_2d(np.asarray(d2, dtype=float))
    n, m = d2.shape
    if n == 0 or m == 0:
        return []
    gate = np.broadcast_to(np.asarray(gate, dtype=float), (n,))
    allowed = d2 <= gate[:, None]
    if not allowed.any():
        return []
    # Forbidden pairs cost more than every track missing (n·G): never chosen over a miss.
    big = float(gate.max()) * (n + 1) + 1.0
    cost = np.full((n, m + n), big)
    cost[:, :m] = np.where(allowed, d2, big)
    cost[np.arange(n), m + np.arange(n)] = gate
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if c < m and allowed[r, c]]

