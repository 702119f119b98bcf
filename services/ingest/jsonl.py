"""The generic gateway's line format, sans I/O: bytes in, :class:`Reading` records out.

One JSON object per line (``docs/ingest.md``; schema ``docs/ingest-line.schema.json``)::

    {"t": 1764612000.25, "kind": "range_az", "az_deg": 41.5, "range_m": 12034.0,
     "std": [1.0, 20.0], "lat_deg": 21.03, "lon_deg": 105.85, "alt_m": 12.0}

``t`` is UTC POSIX seconds. The components are those of the measurement kind
(:mod:`fusion.measurement.kinds`), each a field named after the component with its unit,
``<name>_deg`` for an angle, ``<name>_m`` for a length (``bearing``: ``az_deg``;
``azel``: ``az_deg, el_deg``; ``range_az``: ``az_deg, range_m``; ``az_el_range``: all
three), azimuth clockwise from true north (−180 … 360, wrapped to [0, 360)), elevation
above the horizontal. ``std`` (optional) lists the stated std per component in the same
units (degrees, metres); it must agree with the site file's. The sensor's position
(optional: a sensor the site file does not pin needs it) is geodetic (``lat_deg``,
``lon_deg``, optional ``alt_m``) or ENU ``site_m``.

A kind that reports a position (not *sited*) gives it as its components (ENU metres in
the site's frame) or as ``lat_deg``, ``lon_deg`` and ``alt_m``: then these are the
reported position, and there is no sensor position (no ``site_m``). A kind whose reports
state their own noise (``own_noise``) takes ``std`` as the report's own and an optional
``corr``, the correlation coefficients ``[ρ₁₂, ρ₁₃, …, ρ₂₃, …]`` (the upper triangle, row
by row); with a geodetic position both are in the ENU axes at that position. Any other
field is an error, so a misspelt one is never silently ignored.

:class:`LineSplitter` cuts a byte stream into lines with a bounded buffer;
:func:`reading` turns one line into a reading or a :class:`Rejected` with a stable cause.
"""

from __future__ import annotations

import json
import math

import numpy as np

from fusion.angles import wrap_2pi
from fusion.measurement.components import COMPONENTS, Component
from fusion.measurement.kinds import KINDS

from .gateway import DECODE_ERRORS, Reading, Rejected, undecodable

MAX_LINE = 64 * 1024  # bytes: a line is ~200


def _field(c: Component) -> tuple[str, tuple[float, float, bool, bool]]:
    """A component's line field and its interval ``(lo, hi, lo_open, hi_open)`` in the
    line's units: degrees for an angle (a periodic one from −180), metres for a length."""
    if not c.angle:
        return f"{c.name}_m", (c.lo, c.hi, c.lo_open, c.hi_open)
    if c.periodic:
        return f"{c.name}_deg", (-180.0, 360.0, False, False)
    return f"{c.name}_deg", (math.degrees(c.lo), math.degrees(c.hi), c.lo_open, c.hi_open)


_FIELD = {name: _field(c)[0] for name, c in COMPONENTS.items()}
_LIMITS = {**{key: limits for key, limits in map(_field, COMPONENTS.values())},
           "lat_deg": (-90.0, 90.0, False, False), "lon_deg": (-180.0, 360.0, False, False),
           "alt_m": (-1e4, 1e6, False, False)}
_ALLOWED = {"t", "kind", "std", "corr", "lat_deg", "lon_deg", "alt_m", "site_m", *_FIELD.values()}


class LineSplitter:
    """Bytes of a stream -> complete lines. A line longer than ``max_line`` is dropped
    (reported once as ``line-too-long``) up to its newline; the buffer never holds more
    than ``max_line`` bytes."""

    def __init__(self, max_line: int = MAX_LINE):
        self.max_line = max_line
        self._buf = bytearray()
        self._skipping = False

    def feed(self, data: bytes) -> list[bytes | Rejected]:
        out: list[bytes | Rejected] = []
        start = 0
        while True:
            nl = data.find(b"\n", start)
            chunk = data[start:] if nl < 0 else data[start:nl]
            if not self._skipping:
                if len(self._buf) + len(chunk) > self.max_line:
                    out.append(Rejected("line-too-long", f"a line of more than {self.max_line} bytes"))
                    self._buf.clear()
                    self._skipping = True
                else:
                    self._buf += chunk
            if nl < 0:
                return out
            if not self._skipping and self._buf.strip():
                out.append(bytes(self._buf))
            self._buf.clear()
            self._skipping = False
            start = nl + 1


class _Bad(ValueError):
    def __init__(self, cause: str, detail: str):
        super().__init__(detail)
        self.cause = cause


def _num(d: dict, key: str, required: bool = True) -> float | None:
    if key not in d or d[key] is None:
        if required:
            raise _Bad("missing", f"'{key}' is required")
        return None
    x = d[key]
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise _Bad("type", f"'{key}' must be a number, not {type(x).__name__}")
    try:
        x = float(x)
    except OverflowError:  # an integer beyond any float
        raise _Bad("range", f"'{key}' is beyond any float") from None
    if not math.isfinite(x):
        raise _Bad("non-finite", f"'{key}' is {x!r}")
    lo, hi, lo_open, hi_open = _LIMITS.get(key, (-math.inf, math.inf, False, False))
    if not lo <= x <= hi or (lo_open and x == lo) or (hi_open and x == hi):
        raise _Bad("range", f"'{key}' = {x:g} outside {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}")
    return x


