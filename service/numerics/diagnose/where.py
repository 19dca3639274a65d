"""Where the model fails: what the residual follows (time, temperature, rate, attitude, frequency, extra
columns) and the worst time segments.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.effects.thermal import low_pass
from fluxcal.service.numerics.effects.timebase import sample_grid
from fluxcal.service.numerics.engine import FitResult

WHERE_MAX_ROWS = 20000
LAGS_S = (60.0, 300.0)      # delayed temperatures tried: first-order lags of a minute and of five


def _legendre(x: np.ndarray, deg: int) -> np.ndarray:
    lo, hi = float(np.min(x)), float(np.max(x))
    z = np.zeros_like(x) if hi <= lo else 2.0 * (x - lo) / (hi - lo) - 1.0
    return np.polynomial.legendre.legvander(z, deg)[:, 1:]


def _r2(y: np.ndarray, cols: np.ndarray) -> float:
    """Adjusted R^2 of y on [1, cols], clipped to [0, 1]."""
    n = y.size
    x = np.column_stack([np.ones(n), cols])
    ok = np.all(np.isfinite(x), axis=1) & np.isfinite(y)
    x, yy = x[ok], y[ok]
    n, q = yy.size, x.shape[1] - 1
    if n <= q + 2:
        return 0.0
    sd = x.std(0)
    sd[0] = 1.0
    sd[sd == 0] = 1.0
    beta, *_ = np.linalg.lstsq(x / sd, yy, rcond=None)
    resid = yy - (x / sd) @ beta
    sst = float(np.sum((yy - yy.mean()) ** 2))
    if sst <= 0:
        return 0.0
    r2 = 1.0 - (float(resid @ resid) / (n - q - 1)) / (sst / (n - 1))
    return float(np.clip(r2, 0.0, 1.0))


ETA_BINS = 16


def _eta2(y: np.ndarray, x: np.ndarray, bins: int = ETA_BINS) -> float:
    """The correlation ratio of y on x (the variance of y explained by the mean of y in each of `bins`
    quantile bins of x), adjusted for the bins' degrees of freedom: a tie of any shape, a threshold or an
    oscillation that a polynomial in x misses."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = y.size
    if n <= 2 * bins:
        return 0.0
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)[1:-1]))
    idx = np.searchsorted(edges, x, side="right")
    k = int(idx.max()) + 1
    counts = np.bincount(idx, minlength=k)
    means = np.bincount(idx, weights=y, minlength=k) / np.maximum(counts, 1)
    sst = float(np.sum((y - y.mean()) ** 2))
    if sst <= 0 or k < 2:
        return 0.0
    eta2 = float(np.sum(counts * (means - y.mean()) ** 2)) / sst
    return float(np.clip(1.0 - (1.0 - eta2) * (n - 1) / (n - k), 0.0, 1.0))


