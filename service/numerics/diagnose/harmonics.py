"""Lines of the residual that a logged observable's own motion makes: a non-linear function of a column that moves at
f1 and f2 puts lines at 2 f1, f1 + f2, f2 - f1, 3 f1 ... in the residual. Before a line is called one that no logged
column follows, it is checked against the combinations of each column's own spectral lines (within the record's
frequency resolution); such a line is the column's shape, which discovery's library tries (shapes.py), never a wave
of its own. Numerics only.
"""

from __future__ import annotations

from itertools import product
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.effects.column import usable_columns
from fluxcal.service.numerics.effects.timebase import sample_grid

from .spectra import spectral_lines

#: a column's own line: a periodogram peak this many times the median of its neighbourhood, holding this share of
#: the column's variance; at most MOTION_LINES per column
MOTION_FACTOR = 20.0
MOTION_SHARE = 0.05
MOTION_LINES = 3
#: combinations i f1 + j f2 + k f3 with |i| + |j| + |k| up to this order
MAX_ORDER = 4
#: a residual line matches a combination within this many times the record's resolution 1 / T
RESOLUTIONS = 1.5


def motion_lines(t_s: np.ndarray, x: np.ndarray) -> list[float]:
    """The frequencies (Hz) of a column's own spectral lines: what it moves at (a flap's two swings), strongest
    first; none for a column that wanders or steps."""
    n = x.size
    if n < 64:
        return []
    dt = sample_grid(t_s)[1]                         # a bursty time base: its mean interval (effects.timebase)
    y = x - np.polyval(np.polyfit(t_s - t_s[0], x, 1), t_s - t_s[0])
    p = np.abs(np.fft.rfft(y * np.hanning(n))) ** 2
    f = np.fft.rfftfreq(n, dt)
    total = float(p[1:].sum())
    if total <= 0:
        return []
    half = 8
    hood = np.median(np.lib.stride_tricks.sliding_window_view(np.pad(p, half, mode="edge"), 2 * half + 1), axis=1)
    peak = np.zeros(p.size, bool)
    peak[1:-1] = (p[1:-1] >= p[:-2]) & (p[1:-1] > p[2:])
    out: list[tuple[float, float]] = []
    for i in np.flatnonzero(peak & (p >= MOTION_FACTOR * np.maximum(hood, 1e-300))):
        share = float(p[max(1, i - 2):i + 3].sum()) / total
        if i >= 2 and share >= MOTION_SHARE:
            # the peak between bins: the vertex of the parabola through the three about it (in log power)
            y0, y1, y2 = np.log(np.maximum(p[i - 1:i + 2], 1e-300))
            shift = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2) if (y0 - 2 * y1 + y2) < 0 else 0.0
            out.append((share, float(f[i] + np.clip(shift, -0.5, 0.5) * (f[1] - f[0]))))
    out.sort(reverse=True)
    return [hz for _, hz in out[:MOTION_LINES]]


def combination(hz: float, lines: list[float], duration_s: float) -> str | None:
    """How a residual line at hz is made of the lines `lines` (f1, f2, ...): '2 f1', 'f1 + f2', 'f2 - f1' (order 2 to
    MAX_ORDER; a line at f1 itself is the column's linear coupling, not a harmonic) within RESOLUTIONS / T, the lowest
    order first; None where none is.

    >>> combination(0.1166, [0.0583, 0.1896], 600.0), combination(0.2479, [0.0583, 0.1896], 600.0)
    ('2 f1', 'f1 + f2')
    >>> combination(0.1313, [0.0583, 0.1896], 600.0), combination(0.3, [0.0583, 0.1896], 600.0) is None
    ('f2 - f1', True)
    """
    tol = RESOLUTIONS / max(duration_s, 1e-9)
    best = None
    for coefs in product(range(-MAX_ORDER, MAX_ORDER + 1), repeat=len(lines)):
        order = sum(abs(c) for c in coefs)
        at = sum(c * f for c, f in zip(coefs, lines))
        if 2 <= order <= MAX_ORDER and at > 0 and abs(at - hz) <= tol and (best is None or order < best[0]):
            best = (order, coefs)
    if best is None:
        return None

    def term(c: int, i: int) -> str:
        return f"{abs(c) if abs(c) > 1 else ''}{'' if abs(c) == 1 else ' '}f{i + 1}"
    pos = [term(c, i) for i, c in enumerate(best[1]) if c > 0]
    neg = [term(c, i) for i, c in enumerate(best[1]) if c < 0]
    return " + ".join(pos) + "".join(f" - {t}" for t in neg)


def harmonic_source(hz: float, sources: dict[str, list[float]], duration_s: float) -> tuple[str, str] | None:
    """(column, 'how it is made: 2 f1 of its lines at 0.0583, 0.19 Hz') of the first column whose own lines make a
    residual line at hz, or None."""
    for name, lines in sources.items():
        how = combination(hz, lines, duration_s) if lines else None
        if how is not None:
            return name, f"{how} of its lines at {', '.join(f'{f:.4g}' for f in lines)} Hz"
    return None


def band_source(band_hz: tuple[float, float], sources: dict[str, list[float]]) -> tuple[str, str] | None:
    """(column, what of its motion lies in the band) of the first column whose own lines or their combinations (order
    1 to MAX_ORDER) fall in a band of the residual's excess, or None."""
    lo, hi = band_hz
    for name, lines in sources.items():
        for coefs in product(range(-MAX_ORDER, MAX_ORDER + 1), repeat=len(lines)):
            order = sum(abs(c) for c in coefs)
            if order < 1 or order > MAX_ORDER or next((c for c in coefs if c), 0) < 0:
                continue
            at = abs(sum(c * f for c, f in zip(coefs, lines)))
            if lo <= at <= hi:
                return name, f"its motion's lines at {', '.join(f'{f:.4g}' for f in lines)} Hz and their combinations"
    return None


def column_lines(data: EffectData) -> dict[str, list[float]]:
    """Each usable column's own spectral lines, Hz (harmonics.motion_lines), where it has any."""
    key = "column lines"
    if key not in data._cache:
        out = {}
        for name, v in usable_columns(data).items():
            lines = motion_lines(data.t_s, v)
            if lines:
                out[name] = lines
        data._cache[key] = out
    return data._cache[key]


def harmonic_lines(data: EffectData, fit: Any, noise: np.ndarray) -> dict[float, tuple[str, str]]:
    """The residual's lines that a logged column's motion makes: line (Hz) -> (column, how)."""
    sources = column_lines(data)
    out = {}
    for hz in spectral_lines(fit, noise):
        src = harmonic_source(hz, sources, data.duration_s)
        if src is not None:
            out[hz] = src
    return out

