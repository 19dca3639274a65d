"""Offsets' standard errors that hold when the residual follows the field direction.

A real board's residual is mostly not noise but a misfit the ellipsoid cannot follow (a few hundred nT on
the hand-turned boards of ../shared/real-data, 0.4 % of the field, the same each time the field passes the
same direction). The white-noise errors average it as if every sample were new; the coloured-noise errors
(offset_noise) see its wander in time. Neither sees that it is tied to the direction: a fit over part of the
sphere leans on the misfit of the directions it has, and its offsets move by several of their stated errors
when a region of directions is added or taken away (cuts of the boards' full spheres: a quarter of their
offsets beyond two stated errors from the full fit, an eighth beyond three).

The delete-a-region jackknife says it (for the offsets, the matrix and its named angles and scales): the
directions about the fit are cut into DIRECTION_CELLS² cells per cube face, the fit is repeated without each
cell that holds samples (least squares from per-cell normal equations about the whole data's centre: one pass
over the samples, hours of data in chunks), and the spread of the offsets over those fits,
sqrt((G − 1)/G Σ (o_g − ō)²), is their error under a misfit tied to the direction. On white noise it
agrees with the white-noise error (a direction then carries no misfit of its own).

The same jackknife over stretches of time (time_jackknife) backs `fit_ellipsoid`'s own errors, which have no
time stamps for a spectrum: noise slower than the stretches, or a misfit following the motion, moves the offsets
between them (add_time_spread).

A reduced model order (axes, sphere), chosen because the held-out blocks do not gain from more terms, holds
terms fixed that the samples cannot check; where the full model's offsets differ from it by more than the full
model's own errors, that difference is an error the reduced fit does not state (add_order_bias).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused

from .model import triangular_params_many
from .order import EXPANSIONS
from .quadric import as_total, quadric_design, quadric_to_calibration_many

#: cells per cube-face edge: 6 × 3² = 54 regions of directions
DIRECTION_CELLS = 3
#: samples per chunk of the one pass over the data
CHUNK_ROWS = 65_536
#: fewer occupied cells than this: no jackknife (too few regions to judge)
MIN_CELLS = 8
#: contiguous stretches of the samples of time_jackknife
TIME_BLOCKS = 20


def direction_cells(directions: np.ndarray, m: int = DIRECTION_CELLS) -> np.ndarray:
    """The cell (0 .. 6 m² − 1) of each unit direction (N, 3): its cube face (the largest component and its
    sign), then an m × m grid of the other two components over that one."""
    d = np.asarray(directions, float)
    i = np.arange(d.shape[0])
    axis = np.argmax(np.abs(d), axis=1)
    top = np.abs(d[i, axis])
    top = np.where(top > 0, top, 1.0)
    u = d[i, (axis + 1) % 3] / top
    v = d[i, (axis + 2) % 3] / top
    iu = np.clip(((u + 1.0) * 0.5 * m).astype(int), 0, m - 1)
    iv = np.clip(((v + 1.0) * 0.5 * m).astype(int), 0, m - 1)
    return ((axis * 2 + (d[i, axis] > 0)) * m + iu) * m + iv


@dataclass(frozen=True)
class RegionSpread:
    """What deleting one region (of field directions, or of time) at a time says of a fit's offsets."""

    offset_se: np.ndarray         # (3,) the delete-a-region jackknife's standard errors of the offsets
    matrix_se: np.ndarray         # (3, 3) ... of the matrix
    nonorth_se: np.ndarray        # (3,) ... of the non-orthogonality angles, deg ([FastRotation] eq. 11)
    scale_se: np.ndarray          # (3,) ... of the scale factors (relative to the assumed field if none is given)
    cells: int                    # regions used
    f_ratio: float                # the one-way F ratio of the scalar residual over the regions
    significant: bool             # f_ratio beyond chance for white noise (F distribution, 1 in SIGNIFICANCE)
    failed: int = 0               # regions without which the rest fix no ellipsoid (not in the spread: then
                                  # the errors are lower bounds, and the fit leans on those regions alone)


#: a residual tied to the direction is taken as real when white noise would give its F ratio this rarely
SIGNIFICANCE = 1e-3


def direction_jackknife(field_nT: np.ndarray, total_nT, order: str, offset_nT: np.ndarray,
                        matrix: np.ndarray, needed_only: bool = False) -> RegionSpread | None:
    """The offsets' spread from deleting one region of directions at a time, and whether the scalar residual
    differs between regions beyond its noise within them (one-way analysis of variance); None with fewer than
    MIN_CELLS regions. field_nT (N, 3) finite raw samples of one probe; total_nT as ellipsoid.fit_ellipsoid;
    order the model order fitted; offset_nT and matrix the fit's calibration, which gives each sample's
    direction and residual. Independent of origin and unit, as the fit."""
    return region_jackknife(field_nT, total_nT, order, offset_nT, matrix, lambda a, corr: direction_cells(corr),
                            6 * DIRECTION_CELLS ** 2, needed_only)


