"""The reference field along a track: the World Magnetic Model at every sample's latitude, longitude, altitude and
date, vectorised over the samples (site.py gives it at one point). A platform that climbs, drives or flies sees the
main field change under it (about -25 nT per km of height at mid latitudes; tens of nT per 100 km across the
ground): one --site total makes that change a residual that "follows time" and aliases into the calibration.

    wmm_field(lat, lon, alt_m, year)            (north, east, down) nT, arrays of any shape, WMM-2010 to WMM-2025
    track_reference(block, t0_unix_s, year)     the field along the lat_deg, lon_deg, alt_m columns as extras
                                                (ref_total and its direction) and a note saying it was used

The evaluation is pygeomag's (the WMM report's algorithm: geodetic -> spherical coordinates, Gauss-normalised
Legendre functions by recursion, the sums to degree 12) with the samples as numpy arrays and the terms as the
loop; it agrees with pygeomag's own GeoMag.calculate at sample points to 1e-6 nT (tests/numerics/test_track.py). The model
is the core field only: crustal anomalies and the day's variation (tens to hundreds of nT) are not in it.

Numerics only: the coefficients are the tables pygeomag ships as Python modules; no file is read here.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import DataError

#: the columns of a track (docs/csv.md) and those the reference along it adds
POSITION = ("lat_deg", "lon_deg", "alt_m")
DIRECTION = ("ref_north_nT", "ref_east_nT", "ref_down_nT")
ALTITUDE_RANGE_M = (-1000.0, 850_000.0)
#: samples evaluated at once (memory: about 30 arrays of this many float64)
CHUNK = 1 << 16
_A, _B, _RE = 6378.137, 6356.7523142, 6371.2          # WGS84 semi-axes and the model's reference radius, km


def _models() -> list[tuple]:
    from pygeomag.wmm import wmm_2010, wmm_2015v2, wmm_2020, wmm_2025

    return [wmm_2010.WMM_2010, wmm_2015v2.WMM_2015v2, wmm_2020.WMM_2020, wmm_2025.WMM_2025]


@lru_cache(maxsize=8)
def _coefficients(epoch: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """(g, h, dg, dh, k) (13, 13) Gauss-normalised as the WMM report's recursion wants them, and the model's name."""
    (ep, name, _), rows = next(m for m in _models() if m[0][0] == epoch)
    size = 13
    g, h, dg, dh = (np.zeros((size, size)) for _ in range(4))
    for n, m, gnm, hnm, dgnm, dhnm in rows:
        if n < size:
            g[n, m], h[n, m], dg[n, m], dh[n, m] = gnm, hnm, dgnm, dhnm
    snorm = np.zeros((size, size))
    snorm[0, 0] = 1.0
    k = np.zeros((size, size))
    for n in range(1, size):
        snorm[n, 0] = snorm[n - 1, 0] * (2 * n - 1) / n
        j = 2.0
        for m in range(0, n + 1):
            k[n, m] = ((n - 1) ** 2 - m * m) / ((2 * n - 1) * (2 * n - 3))
            if m > 0:
                snorm[n, m] = snorm[n, m - 1] * np.sqrt((n - m + 1) * j / (n + m))
                j = 1.0
    k[1, 1] = 0.0
    return g * snorm, h * snorm, dg * snorm, dh * snorm, k, str(name)


def model_span() -> tuple[float, float]:
    """The first and last decimal year of the models pygeomag ships (the first's epoch, the last's end of life)."""
    return float(_models()[0][0][0]), float(_models()[-1][0][0]) + 5.0


def model_for(year: float) -> tuple[float, str]:
    """(epoch, name) of the WMM whose five-year life holds `year`; DataError outside all of them."""
    for (ep, name, _), _ in reversed(_models()):
        if ep <= year <= ep + 5.0:
            return float(ep), str(name)
    lo, hi = model_span()
    raise DataError(f"the date {year:.2f} lies outside every World Magnetic Model pygeomag ships ({lo:.0f} to "
                    f"{hi:.0f}): no reference field along the track")


def wmm_field(lat_deg, lon_deg, alt_m, year, *, epoch: float | None = None) -> tuple[np.ndarray, ...]:
    """(north, east, down) nT of the WMM at geodetic latitude, longitude (degrees), height above the WGS84
    ellipsoid (m) and decimal year; arrays broadcast together. epoch: the model (None: the one whose life holds
    the first year)."""
    lat, lon, alt, yr = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (lat_deg, lon_deg, alt_m, year)))
    shape = lat.shape
    lat, lon, alt, yr = (v.reshape(-1) for v in (lat, lon, alt, yr))
    if epoch is None:
        epoch = model_for(float(yr.flat[0]))[0] if yr.size else 2025.0
    out = np.empty((3, lat.size))
    for a in range(0, lat.size, CHUNK):
        s = slice(a, a + CHUNK)
        out[:, s] = _wmm_chunk(lat[s], lon[s], alt[s] / 1000.0, yr[s] - epoch, _coefficients(epoch))
    return tuple(o.reshape(shape) for o in out)


def _wmm_chunk(glat: np.ndarray, glon: np.ndarray, alt: np.ndarray, dt: np.ndarray, coef) -> np.ndarray:
    """The WMM report's algorithm (as pygeomag.GeoMag.calculate) over arrays: (3, n) north, east, down."""
    gn, hn, dgn, dhn, k, _ = coef
    a2, b2 = _A * _A, _B * _B
    c2, a4, b4 = a2 - b2, a2 * a2, b2 * b2
    c4 = a4 - b4
    rlat, rlon = np.radians(glat), np.radians(glon)
    srlat, crlat = np.sin(rlat), np.cos(rlat)
    srlat2, crlat2 = srlat * srlat, crlat * crlat
    # geodetic -> spherical
    q = np.sqrt(a2 - c2 * srlat2)
    q1 = alt * q
    q2 = ((q1 + a2) / (q1 + b2)) ** 2
    ct = srlat / np.sqrt(q2 * crlat2 + srlat2)
    st = np.sqrt(1.0 - ct * ct)
    r = np.sqrt(alt * alt + 2.0 * q1 + (a4 - c4 * srlat2) / (q * q))
    d = np.sqrt(a2 * crlat2 + b2 * srlat2)
    ca = (alt + d) / r
    sa = c2 * crlat * srlat / (r * d)
    sp = [np.zeros_like(rlon), np.sin(rlon)]
    cp = [np.ones_like(rlon), np.cos(rlon)]
    for m in range(2, 13):
        sp.append(sp[1] * cp[m - 1] + cp[1] * sp[m - 1])
        cp.append(cp[1] * cp[m - 1] - sp[1] * sp[m - 1])
    aor = _RE / r
    ar = aor * aor
    zero = np.zeros_like(rlat)
    p = {(0, 0): np.ones_like(rlat)}
    dp = {(0, 0): zero}
    pp = {0: np.ones_like(rlat)}
    br = bt = bp = bpp = zero
    pole = st == 0.0
    for n in range(1, 13):
        ar = ar * aor
        for m in range(0, n + 1):
            if n == m:
                p[n, m] = st * p[n - 1, m - 1]
                dp[n, m] = st * dp[n - 1, m - 1] + ct * p[n - 1, m - 1]
            elif n == 1 and m == 0:
                p[n, m] = ct * p[n - 1, m]
                dp[n, m] = ct * dp[n - 1, m] - st * p[n - 1, m]
            else:
                p2 = p.get((n - 2, m), zero) if m <= n - 2 else zero
                dp2 = dp.get((n - 2, m), zero) if m <= n - 2 else zero
                p[n, m] = ct * p[n - 1, m] - k[n, m] * p2
                dp[n, m] = ct * dp[n - 1, m] - st * p[n - 1, m] - k[n, m] * dp2
            g = gn[n, m] + dt * dgn[n, m]
            par = ar * p[n, m]
            if m == 0:
                t1, t2 = g * cp[m], g * sp[m]
            else:
                hh = hn[n, m] + dt * dhn[n, m]
                t1 = g * cp[m] + hh * sp[m]
                t2 = g * sp[m] - hh * cp[m]
            bt = bt - ar * t1 * dp[n, m]
            bp = bp + m * t2 * par
            br = br + (n + 1) * t1 * par
            if m == 1 and pole.any():                      # at a geographic pole (st = 0)
                pp[n] = pp[n - 1] if n == 1 else ct * pp[n - 1] - k[n, m] * pp[n - 2]
                bpp = bpp + m * t2 * ar * pp[n]
    bp = np.where(pole, bpp, bp / np.where(pole, 1.0, st))
    return np.stack([-bt * ca - br * sa, bp, bt * sa - br * ca])