def _vector(d: dict, key: str, n: int) -> np.ndarray | None:
    v = d.get(key)
    if v is None:
        return None
    if not isinstance(v, list) or len(v) != n or any(isinstance(x, bool) or not isinstance(x, (int, float))
                                                     for x in v):
        raise _Bad("shape", f"'{key}' must be a list of {n} numbers")
    try:
        a = np.array(v, dtype=float)
    except OverflowError:  # an integer beyond any float
        raise _Bad("range", f"'{key}' has a number beyond any float") from None
    if not np.all(np.isfinite(a)):
        raise _Bad("non-finite", f"'{key}' has NaN or inf")
    return a


def _components(d: dict, comps: tuple[Component, ...]) -> np.ndarray:
    """The components' values in SI (radians, azimuth wrapped to [0, 2π); metres)."""
    z = []
    for c in comps:
        x = _num(d, _FIELD[c.name])
        z.append(wrap_2pi(math.radians(x)) if c.periodic else math.radians(x) if c.angle else x)
    return np.array(z)


def _noise(d: dict, comps: tuple[Component, ...]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``std`` in SI (radians for angles) and ``corr`` (the upper triangle of a
    correlation matrix, row by row) as the n × n matrix; None where not given."""
    std = _vector(d, "std", len(comps))
    if std is not None:
        if np.any(std <= 0):
            raise _Bad("range", "'std' must be > 0")
        std = np.array([math.radians(s) if c.angle else s for s, c in zip(std, comps)])
    n = len(comps)
    rho = _vector(d, "corr", n * (n - 1) // 2)
    if rho is None:
        return std, None
    if np.any(np.abs(rho) >= 1.0):
        raise _Bad("range", "'corr' coefficients must lie in (-1, 1)")
    C = np.eye(n)
    C[np.triu_indices(n, 1)] = rho
    return std, np.triu(C) + np.triu(C, 1).T


def reading(line: bytes, sensor: str) -> Reading | Rejected:
    """One line -> a :class:`Reading` of ``sensor`` (SI units, radians) or why not."""
    try:
        d = json.loads(line)
    except DECODE_ERRORS as e:
        return undecodable(e, "json")
    if not isinstance(d, dict):
        return Rejected("json", f"a line must be a JSON object, not {type(d).__name__}")
    try:
        extra = set(d) - _ALLOWED
        if extra:
            raise _Bad("unknown-field", f"'{sorted(extra)[0]}' is not a field of a measurement line")
        kind = d.get("kind")
        if not isinstance(kind, str) or kind not in KINDS:
            raise _Bad("kind", f"'kind' {str(kind)[:20]!r} is not one of {', '.join(KINDS)}")
        k = KINDS[kind]
        comps = k.components
        unused = {_FIELD[c] for c in _FIELD if c not in k.names} & set(d)
        if unused:
            raise _Bad("unknown-field", f"'{sorted(unused)[0]}' is not a component of a {kind}")
        if "corr" in d and not k.own_noise:
            raise _Bad("unknown-field", f"'corr': a {kind} states its sensor's noise (the site file's), not its own")
        t = _num(d, "t")
        if t <= 0:
            raise _Bad("time", f"'t' = {t:g} is not a UTC time (POSIX seconds)")
        if not k.sited:  # a position report: its components, or lat/lon/alt
            if "site_m" in d:
                raise _Bad("unknown-field", f"'site_m': a {kind} report is a position, not seen from a site")
            if not any(key in d for key in ("lat_deg", "lon_deg", "alt_m")):
                z = _components(d, comps)
                std, corr = _noise(d, comps)
                return Reading(sensor=sensor, t=t, kind=kind, z=z, std=std, corr=corr)
            given = [_FIELD[c.name] for c in comps if _FIELD[c.name] in d]
            if given:
                raise _Bad("position", f"give the position as {'/'.join(_FIELD[c.name] for c in comps)} or "
                                       f"lat_deg/lon_deg/alt_m, not both ('{given[0]}')")
            geo = (_num(d, "lat_deg"), _num(d, "lon_deg"), _num(d, "alt_m"))
            std, corr = _noise(d, comps)
            return Reading(sensor=sensor, t=t, kind=kind, z=None, std=std, geodetic=geo, corr=corr)
        z = _components(d, comps)
        std, corr = _noise(d, comps)
        site = _vector(d, "site_m", 3)
        geo = None
        if "lat_deg" in d or "lon_deg" in d:
            if site is not None:
                raise _Bad("position", "give 'site_m' or 'lat_deg'/'lon_deg', not both")
            geo = (_num(d, "lat_deg"), _num(d, "lon_deg"), _num(d, "alt_m", required=False))
        elif "alt_m" in d:
            raise _Bad("position", "'alt_m' without 'lat_deg'/'lon_deg'")
        return Reading(sensor=sensor, t=t, kind=kind, z=z, std=std, site=site, geodetic=geo, corr=corr)
    except _Bad as e:
        return Rejected(e.cause, str(e))
