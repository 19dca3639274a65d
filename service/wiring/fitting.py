"""Batch calibration of lab data with any method of docs/calibration.md (`fluxcal fit` and `diagnose`).

One function per step: the total field to fit against, per-probe fits by method, alignment to a
common frame, and the residual channels the contracts define. `rls` runs the service's own
Pipeline over the data in time order, so `fit --method rls` is exactly what the daemon would learn.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import CalibrationRefused, DataError
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.numerics.calib.alignment import align_probes, borrowed_errors
from fluxcal.service.numerics.calib.determinacy import (
    Determinacy,
    judge_all,
    physical,
    refuse_undetermined,
    shape_problem,
)
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.numerics.channels import channel_names
from fluxcal.service.numerics.jsonsafe import json_safe
from fluxcal.service.numerics.usable import refuse_stuck

#: the probe-samples a nonlinear fit over every sample (diagnose's candidates, fit --effects) is given by default:
#: a longer recording is thinned to every k-th sample, and the output says so. Such a fit holds about 3 kB per
#: probe-sample at its peak (measured: bench/bench_hours.py), so this keeps it near 1.5 GB whatever the length.
NONLINEAR_PROBE_SAMPLES = 500_000

METHODS = ("ellipsoid", "tmi", "sinefit", "two-step", "rls")
ALIGNS = ("regression", "rotation", "pca")


@dataclass
class TotalField:
    values: np.ndarray | float | None     # per sample, constant, or None (estimated)
    source: str                           # "ref_total", "config", "estimated"

    def per_sample(self, n: int, fallback: np.ndarray | None = None) -> np.ndarray:
        if isinstance(self.values, np.ndarray):
            return self.values
        if self.values is not None:
            return np.full(n, float(self.values))
        return np.full(n, float(np.mean(fallback))) if fallback is not None else np.full(n, np.nan)


def total_field(data: LabData, configured_nT: float | None) -> TotalField:
    ref = data.ref_total
    if ref is not None:
        return TotalField(ref, "ref_total")
    if configured_nT is not None:
        return TotalField(float(configured_nT), "config")
    return TotalField(None, "estimated")


def _column(block: SampleBlock, names: tuple[str, ...], what: str) -> np.ndarray:
    for n in names:
        if n in block.extras:
            return block.extras[n]
    raise CalibrationRefused(f"{what}: the data need a column named {' or '.join(map(repr, names))}")


def fit_probe(method: str, raw: np.ndarray, total: TotalField, block: SampleBlock, name: str,
              inclination_deg: float | None = None, core: Any = None) -> ProbeCalibration:
    """One probe's calibration in its own orthogonal frame (core: the determinacy gate's ellipsoid fit of the same
    samples, which the ellipsoid method finishes rather than redoes)."""
    if method == "ellipsoid":
        # the white-noise errors: coloured_fit adds the noise's wander and the directions' spread to them
        return fit_ellipsoid(raw, total.values, name=name, errors="white", core=core).calibration
    if method == "tmi":
        from fluxcal.service.numerics.calib.tmi import fit_tmi

        if total.values is None:
            reason = "tmi needs a scalar reference of the total field, and these data give none"
            advice = ("give one: a ref_total column, the site (--site LAT,LON[,ALT_M[,DATE]]: the field model's total "
                      "there) or [estimator] total_nT in --config; or fit with --method ellipsoid, which estimates it")
            refused = CalibrationRefused(f"{reason}: {advice}")
            refused.reason, refused.advice = reason, advice
            raise refused
        return fit_tmi(raw, total.values, name=name)
    if method == "sinefit":
        from fluxcal.service.numerics.calib.sinefit import fit_sinefit

        angle = np.radians(_column(block, ("angle_deg", "table_deg", "heading_deg"), "sinefit"))
        tv = None if total.values is None else float(np.mean(total.values))
        return fit_sinefit(angle, raw, inclination_deg=inclination_deg, total_nT=tv, t_s=block.t_s, name=name)
    if method == "two-step":
        from fluxcal.service.numerics.calib.twostep import fit_two_step

        turn = _column(block, ("turn", "turn_axis"), "two-step")
        turns = [raw[turn == k] for k in (0, 1, 2)]
        if any(t.shape[0] < 10 for t in turns):
            raise CalibrationRefused("two-step needs three single-axis turns marked in a 'turn' column "
                                     "(0 = about x, 1 = about y, 2 = about z), each with at least 10 samples")
        tv = None if total.values is None else float(np.mean(total.values))
        # [TwoStep] fits step 1's ellipsoid to every sample, the turns' and the rest (tilted sweeps, transitions)
        rest = raw[~np.isin(turn, (0, 1, 2))]
        return fit_two_step(turns, extra_nT=rest if rest.shape[0] else None, total_nT=tv, name=name)
    raise DataError(f"method {method!r} is not allowed (allowed: {', '.join(METHODS)})")


def fit_rls(data: LabData, total: TotalField, *, forgetting: float = 1.0, align: str | None = "rotation",
            positions_m: np.ndarray | None = None) -> ArrayCalibration:
    """The service's pipeline over the data in time order; its last online estimate."""
    from .pipeline import Pipeline

    b = data.block
    n = b.n_samples
    rate = (n - 1) / (b.t_s[-1] - b.t_s[0]) if n > 1 and b.t_s[-1] > b.t_s[0] else 1.0
    pl = Pipeline(n_probes=b.n_probes, probe_names=data.probe_names, positions_m=positions_m,
                  forgetting=forgetting, total_nT=None if isinstance(total.values, np.ndarray) else total.values,
                  align=align or "none", min_samples=min(200, n), window_samples=n,
                  check_every_samples=float("inf"))
    step = max(1, int(round(rate)))                  # one-second blocks, as the daemon sees them
    for i in range(0, n, step):
        pl.process(b.slice(i, i + step))
    pl.flush_estimator()
    pl.gate.spread_errors = False           # the white-noise errors: coloured_fit adds its own, as to the batch fit
    cand = pl.candidate()
    if cand is None:
        est = pl._estimators[0]
        raise CalibrationRefused(f"rls: the online estimate is not determined by these data ({n} samples, "
                                 f"condition {est.condition_:.3g}); rotate about several axes")
    return cand


