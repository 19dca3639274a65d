"""The main geomagnetic field at a site from the World Magnetic Model (the model of the date's five years, WMM-2010
to WMM-2025, from the coefficients pygeomag ships, evaluated as along a track: track.py): the known total field that
`tmi` needs, and that fixes the scale of an ellipsoid, without a scalar magnetometer at the site.

The model describes the core field only: crustal anomalies (tens to hundreds of nT, more near
ore bodies or buildings) and the day's variation (tens of nT) are not in it, so a site figure is a
reference at the 0.1-1 % level, not a substitute for a scalar magnetometer at the nT level.
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import asdict, dataclass

from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.numerics.calib.track import ALTITUDE_RANGE_M, model_for, model_span, wmm_field

SITE_FORMAT = "LAT,LON[,ALT_M[,DATE]] (degrees north, degrees east, metres above the WGS84 ellipsoid, 0 if left " \
              "out; DATE as YYYY-MM-DD or a decimal year, today if left out)"


@dataclass(frozen=True)
class SiteField:
    """The model's field at one place and time (north, east, down components, nT)."""

    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    year: float                  # decimal year
    total_nT: float
    inclination_deg: float       # positive down
    declination_deg: float       # positive east of true north
    north_nT: float
    east_nT: float
    down_nT: float
    model: str

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        return (f"{self.model} at {self.latitude_deg:.4f}°N {self.longitude_deg:.4f}°E, {self.altitude_m:.0f} m, "
                f"{self.year:.2f}: F = {self.total_nT:.1f} nT, inclination {self.inclination_deg:.2f}°, "
                f"declination {self.declination_deg:.2f}°")


def decimal_year(when: _dt.date | _dt.datetime) -> float:
    start = _dt.date(when.year, 1, 1)
    days = (_dt.date(when.year + 1, 1, 1) - start).days
    day = (when.date() if isinstance(when, _dt.datetime) else when) - start
    return when.year + day.days / days


def parse_site(text: str, key: str = "--site") -> tuple[float, float, float, float | None]:
    """(lat, lon, alt_m, year or None) from "LAT,LON[,ALT_M[,DATE]]"; ConfigError naming the key otherwise. The
    altitude left out is 0 m: the main field changes by 0.01-0.03 nT a metre of height (-8 to -32 nT a km in
    WMM-2025 at 30°S 60°W to 75°S 120°E), 0.03-0.06 % a km, within the model's own 0.1-1 % at a site."""
    parts = [p.strip() for p in str(text).split(",")]

    def bad(why: str) -> ConfigError:
        return ConfigError(f"{key}: {text!r} is not allowed ({why}; allowed: {SITE_FORMAT})")

    if len(parts) not in (2, 3, 4):
        raise bad(f"{len(parts)} field{'s' if len(parts) != 1 else ''}")
    try:
        lat, lon, alt = (float(p) for p in (parts + ["0"])[:3])
    except ValueError:
        raise bad("latitude, longitude and altitude must be numbers") from None
    if not -90.0 <= lat <= 90.0:
        raise bad("latitude outside -90..90")
    if not -180.0 <= lon <= 360.0:
        raise bad("longitude outside -180..360")
    if not ALTITUDE_RANGE_M[0] <= alt <= ALTITUDE_RANGE_M[1]:
        raise bad("altitude outside the model's -1000..850000 m")
    year = None
    if len(parts) == 4:
        try:
            year = decimal_year(_dt.date.fromisoformat(parts[3]))
        except ValueError:
            try:
                year = float(parts[3])
            except ValueError:
                raise bad("DATE is neither YYYY-MM-DD nor a decimal year") from None
    return lat, lon, alt, year


def site_field(latitude_deg: float, longitude_deg: float, altitude_m: float, year: float | None = None,
               *, key: str = "--site") -> SiteField:
    """The WMM field at the site (year: decimal year, today when None), from the model whose five-year life holds
    the year (track.model_for: the same model a track of that date is given). ConfigError outside every model pygeomag
    ships, saying what to give instead."""
    if year is None:
        year = decimal_year(_dt.date.today())
    try:
        epoch, name = model_for(float(year))
    except DataError:
        lo, hi = model_span()
        raise ConfigError(f"{key}: the date {year:.2f} is not allowed (no World Magnetic Model pygeomag ships covers "
                          f"it; allowed: {lo:.0f} to {hi:.0f}): give a date within those years, or "
                          f"the total field itself (a ref_total column, or estimator.total_nT in --config)") from None
    north, east, down = (float(c) for c in wmm_field(latitude_deg, longitude_deg, altitude_m, year, epoch=epoch))
    horizontal = math.hypot(north, east)
    return SiteField(latitude_deg, longitude_deg, altitude_m, float(year), math.hypot(horizontal, down),
                     math.degrees(math.atan2(down, horizontal)), math.degrees(math.atan2(east, north)),
                     north, east, down, name)


def site_from_text(text: str, key: str = "--site") -> SiteField:
    return site_field(*parse_site(text, key), key=key)
