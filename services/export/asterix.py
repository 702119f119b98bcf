"""The fused picture as ASTERIX: CAT062 system tracks and CAT065 SDPS status over UDP.

:func:`system_track` is the whole mapping, pure: a fused :class:`~fusion.types.Estimate`
-> a :class:`schemas.asterix.SystemTrack` — time of track (the estimate's time of
validity as a time of day: UTC in a live session, scenario seconds from midnight in a
scenario run), WGS-84 position and geometric altitude (the ENU position through the
site's frame), Cartesian position and velocity in the site's ENU plane (its origin is the
system reference point), and I062/500 from the covariance: σ of x, y, height, vx, vy,
vz (and ax, ay), ``sign(cov_xy)·√|cov_xy|``, and σ of latitude and longitude. An
emitter fix ``[e n]`` or a 2D track ``[e n ve vn]`` has no height and (a fix) no
velocity: those items are left out. zfusion's track ids become CAT062 track numbers
(:class:`TrackNumbers`, 1 … 65535 in order of first appearance).

:class:`AsterixSink` sends each update as it comes (``period_s`` 0) or the whole picture
every ``period_s`` followed by a CAT065 end-of-batch message, and a CAT065 SDPS status
(operational) once a second, in datagrams of at most :data:`DATAGRAM_MAX` octets.
"""

from __future__ import annotations

import math
import time

import numpy as np

from fusion.geodetic import LocalFrame
from fusion.types import Estimate
from schemas import asterix as ax

from .. import geo
from .process import Sink

DATAGRAM_MAX = 1400  # octets: below a 1500-octet Ethernet MTU with IP and UDP headers
STATUS_PERIOD_S = 1.0
NUMBERS = 65535


class TrackNumbers:
    """Track id -> CAT062 track number, 1 … 65535 in order of first appearance, cycling;
    ids of tracks gone from the picture are forgotten once there are twice as many ids
    as live tracks (memory bounded by the picture)."""

    def __init__(self):
        self.numbers: dict[str, int] = {}
        self.next = 1

    def of(self, track: str) -> tuple[int, bool]:
        """(its number, whether it is new)."""
        n = self.numbers.get(track)
        if n is not None:
            return n, False
        n = self.numbers[track] = self.next
        self.next = self.next % NUMBERS + 1
        return n, True

    def forget(self, live: set[str]) -> None:
        if len(self.numbers) > 2 * max(len(live), 64):
            self.numbers = {k: v for k, v in self.numbers.items() if k in live}


def system_track(e: Estimate, frame: LocalFrame, sac: int, sic: int, number: int, first: bool = False,
                 service: int = 1) -> ax.SystemTrack:
    """One fused estimate as a CAT062 record (module docstring)."""
    x, P = np.asarray(e.x, dtype=float), np.asarray(e.P, dtype=float)
    n = x.size
    lat, lon, alt = (float(v) for v in geo.lat_lon_alt(frame, geo.enu3(x)))
    three_d = n >= 6
    sd = np.sqrt(np.clip(np.diag(P), 0.0, None))
    cov = float(P[0, 1])
    acc = dict(apc_x=float(sd[0]), apc_y=float(sd[1]), cov_xy=math.copysign(math.sqrt(abs(cov)), cov))
    if three_d:
        acc = ax.Accuracy.from_covariance(P, lat).__dict__
    else:
        ref = ax.Accuracy.from_covariance(np.diag([P[0, 0], P[1, 1], 0.0, 0.0, 0.0, 0.0]), lat)
        acc.update(apw_lat=ref.apw_lat, apw_lon=ref.apw_lon)
        if n == 4:
            acc.update(atv_x=float(sd[2]), atv_y=float(sd[3]))
    v = geo.velocity(x)
    altitude = alt if three_d and -1500 * 0.3048 <= alt < 150_000 * 0.3048 else None
    ident = e.identity
    # I062/380 ADR is an ICAO 24-bit address: a non-ICAO one ("~" and hex: TIS-B, anonymous) has no place there
    icao = ident is not None and ident.address is not None and len(ident.address) == 6 and ident.address[0] != "~"
    return ax.SystemTrack(
        callsign=ident.callsign if ident is not None else None, address=int(ident.address, 16) if icao else None,
        sac=sac, sic=sic, track_number=number, tod=float(e.t), service=service, lat=lat, lon=lon,
        x=float(x[0]), y=float(x[1]), vx=None if v is None else float(v[0]), vy=None if v is None else float(v[1]),
        status=ax.cat062.TrackStatus(mon=False, src=3 if three_d else 0, tsb=first), altitude=altitude,
        rocd=float(x[5]) if three_d else None, accuracy=ax.Accuracy(**acc))


class AsterixSink(Sink):
    """Sends CAT062 per update (``period_s`` 0) or as a periodic picture, and CAT065."""

    def __init__(self, sender, site, live: bool, sac: int, sic: int, period_s: float = 0.0, service: int = 1,
                 clock=time.monotonic):
        super().__init__(site, live)
        self.sender = sender
        self.sac, self.sic, self.service = sac, sic, service
        self.period_s = period_s
        self.clock = clock
        self.numbers = TrackNumbers()
        self.sent = self.refused = self.batches = 0
        self._batch_at = self._status_at = -math.inf
        self._t = 0.0  # the picture's time (its latest update)

    def _send(self, records: list) -> None:
        for d in ax.encode(records, max_octets=DATAGRAM_MAX):
            self.sent += self.sender.send("asterix", d)

    def _record(self, e: Estimate) -> ax.SystemTrack | None:
        number, first = self.numbers.of(e.track)
        try:
            return system_track(e, self.frame, self.sac, self.sic, number, first, self.service)
        except ValueError:  # beyond what the items can hold (a track thousands of km out)
            self.refused += 1
            return None

    def update(self, table, e: Estimate) -> None:
        self._t = max(self._t, float(e.t))
        if self.period_s <= 0:
            rec = self._record(e)
            if rec is not None:
                self._send([rec])

    def tick(self, table, final: bool = False) -> None:
        now = self.clock()
        if self.period_s > 0 and (final or now - self._batch_at >= self.period_s) and table.tracks:
            self._batch_at = now
            recs = [r for r in map(self._record, table.tracks.values()) if r is not None]
            self.batches += 1
            self._send(recs + [ax.SdpsStatus(self.sac, self.sic, ax.cat065.END_OF_BATCH, self.service, self._t,
                                             batch=self.batches % 256)])
        if final or now - self._status_at >= STATUS_PERIOD_S:
            self._status_at = now
            self.numbers.forget(set(table.tracks))
            self._send([ax.SdpsStatus(self.sac, self.sic, ax.cat065.SDPS_STATUS, self.service, self._t, nogo=0)])

    def counters(self) -> dict[str, float]:
        return {"sent": self.sent, "send_failed": self.sender.failed, "refused": self.refused}

    def close(self) -> None:
        self.sender.close()
