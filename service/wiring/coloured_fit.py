"""`fluxcal fit`'s linear calibration under coloured noise: where a probe's residual is coloured (a power law
above the white level at the record's own periods), its offsets' and matrix's standard errors gain the noise's
wander within the record (fluxcal.service.numerics.calib.offset_noise), and what they cover is said."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration

from .fitting import TotalField, residual_channels

#: the spectra of the residuals are taken over at most this many samples (every k-th: the power law is fitted
#: from 16 cycles per record up, far below the thinned rate)
SPECTRUM_ROWS = 200_000


@dataclass(frozen=True)
class ColouredNoise:
    """A probe whose residual is coloured at the record's own periods (a power law above the white level,
    fluxcal.service.numerics.engine.coloured)."""

    probe: str
    alpha: float                  # the power law's spectral index
    covered: bool                 # its offsets' standard errors now carry the wander within the record
    wander_nT: float | None       # how far its offsets wander per decade of time beyond the record


def coloured_offsets(data: LabData, cal: ArrayCalibration, total: TotalField) -> list[ColouredNoise]:
    """Where a probe's residual is coloured, its offsets' and matrix's white-noise standard errors gain the
    noise's wander within the record (numerics.calib.offset_noise), in place: an ellipsoid-fitted probe's (or
    rls- or tmi-fitted: the same fit without forgetting, or with the total given), and a regression-aligned
    probe's (probes 2 and up, whatever fitted probe 1); others keep white-noise errors and are said to. A
    regression-aligned probe's offsets also gain the reference probe's offset errors, which they inherit (taken as
    independent of the regression's own, though probe 1's noise is in both), on any record. The spectra over at
    most SPECTRUM_ROWS samples (every k-th: the power law is fitted from 16 cycles per record up)."""
    from fluxcal.service.numerics.effects.timebase import MAX_GRID_FILL, sample_grid
    from fluxcal.service.numerics.engine.coloured import FLICKER, MIN_CYCLES

    b = data.block
    if b.n_samples < 512:
        for p in cal.probes[1:] if cal.align == "regression" else []:
            _inherit(p, cal.probes[0])
        return []
    idx = np.arange(0, b.n_samples, max(1, b.n_samples // SPECTRUM_ROWS))
    part = replace(data, block=b.rows(idx))
    values = total.values[idx] if isinstance(total.values, np.ndarray) else total.values
    channels = residual_channels(part, cal, TotalField(values, total.source))
    grid, dt = sample_grid(part.block.t_s)
    duration = grid.size * dt
    ctx = _Spectra(channels, grid, dt, duration, values,
                   gaps=bool(grid[-1] + 1 > MAX_GRID_FILL * grid.size),   # mostly gaps: no spectrum to integrate
                   # below the band the law was fitted on, flicker noise (a steeper law measured on a real board,
                   # whose residual follows the hand's slow turning, claimed 1,100-2,400 nT; its halves' fits
                   # disagree by 220-340)
                   knee=(MIN_CYCLES / duration, FLICKER))
    out = []
    for k, p in enumerate(cal.probes):
        regression = cal.align == "regression" and k > 0
        if regression:
            _inherit(p, cal.probes[0])
        found = _coloured_probe(cal, k, part.block.field_nT[:, k], data.probe_names, regression, ctx)
        if found is not None:
            out.append(found)
    return out


@dataclass(frozen=True)
class _Spectra:
    channels: dict[str, np.ndarray]
    grid: np.ndarray
    dt: float
    duration: float
    total: np.ndarray | float | None
    gaps: bool
    knee: tuple[float, float]



def _fitted_total(cal: ArrayCalibration, total):
    """The total field the calibration's estimator was constrained by, for the fits that stand in for it: rls takes
    a reference's level only (its mean square sets the scale), so its centre and shape are the ellipsoid fit's
    without the reference (None)."""
    return None if cal.method == "rls" else total


def direction_offsets(data: LabData, cal: ArrayCalibration, total: TotalField) -> list[str]:
    """Each ellipsoid-fitted (rls-, tmi-fitted) probe's offsets' (and matrix's, angles', scales') errors at least
    those of deleting one region of directions at a time (numerics.calib.misfit: a residual tied to the direction,
    a misfit the model lacks, which neither the white- nor the coloured-noise errors see), in place, where the residual
    differs between regions beyond chance for white noise (misfit.add_spread); what they raised by more than
    misfit.SAY, said.
    After coloured_offsets (the larger of the two stands); a regression-aligned probe's offsets are not an
    ellipsoid's, and keep theirs."""
    from fluxcal.service.numerics.calib.misfit import add_spread, direction_jackknife

    if cal.method not in ("ellipsoid", "rls", "tmi"):
        return []
    out = []
    ref_se = None if cal.probes[0].offset_se_nT is None else np.array(cal.probes[0].offset_se_nT, float)
    for k, p in enumerate(cal.probes):
        if (cal.align == "regression" and k > 0) or p.offset_se_nT is None:
            continue
        try:
            # the fit's own upper-triangular factor (an aligned probe's matrix is R M: QR gives R and M), so the
            # regions of direction are the fit's whatever the alignment
            rot, tri = np.linalg.qr(p.matrix)
            signs = np.where(np.diag(tri) < 0, -1.0, 1.0)
            rot, tri = rot * signs, tri * signs[:, None]
            got = direction_jackknife(data.block.field_nT[:, k], _fitted_total(cal, total.values),
                                      p.model_order or "full", p.offset_nT, tri, needed_only=True)
        except (np.linalg.LinAlgError, ValueError):
            continue
        # rls takes a reference as an unknown field: its scale (and the matrix's) is another convention than the
        # jackknife's; the angles are the triangular factor's either way
        said = add_spread(p, got, p.name, "regions of field direction", "regions of direction",
                          "a misfit the model lacks, or noise slower than the turning", rotation=rot,
                          scales=cal.method in ("ellipsoid", "tmi"))
        if got is not None and got.significant:
            _say_sizes(p)
        out += said
    if cal.align == "regression" and ref_se is not None:
        # the regression-aligned probes inherited the reference's offset errors before these widened them: they
        # take the widening too (an offset error of the reference moves theirs one to one, _inherit)
        for p in cal.probes[1:]:
            _inherit(p, cal.probes[0], before=ref_se)
    return out


def _inherit(p: ProbeCalibration, ref: ProbeCalibration, *, before: np.ndarray | None = None) -> None:
    """A regression-aligned probe's offset errors with the reference probe's carried over: an offset error
    delta o_1 of the reference moves o_k by -A^-1 M_1 delta o_1 (skipped where the reference has none). before: the
    reference's errors already carried over; only what they grew by since is added."""
    se = np.asarray(ref.offset_se_nT, float)
    if before is not None:
        se = np.sqrt(np.maximum(se ** 2 - np.asarray(before, float) ** 2, 0.0))
        if not np.any(se > 0):
            return
    if p.offset_se_nT is None or not np.all(np.isfinite(se)):
        return
    try:
        carry = np.linalg.solve(p.matrix, ref.matrix)
    except np.linalg.LinAlgError:
        return
    _set_offset_se(p, np.sqrt(np.asarray(p.offset_se_nT, float) ** 2 + np.diag(carry @ np.diag(se ** 2) @ carry.T)))
    _say_sizes(p)


def _set_offset_se(p: ProbeCalibration, se: np.ndarray) -> None:
    p.offset_se_nT = se
    if "offset_nT" in p.params:
        p.params["offset_nT"]["se"] = se.tolist()


def _coloured_probe(cal: ArrayCalibration, k: int, raw: np.ndarray, names: list[str], regression: bool,
                    ctx: _Spectra) -> ColouredNoise | None:
    """Probe k's coloured-noise errors (in place), or None where its residual is white."""
    from fluxcal.service.numerics.calib.offset_noise import (
        ellipsoid_weights,
        record_se,
        regression_weights,
        wander_per_decade,
    )

    p = cal.probes[k]
    if regression:
        laws = [_law(ctx.channels[f"{names[k]}-{names[0]}.{a}"], ctx.dt, ctx.duration) for a in "xyz"]
    else:
        law = _law(ctx.channels[f"{names[k]}.scalar"], ctx.dt, ctx.duration)
        laws = [law] * 3
        if law is not None:
            # the scalar residual is d^T M eps: its power is mean |M^T d|^2 times a raw axis's
            corr = p.apply(raw)
            d = corr / np.linalg.norm(corr, axis=1, keepdims=True)
            gain = float(np.mean(np.sum((d @ p.matrix) ** 2, axis=1)))
            laws = [(law[0] / gain, law[1] / gain, law[2])] * 3
    coloured = [law for law in laws if law is not None]
    if not coloured:
        return None
    # `rls` without forgetting (fit --method rls) is the batch ellipsoid fit, to 1e-6 of the field
    # (tests/numerics/test_real_sensors.py), and `tmi` the ellipsoid fit with the total given, to the digits printed: the
    # same estimator of the same data, so the same weights of the noise
    covered = not ctx.gaps and (regression or cal.method in ("ellipsoid", "rls", "tmi"))
    if covered:
        try:
            w_o, w_m = (regression_weights(raw, p.matrix, p.offset_nT) if regression else
                        ellipsoid_weights(raw, p.offset_nT, p.matrix, p.model_order or "full",
                                          _fitted_total(cal, ctx.total)))
            extra_o = record_se(w_o, ctx.grid, ctx.dt, laws, ctx.knee)
            extra_m = record_se(w_m, ctx.grid, ctx.dt, laws, ctx.knee)
        except (np.linalg.LinAlgError, ValueError):
            covered = False                        # the white-noise errors stand, said to be lower bounds
    if covered:
        _set_offset_se(p, np.hypot(np.asarray(p.offset_se_nT, float), extra_o))
        if p.matrix_se is not None:
            p.matrix_se = np.hypot(np.asarray(p.matrix_se, float), extra_m[:9].reshape(3, 3))
        if not regression:
            _add_in_variance(p, "nonorth_deg", extra_m[9:12])
            _add_in_variance(p, "scale", extra_m[12:15])
        _say_sizes(p)
    return ColouredNoise(names[k], min(law[2] for law in coloured), covered,
                         max(wander_per_decade(law, ctx.duration, ctx.knee) for law in coloured))


def _add_in_variance(p: ProbeCalibration, key: str, extra: np.ndarray) -> None:
    """A named parameter's standard errors (where it has them: an order may hold it fixed) with `extra` added in
    variance."""
    entry = p.params.get(key)
    if entry is not None and entry.get("se") is not None:
        entry["se"] = np.hypot(np.asarray(entry["se"], float), extra).tolist()


def _say_sizes(p: ProbeCalibration) -> None:
    """The size warnings (calib.order.size_warnings) with the errors as they now stand: the fit said them with
    its white-noise ones."""
    from fluxcal.service.numerics.calib.order import SIZE_WARNING, size_warnings

    p.warnings = [w for w in p.warnings if not w.endswith(SIZE_WARNING)] + size_warnings(p.name, p.params)


def _law(y: np.ndarray, dt: float, duration: float) -> tuple[float, float, float] | None:
    """The power law of y's spectrum when it is coloured, extended at least as steeply as flicker noise
    (as the drift's errors, engine/coloured.py); None for white noise."""
    from fluxcal.service.numerics.engine.coloured import FLICKER, is_coloured, power_law

    law = power_law(y, dt)
    if not is_coloured(law, duration):
        return None
    if law[2] > FLICKER:
        law = power_law(y, dt, np.array([FLICKER])) or law
    return law