def fit_array(data: LabData, *, method: str = "ellipsoid", align: str | None = None,
              configured_total_nT: float | None = None, positions_m: np.ndarray | None = None,
              inclination_deg: float | None = None, progress: Callable[[str], None] | None = None,
              judged: list[Determinacy] | None = None) -> tuple[ArrayCalibration, TotalField]:
    """Every probe fitted by `method`, then aligned (arrays: regression by default), once the determinacy gate
    (judge_data; `judged`: its verdicts already asked) found every probe's samples determine a calibration."""
    b = data.block
    total = total_field(data, configured_total_nT)
    judged = judged if judged is not None else judge_data(data, configured_total_nT)
    if method != "sinefit":             # (a sine fit is made of one turn about a chosen axis, by design)
        refuse_undetermined(judged)
    p = b.n_probes
    if align is None and p > 1:
        align = "regression"
    if p == 1:
        align = None
    if method == "rls":
        cal = fit_rls(data, total, align=align if align in ("rotation", "regression") else "rotation",
                      positions_m=positions_m)
        cal.total_nT = None if isinstance(total.values, np.ndarray) or total.values is None else float(total.values)
        _refuse_unphysical(cal, data)
        if align == "regression":
            _say_borrowed(cal.probes, judged, data, total)
        return cal, total
    probes = []
    for k in range(p):
        if progress:
            progress(f"fitting {data.probe_names[k]} ({method})")
        if align == "regression" and k > 0:
            probes.append(None)                     # filled by the regression onto probe 1 below
            continue
        probes.append(fit_probe(method, b.field_nT[:, k], total, b, data.probe_names[k], inclination_deg,
                                core=judged[k].fit))
    if align == "regression":
        probes = align_probes([probes[0]] * p, b.field_nT, method="regression")
        for k, pr in enumerate(probes):
            pr.name = data.probe_names[k]
        _say_borrowed(probes, judged, data, total)
    elif align == "rotation":
        probes = align_probes(probes, b.field_nT, method="rotation")
    elif align == "pca":
        from fluxcal.service.numerics.calib.twostep import align_pca

        turn = _column(b, ("turn", "turn_axis"), "align pca")
        probes = align_pca(probes, b.field_nT, turn)
    cal = ArrayCalibration(method=method, align=align, probes=probes,
                           total_nT=None if not isinstance(total.values, float) else total.values,
                           span=(float(b.t_s[0]), float(b.t_s[-1]), b.n_samples))
    _refuse_unphysical(cal, data)
    return cal, total


