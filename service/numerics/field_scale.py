"""Data in the wrong unit: the raw field's size against what a field in nT can be, and against the total field
given, so that µT data (or counts) are said, not silently scaled by 1000 by the calibration.

Bounds, in nT: Earth's field is 22,000-67,000 nT at the surface; a platform's own field, coils or a partial
shield move that, so only a median |B| below 1,000 nT (2 % of the weakest Earth field: too weak a field to
calibrate a fluxgate by turning it) or above 1,000,000 nT (1 mT: 15 times the strongest Earth field, beyond
nearly every fluxgate's range) is called implausible. The same numbers in other units: µT 22-67, mG
220-670, G 0.22-0.67, pT 2.2e7-6.7e7.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: a median |B| about the centre outside these (nT) is not a field in nT (see the module docstring)
PLAUSIBLE_NT = (1_000.0, 1_000_000.0)
#: Earth's field at the surface, nT
EARTH_NT = (22_000.0, 67_000.0)
#: the Earth's field as a compass on a platform may read it, nT: the surface's 22,000-67,000 nT with a margin for the
#: platform's own field; a calibration whose total field lies outside is no Earth's (determinacy.physical)
EARTH_RANGE_NT = (20_000.0, 70_000.0)
#: a given total field this many times the data's scale (or less than its inverse) is said loudly: the calibration
#: would give the sensor a gain this far from 1 on every axis, where a fluxgate's is within about 1 %; beyond
#: SITE_RATIO_MAX the fits refuse it (a unit or gain setting that far off is no calibration's to take)
TOTAL_RATIO_LIMIT = 1.25
#: a given total field further than this factor from the data's own size (median |raw - centre|) is not theirs:
#: the fits refuse it (determinacy.physical); within it, a logger's gain setting off by a step (a MEMS part's gain
#: steps differ 1.1-1.5 times) is taken into the matrix, said loudly above TOTAL_RATIO_LIMIT
SITE_RATIO_MAX = 2.0
#: units a lab file may be in, and nT per unit
_UNITS = (("µT", 1e3), ("mG", 1e2), ("G", 1e5), ("mT", 1e6), ("T", 1e9), ("pT", 1e-3))


def sphere_centre(b: np.ndarray) -> np.ndarray:
    """The centre of the sphere |b - c| = r fitted to samples b (N, 3) by linear least squares
    (|b|^2 = 2 b.c + r^2 - |c|^2), centred and scaled first; the mean when the samples do not fix it.

    >>> t = np.linspace(0, 2 * np.pi, 40)
    >>> ring = np.column_stack([np.cos(t), np.sin(t), 0 * t])
    >>> b = np.vstack([ring, ring[:, [2, 0, 1]]]) * 50.0 + [300.0, -200.0, 100.0]
    >>> np.round(sphere_centre(b), 6).tolist()
    [300.0, -200.0, 100.0]
    """
    b = np.asarray(b, dtype=np.float64)
    b = b[np.isfinite(b).all(axis=1)]
    if b.shape[0] < 4:
        return b.mean(axis=0) if b.shape[0] else np.zeros(3)
    m = b.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((b - m) ** 2, axis=1)))) or 1.0
    u = (b - m) / s
    a = np.column_stack([2.0 * u, np.ones(u.shape[0])])
    if np.linalg.cond(a) > 1e6:                    # a plane or a line of samples: the centre is not fixed
        return m
    sol = np.linalg.lstsq(a, np.sum(u * u, axis=1), rcond=None)[0]
    return m + s * sol[:3]


def median_field(field_nT: np.ndarray, centres_nT: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Each probe's median |B - centre| (P,) of raw samples (N, P, 3); centres: the fitted offsets, else a
    sphere fitted to each probe's samples."""
    f = np.asarray(field_nT, dtype=np.float64)
    out = np.empty(f.shape[1])
    for k in range(f.shape[1]):
        c = np.asarray(centres_nT[k], float) if centres_nT is not None else sphere_centre(f[:, k])
        # in chunks: no (N, 3) temporaries beside the data (hours of it)
        r = np.concatenate([np.linalg.norm(f[a:a + 65_536, k] - c, axis=1) for a in range(0, f.shape[0], 65_536)]
                           or [np.empty(0)])
        r = r[np.isfinite(r)]
        out[k] = float(np.median(r)) if r.size else np.nan
    return out


