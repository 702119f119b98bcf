"""ASTERIX feeds, sans I/O: datagrams in, radar measurements, scan watermarks and ADS-B
position reports out.

Everything that decides what an ASTERIX record means to zfusion lives here; sockets and
Zenoh live in the process. :class:`AsterixFeed` turns a datagram (any mix of categories
and radars) into events: a CAT048 plot of a radar the site file names by ``sac_sic``
becomes a :class:`~services.ingest.gateway.Reading` of that sensor; a CAT034 north
marker or sector crossing becomes a :class:`ScanMark`, a promise that the radar's plots
older than the crossing ``sector_lag`` crossings ago have all been sent (radars send a
sector's plots after its crossing message, so one sector of slack by default; a snapshot
radar's north marker, one per scan at the scan's time with its plots after it, promises
the plots before its own time: the direct stream's watermark after the scan before); a CAT021
ADS-B report becomes a :class:`StationReport`: the ADS-B gateways' position report
(:class:`services.ingest.adsb.PositionReport`) and the ground station's SAC/SIC. Times
of day are placed on the UTC time line next to the receiver's clock
(:func:`schemas.asterix.utc_of_tod`). What cannot be used is a :class:`~services.ingest.gateway.Rejected` with a stable cause (the codec's
``truncated``, ``malformed``, ``unknown-category``, ``missing-item``; ``unknown-source``,
``no-time``, ``no-position``, ``no-height``, ``geometry``, ``no-address``,
``no-accuracy``). :class:`AsterixIngest` hands the events to the
:class:`~services.ingest.gateway.Gateway`, which checks and publishes.

A plot is ``(θ, ρ)`` at the radar: azimuth from the radar's own north, slant range. The
site's ENU frame is tangent at its origin, so a radar away from the origin sees north
turned by the meridian convergence γ (≈ Δλ·sin φ: about 1° at 100 km east, 52° N).
With ``R`` the rotation from the radar's ENU to the site's (both from ECEF, WGS-84)::

    sin ε = ((r + h)² − (r + h_r)² − ρ²) / (2 (r + h_r) ρ)     (elevation at the radar, on
            a sphere of radius r, the Gaussian radius there; h from I048/110, else the
            validated Mode C flight level as pressure altitude, FL·100 ft; a 2D radar's
            plot without either: ε = 0)
    d = R · ρ (cos ε sin θ, cos ε cos θ, sin ε);   az, el of d;   range = ρ

so a 2D plot's azimuth turns by about γ = atan2(R[0,1], R[1,1]). :meth:`Radar.from_site`
inverts it exactly (an emitter's side). An ADS-B position's
σ follows the ADS-B gateways' rules (:mod:`services.ingest.adsb`: NACp's 95 % bound over
2.448 per horizontal axis, GVA's over 1.96 vertically), with NUCp's bound for MOPS
version 0 reports.
"""

from __future__ import annotations

import math
import re
import struct
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, Mapping

import numpy as np

import sensors_sim
from fusion.geodetic import LocalFrame
from fusion.measurement.kinds import KINDS
from schemas import asterix as ax

from . import adsb
from .adsb import PositionReport, position_reading
from .gateway import Gateway, Reading, Rejected
from .krakensdr import Skipped

FT, NM = adsb.FT, adsb.NM
WGS84_A, WGS84_E2 = 6378137.0, 6.69437999014e-3
RADAR_KINDS = ("range_az", "az_el_range")
# DO-260 (MOPS version 0) NUCp: the 95 % horizontal containment μ, metres; 0 = unknown.
NUCP_95_M = {1: 10 * NM, 2: 5 * NM, 3: 1 * NM, 4: 0.5 * NM, 5: 0.25 * NM, 6: 0.1 * NM, 7: 0.05 * NM, 8: 10.0,
             9: 3.0}


def enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """ECEF -> the ENU axes at a point (rows e, n, u)."""
    p, lam = math.radians(lat_deg), math.radians(lon_deg)
    sp, cp, sl, cl = math.sin(p), math.cos(p), math.sin(lam), math.cos(lam)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


