"""The two value types that cross every boundary of the library.

A :class:`Measurement` is what a sensor reports; an :class:`Estimate` is what a
tracker or fuser reports. Both are plain, immutable records in SI units and the
conventions of :mod:`fusion.angles`. ``schemas/`` maps them to and from the wire.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Identity:
    """Who a cooperative target says it is: its ICAO 24-bit address (six lower-case hex
    digits, or a non-ICAO address as the source gives it) and its flight identification
    (callsign). Either may be unknown (None). An identity is a claim, not a proof: a
    tracker may use it to prefer an association, never to merge what the gate keeps apart.
    """

    address: str | None = None
    callsign: str | None = None


@dataclass(frozen=True, eq=False)
class Measurement:
    """One report of one sensor.

    Attributes:
        t: time of validity, seconds of scenario time.
        sensor: id of the reporting sensor.
        kind: a measurement kind (:data:`fusion.measurement.kinds.KINDS`).
        z: measured values in the order of the kind's components; azimuth is
            compass azimuth in [0, 2π), elevation in [-π/2, π/2], range in metres.
        std: the stated noise standard deviation per component.
        site: ENU position (3,) of the sensor at ``t`` (moves for airborne sensors).
        seq: the sensor's message counter; ``(t, sensor, seq)`` orders a stream.
        corr: the stated correlation matrix of the noise (n_z × n_z, unit diagonal), for
            a kind whose reports state one; None: uncorrelated components.
        identity: the target's own claim of who it is (a position report's address and
            callsign), or None.
    """

    t: float
    sensor: str
    kind: str
    z: np.ndarray
    std: np.ndarray
    site: np.ndarray
    seq: int = 0
    corr: np.ndarray | None = None
    identity: Identity | None = None

    @property
    def R(self) -> np.ndarray:
        """The noise covariance: ``diag(std²)``, or ``σᵢ σⱼ ρᵢⱼ`` with a stated ``corr``."""
        std = np.asarray(self.std, dtype=float)
        if self.corr is None:
            return np.diag(std**2)
        return np.outer(std, std) * np.asarray(self.corr, dtype=float)

    @property
    def order_key(self) -> tuple[float, str, int]:
        return (self.t, self.sensor, self.seq)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Measurement):
            return NotImplemented
        return (
            self.t == other.t
            and self.sensor == other.sensor
            and self.kind == other.kind
            and self.seq == other.seq
            and np.array_equal(self.z, other.z)
            and np.array_equal(self.std, other.std)
            and np.array_equal(self.site, other.site)
            and (self.corr is None) == (other.corr is None)
            and (self.corr is None or np.array_equal(self.corr, other.corr))
            and self.identity == other.identity
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Estimate:
    """A state estimate with its covariance, as produced by a tracker or fuser.

    Attributes:
        t: time of validity.
        x: state vector; 3D targets ``[px py pz vx vy vz (ax ay az)]``, emitters ``[px py]``.
        P: full covariance of ``x``.
        method: the method that produced it (``SS``, ``HNV``, ``EKF``, ...).
        node: the producing node (a sensor's local tracker id, or ``centre``).
        track: track id.
        nis: normalised innovation squared of the update that produced it, if any.
        nis_dof: degrees of freedom of that NIS.
        existence: the probability that the track's target exists, from a tracker that
            holds one (JIPDA), else None.
        identity: the identity the track's target claims (from position reports that
            carry one), else None.
    """

    t: float
    x: np.ndarray
    P: np.ndarray
    method: str
    node: str = "centre"
    track: str = "T1"
    nis: float | None = None
    nis_dof: int | None = None
    extra: dict = field(default_factory=dict)
    existence: float | None = None
    identity: Identity | None = None
