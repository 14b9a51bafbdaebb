"""The site frame on the globe: a WGS 84 local tangent plane around a datum (x east, y north).

A fleet's site frame has its origin at a datum (lat [deg], lon [deg], alt [m]) and its axes
along the datum's local east and north: a point's site (x, y) are the east and north
components of its ENU (east-north-up) vector from the datum. This is the one copy of that
conversion: the MAVLink driver places a rover by its ``GLOBAL_POSITION_INT`` with it and the
simulated rover (``stack.sim_bridge.rover_sim``) sends its ``GLOBAL_POSITION_INT`` and
``LOCAL_POSITION_NED`` with it.

Formulas (exact on the WGS 84 ellipsoid, no small-offset approximation; NIMA TR8350.2, 3rd
ed. (2000): the constants in its Table 3.1, geodetic -> ECEF in its section 4.1):

* geodetic -> ECEF: ``N = a / sqrt(1 - e^2 sin^2(lat))``;
  ``X = (N + h) cos(lat) cos(lon)``, ``Y = (N + h) cos(lat) sin(lon)``, ``Z = (N (1 - e^2) + h) sin(lat)``.
* ECEF -> ENU at the datum (lat0, lon0): ``e = -sin(lon0) dX + cos(lon0) dY``,
  ``n = -sin(lat0) cos(lon0) dX - sin(lat0) sin(lon0) dY + cos(lat0) dZ``,
  ``u = cos(lat0) cos(lon0) dX + cos(lat0) sin(lon0) dY + sin(lat0) dZ`` (the rotation of, e.g.,
  Hofmann-Wellenhof, Lichtenegger & Wasle, *GNSS*, Springer 2008, section 2.2.3); ENU -> ECEF
  is its transpose.
* ECEF -> geodetic: the fixed-point iteration ``lat = atan2(Z + e^2 N sin(lat), p)``,
  ``p = sqrt(X^2 + Y^2)`` (same book, section 2.2.1), to 1e-12 rad (a few um).

A rover drives on the ground, not on the tangent plane (which rises 7.8 cm above the
ground 1 km out): ``site_to_geodetic`` puts a site point at the datum's altitude (or the
one given) and ``geodetic_to_site`` projects a fix at its own altitude onto the plane, so a
round trip is exact to micrometres; the site frame is metric to better than 1 mm over 5 km
(the projection shortens a ground distance d by about d^3 / (6 R^2)). Altitudes are taken
as the datum's (GLOBAL_POSITION_INT ``alt`` is above mean sea level, not the ellipsoid: the
geoid's separation is nearly constant over a site, and 10 m of height moves a fix 1 km
out by 1.6 mm horizontally).

Not ArduPilot's model: ArduPilot's ``Location`` (and pymavlink's ``mavextra.gps_offset``)
use a sphere of radius 6 378 100 m; its north metres are ``M / 6378100`` of ours (M the
meridian radius: 0.13 % short at 47 deg latitude) and its east metres ``N / 6378100``. Every
rover's GLOBAL_POSITION_INT is converted here, so the fleet agrees whatever the vehicles use
inside.

>>> datum = (47.3977, 8.5456, 488.0)
>>> x, y = geodetic_to_site(datum, *site_to_geodetic(datum, 120.0, -35.0))
>>> round(x, 6), round(y, 6)
(120.0, -35.0)
"""

from __future__ import annotations

import math
from typing import Any

WGS84_A = 6_378_137.0
"""[m] WGS 84 semi-major axis (NIMA TR8350.2 Table 3.1)."""
WGS84_F = 1.0 / 298.257223563
"""WGS 84 flattening (NIMA TR8350.2 Table 3.1)."""
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
"""First eccentricity squared."""

LAT_LIMIT = 89.0
"""[deg] a datum's latitude within +-89 deg: the tangent plane's east axis is undefined at the poles."""
ALT_RANGE = (-1000.0, 10_000.0)
"""[m] a datum's altitude range (the Dead Sea shore to above any site)."""

Datum = tuple[float, float, float]