def _say_borrowed(probes: list[ProbeCalibration], judged: list[Determinacy], data: LabData, total: TotalField) -> None:
    """Each probe aligned by regression whose scalar residual its own ellipsoid (the determinacy judge's, as every
    method is gated on) leaves BORROWED_RATIO times smaller: said among its warnings (alignment.borrowed_errors)."""
    b = data.block
    own = [None if j.fit is None else (j.fit.fit.calibration.offset_nT, j.fit.fit.calibration.matrix) for j in judged]
    per_sample = None if total.values is None else total.per_sample(b.n_samples)
    for k, words in borrowed_errors(probes, own, b.field_nT, per_sample).items():
        probes[k].warnings.append(words)


def _refuse_unphysical(cal: ArrayCalibration, data: LabData) -> None:
    """A fitted matrix no sensor has (determinacy.shape_problem) from whichever method: refused with what would help
    (a real flight's cone of directions, with the total field estimated, passed the cone check on its own garbage
    shape)."""
    from fluxcal.service.numerics.calib.excitation import coverage_hint

    for k, p in enumerate(cal.probes):
        problem = shape_problem(p.matrix)
        if problem:
            raise CalibrationRefused(f"{data.probe_names[k]}: {problem}; "
                                     f"{coverage_hint(data.block.field_nT[:, k], p.offset_nT)}")


def judge_data(data: LabData, configured_total_nT: float | None = None, total_source: str = "",
               physical_check: bool = True) -> list[Determinacy]:
    """The determinacy gate (fluxcal.service.numerics.calib.determinacy) of every probe of the data, against the total field
    the fit takes (total_field): what fit of every method, diagnose and inspect ask alike; with physical_check, a field
    that is neither the site's (the reference given; total_source says what it is) nor, without one, the Earth's, is
    refused too (determinacy.physical). DataError first for samples that hold NaN, and for a probe that did not
    measure."""
    _refuse_non_finite(data)
    field_nT = data.block.field_nT
    refuse_stuck(field_nT, data.probe_names)
    total = total_field(data, configured_total_nT)
    judged = judge_all(field_nT, total.values, data.probe_names)
    if not physical_check:
        return judged
    source = total_source or {"ref_total": "the ref_total column", "config": "configured"}.get(total.source, "")
    return [physical(j, field_nT[:, k], total.values, source) for k, j in enumerate(judged)]


def gate_centres(judged: Sequence[Determinacy]) -> list[np.ndarray] | None:
    """Every probe's centre as the determinacy gate fitted it (the data's size is said about these by fit, diagnose
    and inspect alike), or None where the gate fitted none for some probe."""
    centres = [j.centre_nT for j in judged]
    return None if any(c is None for c in centres) else centres


def _refuse_non_finite(data: LabData) -> None:
    bad = ~np.isfinite(data.block.field_nT).all(axis=(1, 2))
    if bad.any():
        rows = np.flatnonzero(bad)
        raise DataError(f"{data.path}: {rows.size} sample(s) hold NaN or inf (first at index "
                        f"{rows[0]}, t = {data.block.t_s[rows[0]]} s): saturated or invalid; remove them")


def iter_residual_channels(data: LabData, cal: ArrayCalibration, total: TotalField):
    """(name, values) of each residual channel of docs/contracts.md in turn: s<k>.scalar = |corrected| − F, and for arrays
    s<k>-s1.<axis>; one probe's corrected samples at a time besides probe 1's (hours of data)."""
    b = data.block
    names = iter(channel_names(data.probe_names))
    first = cal.probes[0].apply(b.field_nT[:, 0])                  # (N, 3), probe 1
    f = None
    for k in range(b.n_probes):
        corr = first if k == 0 else cal.probes[k].apply(b.field_nT[:, k])
        mag = np.linalg.norm(corr, axis=1)
        if f is None:
            f = total.per_sample(b.n_samples, fallback=mag)
        yield next(names), mag - f
    for k in range(1, b.n_probes):
        corr = cal.probes[k].apply(b.field_nT[:, k])
        for a in range(3):
            yield next(names), corr[:, a] - first[:, a]


def residual_channels(data: LabData, cal: ArrayCalibration, total: TotalField) -> dict[str, np.ndarray]:
    """The residual channels of docs/contracts.md: s<k>.scalar = |corrected| − F, and for arrays s<k>-s1.<axis>."""
    return dict(iter_residual_channels(data, cal, total))