def decimal_years(unix_s: np.ndarray) -> np.ndarray:
    """Decimal years of UNIX times (the fraction of each sample's own calendar year).

    >>> round(float(decimal_years(np.array([1735689600.0 + 86400 * 73]))[0]), 6)     # 2025-03-15
    2025.2
    """
    u = np.asarray(unix_s, np.float64)
    years = u.astype("datetime64[s]").astype("datetime64[Y]")
    start = years.astype("datetime64[s]").astype(np.float64)
    end = (years + 1).astype("datetime64[s]").astype(np.float64)
    return years.astype(np.float64) + 1970.0 + (u - start) / (end - start)


@dataclass(frozen=True)
class Track:
    """The reference field along a track: the block with it in its extras, and what was used, as a note."""

    block: SampleBlock
    model: str
    total_nT: np.ndarray
    note: str
    notes: list[str] = field(default_factory=list)


def track_reference(block: SampleBlock, *, t0_unix_s: float | None = None, year: float | None = None) -> Track | None:
    """The WMM along the block's lat_deg, lon_deg, alt_m columns (None when it has not all three): extras ref_total
    (the model's total; a measured ref_total already in the block is kept and only the direction added) and
    ref_north_nT, ref_east_nT, ref_down_nT, each sample at its own date (t0_unix_s + t_s; else `year` for all; else
    today's, said). DataError for positions outside the model's range."""
    ex = block.extras
    if not all(c in ex for c in POSITION):
        return None
    lat, lon, alt = (np.asarray(ex[c], np.float64) for c in POSITION)
    bad = ~(np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt))
    if bad.any():
        raise DataError(f"lat_deg, lon_deg, alt_m: {int(bad.sum())} sample(s) without a finite position")
    if np.any(np.abs(lat) > 90.0) or np.any((lon < -180.0) | (lon > 360.0)):
        raise DataError("lat_deg, lon_deg: outside -90..90 and -180..360 degrees: not a position")
    lo, hi = ALTITUDE_RANGE_M
    if np.any((alt < lo) | (alt > hi)):
        raise DataError(f"alt_m: {float(alt.min()):.0f} to {float(alt.max()):.0f} m, outside the model's "
                        f"{lo:.0f} to {hi:.0f} m")
    notes = []
    if t0_unix_s is not None:
        yr = decimal_years(t0_unix_s + np.asarray(block.t_s, np.float64))
        when = f"each sample's date ({_dt.datetime.fromtimestamp(t0_unix_s, _dt.timezone.utc):%Y-%m-%d})"
    elif year is not None:
        yr = np.full(block.n_samples, float(year))
        when = f"the date given ({float(year):.2f})"
    else:
        from fluxcal.service.numerics.calib.site import decimal_year

        yr = np.full(block.n_samples, decimal_year(_dt.date.today()))
        when = "today's date (the recording does not say its date: give one)"
        notes.append("reference field along the track: the recording does not say its date, so the model is taken "
                     "at today's; the main field changes by up to about 150 nT a year (give the date)")
    epoch, name = model_for(float(yr[0]))
    north, east, down = wmm_field(lat, lon, alt, yr, epoch=epoch)
    total = np.sqrt(north * north + east * east + down * down)
    extras = dict(ex)
    measured = "ref_total" in ex
    if not measured:
        extras["ref_total"] = total
    extras.update(dict(zip(DIRECTION, (north, east, down))))
    rise = float(alt.max() - alt.min())
    note = (f"reference field along the track: {name} at every sample's lat_deg, lon_deg, alt_m and {when}: "
            f"{float(total.min()):,.1f} to {float(total.max()):,.1f} nT over {rise:,.0f} m of height"
            + (" (the measured ref_total column kept as the total; the model gives the direction, ref_north_nT, "
               "ref_east_nT, ref_down_nT)" if measured else
               " as ref_total, the total every sample is fitted to (crustal anomalies and the day's variation, "
               "tens to hundreds of nT, are not in the model)"))
    out = SampleBlock(t_s=block.t_s, seq=block.seq, field_nT=block.field_nT, temp_C=block.temp_C,
                      flags=block.flags, extras=extras)
    return Track(out, name, total, note, notes)


#: a residual that follows the height this strongly (explained variance, diagnose's `where`) is the main field's
#: change with height, when the reference field along the track is not used
FOLLOWS_HEIGHT = 0.5


def follows_height_note(where: list[dict], *, track_used: bool) -> str | None:
    """The note diagnose adds when its residual follows alt_m (diagnose's `where` entries: observable, strength) and
    the reference field along the track was not used: the field falls with height (about 25 nT per km), which a
    single total field (--site, the configuration's, or one estimated) cannot follow, and which a drift in time
    would only mimic on a steady climb."""
    if track_used:
        return None
    hits = [w for w in where if w.get("observable") == "alt_m" and float(w.get("strength", 0.0)) >= FOLLOWS_HEIGHT]
    if not hits:
        return None
    s = max(float(w["strength"]) for w in hits)
    return (f"the residual follows alt_m (explains {s:.0%} of it): the main field changes with height (the World "
            f"Magnetic Model: about -25 nT per km at mid latitudes), which one total field cannot follow; with the "
            f"lat_deg, lon_deg, alt_m columns the reference field along the track takes it (an effect that follows "
            f"time, such as drift, only mimics it on a steady climb)")