def unit_guess(scale: float) -> str:
    """The units in which a field of `scale` would be an Earth field, said as a question; "" if none.

    >>> unit_guess(52.8)
    'µT? (x 1000: 52,800 nT)'
    >>> unit_guess(528.0), unit_guess(7.0)
    ('mG? (x 100: 52,800 nT)', '')
    """
    lo, hi = EARTH_NT[0] / 2.0, EARTH_NT[1] * 2.0          # a platform, a coil or an anomaly moves it a little
    return " or ".join(f"{u}? (x {n:g}: {scale * n:,.0f} nT)" for u, n in _UNITS if lo <= scale * n <= hi)


def field_scale_warnings(field_nT: np.ndarray, probe_names: Sequence[str],
                         centres_nT: Sequence[np.ndarray] | None = None, total_nT: float | None = None,
                         total_source: str = "") -> tuple[list[str], list[str]]:
    """(warnings, loud): probes whose median |B| about the centre is implausible for nT, said with what the
    data look like; loud: a given total field more than TOTAL_RATIO_LIMIT times off the data's scale (the
    calibration's matrix would take that factor). Never a refusal: a shielded lab may be right. Without
    `centres_nT` (the fitted centres), about a sphere fitted to each probe's samples, and said so."""
    med = median_field(field_nT, centres_nT)
    about = "the fitted centre" if centres_nT is not None else "a sphere fitted to them"
    warnings, loud = [], []
    bad = [k for k, m in enumerate(med) if np.isfinite(m) and not PLAUSIBLE_NT[0] <= m <= PLAUSIBLE_NT[1]]
    if bad:
        scale = float(np.median(med[bad]))
        what = unit_guess(scale) or "raw counts? (counts x lsb_nT gives nT)"
        shown = ", ".join(f"{probe_names[k]} {med[k]:.3g}" for k in bad)
        warnings.append(f"median |B| about {about}: {shown}: implausible for nT (Earth's field is "
                        f"{EARTH_NT[0]:,.0f}-{EARTH_NT[1]:,.0f} nT; a field below {PLAUSIBLE_NT[0]:,.0f} or above "
                        f"{PLAUSIBLE_NT[1]:,.0f} nT is not one a fluxgate is calibrated in): {what}; the CSV contract "
                        f"is nT (docs/csv.md), and the offsets and residuals are reported in the data's unit")
    data_scale = float(np.nanmedian(med)) if np.isfinite(med).any() else np.nan
    if total_nT is not None and np.isfinite(total_nT) and np.isfinite(data_scale) and data_scale > 0:
        ratio = float(total_nT) / data_scale
        if not 1.0 / TOTAL_RATIO_LIMIT <= ratio <= TOTAL_RATIO_LIMIT:
            like = [u for u, n in _UNITS if abs(np.log10(ratio / n)) < np.log10(2.0)]   # the ratio near 1000: µT
            why = (f"are the data in {like[0]}? the CSV contract is nT" if like
                   else "the field given (the site, the configuration, the reference column) is wrong, or the "
                        "data's unit or gain (lsb_nT)")
            times = f"{ratio:,.0f}" if ratio >= 10 else f"{ratio:.3g}"
            loud.append(f"the total field given ({total_nT:,.0f} nT, {total_source}) is {times} times the data's "
                        f"median |B| about {about} ({data_scale:,.6g}): the calibration's matrix scales the data by "
                        f"about {times} on every axis to meet it (its residuals too), where a sensor's own gain is "
                        f"within a few % of its data sheet: the factor is the data's unit or gain setting, or the "
                        f"field given is wrong ({why}); the calibration is made with the factor in its matrix "
                        f"(refused beyond {SITE_RATIO_MAX:g} times): check which before using it")
    return warnings, loud
