"""The recording's map: what the 3D scene shows, in latitude and longitude.

Every recording of a session with a geodetic origin gets a ``map/`` tree beside
``world/``, shown by the blueprint's map view (OpenStreetMap background). Each entity
mirrors a ``world/`` entity (``world/<rest>`` -> ``map/<rest>``), is drawn from the
same ENU positions the recorder draws in 3D (converted with pymap3d, :mod:`services.geo`)
and in the same colours::

    map/sites/<sensor>             GeoPoints (+ GeoLineStrings: an airborne site's path)
    map/meas/<sensor>              DF bearings of the current scan, GeoLineStrings
    map/tracks/<sensor>/uplink     the bearings a DF station's tracker sent up (KF+TR)
    map/truth/<target>             GeoPoints; its path in map/truth/<target>/path
    map/tracks/<node>/<track>      GeoPoints + the 95 % ring of its horizontal position
                                   (emitter fixes and 3D tracks alike); the ground track
                                   in map/tracks/<node>/<track>/path

The map panel opens zoomed on the session's area (:func:`area`: its sites, jammers and
targets' starting points, or the scale of its sensors around a single site): left to
itself, Rerun's map view fits the data of its first frame and keeps that zoom, and with
a single site in it (patent-3d's radar and angle sensor share one) it kept street level
(zoom 16) at the middle of a track 10 km away: an empty panel (:func:`fit_zoom`).

A truth or track is drawn on the map only with the rows that add a point to its 3D path
(at most every ``TRAIL_STEP_S`` of scenario time; docs/notes.md, "Recorder paths"), so the map's
cost does not grow with the update rate: a 3D track fused at 1,000 updates/s is drawn
twice a second, a DF fix at 1 Hz every time. A cleared 3D track clears its map entity
too (recursively: its path goes with it).

Rows go through the recorder's own queue (``log(path, t, *parts)``, a part being an
archetype and its component lists), so they are sent as columns with the rest.
"""

from __future__ import annotations

import functools
import math
from typing import Callable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from fusion.geodetic import LocalFrame
from fusion.types import Estimate
from sensors_sim.trajectories import truth_trajectories

from .. import geo
from .draw import Trail

MAP_ROOT = "map"
POINT_UI = -5.0  # radii in UI points (negative: rerun's convention)
SITE_UI = -7.0
LINE_UI = -1.0
PANEL_PT = (480.0, 720.0)  # the map panel of a 1600 x 900 window (3 of 10 columns), UI points
TILE_PX = 256.0  # OpenStreetMap's tile: zoom z shows the world 256·2^z points wide
MARGIN = 1.2  # the area fills at most 1/1.2 of the panel either way
MIN_HALF_M = 1_000.0  # the least half-width shown around a single point

Log = Callable[..., None]


def view(name: str = "Map (WGS-84, 95 % rings)", zoom: float | None = None) -> rrb.MapView:
    """The blueprint's map panel, at ``zoom`` (OpenStreetMap's levels; None: Rerun's own)."""
    return rrb.MapView(origin=MAP_ROOT, name=name, background=rrb.MapProvider.OpenStreetMap, zoom=zoom)


def _mercator_y(lat_deg: np.ndarray) -> np.ndarray:
    """Web Mercator's y of a latitude, the world being 0..1."""
    return 0.5 + np.arcsinh(np.tan(np.radians(lat_deg))) / (2 * math.pi)


def fit_zoom(lat_lon: np.ndarray, panel: tuple[float, float] = PANEL_PT) -> float:
    """The zoom level at which the points ``lat_lon`` ((n, 2), degrees) fill ``panel``
    (width, height in UI points) with a margin: Web Mercator, ``256·2^z`` points for the
    world's width (what Rerun's map view computes for the data it is shown; the area's
    extent is at least ``2·MIN_HALF_M``)."""
    lat, lon = lat_lon[:, 0], lat_lon[:, 1]
    y = _mercator_y(lat)
    # the least extent, as a fraction of the world, at the area's latitude
    least = 2 * MIN_HALF_M / (40_075_016.686 * math.cos(math.radians(float(np.mean(lat)))))
    wide = max(float(lon.max() - lon.min()) / 360.0, least)
    high = max(float(y.max() - y.min()), least)
    zoom_x = math.log2(panel[0] / (MARGIN * wide * TILE_PX))
    zoom_y = math.log2(panel[1] / (MARGIN * high * TILE_PX))
    return round(min(zoom_x, zoom_y), 2)


AREA_SAMPLES = 17  # points of each target's path over the scenario's duration


def area(sc, scale_m: float) -> np.ndarray:
    """The session's area, ENU (n, 3): its sites (where moving ones go), jammers, targets'
    paths (run 0's, at ``AREA_SAMPLES`` times) and a traffic box's corners; with fewer than
    two distinct places (a site with one sensor, or sensors sharing one mast), that place
    ± ``scale_m``, the reach the recorder gives its rays."""
    pts: list[np.ndarray] = []
    sites = [s.site for s in sc.sensors.values() if s.site is not None]
    sites += [j.site for j in getattr(sc, "jammers", {}).values()]
    for site in sites:
        pts.extend(np.atleast_2d(site.points))
    if getattr(sc, "targets", None):
        times = np.linspace(0.0, float(sc.duration), AREA_SAMPLES)
        pts.extend(traj.state(float(t))[:3] for traj in truth_trajectories(sc).values() for t in times)
    traffic = getattr(sc, "traffic", None)
    if traffic is not None:
        x0, x1, y0, y1 = traffic.box
        pts.extend(np.array([x, y, 0.0]) for x in (x0, x1) for y in (y0, y1))
    out = np.array(pts, dtype=float).reshape(-1, 3)
    centre = out.mean(axis=0) if len(out) else np.zeros(3)
    if len(out) < 2 or float(np.ptp(out[:, :2], axis=0).max()) < 1.0:
        out = np.vstack([out, centre + [[-scale_m, -scale_m, 0.0], [scale_m, scale_m, 0.0]]])
    return out


