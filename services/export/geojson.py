"""The fused picture as an RFC 7946 GeoJSON FeatureCollection (pure: no I/O but :func:`write_atomic`).

Features, all in WGS-84 ``[lon °, lat °, alt m]`` (RFC 7946 §3.1.1), converted from the
session's ENU frame with pymap3d (:mod:`services.geo`):

* one ``Point`` per fused track or emitter fix; properties ``id`` (the track id),
  ``kind`` (``track``: a 3D track; ``fix``: an emitter fix on the map plane, moving or
  not: :func:`.tracks.is_fix`), ``method``,
  ``time`` (ISO 8601 UTC in a live session, scenario seconds otherwise) and
  ``position_std_m`` (√ trace of the position covariance); a 3D track or a moving
  fix also ``velocity_enu_mps``, and ``existence`` (the probability that its target exists)
  where its tracker holds one (JIPDA); ``callsign`` and ``address`` where its target
  claims an identity (:class:`fusion.types.Identity`);
* one ``Polygon`` per emitter fix: its 95 % confidence ellipse (``kind`` ``ellipse``,
  ``id`` the fix's), a closed ring, counter-clockwise (RFC 7946 §3.1.6);
* one ``Point`` per sensor (``kind`` ``sensor``, ``sensor_kind``: ``df``, ``radar2d``, ...).

:func:`write_atomic` replaces the file in one step (a temporary file beside it, then
``os.replace``), so a reader never sees half a document.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

import numpy as np

from fusion.geodetic import LocalFrame
from fusion.types import Estimate

from .. import geo
from .tracks import is_fix, session_time

DEGREES = 7  # decimals of a degree kept: about 1 cm
METRES = 2


def _round(x: float, decimals: int) -> float:
    """``x`` rounded, never ``-0.0`` (a value that rounds to zero is 0)."""
    return round(float(x), decimals) + 0.0


def _position(g: np.ndarray) -> list[float]:
    lat, lon, alt = (float(v) for v in g)
    return [_round(lon, DEGREES), _round(lat, DEGREES), _round(alt, METRES)]


def estimate_features(e: Estimate, frame: LocalFrame, live: bool) -> list[dict]:
    """The Point of a track or fix, and a fix's 95 % ellipse."""
    common = {"id": e.track, "method": e.method, "time": session_time(e.t, live)}
    props = {**common, "kind": "fix" if is_fix(e) else "track", "position_std_m": _round(geo.position_std(e.x, e.P), 3)}
    v = geo.velocity(e.x)
    if v is not None:
        props["velocity_enu_mps"] = [_round(c, 3) for c in v]
    if e.existence is not None:
        props["existence"] = _round(e.existence, 4)
    if e.identity is not None:  # what the target claims: its callsign and address, where known
        props.update({k: v for k, v in (("callsign", e.identity.callsign), ("address", e.identity.address))
                      if v is not None})
    pos = geo.enu3(e.x)
    out = [{"type": "Feature", "geometry": {"type": "Point", "coordinates": _position(geo.lat_lon_alt(frame, pos))},
            "properties": props}]
    if is_fix(e):
        ring = geo.ring(frame, pos, geo.horizontal_cov(e.P))
        coords = [[_round(lon, DEGREES), _round(lat, DEGREES)] for lat, lon, _ in ring]
        coords[-1] = coords[0]  # closed exactly, after rounding too
        out.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [coords]},
                    "properties": {**common, "kind": "ellipse", "confidence": geo.CONFIDENCE}})
    return out


def sensor_feature(sensor: str, kind: str, enu: np.ndarray, frame: LocalFrame) -> dict:
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": _position(geo.lat_lon_alt(frame, enu))},
            "properties": {"id": sensor, "kind": "sensor", "sensor_kind": kind}}


def feature_collection(estimates: Iterable[Estimate], sensors: dict[str, tuple[str, np.ndarray]],
                       frame: LocalFrame, live: bool) -> dict:
    """The whole picture: sensors first, then every track or fix (with its ellipse)."""
    features = [sensor_feature(sid, kind, enu, frame) for sid, (kind, enu) in sensors.items()]
    for e in estimates:
        features.extend(estimate_features(e, frame, live))
    return {"type": "FeatureCollection", "features": features}


def write_atomic(path: Path, doc: dict) -> None:
    """Replace ``path`` with ``doc`` as JSON in one step (temporary file, then ``os.replace``)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(doc, f, separators=(",", ":"))
    os.replace(tmp, path)