def observables(data: EffectData, fit: FitResult, rows: np.ndarray) -> dict[str, Any]:
    """Observable bases at the given rows (indices into the full data): name -> per-channel function."""
    pr = fit.problem
    full_rows = pr.rows[rows]
    t = data.t_s[full_rows]
    out: dict[str, Any] = {"time": _with_scalar(lambda c: _legendre(t, 4), t)}
    if data.has_temperature() and float(np.ptp(data.temperature(0))) > 1e-6:
        temps = [data.temperature(k)[full_rows] for k in range(data.n_probes)]

        def temp_basis(c: int) -> np.ndarray:
            kind, k = pr.channel_probe(c)
            ks = [k, 0] if kind == "diff" else [k]
            cols = []
            for k in ks:
                cols += [temps[k], temps[k] ** 2]
            return np.column_stack(cols)
        out["temperature"] = _with_scalar(temp_basis, lambda c: temps[pr.channel_probe(c)[1]])
        # its rate and delayed versions: a core that lags its logged temperature follows these better
        full_t = [data.temperature(k) for k in range(data.n_probes)]
        rates = [np.gradient(low_pass(data.t_s, v, 10.0), data.t_s)[full_rows] for v in full_t]
        lagged = [np.column_stack([low_pass(data.t_s, v, tau)[full_rows] for tau in LAGS_S]) for v in full_t]

        def of_probes(per_probe: list[np.ndarray]) -> Any:
            def basis(c: int) -> np.ndarray:
                kind, k = pr.channel_probe(c)
                return np.column_stack([per_probe[j] for j in ([k, 0] if kind == "diff" else [k])])
            return basis
        out["temperature rate"] = of_probes(rates)
        out["temperature, delayed"] = of_probes(lagged)
    # angular rate from probe 1: omega_perp = |b x db/dt| / |b|^2 (rad/s); and the rate's direction
    s1 = data.smooth(0)[full_rows]
    r1 = data.rate(0)[full_rows]
    b2 = np.sum(s1 ** 2, axis=1)
    omega = np.linalg.norm(np.cross(s1, r1), axis=1) / b2
    rate_dir = r1 / np.sqrt(b2)[:, None]
    out["angular rate"] = _with_scalar(lambda c: np.column_stack([omega, omega ** 2, rate_dir]), omega)
    us = [fit.ev.nhat[k][rows] for k in range(pr.P)]

    def probe_u(c: int) -> np.ndarray:
        kind, k = pr.channel_probe(c)
        return us[0] if kind == "diff" else us[k]

    def orient(c: int) -> np.ndarray:
        u = probe_u(c)
        return np.column_stack([u, u[:, 0] ** 2 - u[:, 2] ** 2, u[:, 1] ** 2 - u[:, 2] ** 2,
                                u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]])
    out["orientation"] = orient

    def heading(c: int) -> np.ndarray:
        u = probe_u(c)
        psi = np.arctan2(u[:, 1], u[:, 0])
        return np.column_stack([f(k * psi) for k in (1, 2, 3) for f in (np.cos, np.sin)])
    out["heading"] = _with_scalar(heading, lambda c: np.arctan2(probe_u(c)[:, 1], probe_u(c)[:, 0]))
    if data.ref_total_nT is not None and float(np.ptp(data.ref_total_nT)) > 1.0:
        f = data.ref_total_nT[full_rows]
        out["field magnitude"] = _with_scalar(lambda c: np.column_stack([f, f ** 2]), f)
    for name, vals in data.observables().items():
        v = vals[full_rows]
        if float(np.ptp(v)) > 0:
            out[name] = _with_scalar(lambda c, _v=v: np.column_stack([_v, _v ** 2]), v)
            out[f"{name} x field direction"] = _times_direction(v, probe_u)
    if "temperature" in out:
        out["temperature x field direction"] = _times_direction(
            lambda c: temps[pr.channel_probe(c)[1]], probe_u)
    return out


def _times_direction(x: Any, direction: Any) -> Any:
    """The basis x n_a, x (n_a^2 - 1/3) of an observable x times the field's direction n in the channel's probe:
    an offset that follows x shows in a scalar channel as x n.b, a scale that follows it as x n_a^2, which no
    association with x alone, or with the direction alone, sees (a heater current coupled into a probe's axes)."""
    def basis(c: int) -> np.ndarray:
        v = x(c) if callable(x) else x
        u = direction(c)
        v = v - np.mean(v)
        return np.column_stack([v[:, None] * u, v[:, None] * (u[:, :2] ** 2 - 1.0 / 3.0)])
    return basis


def _with_scalar(basis: Any, scalar: Any) -> Any:
    """A basis that also names its observable as one column per channel (an array, or channel -> array), whose
    tie of any shape (thresholds, steps, oscillations a small polynomial misses) is measured too."""
    basis.scalar = scalar if callable(scalar) else (lambda c, _x=scalar: _x)
    return basis


#: the width of the band named: the span from the record's longest period to the Nyquist frequency in BANDS equal
#: steps of log frequency; the band slides in steps of 1/FINE_PER_BAND of its width to where it holds the most
BANDS = 12
FINE_PER_BAND = 16


@dataclass(frozen=True)
class ExcessSpectrum:
    """A residual's periodogram averaged in log-spaced bins, against its white floor, and the band of its excess
    that `where` names: what the diagnose report draws and what its text says, from one computation."""

    freq_hz: np.ndarray                   # (m,) each non-empty fine bin: the geometric mean of its FFT frequencies
    density: np.ndarray                   # (m,) its mean one-sided periodogram, nT²/Hz
    floor: float                          # the white floor's one-sided density 2 σ² dt, nT²/Hz
    share: float                          # the fraction of the variance above the floor in the band (0: none)
    band_hz: tuple[float, float] | None   # the band, Hz; None without any excess

    @property
    def band(self) -> str:
        return "" if self.band_hz is None else f"{self.band_hz[0]:.3g}-{self.band_hz[1]:.3g} Hz"