def time_jackknife(field_nT: np.ndarray, total_nT, order: str, offset_nT: np.ndarray, matrix: np.ndarray,
                   blocks: int = TIME_BLOCKS, needed_only: bool = False) -> RegionSpread | None:
    """As direction_jackknife, the regions `blocks` contiguous stretches of the samples in their order (time):
    noise slower than the record's blocks (1/f), or a misfit that follows the motion, moves the offsets between
    them by more than the white-noise errors say (simulated tumbles under 1/f noise, 30 seeds: the offsets'
    errors 7.8 times too small with white-noise errors, within 1.12 of right with these)."""
    n = np.asarray(field_nT).shape[0]
    return region_jackknife(field_nT, total_nT, order, offset_nT, matrix,
                            lambda a, corr: (np.arange(a, a + corr.shape[0]) * blocks) // max(n, 1), blocks,
                            needed_only)


def region_jackknife(field_nT: np.ndarray, total_nT, order: str, offset_nT: np.ndarray, matrix: np.ndarray,
                     regions: Callable[[int, np.ndarray], np.ndarray], n_regions: int,
                     needed_only: bool = False) -> RegionSpread | None:
    """The delete-a-region jackknife of direction_jackknife, the region of each sample given by
    regions(first row of the chunk, the chunk's calibrated samples (n, 3)) -> labels 0 .. n_regions − 1.
    needed_only: where the residual does not differ between regions, only the F ratio (the errors zero)."""
    raw = np.asarray(field_nT, float)
    n = raw.shape[0]
    # u = (r − c) / s of order one, c the mean, s the rms distance from it, in chunks (hours of data: no (N, 3)
    # temporaries beside the caller's). The right side 1 is fixed about c for every region left out (a refit
    # would take the rest's own mean): under a 410 nT misfit the offsets differ from refits by 0.2-0.7 nT
    center = raw.mean(axis=0)
    scale = float(np.sqrt(sum(float(np.sum((raw[a:a + CHUNK_ROWS] - center) ** 2)) for a in range(0, n, CHUNK_ROWS))
                          / max(n, 1))) or 1.0
    known = total_nT is not None
    f = as_total(total_nT, n, raw)[0] if known else None
    use_delta = f is not None and float(np.std(f)) > 1.0    # as solve_quadric: the δ column only for a varying F
    delta = (f ** 2 - float(np.mean(f ** 2))) / scale ** 2 if use_delta else None
    t = EXPANSIONS[order]
    k = t.shape[1] + int(use_delta)
    m = np.asarray(matrix, float)

    def chunks():
        for a in range(0, n, CHUNK_ROWS):
            r = raw[a:a + CHUNK_ROWS]
            corr = (r - offset_nT) @ m.T
            yield a, r, corr, regions(a, corr)

    # per region: samples, Σ e and Σ e² of the scalar residual e = |M (r − o)| − F (F unknown: its mean)
    counts, e_sum, e_sq = np.zeros(n_regions), np.zeros(n_regions), np.zeros(n_regions)
    for a, r, corr, cells in chunks():
        mag = np.linalg.norm(corr, axis=1)
        e = mag - f[a:a + CHUNK_ROWS] if f is not None else mag
        counts += np.bincount(cells, minlength=n_regions)
        e_sum += np.bincount(cells, e, minlength=n_regions)
        e_sq += np.bincount(cells, e * e, minlength=n_regions)
    used = np.flatnonzero(counts > 0)
    if used.size < MIN_CELLS:
        return None
    f_ratio, significant = _anova(counts[used], e_sum[used], e_sq[used])
    if needed_only and not significant:           # the fits left out are not needed: one pass, no normal equations
        return RegionSpread(np.zeros(3), np.zeros((3, 3)), np.zeros(3), np.zeros(3), used.size, f_ratio, False)
    grams = np.zeros((n_regions, k, k))
    rhs = np.zeros((n_regions, k))
    for a, r, corr, cells in chunks():
        phi = quadric_design((r - center) / scale) @ t
        if delta is not None:
            phi = np.column_stack([phi, -delta[a:a + CHUNK_ROWS]])
        order_rows = np.argsort(cells, kind="stable")
        cs = cells[order_rows]
        starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
        for lo, hi in zip(starts, np.r_[starts[1:], cs.size]):     # a few dozen regions: one product each
            part = phi[order_rows[lo:hi]]
            grams[cs[lo]] += part.T @ part
            rhs[cs[lo]] += part.sum(axis=0)
    g_all, r_all = grams.sum(axis=0), rhs.sum(axis=0)
    f2 = float(np.mean(f ** 2)) if f is not None else None
    try:
        x, failed = _left_out_many(g_all, r_all, grams[used], rhs[used], t, scale, center, f2), 0
    except (np.linalg.LinAlgError, ValueError):     # some region's absence leaves no ellipsoid: one at a time
        x, failed = _left_out_each(g_all, r_all, grams[used], rhs[used], t, scale, center, f2)
    if x.shape[0] < MIN_CELLS:
        return None
    g = x.shape[0]
    jack = np.sqrt((g - 1) / g * np.sum((x - x.mean(axis=0)) ** 2, axis=0))
    return RegionSpread(jack[:3], jack[3:12].reshape(3, 3), jack[12:15], jack[15:18], g, f_ratio, significant,
                        failed)