@dataclass(frozen=True)
class Reduced:
    """A residual channel reduced to what its RMS needs: the sum of squares and the count."""

    sumsq: float
    n: int


#: rows per chunk when channels are only summed (hours of data: no channel is held whole)
CHUNK_ROWS = 1 << 18


def channel_sums(data: LabData, cal: ArrayCalibration, total: TotalField,
                 chunk: int = CHUNK_ROWS) -> dict[str, Reduced]:
    """The channels of residual_channels, each reduced to its sum of squares over chunks of rows: the memory
    of one chunk, whatever the recording's length. An estimated total field (no reference, none configured) is
    the mean |corrected| of probe 1 over every sample, as in iter_residual_channels, taken in a first pass."""
    b = data.block
    n = b.n_samples
    if total.values is None and n:
        s = sum(float(np.sum(np.linalg.norm(cal.probes[0].apply(b.field_nT[lo:lo + chunk, 0]), axis=1)))
                for lo in range(0, n, chunk))
        total = TotalField(s / n, total.source)
    acc: dict[str, list[float]] = {}
    for lo in range(0, n, chunk):
        part = replace(data, block=b.slice(lo, lo + chunk))
        values = total.values[lo:lo + chunk] if isinstance(total.values, np.ndarray) else total.values
        for name, v in iter_residual_channels(part, cal, TotalField(values, total.source)):
            a = acc.setdefault(name, [0.0, 0])
            a[0] += float(np.dot(v, v))
            a[1] += v.size
    return {name: Reduced(s, int(m)) for name, (s, m) in acc.items()}


def uncalibrated_rms(data: LabData, total: TotalField) -> dict[str, float]:
    """RMS of the same channels with no calibration at all (raw nT), for 'before'; no channel is kept."""
    ident = ArrayCalibration("none", None, [ProbeCalibration(n, np.zeros(3), np.eye(3)) for n in data.probe_names])
    return {name: rms(r) for name, r in channel_sums(data, ident, total).items()}


def rms(x: np.ndarray | Reduced) -> float:
    if isinstance(x, Reduced):
        return float(np.sqrt(x.sumsq / x.n)) if x.n else float("nan")
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def rms_all(arrays: list[np.ndarray | Reduced]) -> float:
    """RMS over every value of several arrays (or their Reduced sums), without joining them."""
    def sums(a: np.ndarray | Reduced) -> tuple[float, int]:
        return (a.sumsq, a.n) if isinstance(a, Reduced) else (float(np.dot(np.ravel(a), np.ravel(a))), np.size(a))

    parts = [sums(a) for a in arrays]
    n = sum(m for _, m in parts)
    return float(np.sqrt(sum(s for s, _ in parts) / n)) if n else float("nan")


def contract_json(cal: ArrayCalibration, channels: dict[str, np.ndarray], probe_names: list[str],
                  coverages: list[Any] | None = None, warnings: list[str] | None = None) -> dict[str, Any]:
    """`fluxcal fit --json`: docs/contracts.md: its keys and what the text shows besides: standard
    errors, named parameters, the model order, the coverage about each fitted offset, and warnings."""
    diff = [v for k, v in channels.items() if not k.endswith(".scalar")]
    sensors = []
    for k, p in enumerate(cal.probes):
        entry = {"name": p.name, "offset_nT": p.offset_nT.tolist(), "matrix": p.matrix.tolist(),
                 "scalar_rms_nT": rms(channels[f"{p.name}.scalar"]),
                 "offset_se_nT": json_safe(p.offset_se_nT), "matrix_se": json_safe(p.matrix_se),
                 "model_order": p.model_order, "params": json_safe(p.params)}
        if coverages is not None:
            c = coverages[k]
            entry["coverage"] = {"fraction": c.fraction, "missing": [
                {"direction": r.label, "bins": r.bins, "turn_about": r.axes} for r in c.regions],
                "advice": c.advice(), "usable": c.usable}
        sensors.append(entry)
    return {
        "method": cal.method,
        "align": cal.align,
        "effects": list(cal.effects),
        "sensors": sensors,
        "differential_rms_nT": rms_all(diff) if diff else None,
        "rms_nT": rms_all(list(channels.values())),
        "warnings": list(warnings or []),
        # the effect terms' parameters, as the text lists them: {effect: {name: {"value", "se", "unit"}}}
        "effect_params": json_safe({eff: {name: dict(v) for name, v in ps.items()}
                                    for eff, ps in (cal.effect_params or {}).items()}),
    }


