"""Geodesy at the edge of the estimator: WGS-84 <-> local east/north (pymap3d), and the magnetic
declination of the World Magnetic Model (pygeomag), so a magnetometer gives a true heading."""

from __future__ import annotations

import datetime
import math

import pymap3d
from pygeomag import GeoMag


class LocalFrame:
    """A local tangent plane (ENU) with its origin at the first GNSS fix."""

    def __init__(self, lat_deg: float, lon_deg: float, alt_m: float):
        self.lat0, self.lon0, self.alt0 = lat_deg, lon_deg, alt_m
        self._ecef0 = pymap3d.geodetic2ecef(lat_deg, lon_deg, alt_m)

    def to_en(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """pymap3d's geodetic2enu, with the origin's ECEF computed once."""
        x, y, z = pymap3d.geodetic2ecef(lat_deg, lon_deg, self.alt0)
        x0, y0, z0 = self._ecef0
        e, n, _ = pymap3d.uvw2enu(x - x0, y - y0, z - z0, self.lat0, self.lon0)
        return float(e), float(n)


# the World Magnetic Model's epoch: the date taken when a log does not say when it was recorded
# (the declination moves by about 0.1 degree a year; the compass offset the filter learns takes up
# what a wrong year leaves)
WMM_EPOCH = datetime.date(2025, 1, 1)


def declination_rad(lat_deg: float, lon_deg: float, alt_m: float, when: datetime.date) -> float:
    """Magnetic declination (east positive) from the World Magnetic Model on the day `when`.
    The core never reads the clock: the caller says which day (a log's, or today for a live link)."""
    year = when.year + (when.timetuple().tm_yday - 1) / 365.25
    r = GeoMag().calculate(glat=lat_deg, glon=lon_deg, alt=alt_m / 1000.0, time=year,
                           allow_date_outside_lifespan=True)
    return math.radians(r.d)


def wrap_pi(angle: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))