def _left_out_many(g_all: np.ndarray, r_all: np.ndarray, grams: np.ndarray, rhs: np.ndarray, t: np.ndarray,
                   scale: float, center: np.ndarray, f2: float | None) -> np.ndarray:
    """(R, 18): per region left out its fit's offset (3), matrix (9), angles (3) and scales (3), every region at
    once; LinAlgError or ValueError if any of them fixes no ellipsoid."""
    col = np.sqrt(np.diag(g_all))
    lhs = (g_all[None] - grams) / np.outer(col, col)[None]
    theta = np.linalg.solve(lhs, ((r_all[None] - rhs) / col)[..., None])[..., 0] / col
    nine = theta[:, :t.shape[1]] @ t.T
    offset, m1 = quadric_to_calibration_many(nine, scale, 1.0, center)
    # M scales as √F₀²; the field the fit assumes when none is given makes det M = 1, per fit
    f2s = np.full(nine.shape[0], f2) if f2 is not None else np.linalg.det(m1) ** (-2.0 / 3.0)
    matrix = m1 * np.sqrt(f2s)[:, None, None]
    angles, scales = triangular_params_many(matrix)
    return np.column_stack([offset, matrix.reshape(-1, 9), angles, scales])


def _left_out_each(g_all: np.ndarray, r_all: np.ndarray, grams: np.ndarray, rhs: np.ndarray, t: np.ndarray,
                   scale: float, center: np.ndarray, f2: float | None) -> tuple[np.ndarray, int]:
    """_left_out_many one region at a time, leaving out those without which the rest fix no ellipsoid: (the
    fits, how many were left out)."""
    fits, failed = [], 0
    for g, r in zip(grams, rhs):
        try:
            fits.append(_left_out_many(g_all, r_all, g[None], r[None], t, scale, center, f2)[0])
        except (np.linalg.LinAlgError, ValueError):
            failed += 1                   # without this region the rest fix no ellipsoid: counted, said
    return (np.array(fits) if fits else np.zeros((0, 18))), failed


def _anova(counts: np.ndarray, sums: np.ndarray, squares: np.ndarray) -> tuple[float, bool]:
    """One-way analysis of variance of a residual over regions: (between-region over within-region mean
    square, whether white noise gives that F ratio less often than SIGNIFICANCE)."""
    from scipy.special import fdtri

    n, g = float(counts.sum()), counts.size
    if n <= g or g < 2:
        return float("nan"), False
    grand = sums.sum() / n
    between = float(np.sum(sums ** 2 / counts) - n * grand ** 2) / (g - 1)
    within = float(squares.sum() - np.sum(sums ** 2 / counts)) / (n - g)
    if not within > 0:
        return float("inf"), between > 0
    ratio = between / within
    # scipy.stats.f.isf(q, dfn, dfd) is fdtri(dfn, dfd, 1 − q), the same number, without the distribution
    # object's argument checks (the gate asks eight times a check)
    return ratio, bool(ratio > fdtri(g - 1, n - g, 1.0 - SIGNIFICANCE))


def add_order_bias(fit: Any, full_fit: Callable[[], Any], name: str) -> list[str]:
    """A reduced order's offsets' errors (fit: ellipsoid.EllipsoidFit, in place) with the part of their difference
    d from the full model's offsets that the full fit's own errors s do not explain, sqrt(max(0, d² − s²)), added
    in variance: which of the two models holds, these samples do not say (cuts of a real board's sphere fitted
    with `axes` were 5.6-7.3 stated errors from the full sphere's offsets; the full model's were 2-3 away).
    Returns a warning where it more than doubles an error; nothing where the full model is no ellipsoid here."""
    try:
        full = full_fit()
    except (CalibrationRefused, np.linalg.LinAlgError):
        return []
    cal = fit.calibration
    se = np.asarray(cal.offset_se_nT, float)
    full_se = np.asarray(full.calibration.offset_se_nT, float)
    if not (np.all(np.isfinite(se)) and np.all(np.isfinite(full_se))):
        return []
    diff = cal.offset_nT - full.calibration.offset_nT
    extra = np.sqrt(np.maximum(diff ** 2 - full_se ** 2, 0.0))
    new = np.hypot(se, extra)
    cal.offset_se_nT = new
    if "offset_nT" in cal.params:
        cal.params["offset_nT"]["se"] = new.tolist()
    if not np.any(new > 2 * se):
        return []
    return [f"{name}: the full model's offsets differ from these by {', '.join(f'{v:.3g}' for v in diff)} nT, more "
            f"than its errors explain, and these samples cannot tell the two models apart: the offsets' errors "
            f"include that difference"]