def gaussian_radius(lat_deg: float) -> float:
    """√(M N), the Earth's mean radius of curvature at a latitude (WGS-84)."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    return WGS84_A * math.sqrt(1 - WGS84_E2) / (1 - WGS84_E2 * s2)


@dataclass(frozen=True, eq=False)
class Radar:
    """A site-file radar fed by ASTERIX and the geometry of its plots in the site's frame
    (module docstring): ``rotation`` its ENU axes -> the site's, ``gamma`` the azimuth of
    its north there, ``radius`` and ``height`` its Earth radius and height above it;
    ``snapshot``: a whole scan at one time (no rotation: CAT034 north markers only)."""

    sensor: str
    sac_sic: tuple[int, int]
    kind: str
    site: np.ndarray
    rotation: np.ndarray
    gamma: float
    radius: float
    height: float
    snapshot: bool = False
    _rows: tuple = field(init=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "_rows", tuple(tuple(float(x) for x in row) for row in self.rotation))

    @classmethod
    def at(cls, sensor: str, sac_sic: tuple[int, int], kind: str, site: np.ndarray, frame: LocalFrame,
           snapshot: bool = False) -> "Radar":
        if kind not in RADAR_KINDS:
            raise ValueError(f"sensor {sensor!r} measures {kind}: ASTERIX plots are {' or '.join(RADAR_KINDS)} "
                             f"(a radar2d or radar3d sensor)")
        lat, lon, h = (float(v) for v in frame.to_geodetic(np.asarray(site, dtype=float)))
        if not frame.deg:
            lat, lon = math.degrees(lat), math.degrees(lon)
        lat0, lon0 = (frame.lat0, frame.lon0) if frame.deg else (math.degrees(frame.lat0), math.degrees(frame.lon0))
        rot = enu_rotation(lat0, lon0) @ enu_rotation(lat, lon).T
        return cls(sensor, tuple(sac_sic), kind, np.asarray(site, dtype=float), rot,
                   math.atan2(rot[0, 1], rot[1, 1]), gaussian_radius(lat), h, snapshot)

    def elevation(self, rho: float, height: float) -> float:
        """The elevation at the radar of a point at slant range ``rho`` and ``height``."""
        a, b = self.radius + self.height, self.radius + height
        if not rho > 0.0:
            raise ValueError(f"a slant range of {rho:g} m has no elevation")
        s = (b * b - a * a - rho * rho) / (2.0 * a * rho)
        if not -1.0 <= s <= 1.0:
            raise ValueError(f"height {height:.0f} m cannot be seen at slant range {rho:.0f} m")
        return math.asin(s)

    def to_site(self, theta: float, rho: float, height: float | None = None) -> np.ndarray:
        """A plot -> the measurement vector of this radar's kind in the site's frame. A 2D
        radar's plot without a height is taken on the radar's horizon (ε = 0)."""
        if height is None:
            if self.kind == "az_el_range":
                raise ValueError("a 3D plot needs a height")
            el = 0.0
        else:
            el = self.elevation(rho, height)
        ce = math.cos(el)
        v = (rho * ce * math.sin(theta), rho * ce * math.cos(theta), rho * math.sin(el))
        e, n, u = (r[0] * v[0] + r[1] * v[1] + r[2] * v[2] for r in self._rows)  # R · v, in floats: fast
        az = math.atan2(e, n) % (2 * math.pi)
        if self.kind == "range_az":
            return np.array([az, rho])
        return np.array([az, math.atan2(u, math.hypot(e, n)), rho])

    def plot(self, z: np.ndarray, tod: float) -> ax.TargetReport:
        """A measurement of this radar's kind in the site's frame -> the CAT048 plot (a
        PSR detection) that this radar sends for it at time of day ``tod``: the inverse of
        :meth:`AsterixFeed.receive`'s reading, to the items' resolution (:meth:`from_site`;
        a 3D plot's height in I048/110, a 2D plot without one: on the horizon).
        ValueError for what the items cannot hold (a range beyond 256 NM)."""
        theta, rho, height = self.from_site(z)
        return ax.TargetReport(sac=self.sac_sic[0], sic=self.sac_sic[1], tod=tod, typ=1, rho=rho, theta=theta,
                               height_3d=height)

    def from_site(self, z: np.ndarray, height: float | None = None) -> tuple[float, float, float | None]:
        """The inverse of :meth:`to_site`: ``(θ, ρ, height)``; a 2D measurement needs the
        height it was converted with (None: the horizon), a 3D one carries it."""
        rho = float(z[-1])
        if self.kind == "range_az":
            # the direction of azimuth az in the site frame at elevation ε above the radar's
            # horizon: v = cos β h + sin β ẑ with v·u = sin ε (u: the radar's up)
            az = float(z[0])
            sin_e = 0.0 if height is None else math.sin(self.elevation(rho, height))
            h = np.array([math.sin(az), math.cos(az), 0.0])
            u = self.rotation[:, 2]
            a, b = float(h @ u), float(u[2])
            beta = math.atan2(b, a) - math.acos(max(-1.0, min(1.0, sin_e / math.hypot(a, b))))
            d = self.rotation.T @ (math.cos(beta) * h + np.array([0.0, 0.0, math.sin(beta)]))
            return math.atan2(d[0], d[1]) % (2 * math.pi), rho, height
        az, el = float(z[0]), float(z[1])
        d = self.rotation.T @ np.array([rho * math.cos(el) * math.sin(az), rho * math.cos(el) * math.cos(az),
                                        rho * math.sin(el)])
        a = self.radius + self.height
        height = math.sqrt(a * a + rho * rho + 2.0 * a * d[2]) - self.radius
        return math.atan2(d[0], d[1]) % (2 * math.pi), rho, height


def radars(site, frame: LocalFrame) -> dict[tuple[int, int], Radar]:
    """The site's sensors with a ``sac_sic``, by SAC/SIC; ValueError for a shared one, a
    kind that is not a radar's, or a mobile site."""
    out: dict[tuple[int, int], Radar] = {}
    for sid, spec in site.sensors.items():
        if spec.sac_sic is None or not KINDS[spec.measurement_kind].sited:  # (an ADS-B ground station: stations())
            continue
        if spec.sac_sic in out:
            raise ValueError(f"sensors {out[spec.sac_sic].sensor!r} and {sid!r} share sac_sic "
                             f"{list(spec.sac_sic)}: each radar needs its own")
        if spec.site is None or not spec.site.fixed:
            raise ValueError(f"sensor {sid!r} has sac_sic but no fixed position: a radar's plots are relative to it")
        out[spec.sac_sic] = Radar.at(sid, spec.sac_sic, spec.measurement_kind, spec.site.points[0], frame,
                                     snapshot=not spec.sectors)
    if not out and not stations(site):
        raise ValueError("no sensor of the site file has sac_sic = [SAC, SIC]: nothing to publish")
    return out


def stations(site) -> dict[tuple[int, int], str]:
    """The site's ADS-B ground stations (sensors of a position kind, ``kind = "adsb"``)
    with a ``sac_sic``: SAC/SIC -> sensor id, whose CAT021 reports it publishes."""
    return {spec.sac_sic: sid for sid, spec in site.sensors.items()
            if spec.sac_sic is not None and not KINDS[spec.measurement_kind].sited}


def with_sac_sic(text: str, site, sac: int = 0) -> tuple[str, dict[str, tuple[int, int]]]:
    """A scenario's (or site file's) TOML ``text`` with ``sac_sic = [sac, n]`` added to
    each fixed radar (``radar2d``, ``radar3d``) and ADS-B ground station (``adsb``) of
    ``site`` (the same file, loaded) that has none, ``n`` = 1, 2, ... in the sensors'
    order, past those taken; and every such sensor's SAC/SIC. ValueError where a
    sensor's table is not a ``[sensors.<id>]`` header of its own."""
    taken = {spec.sac_sic for spec in site.sensors.values() if spec.sac_sic is not None}
    out: dict[str, tuple[int, int]] = {}
    sic = 0
    for sid, spec in site.sensors.items():
        radar = spec.measurement_kind in RADAR_KINDS and spec.site is not None and spec.site.fixed
        if not (radar or spec.kind == "adsb"):
            continue
        if spec.sac_sic is not None:
            out[sid] = spec.sac_sic
            continue
        sic += 1
        while (sac, sic) in taken:
            sic += 1
        if sic > 255:
            raise ValueError(f"no SIC of SAC {sac} left for sensor {sid!r}")
        name = "|".join(q + re.escape(sid) + q for q in ("", '"', "'"))
        header = re.compile(rf"^[ \t]*\[[ \t]*sensors[ \t]*\.[ \t]*(?:{name})[ \t]*\][^\n]*\n", re.MULTILINE)
        m = header.search(text)
        if m is None:
            raise ValueError(f"sensor {sid!r} has no [sensors.{sid}] header line to add sac_sic under")
        text = f"{text[:m.end()]}sac_sic = [{sac}, {sic}]\n{text[m.end():]}"
        out[sid] = (sac, sic)
    return text, out


def write_site(scenario_ref: str, scenario, path: Path) -> tuple[str, ...]:
    """Writes to ``path`` the scenario (a file, or a built-in's name) with a SAC/SIC for
    each of its radars and ADS-B stations (:func:`with_sac_sic`): the file a run's ASTERIX
    sensors and gateway read (``zfusion run --asterix``); returns those sensors' ids.
    ValueError if it has none, OSError if the file cannot be written."""
    source = Path(scenario_ref)
    if not source.is_file():
        source = Path(sensors_sim.__file__).parent / "scenarios" / f"{scenario_ref}.toml"
    text, assigned = with_sac_sic(source.read_text(encoding="utf-8"), scenario)
    if not assigned:
        raise ValueError(f"scenario {scenario.name} has no radar (radar2d, radar3d at a fixed site) or ADS-B "
                         f"ground station (adsb) to send ASTERIX")
    path.write_text(text, encoding="utf-8")
    return tuple(assigned)


@dataclass(frozen=True)
class ScanMark:
    """A radar's promise: none of its plots at or before ``t`` will follow."""

    sensor: str
    t: float


@dataclass(frozen=True)
class StationReport:
    """A CAT021 report as the ADS-B gateways give theirs (:class:`adsb.PositionReport`,
    ``fmt = "asterix"``), with the SAC/SIC of the ground station that sent it."""

    sac_sic: tuple[int, int]
    report: PositionReport


def horizontal_std(q: ax.Quality | None, mops: int | None) -> float | None:
    """σ per horizontal axis (m) from the quality indicators, None if unknown: NACp (the
    ADS-B gateways' rule, :func:`adsb.horizontal_std`) for MOPS version 1 and later, or
    when the NACp extension came without a version; NUCp for version 0, its 95 % bound
    treated alike (EPU/2.448 with the CPR cell added)."""
    if q is not None and (mops == 0 or (mops is None and q.nacp is None)):
        if q.nucp_nic not in NUCP_95_M:
            return None
        return math.hypot(NUCP_95_M[q.nucp_nic] / adsb.K95_2D, adsb.CPR_CELL_M / math.sqrt(12.0))
    return adsb.horizontal_std("adsb", None if q is None else q.nacp)


class AsterixFeed:
    """Datagrams -> events (module docstring). State: per radar, the times of its last
    ``lag + 1`` crossings (``lag``: ``sector_lag``, 0 for a snapshot radar)."""

    def __init__(self, radars: Mapping[tuple[int, int], Radar], sector_lag: int = 1):
        if sector_lag < 0:
            raise ValueError(f"sector lag must be 0 or more crossings, not {sector_lag}")
        self.radars = dict(radars)
        self.sector_lag = sector_lag
        self._lag = {r.sensor: 0 if r.snapshot else sector_lag for r in self.radars.values()}
        self._crossings: dict[str, deque] = {s: deque(maxlen=lag + 1) for s, lag in self._lag.items()}
        self.counters = {"datagrams": 0, "records.cat048": 0, "records.cat034": 0, "records.cat021": 0}

    def receive(self, data: bytes, now: float) -> list:
        """One datagram, read at ``now`` (UTC s) -> Reading, ScanMark, StationReport,
        Rejected and Skipped events, in the datagram's order."""
        self.counters["datagrams"] += 1
        out = []
        for r in ax.decode(data):
            if isinstance(r, ax.TargetReport):
                self.counters["records.cat048"] += 1
                out.append(self._plot(r, now))
            elif isinstance(r, ax.ServiceMessage):
                self.counters["records.cat034"] += 1
                ev = self._service(r, now)
                if ev is not None:
                    out.append(ev)
            elif isinstance(r, ax.AdsbReport):
                self.counters["records.cat021"] += 1
                out.append(self._adsb(r, now))
            elif isinstance(r, ax.Undecodable):
                out.append(Rejected(r.cause, r.detail))
            else:  # CAT062/065: read, but not a measurement
                out.append(Skipped(f"cat{r.category:03d}"))
        return out

    def _radar(self, sac: int, sic: int) -> Radar | Rejected:
        radar = self.radars.get((sac, sic))
        if radar is None:
            return Rejected("unknown-source", f"SAC/SIC {sac}/{sic} is no sensor of the site file (it names "
                                              f"{', '.join(f'{s}/{c}' for s, c in self.radars)})")
        return radar

    def _plot(self, r: ax.TargetReport, now: float) -> Reading | Rejected:
        radar = self._radar(r.sac, r.sic)
        if isinstance(radar, Rejected):
            return radar
        if r.tod is None:
            return Rejected("no-time", f"{radar.sensor}: a plot without I048/140 (time of day)")
        if r.rho is None:
            return Rejected("no-position", f"{radar.sensor}: a plot without I048/040 (measured position)")
        height = r.height_3d
        if height is None and r.flight_level is not None and r.fl_validated and not r.fl_garbled:
            height = r.flight_level * 100.0 * FT
        if radar.kind == "az_el_range" and height is None:
            return Rejected("no-height", f"{radar.sensor} is a 3D radar: a plot needs I048/110 or a valid Mode C")
        try:
            z = radar.to_site(r.theta, r.rho, height)
        except ValueError as e:
            if radar.kind == "az_el_range":
                return Rejected("geometry", f"{radar.sensor}: {e}")
            z = radar.to_site(r.theta, r.rho)  # a 2D radar's impossible Mode C: on its horizon
        return Reading(sensor=radar.sensor, t=ax.utc_of_tod(r.tod, now), kind=radar.kind, z=z)

    def _service(self, m: ax.ServiceMessage, now: float) -> ScanMark | Rejected | Skipped | None:
        radar = self._radar(m.sac, m.sic)
        if isinstance(radar, Rejected):
            return radar
        if m.message_type not in (ax.NORTH_MARKER, ax.SECTOR_CROSSING):
            return Skipped("service-message")
        if m.tod is None:
            return Rejected("no-time", f"{radar.sensor}: a CAT034 message without I034/030 (time of day)")
        t = ax.utc_of_tod(m.tod, now)
        marks = self._crossings[radar.sensor]
        if marks and t <= marks[-1]:  # the north marker beside sector 0's crossing; or a restart
            if t < marks[-1]:
                marks.clear()
                marks.append(t)
            return None
        marks.append(t)
        if len(marks) <= self._lag[radar.sensor]:
            return None
        return ScanMark(radar.sensor, math.nextafter(marks[0], -math.inf))

    def _adsb(self, r: ax.AdsbReport, now: float) -> StationReport | Rejected:
        who = f"ADS-B {r.sac}/{r.sic}" + ("" if r.address is None else f" {r.address:06X}")
        tod = r.time()
        if tod is None:
            return Rejected("no-time", f"{who}: neither I021/071 nor I021/073 (time of position)")
        if r.lat is None:
            return Rejected("no-position", f"{who}: neither I021/131 nor I021/130 (position)")
        if r.address is None:
            return Rejected("no-address", f"{who}: no I021/080 (target address)")
        std_h = horizontal_std(r.quality, r.mops)
        if std_h is None:
            return Rejected("no-accuracy", f"{who}: NACp/NUCp 0 (unknown accuracy)")
        if r.geometric_height is not None:
            alt, ref = r.geometric_height, "geometric"
        elif r.flight_level is not None:
            alt, ref = r.flight_level * 100.0 * FT, "barometric"
        else:
            alt, ref = None, "ground" if r.gbs else "none"
        q = r.quality
        velocity = None if r.ground_speed is None else (r.ground_speed * math.sin(r.track_angle),
                                                        r.ground_speed * math.cos(r.track_angle))
        report = PositionReport(
            t=ax.utc_of_tod(tod, now), address=("" if r.atp in (0, None) else "~") + f"{r.address:06x}",
            lat_deg=r.lat, lon_deg=r.lon, alt_m=alt, alt_ref=ref, source="adsb", std_h_m=std_h,
            std_v_m=adsb.vertical_std(ref, None if q is None else q.gva, None if q is None else q.nacp),
            callsign=r.callsign or None, velocity_m_s=velocity, nac_p=None if q is None else q.nacp, fmt="asterix")
        return StationReport((r.sac, r.sic), report)


@dataclass
class AsterixIngest:
    """The whole decision, sans I/O: datagrams -> the ``(key, bytes)`` messages to
    publish. ``reject(src, cause, detail)`` counts and logs refusals; ``skipped`` counts
    what is deliberately not published, by cause. A CAT021 report is a ``position``
    reading of the ground station its SAC/SIC names (``stations``)."""

    feed: AsterixFeed
    gateway: Gateway
    reject: Callable[[str, str, str], None]
    src: str = "asterix"
    skipped: dict[str, int] = field(default_factory=dict)
    t_last: float = 0.0
    stations: Mapping[tuple[int, int], str] = field(default_factory=dict)  # SAC/SIC -> ADS-B sensor id

    def receive(self, data: bytes, now: float) -> list[tuple[str, bytes]]:
        out: list[tuple[str, bytes]] = []
        for ev in self.feed.receive(data, now):
            if isinstance(ev, Reading):
                out.extend(self.gateway.offer(ev, now))
                self.t_last = max(self.t_last, ev.t)
            elif isinstance(ev, ScanMark):
                out.extend(self.gateway.promise(ev.sensor, ev.t))
            elif isinstance(ev, StationReport):
                sensor = self.stations.get(ev.sac_sic)
                reading = position_reading(ev.report, sensor) if sensor is not None else Rejected(
                    "unknown-source", f"ADS-B station SAC/SIC {ev.sac_sic[0]}/{ev.sac_sic[1]} is no sensor of the site "
                                      f"file (give its [sensors.<id>] kind = \"adsb\" and sac_sic)")
                if isinstance(reading, Reading):
                    out.extend(self.gateway.offer(reading, now))
                    self.t_last = max(self.t_last, reading.t)
                elif isinstance(reading, Rejected):
                    self.reject(self.src, reading.cause, reading.detail)
                else:
                    self.skipped[reading.cause] = self.skipped.get(reading.cause, 0) + 1
            elif isinstance(ev, Rejected):
                self.reject(self.src, ev.cause, ev.detail)
            else:
                self.skipped[ev.cause] = self.skipped.get(ev.cause, 0) + 1
        return out

    def counters(self) -> dict[str, float]:
        return {**self.gateway.counters, **self.feed.counters,
                **{f"skipped.{c}": n for c, n in self.skipped.items()}}


# ------------------------------------------------------------------ captures

PCAP_MAGIC = {b"\xd4\xc3\xb2\xa1": ("<", 1e-6), b"\xa1\xb2\xc3\xd4": (">", 1e-6),
              b"\x4d\x3c\xb2\xa1": ("<", 1e-9), b"\xa1\xb2\x3c\x4d": (">", 1e-9)}
# link type -> octets before the IP header
PCAP_LINKS = {1: 14, 101: 0, 12: 0, 113: 16, 276: 20, 0: 4}


class CaptureError(ValueError):
    """A file that is not a classic pcap capture this reader knows."""


def pcap_datagrams(data: bytes) -> Iterator[tuple[float, bytes]]:
    """``(capture time, UDP payload)`` of every UDP/IPv4 or IPv6 packet of a classic
    libpcap capture (Ethernet with or without VLAN tags, raw IP, Linux cooked v1/v2, BSD
    loopback). Other packets, IP fragments and a truncated last record are skipped."""
    if len(data) < 24 or data[:4] not in PCAP_MAGIC:
        raise CaptureError("not a pcap capture (pcapng is not read: convert it with editcap -F pcap)")
    end, unit = PCAP_MAGIC[data[:4]]
    link = struct.unpack(end + "I", data[20:24])[0]
    if link not in PCAP_LINKS:
        raise CaptureError(f"link type {link} is not read (Ethernet, raw IP, Linux cooked or loopback)")
    rec = struct.Struct(end + "IIII")
    pos = 24
    while pos + 16 <= len(data):
        sec, frac, incl, _ = rec.unpack_from(data, pos)
        pkt = data[pos + 16:pos + 16 + incl]
        pos += 16 + incl
        if len(pkt) < incl:
            return
        payload = _udp_payload(pkt, link)
        if payload is not None:
            yield sec + frac * unit, payload


def _udp_payload(pkt: bytes, link: int) -> bytes | None:
    off = PCAP_LINKS[link]
    if link == 1:
        while len(pkt) >= off + 4 and pkt[off - 2:off] in (b"\x81\x00", b"\x88\xa8"):  # VLAN tags
            off += 4
    if len(pkt) < off + 20:
        return None
    version = pkt[off] >> 4
    if version == 4:
        ihl = (pkt[off] & 0x0F) * 4
        frag = struct.unpack_from(">H", pkt, off + 6)[0]
        if pkt[off + 9] != 17 or frag & 0x3FFF:  # not UDP, or a fragment
            return None
        udp = off + ihl
    elif version == 6 and len(pkt) >= off + 48 and pkt[off + 6] == 17:
        udp = off + 40
    else:
        return None
    if len(pkt) < udp + 8:
        return None
    length = struct.unpack_from(">H", pkt, udp + 4)[0]
    return pkt[udp + 8:udp + max(8, length)]


PCAP_HEADER = struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 101)  # classic pcap, µs, raw IP


def pcap_record(t: float, payload: bytes, port: int = 8600) -> bytes:
    """One UDP datagram to 127.0.0.1:``port`` at time ``t`` as a record of a
    :data:`PCAP_HEADER` capture (raw IPv4)."""
    sec = math.floor(t)
    usec = min(999_999, round((t - sec) * 1e6))
    udp = struct.pack(">HHHH", port, port, 8 + len(payload), 0) + payload
    ip = struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0x4000, 64, 17, 0, bytes((127, 0, 0, 1)),
                     bytes((127, 0, 0, 1))) + udp
    return struct.pack("<IIII", sec, usec, len(ip), len(ip)) + ip


def pcap_file(packets: Iterable[tuple[float, bytes]], port: int = 8600) -> bytes:
    """A classic pcap capture (raw IPv4, µs) of UDP datagrams to 127.0.0.1:``port`` at
    the given times: what :func:`pcap_datagrams` reads back (an emitter's recording)."""
    return PCAP_HEADER + b"".join(pcap_record(t, payload, port) for t, payload in packets)