def excess_spectrum(y: np.ndarray, dt: float, noise: float) -> ExcessSpectrum:
    """The band of a residual's spectrum holding the largest share of its variance above the white-noise floor,
    among the bands 1/BANDS of the record's span in log frequency wide, slid in fine steps: placed where the
    excess lies. (Bands at fixed edges named the one holding most of a hump that straddled two: "1.19-2.55 Hz"
    for a hump at 0.9-1.8 Hz, 50 Hz for 370 s, while the report's plot showed the hump.)"""
    n = y.size
    empty = ExcessSpectrum(np.zeros(0), np.zeros(0), 2.0 * noise ** 2 * dt, 0.0, None)
    if n < 64:
        return empty
    y = y - y.mean()
    spec = np.abs(np.fft.rfft(y)) ** 2 / n                  # periodogram, E = variance for white noise
    freq = np.fft.rfftfreq(n, dt)
    total = float(np.sum(y ** 2) / n)
    if total <= 0:
        return empty
    spec, freq = spec[1:], freq[1:]                           # no mean
    edges = np.geomspace(freq[0], freq[-1] * 1.0001, BANDS * FINE_PER_BAND + 1)
    which = np.clip(np.searchsorted(edges, freq, side="right") - 1, 0, edges.size - 2)
    m = edges.size - 1
    count = np.bincount(which, minlength=m)
    summed = np.bincount(which, weights=spec, minlength=m)
    # share of the mean square per fine bin: (2/n) sum spec; white noise of variance s^2 has E[spec] = s^2
    excess = (2.0 / n) * (summed - noise ** 2 * count) / total
    ok = count > 0
    first = np.searchsorted(which, np.arange(m), side="left")
    last = np.searchsorted(which, np.arange(m), side="right") - 1
    centre = np.sqrt(freq[first[ok]] * freq[last[ok]])
    density = 2.0 * dt * summed[ok] / count[ok]
    floor = 2.0 * noise ** 2 * dt
    # each band of FINE_PER_BAND fine bins that holds a frequency of the record, by its share
    cum = np.concatenate([[0.0], np.cumsum(excess)])
    held = cum[FINE_PER_BAND:] - cum[:-FINE_PER_BAND]
    ccount = np.concatenate([[0], np.cumsum(count)])
    held = np.where(ccount[FINE_PER_BAND:] - ccount[:-FINE_PER_BAND] > 0, held, -np.inf)
    k = int(np.argmax(held))
    share = float(held[k])
    if not share > 0:
        return ExcessSpectrum(centre, density, floor, 0.0, None)
    # a line or a narrow hump lies in many bands alike (their shares differ by the periodogram's scatter, whose
    # standard deviation in a band of c bins is sqrt(c) (2/n) s^2 / total): of those, the one centred on it
    scatter = 2.0 * np.sqrt(ccount[k + FINE_PER_BAND] - ccount[k]) * (2.0 / n) * noise ** 2 / total
    pos = np.clip(excess[k:k + FINE_PER_BAND], 0.0, None)
    mid = np.log(np.sqrt(edges[:-1] * edges[1:]))                  # each fine bin's middle, log Hz
    at = float(np.sum(pos * mid[k:k + FINE_PER_BAND]) / np.sum(pos))
    alike = np.flatnonzero(held >= share - scatter)
    k = int(alike[np.argmin(np.abs(0.5 * (np.log(edges[alike]) + np.log(edges[alike + FINE_PER_BAND])) - at))])
    share = float(held[k])
    return ExcessSpectrum(centre, density, floor, float(min(share, 1.0)),
                          (float(edges[k]), float(edges[k + FINE_PER_BAND])))