#: the delete-a-region errors are said when they raise an offset's error by more than this factor
SAY = 1.5


def add_time_spread(cal: Any, order: str, raw: np.ndarray, total_nT, name: str) -> list[str]:
    """A probe calibration's (an upper-triangular fit's) offsets', matrix's, angles' and scales' errors at least
    the delete-a-time-block jackknife's (time_jackknife), in place, where the scalar residual differs between the
    blocks beyond chance for white noise: noise slower than the blocks or a misfit following the motion, which
    white-noise errors average away. `raw` the fit's finite samples in time order, `order` its model order.
    Returns a warning where an offset's error rises by more than SAY, and where without some block the rest
    fix no ellipsoid."""
    return _add_region_spread(cal, order, raw, total_nT, name, "time")


def add_direction_spread(cal: Any, order: str, raw: np.ndarray, total_nT, name: str) -> list[str]:
    """As add_time_spread, with the delete-a-region jackknife over regions of field direction (a misfit tied to
    the direction, which a fit over part of the sphere leans on)."""
    return _add_region_spread(cal, order, raw, total_nT, name, "direction")


#: per kind of region: the jackknife, and the words of its warning (the regions, their short name, the cause)
_REGIONS = {"time": (time_jackknife, "stretches of time", "blocks of time",
                     "noise slower than the turning, or a misfit that follows the motion"),
            "direction": (direction_jackknife, "regions of field direction", "regions of direction",
                          "a misfit the model lacks, or noise slower than the turning")}


def _add_region_spread(cal: Any, order: str, raw: np.ndarray, total_nT, name: str, kind: str) -> list[str]:
    jackknife, regions, short, cause = _REGIONS[kind]
    try:
        got = jackknife(raw, total_nT, order, cal.offset_nT, cal.matrix, needed_only=True)
    except (np.linalg.LinAlgError, ValueError):
        return []
    return add_spread(cal, got, name, regions, short, cause)


def add_spread(cal: Any, got: RegionSpread | None, name: str, regions: str, short: str, cause: str, *,
               rotation: np.ndarray | None = None, scales: bool = True) -> list[str]:
    """cal's errors (offsets, matrix, angles, scales) at least got's where got is significant, in place; the
    warnings of add_time_spread. An unknown error (NaN) stays unknown. rotation: R of an aligned probe's matrix
    R M, whose errors are turned as ProbeCalibration.rotated turns them (the spread is the fit's own triangular
    M's); scales=False leaves the matrix's and the scales' errors (a fit whose scale is another convention)."""
    if got is None or not got.significant:
        return []
    se = np.asarray(cal.offset_se_nT, float)
    new = np.maximum(se, got.offset_se)
    cal.offset_se_nT = new
    if cal.matrix_se is not None and scales:
        m_se = got.matrix_se if rotation is None else np.sqrt((rotation ** 2) @ (got.matrix_se ** 2))
        cal.matrix_se = np.maximum(np.asarray(cal.matrix_se, float), m_se)
    named = (("offset_nT", new), ("nonorth_deg", got.nonorth_se), ("scale", got.scale_se if scales else None))
    for key, value in named:
        entry = cal.params.get(key)
        if value is not None and entry is not None and entry.get("se") is not None:   # an order may fix the angles
            entry["se"] = np.maximum(np.asarray(entry["se"], float), value).tolist()
    out = []
    raised = new > SAY * se
    if raised.any():
        axes = ", ".join(f"{a} {s:.3g} -> {j:.3g} nT" for a, s, j, r in zip("xyz", se, new, raised) if r)
        out.append(f"{name}: the residual differs between {regions} beyond its noise within them (F ratio "
                   f"{got.f_ratio:.3g} over {got.cells} {short}, p < 0.001: {cause}): the offsets' errors are "
                   f"those of leaving one out ({axes})")
    if got.failed:
        out.append(f"{name}: without {got.failed} of the {got.cells + got.failed} {short} the rest fix no "
                   f"ellipsoid: the fit leans on those alone, and its errors are lower bounds")
    return out
