"""The residual's spectra for discovery's library (library.py): the sets of series whose summed spectrum shows a
field at a frequency, their excess power over the white floor, and the residual's spectral lines; each can leave out
a span of rows (a held-out block, which the lines and bands of its fold must not see). Numerics only."""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.timebase import sample_grid

#: a spectral line: a Welch bin this many times the median of its neighbourhood, holding this share of a channel's
#: excess power; at most MAX_LINES lines
LINE_FACTOR = 8.0
LINE_SHARE = 0.05
MAX_LINES = 2


def series(fit: Any, noise: np.ndarray, exclude: tuple[int, int] | None = None) -> list[tuple[np.ndarray, float]]:
    """The residual as sets of series whose summed spectrum shows a field at a frequency, each with its white
    floor (one-sided density): per probe its scalar residual times each component of its field direction (a
    field b cos(w t) on the probe puts n.b cos(w t) in its scalar channel: the carrier at w is in r n, not in r,
    whose spectrum the turning direction spreads into sidebands), per difference vector its three axes. Each
    series less its mean; exclude = (start, stop) of the fit's rows: those rows held at zero (a held-out block,
    which the lines and bands of its fold's library must not see), the floor scaled to the rows kept."""
    pr, vals = fit.problem, fit.channels.values
    dt = sample_grid(fit.channels.t_s)[1]          # the samples in order (bursty: mean interval)
    keep = np.ones(vals.shape[0], bool)
    if exclude is not None:
        keep[exclude[0]:exclude[1]] = False
    share = float(keep.mean())
    out = []

    def centred(x: np.ndarray) -> np.ndarray:
        x = x - x[keep].mean(0)
        x[~keep] = 0.0
        return x
    for k in range(pr.P):
        out.append((centred(vals[:, k:k + 1] * fit.ev.nhat[k]), 2.0 * float(noise[k]) ** 2 * dt * share))
    for k in range(1, pr.P):
        cols = pr._cols("diff", k)
        out.append((centred(vals[:, cols]), 2.0 * float(np.sum(noise[cols] ** 2)) * dt * share))
    return out


def set_spectra(fit: Any, noise: np.ndarray, exclude: tuple[int, int] | None = None) -> tuple[list, list]:
    """The sets of series (series) and each one's Welch spectrum summed over its series, (frequencies, power), on
    segments of an eighth of the record (none under 256 samples): what excess_spectra and spectral_lines read, taken
    once where both are wanted (library.wave_features)."""
    n = fit.channels.values.shape[0]
    if n < 256:
        return [], []
    dt = sample_grid(fit.channels.t_s)[1]          # the samples in order (bursty: mean interval)
    nper = int(2 ** np.floor(np.log2(n / 8)))
    from scipy.signal import welch                      # here, not at import (a command's start)

    sets, out = series(fit, noise, exclude), []
    for x, _ in sets:
        f, p = welch(x, fs=1.0 / dt, nperseg=nper, axis=0)
        out.append((f, p.sum(axis=1)))
    return sets, out


def excess_spectra(fit: Any, noise: np.ndarray, exclude: tuple[int, int] | None = None,
                   spectra: tuple[list, list] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per set of series (series): (frequencies, excess power density over its white floor). spectra: set_spectra's,
    when already taken."""
    sets, summed = spectra if spectra is not None else set_spectra(fit, noise, exclude)
    return [(f[1:], np.clip(p[1:] - white, 0.0, None)) for (_, white), (f, p) in zip(sets, summed)]


def spectral_lines(fit: Any, noise: np.ndarray, exclude: tuple[int, int] | None = None,
                   spectra: tuple[list, list] | None = None) -> list[float]:
    """Frequencies (Hz) of the residual's spectral lines: Welch peaks (of the sets of series) standing
    LINE_FACTOR above the median of their neighbourhood and holding LINE_SHARE of a set's excess, strongest first
    (MAX_LINES), each refined on the residual to a fraction of a Welch bin (the largest summed periodogram
    over a fine grid about it). exclude: rows of the fit not looked at (series). spectra: set_spectra's, when
    already taken."""
    t = fit.channels.t_s
    n = t.size
    if n < 512:
        return []
    dt = sample_grid(t)[1]
    nper = int(2 ** np.floor(np.log2(n / 8)))
    sets, summed = spectra if spectra is not None else set_spectra(fit, noise, exclude)
    peaks: list[tuple[float, float, int]] = []
    for c, ((_, white), (f, p)) in enumerate(zip(sets, summed)):
        excess = np.clip(p - white, 0.0, None)
        tot = float(excess[1:].sum())
        if tot <= 0:
            continue
        half = 16
        padded = np.pad(p, half, mode="edge")
        hood = np.median(np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1), axis=1)
        local_max = np.zeros(p.size, bool)
        local_max[1:-1] = (p[1:-1] >= p[:-2]) & (p[1:-1] >= p[2:])
        cand = np.flatnonzero(local_max & (p >= LINE_FACTOR * np.maximum(hood, white)))
        for i in cand[cand >= 4]:
            share = float(excess[max(1, i - 2):i + 3].sum()) / tot
            if share >= LINE_SHARE:
                peaks.append((share * tot / white, float(f[i]), c))
    peaks.sort(reverse=True)
    out: list[float] = []
    df = 1.0 / (nper * dt)
    stride = max(1, n // 50000)
    for _, f0, c in peaks:
        if any(abs(f0 - g) < 3 * df for g in out):
            continue
        grid = np.linspace(f0 - df, f0 + df, 81)
        x = sets[c][0][::stride]
        e = np.exp(-2j * np.pi * np.outer(grid, t[::stride] - t[0]))
        pw = np.sum(np.abs(e @ x) ** 2, axis=1)
        i = int(np.clip(np.argmax(pw), 1, grid.size - 2))
        # the peak between grid points: the vertex of the parabola through the three about the largest
        y0, y1, y2 = np.log(np.maximum(pw[i - 1:i + 2], 1e-300))
        shift = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) if (y0 - 2 * y1 + y2) < 0 else 0.0
        out.append(_rounded(grid[i] + np.clip(shift, -1, 1) * (grid[1] - grid[0]), float(t[-1] - t[0])))
        if len(out) >= MAX_LINES:
            break
    return out


#: a line's frequency is written to a step that moves its phase by at most this many cycles over the record
PHASE_CYCLES = 0.01


def _rounded(hz: float, duration_s: float) -> float:
    """hz to a decimal step of at most PHASE_CYCLES per record (written into the effect, read in the report): six
    significant figures were 0.18 cycles over an hour at 50 Hz.

    >>> _rounded(50.00012345678, 3600.0), _rounded(1.3712345678, 100.0)
    (50.000123, 1.3712)
    """
    step = 10.0 ** np.floor(np.log10(PHASE_CYCLES / max(duration_s, 1e-9)))
    return float(round(round(hz / step) * step, 12))