def check_datum(value: Any, name: str = "datum") -> Datum:
    """``[lat_deg, lon_deg, alt_m]`` (a list or tuple of three finite numbers in range) -> a tuple of floats;
    anything else raises a one-line ValueError naming ``name`` and what is wrong."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise ValueError(f"{name} must be [lat_deg, lon_deg, alt_m], not {value!r}")
    limits = (("latitude", -LAT_LIMIT, LAT_LIMIT), ("longitude", -180.0, 180.0), ("altitude", *ALT_RANGE))
    for v, (what, low, high) in zip(value, limits):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"{name} {what} must be a finite number, not {v!r}")
        if not low <= v <= high:
            raise ValueError(f"{name} {what} must be within [{low:g}, {high:g}], not {v!r}")
    return float(value[0]), float(value[1]), float(value[2])


# --- ellipsoid <-> ECEF <-> ENU ------------------------------------------------------------
def geodetic_to_ecef(lat: float, lon: float, alt: float) -> tuple[float, float, float]:
    """(lat [deg], lon [deg], height [m]) -> Earth-centred Earth-fixed (X, Y, Z) [m] (TR8350.2 section 4.1)."""
    phi, lam = math.radians(lat), math.radians(lon)
    s = math.sin(phi)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
    return ((n + alt) * math.cos(phi) * math.cos(lam), (n + alt) * math.cos(phi) * math.sin(lam),
            (n * (1.0 - WGS84_E2) + alt) * s)


def ecef_to_geodetic(x: float, y: float, z: float) -> tuple[float, float, float]:
    """ECEF (X, Y, Z) [m] -> (lat [deg], lon [deg], height [m]), by fixed-point iteration on the latitude."""
    p = math.hypot(x, y)
    phi = math.atan2(z, p * (1.0 - WGS84_E2))
    for _ in range(10):
        s = math.sin(phi)
        n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
        nxt = math.atan2(z + WGS84_E2 * n * s, p)
        done = abs(nxt - phi) < 1e-12
        phi = nxt
        if done:
            break
    s, c = math.sin(phi), math.cos(phi)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
    h = p / c - n if abs(c) > 1e-3 else z / s - n * (1.0 - WGS84_E2)
    return math.degrees(phi), math.degrees(math.atan2(y, x)), h


def _axes(lat0: float, lon0: float) -> tuple[tuple[float, float, float], ...]:
    """The datum's east, north and up unit vectors in ECEF (rows of the ECEF -> ENU rotation)."""
    sp, cp = math.sin(math.radians(lat0)), math.cos(math.radians(lat0))
    sl, cl = math.sin(math.radians(lon0)), math.cos(math.radians(lon0))
    return (-sl, cl, 0.0), (-sp * cl, -sp * sl, cp), (cp * cl, cp * sl, sp)


def geodetic_to_enu(datum: Datum, lat: float, lon: float, alt: float) -> tuple[float, float, float]:
    """(east, north, up) [m] of (lat, lon, alt) from ``datum`` (lat, lon, alt)."""
    x0, y0, z0 = geodetic_to_ecef(*datum)
    x, y, z = geodetic_to_ecef(lat, lon, alt)
    d = (x - x0, y - y0, z - z0)
    return tuple(sum(a * b for a, b in zip(row, d)) for row in _axes(datum[0], datum[1]))  # type: ignore[return-value]


def enu_to_geodetic(datum: Datum, east: float, north: float, up: float) -> tuple[float, float, float]:
    """(lat, lon, alt) of the point (east, north, up) [m] from ``datum``: the inverse of geodetic_to_enu."""
    e, n, u = _axes(datum[0], datum[1])
    x0, y0, z0 = geodetic_to_ecef(*datum)
    return ecef_to_geodetic(x0 + e[0] * east + n[0] * north + u[0] * up,
                            y0 + e[1] * east + n[1] * north + u[1] * up,
                            z0 + e[2] * east + n[2] * north + u[2] * up)


# --- the site frame (x east, y north) and NED offsets ----------------------------------------
def site_to_geodetic(datum: Datum, x: float, y: float, alt: float | None = None) -> Datum:
    """A site-frame position (x east, y north) [m] on the ground at ``alt`` (default the datum's):
    (lat [deg], lon [deg], alt [m]). Its inverse is geodetic_to_site."""
    h0 = datum[2] if alt is None else alt
    up = h0 - datum[2] - (x * x + y * y) / (2.0 * WGS84_A)  # the ground falls away below the plane
    for _ in range(4):  # the up that puts the point at height h0 (dh/du is 1 to 1e-6 over a site)
        lat, lon, h = enu_to_geodetic(datum, x, y, up)
        if abs(h - h0) < 1e-7:
            break
        up -= h - h0
    return lat, lon, h0


def geodetic_to_site(datum: Datum, lat: float, lon: float, alt: float | None = None) -> tuple[float, float]:
    """Site (x east, y north) [m] of (lat, lon) at ``alt`` (default the datum's), projected on the datum's plane."""
    east, north, _ = geodetic_to_enu(datum, lat, lon, datum[2] if alt is None else alt)
    return east, north


def ne_to_geodetic(origin: Datum, north: float, east: float) -> Datum:
    """(lat, lon, alt) at (north, east) [m] from ``origin`` (an EKF origin: LOCAL_POSITION_NED's x, y)."""
    return site_to_geodetic(origin, east, north)


def geodetic_to_ne(origin: Datum, lat: float, lon: float, alt: float | None = None) -> tuple[float, float]:
    """(north, east) [m] of (lat, lon) from ``origin``: the inverse of ne_to_geodetic."""
    east, north = geodetic_to_site(origin, lat, lon, alt)
    return north, east


__all__ = ["ALT_RANGE", "Datum", "LAT_LIMIT", "WGS84_A", "WGS84_E2", "WGS84_F", "check_datum", "ecef_to_geodetic",
           "enu_to_geodetic", "geodetic_to_ecef", "geodetic_to_enu", "geodetic_to_ne", "geodetic_to_site",
           "ne_to_geodetic", "site_to_geodetic"]