def _band_excess(y: np.ndarray, dt: float, noise: float) -> tuple[float, str, tuple[float, float] | None]:
    """Strongest frequency band of a residual above its white-noise floor: (fraction of variance, band, its edges
    in Hz); excess_spectrum."""
    ex = excess_spectrum(y, dt, noise)
    return float(np.clip(ex.share, 0.0, 1.0)), ex.band, ex.band_hz


#: a residual band that holds at least this share of the turning of the field's direction, where it turns by
#: TURN_MIN_RAD or more within the band, is at the rates the probe turns (hand-turned real boards: the sphere 0.32),
#: no disturbance near it (band_share; signature's advice)
TURNING_SHARE = 0.3
TURN_MIN_RAD = 0.05


def band_share(x: np.ndarray, dt: float, band_hz: tuple[float, float]) -> float:
    """The fraction of the turning of the field's direction x / |x| (x: (N, 3), its mean direction taken out) at
    frequencies within band_hz, 0 where it turns by less than TURN_MIN_RAD (rms) there: the field a probe reads turns
    at the rates the probe turns, so a residual band that holds much of that is the turning's. The direction, not the
    field: a still probe's field varies only by what disturbs it (a pump at 1.5 Hz was 0.94 of the raw field's
    variation, and read as a turning it was not)."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.all(np.isfinite(x), axis=1)]
    mag = np.linalg.norm(x, axis=1)
    x = x[mag > 0] / mag[mag > 0, None]
    if x.shape[0] < 8:
        return 0.0
    spec = np.abs(np.fft.rfft(x - x.mean(0), axis=0)) ** 2
    power = spec.sum(1)
    f = np.fft.rfftfreq(x.shape[0], dt)
    total = float(power[1:].sum())
    inside = (f >= band_hz[0]) & (f <= band_hz[1])
    # the band's rms turning in radians: Parseval for the one-sided spectrum of a real signal
    turned = float(np.sqrt(2.0 * power[inside].sum()) / x.shape[0])
    return float(power[inside].sum() / total) if total > 0 and turned >= TURN_MIN_RAD else 0.0


def where_it_fails(data: EffectData, fit: FitResult, noise_nT: np.ndarray, *, top: int = 30,
                   min_strength: float = 0.05) -> list[dict[str, Any]]:
    """(channel, observable, strength) sorted strongest first; strength = explained variance fraction (adjusted
    R^2 of a small basis in the observable, or its correlation ratio over quantile bins of the observable as one
    column, whichever is larger: time, temperature, angular rate, heading, field magnitude, logged columns)."""
    pr = fit.problem
    m = pr.M
    stride = max(1, m // WHERE_MAX_ROWS)
    rows = np.arange(0, m, stride)
    obs = observables(data, fit, rows)
    vals = fit.channels.values
    step = sample_grid(fit.channels.t_s)[1]      # the spectra's interval: a bursty time base's mean, as everywhere
    out = []
    for c, name in enumerate(fit.channels.names):
        y = vals[rows, c]
        for oname, basis in obs.items():
            s = _r2(y, basis(c))
            x = getattr(basis, "scalar", None)
            if x is not None:
                s = max(s, _eta2(y, x(c)))
            if s >= min_strength:
                out.append({"channel": name, "observable": oname, "strength": s})
        s, band, edges = _band_excess(vals[:, c], step, float(noise_nT[c]))
        if s >= min_strength:
            field = data.raw_nT[pr.rows, pr.channel_probe(c)[1]]
            out.append({"channel": name, "observable": "frequency", "strength": s, "band": band,
                        "band_hz": list(edges), "turning_share": band_share(field, step, edges)})
    out.sort(key=lambda d: -d["strength"])
    return out[:top]


def worst_segments(fit: FitResult, *, n_segments: int = 20, top: int = 3) -> list[dict[str, Any]]:
    """The time segments with the largest RMS over all channels."""
    vals, t = fit.channels.values, fit.channels.t_s
    edges = np.linspace(0, vals.shape[0], n_segments + 1).round().astype(int)
    segs = []
    for a, b in zip(edges[:-1], edges[1:]):
        if b <= a:
            continue
        per = np.sqrt(np.mean(vals[a:b] ** 2, axis=0))
        c = int(np.argmax(per))
        segs.append({"t_start_s": float(t[a]), "t_end_s": float(t[b - 1]),
                     "rms_nT": float(np.sqrt(np.mean(vals[a:b] ** 2))),
                     "worst_channel": fit.channels.names[c], "worst_channel_rms_nT": float(per[c])})
    segs.sort(key=lambda d: -d["rms_nT"])
    return segs[:top]


#: a stretch of time is gross where its residual RMS (in noise units, over all channels) is this many times the
#: median segment's; measured on real boards: 1.3-2.2 x on full spheres (suarez, freeimucal, sensorfusion), 4 x
#: on two hand-held ones (nliaudat, a flight), 7 x on a hand-held sphere with a 47-s disturbance (Magneto's test
#: file); 1.06 on a simulated pair
GROSS_RATIO = 3.0
#: ... and covers at most this share of the record (more is no stretch but the residual's way)
GROSS_SHARE = 0.1


def _segments(fit: FitResult, noise: np.ndarray,
              n_segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Each row's mean square residual in noise units over the channels, the edges of n_segments equal segments
    (at least 20 rows each), each segment's mean square and their median; None when too short to say."""
    vals = fit.channels.values
    n = vals.shape[0]
    k = min(n_segments, n // 20)
    if k < 5:
        return None
    z2 = np.nanmean((vals / noise[None, :]) ** 2, axis=1)
    edges = np.linspace(0, n, k + 1).round().astype(int)
    m = np.array([np.nanmean(z2[a:b]) for a, b in zip(edges[:-1], edges[1:])])
    typical = float(np.nanmedian(m))
    return (z2, edges, m, typical) if typical > 0 else None


def gross_stretch(fit: FitResult, noise: np.ndarray, *, n_segments: int = 50) -> dict[str, Any] | None:
    """The one stretch of time where the residual stands far above the rest: the worst of n_segments equal
    segments with its neighbours that are as gross, when its RMS in noise units is at least GROSS_RATIO times the
    median segment's and the stretch covers at most GROSS_SHARE of the rows; else None.
    {"t_start_s", "t_end_s", "ratio"} (ratio: the stretch's RMS over the median segment's)."""
    seg = _segments(fit, noise, n_segments)
    if seg is None:
        return None
    z2, edges, m, typical = seg
    ratio = np.sqrt(np.where(np.isfinite(m), m, 0.0) / typical)
    k = ratio.size
    worst = int(np.argmax(ratio))
    if ratio[worst] < GROSS_RATIO:
        return None
    # its neighbours join where they are gross too, and within a factor 3 of it (a strong disturbance's pull on the
    # fit makes other segments a few times the median: they are its echo, not the disturbance)
    join = max(GROSS_RATIO, ratio[worst] / 3.0)
    lo = hi = worst
    while lo > 0 and ratio[lo - 1] >= join:
        lo -= 1
    while hi < k - 1 and ratio[hi + 1] >= join:
        hi += 1
    a, b = edges[lo], edges[hi + 1]
    # the disturbance need not start and end on segment edges: grown by fifths of a segment that are as gross
    fine, bar = max(4, (edges[1] - edges[0]) // 5), join ** 2 * typical
    while a > 0 and np.nanmean(z2[max(0, a - fine):a]) >= bar:
        a = max(0, a - fine)
    while b < z2.size and np.nanmean(z2[b:b + fine]) >= bar:
        b = min(z2.size, b + fine)
    if b - a > GROSS_SHARE * z2.size:
        return None
    t = fit.channels.t_s
    return {"t_start_s": float(t[a]), "t_end_s": float(t[b - 1]),
            "ratio": float(np.sqrt(np.nanmean(z2[a:b]) / typical))}


def stretch_ratio(fit: FitResult, noise: np.ndarray, t_start_s: float, t_end_s: float, *,
                  n_segments: int = 50) -> float:
    """The RMS (noise units) of fit's residual over [t_start_s, t_end_s] against its median segment's (as
    gross_stretch measures it): how gross a fit leaves a stretch another fit found gross."""
    seg = _segments(fit, noise, n_segments)
    if seg is None:
        return float("nan")
    z2, _, _, typical = seg
    t = fit.channels.t_s
    inside = (t >= t_start_s) & (t <= t_end_s)
    return float(np.sqrt(np.nanmean(z2[inside]) / typical)) if inside.any() else float("nan")
