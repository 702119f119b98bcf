"""The gateway core, sans I/O: readings of a device in, checked wire messages out.

Both gateways (:mod:`~services.ingest.krakensdr`, :mod:`~services.ingest.jsonl`) turn
what a device says into :class:`Reading` records and hand them to :class:`Gateway`,
which decides everything that protects the fuser: the sensor must be in the site
file with that measurement kind and stated std, its site is the site file's (a fixed
station) or the message's (a mobile one, converted to the site's ENU frame), its time
must be on the UTC time base (not more than ``max_skew`` ahead of the gateway's clock,
not older than ``max_age``) and after what it already promised. Each accepted reading
becomes a measurement message, validated by :func:`schemas.encode_measurement`,
followed by a watermark just below its time (another detection of the same scan may
still follow). :meth:`Gateway.tick` publishes *heartbeat* watermarks at ``now − lag``
so that a fuser never waits for a quiet sensor (squelch closed): a reading that
arrives after its time was promised is ``late`` and dropped, as is anything that fails
a check, counted per cause and logged once per cause (:class:`services.node.RejectLog`).

A kind that reports a position (not *sited*, :mod:`fusion.measurement.kinds`) may give
it in geodetic coordinates: it is converted to the site's ENU frame, and its stated
covariance turned from the ENU axes at that position into the frame's
(:meth:`fusion.geodetic.LocalFrame.rotation_from`). A kind whose reports state their own
noise (``own_noise``) is published with the reading's std and correlations (the site
file's std when the reading states none), not checked against the site file's.

An identical repeat of a reading (a device page polled twice between two updates) is
not published again, nor refused again: it is counted as ``repeats``.

The clock is a parameter (``now``, UTC seconds): the process passes ``time.time()``,
tests pass what they want. Memory: per sensor, its last time, watermark and the
digests of the readings offered (at most :data:`MAX_DIGESTS`, then forgotten at once:
a repeat of a forgotten reading is refused as ``late``, once).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from fusion.geodetic import LocalFrame
from fusion.measurement.kinds import KINDS
from fusion.types import Identity, Measurement
from schemas import KeySpace, SchemaError, encode, encode_measurement

MAX_DIGESTS = 4096


@dataclass(frozen=True)
class Rejected:
    """A line or document that cannot be used. ``cause`` is short and stable (counters)."""

    cause: str
    detail: str


#: what a decoder (``json.loads``, an XML parser) raises on a document it cannot read:
#: malformed or not UTF-8 (``ValueError``, which ``UnicodeDecodeError`` is), nested
#: deeper than the interpreter's recursion limit, or too big to hold
DECODE_ERRORS = (ValueError, RecursionError, MemoryError)


def undecodable(e: BaseException, fmt: str) -> Rejected:
    """The refusal of a document whose decoder raised ``e`` (one of :data:`DECODE_ERRORS`),
    by cause: ``too-deep`` (recursion), ``too-large`` (memory), ``encoding`` (not UTF-8),
    else ``fmt`` (not valid JSON, XML, ...)."""
    cause = ("too-deep" if isinstance(e, RecursionError) else "too-large" if isinstance(e, MemoryError)
             else "encoding" if isinstance(e, UnicodeError) else fmt)
    return Rejected(cause, f"not {fmt} ({type(e).__name__}: {str(e)[:80]})")


@dataclass(frozen=True, eq=False)
class SensorSite:
    """What the site file says of one sensor: measurement ``kind``, stated ``std`` (SI,
    in the kind's component order), its ENU ``site``, or None: from the messages, and its
    nominal ``period`` (s), which sizes its publisher's recovery cache."""

    id: str
    kind: str
    std: np.ndarray
    site: np.ndarray | None = None
    period: float = 1.0


@dataclass(frozen=True, eq=False)
class Reading:
    """One measurement as a device gave it, in SI units and compass azimuth.

    ``std`` None: the site file's. Position: ``site`` (ENU m) or ``geodetic``
    (lat °, lon °, alt m or None), or neither; used only for a sensor the site file
    does not pin. A position report (a kind that is not sited) has no site: ``geodetic``
    is then the reported position, and ``z`` None. ``corr``: the stated correlation
    matrix of a kind whose reports state their own noise. ``identity``: what a
    cooperative target says it is (a position report's address and callsign), or None.
    """

    sensor: str
    t: float
    kind: str
    z: np.ndarray | None
    std: np.ndarray | None = None
    site: np.ndarray | None = None
    geodetic: tuple[float, float, float | None] | None = None
    corr: np.ndarray | None = None
    identity: Identity | None = None

    def digest(self) -> tuple:
        def values(a):
            return None if a is None else tuple(np.asarray(a, float).ravel().tolist())
        return (self.kind, values(self.z), values(self.std), values(self.site), self.geodetic, values(self.corr),
                self.identity)


@dataclass
class _Stream:
    """Per-sensor state: what was published, what was promised."""

    seq: int = 0
    wm_seq: int = 0
    last_t: float = -math.inf
    watermark: float = -math.inf
    seen: set = field(default_factory=set)  # (t, digest) of readings offered


class Gateway:
    """Checks readings and builds the messages to publish, ``(key, bytes)``.

    Args:
        sensors: the site file's sensors this gateway publishes for.
        frame: the site's ENU frame (degrees), for positions given in lat/lon.
        keys: the deployment's key space.
        reject: counts and logs rejections (``reject(src, cause, detail)``).
        max_skew: seconds a time stamp may be ahead of the clock.
        max_age: seconds a time stamp may be behind it.
        lag: heartbeat watermarks are at ``now − lag``; 0: no heartbeats.
    """

    def __init__(self, sensors: Mapping[str, SensorSite], frame: LocalFrame, keys: KeySpace, reject,
                 max_skew: float = 5.0, max_age: float = 60.0, lag: float = 2.0):
        self.sensors = dict(sensors)
        self.frame = frame
        self.keys = keys
        self.reject = reject
        self.max_skew, self.max_age, self.lag = max_skew, max_age, lag
        self.streams = {s: _Stream() for s in self.sensors}
        self.counters = {"received": 0, "published": 0, "repeats": 0, "watermarks": 0}

    def refuse(self, sensor: str, cause: str, detail: str) -> list:
        self.reject(sensor, cause, detail)
        return []

    def offer(self, r: Reading, now: float) -> list[tuple[str, bytes]]:
        """One reading -> the measurement and watermark to publish (or nothing)."""
        self.counters["received"] += 1
        spec = self.sensors.get(r.sensor)
        if spec is None:
            return self.refuse(r.sensor, "unknown-sensor", f"{r.sensor!r} is not a sensor of the site file "
                                                           f"(this gateway has {', '.join(self.sensors)})")
        if r.kind != spec.kind:
            return self.refuse(r.sensor, "kind-mismatch", f"{r.sensor} is a {spec.kind} sensor, the reading "
                                                          f"is {r.kind}")
        own_noise = KINDS[r.kind].own_noise
        if r.std is not None and (np.shape(r.std) != np.shape(spec.std)
                                  or not (own_noise or np.allclose(r.std, spec.std, rtol=1e-9, atol=0.0))):
            return self.refuse(r.sensor, "std-mismatch", f"{r.sensor} states std {spec.std.tolist()} in the "
                                                         f"site file, the reading says {np.asarray(r.std).tolist()}")
        if not math.isfinite(r.t):
            return self.refuse(r.sensor, "non-finite", f"time {r.t!r}")
        st = self.streams[r.sensor]
        digest = (r.t, r.digest())
        if digest in st.seen:  # the same reading again (published or refused before)
            self.counters["repeats"] += 1
            return []
        if len(st.seen) >= MAX_DIGESTS:
            st.seen.clear()
        st.seen.add(digest)
        if r.t > now + self.max_skew:
            return self.refuse(r.sensor, "future", f"t = {r.t:.3f} is {r.t - now:.1f} s ahead of this clock "
                                                   f"(max {self.max_skew:g} s): is the device's clock set?")
        if r.t < now - self.max_age:
            return self.refuse(r.sensor, "stale", f"t = {r.t:.3f} is {now - r.t:.1f} s old (max "
                                                  f"{self.max_age:g} s): is the device's clock set?")
        if r.t <= st.watermark:
            return self.refuse(r.sensor, "late", f"t = {r.t:.3f} is not after what was already promised "
                                                 f"({st.watermark:.3f}); out of order, or later than the "
                                                 f"heartbeat lag ({self.lag:g} s) allows")
        std = r.std if own_noise and r.std is not None else spec.std
        corr = r.corr if own_noise else None
        try:
            if KINDS[r.kind].sited:
                z, site = r.z, self._site(spec, r)
            else:  # a position report
                (z, std, corr), site = self._position(r, std, corr), spec.site if spec.site is not None else np.zeros(3)
        except ValueError as e:
            return self.refuse(r.sensor, "position", f"{r.sensor}: {e}")
        if site is None:
            return self.refuse(r.sensor, "no-position", f"{r.sensor} has no site in the site file and the "
                                                        f"reading gives none (no GPS fix?)")
        m = Measurement(t=float(r.t), sensor=r.sensor, kind=r.kind, z=np.asarray(z, dtype=float), std=std,
                        site=site, seq=st.seq + 1, corr=corr, identity=r.identity)
        try:
            data = encode_measurement(m, r.sensor)
        except (SchemaError, ValueError, TypeError) as e:
            return self.refuse(r.sensor, getattr(e, "cause", "value"), str(e))
        st.seq += 1
        st.last_t = r.t
        self.counters["published"] += 1
        key = self.keys.meas(r.sensor)
        return [(key, data), *self._watermark(r.sensor, math.nextafter(r.t, -math.inf))]

    def tick(self, now: float) -> list[tuple[str, bytes]]:
        """Heartbeat watermarks at ``now − lag`` for every sensor (none with ``lag`` 0:
        the watermarks follow the data alone, e.g. a replay)."""
        if not self.lag > 0:
            return []
        out = []
        for s in self.sensors:
            out.extend(self._watermark(s, now - self.lag))
        return out

    def promise(self, sensor: str, t: float) -> list[tuple[str, bytes]]:
        """A watermark at ``t`` for ``sensor``: the device itself says that nothing of
        this time or older will follow (a rotating radar's sector crossing)."""
        return self._watermark(sensor, t) if math.isfinite(t) else []

    def flush(self) -> list[tuple[str, bytes]]:
        """Watermarks at each sensor's last time: what was sent is complete (the end of
        an input)."""
        return [kv for s, st in self.streams.items() for kv in self._watermark(s, st.last_t)]

    def end(self, t: float) -> list[tuple[str, bytes]]:
        """Final watermarks: every sensor's stream has ended (a scenario run's senders are
        done), each at ``t`` or what it already sent or promised, if later."""
        return [kv for s, st in self.streams.items()
                for kv in self._watermark(s, max(t, st.last_t, st.watermark), final=True)]

    def _watermark(self, sensor: str, t: float, final: bool = False) -> list[tuple[str, bytes]]:
        st = self.streams[sensor]
        if not (t > st.watermark or final and t == st.watermark):
            return []
        st.watermark = t
        st.wm_seq += 1
        self.counters["watermarks"] += 1
        return [(self.keys.meas(sensor), encode("watermark", sensor, st.wm_seq, t, final=final))]

    def _position(self, r: Reading, std: np.ndarray, corr: np.ndarray | None):
        """A position report's ``(z, std, corr)`` in the site's frame: as given (ENU), or
        from geodetic, its noise ``C = D ρ D`` turned by ``T = R(origin) R(position)ᵀ``."""
        if r.geodetic is None:
            return r.z, std, corr
        lat, lon, alt = r.geodetic
        z = self.frame.to_enu(lat, lon, self.frame.alt0 if alt is None else alt)
        T = self.frame.rotation_from(lat, lon)
        std = np.asarray(std, dtype=float)
        C = np.outer(std, std) * (np.eye(std.size) if corr is None else corr)
        C = T @ C @ T.T
        s = np.sqrt(np.diag(C))
        rho = 0.5 * (C + C.T) / np.outer(s, s)
        np.fill_diagonal(rho, 1.0)
        return z, s, rho

    def _site(self, spec: SensorSite, r: Reading) -> np.ndarray | None:
        if spec.site is not None:
            return spec.site
        if r.site is not None:
            return np.asarray(r.site, dtype=float)
        if r.geodetic is not None:
            lat, lon, alt = r.geodetic
            return self.frame.to_enu(lat, lon, self.frame.alt0 if alt is None else alt)
        return None


def sensor_sites(site, ids: list[str]) -> dict[str, SensorSite]:
    """The :class:`SensorSite` of each id from a loaded site (or scenario); ValueError
    naming what is missing."""
    out = {}
    for sid in ids:
        spec = site.sensors.get(sid)
        if spec is None:
            raise ValueError(f"sensor {sid!r} is not in the site file (it has "
                             f"{', '.join(site.sensors) or 'no sensors'}); add [sensors.{sid}]")
        # A site file's mobile station (site = "messages") has none; a scenario's flight path is
        # taken as mobile too: the messages say where it is.
        pos = spec.site.points[0].copy() if spec.site is not None and spec.site.fixed else None
        out[sid] = SensorSite(sid, spec.measurement_kind, np.asarray(spec.std, dtype=float), pos, spec.period)
    return out


def local_frame(site) -> LocalFrame:
    lat, lon, alt = site.origin
    return LocalFrame(lat, lon, alt, deg=True)


__all__ = ["Gateway", "Reading", "Rejected", "SensorSite", "sensor_sites", "local_frame"]
