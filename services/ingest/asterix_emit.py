"""ASTERIX out of an emulated sensor, sans I/O: what a radar or an ADS-B ground station at
a scenario's site would send, so that a scenario runs end to end through
``zfusion ingest asterix`` (``zfusion sensor --asterix``; ``docs/asterix.md``).

The inverse of :class:`services.ingest.asterix.AsterixFeed`, written with its pieces:
a radar measurement becomes the CAT048 plot :meth:`Radar.plot` makes of it (the plot's
``(θ, ρ)`` at the radar from the site-frame measurement, a 3D plot's height in I048/110),
so what the gateway reads back is the measurement on the items' grid (θ 360°/2¹⁶,
ρ 1/256 NM, height 25 ft, time 1/128 s). A rotating radar's sector (a
:class:`sensors_sim.emulators.Batch`, complete when the beam leaves it at ``t1``) goes out
as the radar sends it: the CAT034 sector crossing at ``t1`` (and the north marker when
``t1`` is a north crossing), then the sector's plots. So crossing ``k`` comes before the
plots of the sector it closes, and promises, ``sector_lag`` = 1 crossing later, only
plots already sent. After the last sector two more crossings go out (the antenna keeps
turning; nothing more was seen), so the gateway can promise the last plots too. A
snapshot radar (a whole scan at one time) sends per scan one CAT034 north marker at the
scan's time (with the scan period in I034/041), then the scan's plots; the marker of
scan ``k`` promises everything before it, and one more marker a period after the last
scan promises the last plots.

An ADS-B ground station's ``position`` measurement (the site-frame ENU point) becomes a
CAT021 report: WGS-84 position (I021/131), geometric height (I021/140), the NACp and GVA
whose σ (the ADS-B gateways' rules, :mod:`services.ingest.adsb`) is nearest the station's
stated σ, MOPS version 2, and a 24-bit address made from the target's id (an emulated
aircraft has none; it stays one address for one target).

Times: ``stamp(t)`` maps the scenario's time to the wire's (UTC in a live run, else
scenario seconds: a time of day from midnight). A datagram holds at most
:data:`DATAGRAM_MAX` octets.
"""

from __future__ import annotations

import math
import zlib
from typing import Callable, Iterable

import numpy as np

from fusion.geodetic import LocalFrame
from schemas import asterix as ax

from . import adsb
from .asterix import Radar, radars, stations
from .gateway import local_frame

DATAGRAM_MAX = 1400  # octets: below a 1500-octet Ethernet MTU with IP and UDP headers
TRAILING_CROSSINGS = 2  # after the last sector: enough for a gateway with sector_lag 1 to promise it


class RadarEmitter:
    """One radar's measurements -> CAT048 plots and CAT034 crossings (module
    docstring). ``unencodable`` counts plots the items cannot hold."""

    def __init__(self, radar: Radar, period: float, sectors: int = 0, start: float = 0.0):
        self.radar = radar
        self.period, self.sectors, self.start = period, sectors, start
        self.unencodable = 0
        self._boundary: int | None = None  # the last crossing sent

    def _crossings(self, k: int, tod: float) -> list[ax.ServiceMessage]:
        """Crossing ``k`` (a snapshot radar: scan ``k``) at ``tod``: a rotating radar's
        sector crossing, and the north marker when it is north; a snapshot radar's
        north marker."""
        sac, sic = self.radar.sac_sic
        out = [ax.ServiceMessage(sac, sic, ax.SECTOR_CROSSING, tod=tod,
                                 sector=2 * math.pi * (k % self.sectors) / self.sectors)] if self.sectors else []
        if not self.sectors or k % self.sectors == 0:
            out.append(ax.ServiceMessage(sac, sic, ax.NORTH_MARKER, tod=tod, sector=0.0,
                                         rotation_period=self.period))
        self._boundary = k
        return out

    def _boundary_at(self, t1: float) -> int | None:
        """The crossing (or scan) at ``t1``, None inside a sector (the scenario's end)."""
        per = self.period / (self.sectors or 1)
        k = round((t1 - self.start) / per)
        return k if math.isclose(self.start + k * per, t1, rel_tol=0.0, abs_tol=1e-9) else None

    def records(self, t1: float, events: Iterable, stamp: Callable[[float], float]) -> list:
        """One batch (a sector closed at ``t1``, or a scan) -> its records."""
        out: list = []
        k = self._boundary_at(t1)
        if k is not None:
            out.extend(self._crossings(k, stamp(t1)))
        out.extend(_encodable(self, events, ax.cat048, lambda ev, m: self.radar.plot(m.z, stamp(m.t))))
        return out

    def end(self, stamp: Callable[[float], float]) -> list[tuple[float, list]]:
        """``(scenario time, records)`` of the crossings after the last sector (the
        marker after a snapshot radar's last scan)."""
        if self._boundary is None:
            return []
        out = []
        for k in range(self._boundary + 1, self._boundary + 1 + (TRAILING_CROSSINGS if self.sectors else 1)):
            t = self.start + k * self.period / (self.sectors or 1)
            out.append((t, self._crossings(k, stamp(t))))
        return out