def zoom_of(sc, scale_m: float, panel: tuple[float, float] = PANEL_PT) -> float:
    """The map panel's zoom for the session ``sc`` (a scenario or a site): its :func:`area`."""
    return fit_zoom(_lat_lon_of(geo.frame_of(sc.origin), area(sc, scale_m)), panel)



def map_path(world_path: str) -> str:
    """``/world/<rest>`` -> ``/map/<rest>``."""
    head, _, rest = world_path.lstrip("/").partition("/")
    assert head == "world", world_path
    return f"/{MAP_ROOT}/{rest}"


def _lat_lon(g: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(g[..., :2])


def _lat_lon_of(frame: LocalFrame, enu: np.ndarray) -> np.ndarray:
    return _lat_lon(geo.lat_lon_alt(frame, enu))


class MapLayer:
    """Draws on the map what the recorder draws in 3D; ``frame`` is the session's ENU
    frame, ``log`` the recorder's row queue."""

    def __init__(self, frame: LocalFrame, log: Log):
        self.frame = frame
        self._log = log
        self._to_map = functools.partial(_lat_lon_of, frame)  # what Trail.mapped converts with

    @classmethod
    def at(cls, origin: tuple[float, float, float], log: Log) -> "MapLayer":
        """The layer of a session whose ENU origin is ``(lat °, lon °, alt m)``."""
        return cls(geo.frame_of(origin), log)

    def _converted(self, trail: Trail, *enu: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """Points (each ``enu`` an (n, 3) or (3,) array) and the points ``trail`` has
        gained since its last conversion, in latitude and longitude by one conversion: its
        cost is per call far more than per point. Returns the converted ``enu`` and the
        trail's whole path (:meth:`~services.recording.draw.Trail.mapped`)."""
        head = np.vstack([np.atleast_2d(a) for a in enu])
        got: list[np.ndarray] = []

        def convert(new: np.ndarray) -> np.ndarray:
            g = self._to_map(np.vstack([head, new]))
            got.append(g[:len(head)])
            return g[len(head):]

        path = trail.mapped(convert)
        g = got[0] if got else self._to_map(head)
        return np.split(g, np.cumsum([len(np.atleast_2d(a)) for a in enu])[:-1]), path

    def _points(self, g: np.ndarray, color, radius: float = POINT_UI) -> tuple:
        """One point, ``g`` its (1, 2) ``[lat, lon]``."""
        return rr.GeoPoints, {"positions": [g[0]], "colors": [color], "radii": [radius]}

    def site(self, world_path: str, t: float, pos: np.ndarray, trail: Trail, color) -> None:
        (g,), path = self._converted(trail, pos)
        parts = [self._points(g, color, SITE_UI)]
        if len(path) > 1:
            parts.append((rr.GeoLineStrings, {"line_strings": [path], "colors": [color], "radii": [LINE_UI]}))
        self._log(map_path(world_path), t, *parts)

    def bearings(self, world_path: str, t: float, rays: list[np.ndarray], color) -> None:
        """The DF bearings of a scan, each an ENU segment from its site."""
        strips = [_lat_lon(geo.line(self.frame, r[0], r[1])) for r in rays]
        self._log(map_path(world_path), t, (rr.GeoLineStrings, {"line_strings": strips, "colors": [color],
                                                                "radii": [LINE_UI]}))

    def truth(self, world_path: str, t: float, pos: np.ndarray, trail: Trail, grew: bool, color) -> None:
        """The true position and path, when the path ``grew`` (module docstring)."""
        if grew:
            (g,), path = self._converted(trail, pos)
            self._log(map_path(world_path), t, self._points(g, color))
            self._path(world_path, t, path, color)

    def estimate(self, world_path: str, t: float, e: Estimate, color, trail: Trail, grew: bool) -> None:
        """A fix or 3D track, when its path ``grew``: its position, the 95 % ring of its
        horizontal position, its ground track."""
        if not grew:
            return
        pos = geo.enu3(e.x)
        (g, ring), path = self._converted(trail, pos, geo.ring_enu(pos, geo.horizontal_cov(e.P)))
        self._log(map_path(world_path), t, self._points(g, color),
                  (rr.GeoLineStrings, {"line_strings": [geo.closed_ring(ring)], "colors": [color], "radii": [LINE_UI]}))
        self._path(world_path, t, path, color)

    def _path(self, world_path: str, t: float, path: np.ndarray, color) -> None:
        if len(path) > 1:
            self._log(map_path(world_path) + "/path", t,
                      (rr.GeoLineStrings, {"line_strings": [path], "colors": [color], "radii": [LINE_UI]}))

    def clear(self, world_path: str, t: float) -> None:
        self._log(map_path(world_path), t, (rr.Clear, {"is_recursive": [True]}))
