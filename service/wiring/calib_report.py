"""The calibration section of a report from what `fit` or `diagnose` computed: each probe's raw samples,
fitted offset, scalar residual and coverage go to calib.sky, its parameters to calib.param_table; the
drawing is fluxcal.service.io.report's.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.calib.coverage import coverage
from fluxcal.service.numerics.calib.param_table import effect_rows, probe_rows
from fluxcal.service.numerics.calib.sky import CalibrationSection, probe_sky
from fluxcal.service.numerics.diagnose.text import reference_words

#: the median |raw| is taken over at most this many samples, evenly spaced (hours of data: no copy of them all)
SCALE_ROWS = 100_000


def _field_scale_nT(cal: Any, raw_nT: np.ndarray) -> float:
    """The total field the offsets are judged against: the calibration's, else the median |raw|."""
    if getattr(cal, "total_nT", None):
        return float(cal.total_nT)
    step = max(1, raw_nT.shape[0] // SCALE_ROWS)
    return float(np.median(np.linalg.norm(raw_nT[::step].reshape(-1, 3), axis=1)))


def section_from_fit(data: Any, cal: Any, channels: dict[str, np.ndarray], coverages: list[Any],
                     warnings: list[str], total_source: str, rows: np.ndarray | None = None) -> CalibrationSection:
    """`fluxcal fit`: `channels` the residual channels it printed; `rows` the samples they belong to
    (None: every sample of the data)."""
    raw = data.block.field_nT if rows is None else data.block.field_nT[rows]
    field = _field_scale_nT(cal, raw)
    skies = [probe_sky(p.name, raw[:, k], p.offset_nT, channels[f"{p.name}.scalar"], coverages[k])
             for k, p in enumerate(cal.probes)]
    table = [r for p in cal.probes for r in probe_rows(p, warnings, field)] + effect_rows(cal.effect_params)
    desc = (f"method {cal.method}, alignment {cal.align or '-'}, effects {', '.join(cal.effects) or '-'}; "
            f"total field from {total_source}; directions about each fitted offset")
    return CalibrationSection(f"{cal.method} fit", desc, skies, table, list(warnings))


def section_from_diagnosis(d: Any) -> CalibrationSection:
    """`fluxcal diagnose`: the linear part of the model it compared (refitted, or held fixed from
    --calibration) with the effect parameters, and its residual."""
    from fluxcal.service.numerics.engine.model_fit import effects_fit_from

    fit = d.fit
    pr = fit.problem
    raw = pr.data.raw_nT[pr.rows]
    cal = effects_fit_from(fit, d.reference).calibration()
    field = _field_scale_nT(None, raw)
    skies, table, warnings = [], [], []
    refit = d.linear == "refit"
    for k, p in enumerate(cal.probes):
        cov = coverage(raw[:, k], centre_nT=p.offset_nT)
        skies.append(probe_sky(p.name, raw[:, k], p.offset_nT, fit.channels.values[:, k], cov))
        if refit:
            lost = [f"offset_nT.{a}" for a, s in zip("xyz", p.offset_se_nT) if not np.isfinite(s)]
            table += probe_rows(p, (), field, undetermined=lost)
            warnings += [f"{p.name}: {name} not determined by these data" for name in lost]
        else:
            table += [r.__class__(**{**r.__dict__, "note": "held fixed (--calibration)"})
                      for r in probe_rows(p, (), field)]
        if cov.regions:
            warnings.append(f"{p.name}: only {cov.fraction:.0%} of the field directions about the fitted offset were "
                            f"seen; {cov.advice()}")
    table += effect_rows(cal.effect_params)
    desc = (f"the linear part of {d.model}, {'refitted to these data' if refit else 'held fixed (--calibration)'}, "
            f"with its effects; total field {reference_words(d.reference)}; matrix standard errors are not given by this fit")
    return CalibrationSection("Linear calibration of the model compared", desc, skies, table, warnings)


__all__ = ["section_from_fit", "section_from_diagnosis"]