def _encodable(emitter, events: Iterable, category, record: Callable) -> list:
    """``record(event, measurement)`` of each event with a measurement that ``category``
    can encode; the others (a value beyond its item: counted here, not when packed) are
    counted in ``emitter.unencodable``."""
    out = []
    for ev in events:
        if ev.measurement is None:
            continue
        try:
            rec = record(ev, ev.measurement)
            category.encode(rec)
        except ValueError:
            emitter.unencodable += 1
            continue
        out.append(rec)
    return out


def _nearest(table: dict[int, float], std: float) -> int:
    return min(table, key=lambda c: (abs(math.log(table[c] / std)), c))


class StationEmitter:
    """One ADS-B ground station's ``position`` measurements -> CAT021 reports (module
    docstring)."""

    def __init__(self, sac_sic: tuple[int, int], frame: LocalFrame, std: np.ndarray):
        self.sac_sic = tuple(sac_sic)
        self.frame = frame
        self.nacp = _nearest({c: adsb.nacp_std_m(c) for c in adsb.NACP_EPU_M}, float(std[0]))
        gva = {c: adsb.vertical_std("geometric", gva=c) for c in adsb.GVA_M}
        self.gva = _nearest(gva, float(std[2])) if len(std) > 2 else 1
        self.unencodable = 0

    def records(self, t1: float, events: Iterable, stamp: Callable[[float], float]) -> list:
        def report(ev, m) -> ax.AdsbReport:
            lat, lon, h = (float(v) for v in self.frame.to_geodetic(np.asarray(m.z, dtype=float)))
            return ax.AdsbReport(sac=self.sac_sic[0], sic=self.sac_sic[1], tod_position=stamp(m.t), atp=0,
                                 lat=lat, lon=lon, high_resolution=True, address=zlib.crc32(ev.target.encode()) & 0xFFFFFF,
                                 geometric_height=h, mops=2, quality=ax.Quality(nacp=self.nacp, gva=self.gva))
        return _encodable(self, events, ax.cat021, report)

    def end(self, stamp: Callable[[float], float]) -> list[tuple[float, list]]:
        return []


def emitter(site, sensor_id: str) -> RadarEmitter | StationEmitter:
    """The emitter of a site's (or scenario's) sensor, by its ``sac_sic``, in the site's
    frame; ValueError for a sensor without one, or of a kind ASTERIX does not carry here."""
    frame = local_frame(site)
    spec = site.sensors[sensor_id]
    if spec.sac_sic is None:
        raise ValueError(f"sensor {sensor_id!r} has no sac_sic = [SAC, SIC]: give it one to send ASTERIX")
    station = {sid: sac_sic for sac_sic, sid in stations(site).items()}.get(sensor_id)
    if station is not None:
        return StationEmitter(station, frame, spec.std)
    radar = next(r for r in radars(site, frame).values() if r.sensor == sensor_id)
    return RadarEmitter(radar, spec.period, spec.sectors, spec.start)


def datagrams(records: list) -> list[bytes]:
    """Records -> datagrams of at most :data:`DATAGRAM_MAX` octets."""
    return ax.encode(records, max_octets=DATAGRAM_MAX)
