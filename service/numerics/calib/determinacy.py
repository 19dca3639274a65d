"""The one determinacy gate: whether a probe's samples determine a calibration, with the same test, the same axis
and the same figures whichever command asks (`fit` of every method, `diagnose`, `inspect`'s verdict, the online
gate of the service, and a fleet through them).

The judge is the ellipsoid fit of order `auto` of the samples against the reference the data give (a ref_total
column, a configured or site field, else estimated): a function of the samples and the reference alone, never of
the method that then calibrates them. Its fitted centre and frame give the field directions; the gate refuses

    - what the solve cannot fix: too few samples, one plane, a design conditioned beyond the limit, no ellipsoid;
    - one cone of directions (excitation.cone_of): the offset along its axis rests on the wobble;
    - offsets the fit's standard errors leave undetermined (a tenth of the field);
    - a fitted shape no sensor has (shape_problem: the judge's matrix conditioned beyond MAX_SHAPE_CONDITION);
    - too small a share of the directions seen about the judge's centre, where the caller sets one: the service's
      gate (gate_coverage), which replaces a calibration in use unattended; a batch command fits what the directions
      determine (the model order) and says what they miss, so it asks none (min_fraction 0).

    judge(raw_nT, total_nT, name=...) -> Determinacy     one probe
    judge_all(field_nT, total_nT, names) -> [Determinacy]
    refuse_undetermined(judgements, then=...)             CalibrationRefused for the first probe not determined
    physical(judgement, raw_nT, given_total_nT, source)   the same verdict where the field it gives is no Earth's
    shell_thickness(judgement, raw_nT)                    how far the samples lie from the judge's ellipsoid

The estimators stay indifferent to the data's unit and origin; `physical` is what the commands that read files
(fit, diagnose, inspect) add: a calibration whose total field is not the site's (a reference the data give: the
model along their track, --site, a ref_total column, a configured field), or with none, not the Earth's
(field_scale.EARTH_RANGE_NT), is refused with the unit the data's size suggests, or, where the samples lie on no one
ellipsoid (SHELL_MAX) or read an Earth's field about zero and not about the centre, with the turns they lack.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused

from ..field_scale import EARTH_RANGE_NT, SITE_RATIO_MAX, median_field, unit_guess
from .coverage import Coverage, coverage
from .excitation import Cone
from .quadric import MAX_CONDITION

#: the largest condition number of a fitted matrix taken as a sensor's: axes whose gains differ 5-fold (the real
#: boards of ../shared/real-data: 1.2 to 2.2; a real flight's cone of directions fitted with the total estimated: 9.4)
MAX_SHAPE_CONDITION = 5.0


def shape_problem(matrix: np.ndarray) -> str:
    """Why a fitted matrix is no sensor's (a mirror, a scale of 2.3 with 62 degrees of non-orthogonality: the data do
    not determine the shape), "" where it may be one. Only the shape is judged, a condition up to MAX_SHAPE_CONDITION:
    the overall scale is the data's unit or the field's (physical says that). The gate asks it of its own fit, `fit`
    of the calibration every method gives."""
    from .plausible import CalibrationLimits, matrix_problem

    found = matrix_problem(matrix, CalibrationLimits(max_condition=MAX_SHAPE_CONDITION, max_scale=float("inf")),
                           keys=False)
    return "" if found is None else (f"the fitted calibration is no sensor's (fails the {found[0]} check: {found[1]}): "
                                     f"these data do not determine it")


@dataclass(frozen=True)
class Determinacy:
    """One probe's verdict: `problem` "" where its samples determine a calibration, else why not (naming the probe)
    and `advice`, what would help; the figures it rests on: the judge's centre, the cone, the coverage."""

    probe: str
    n_samples: int
    problem: str
    advice: str
    coverage: Coverage
    cone: Cone | None = None
    centre_nT: np.ndarray | None = None
    field_nT: float | None = None                  # the judge's field: the reference's mean, or the one it assumed
    fit: Any = None                                # the judge's ellipsoid fit (ellipsoid.EllipsoidCore), if it fitted

    @property
    def determined(self) -> bool:
        return not self.problem

    def as_dict(self) -> dict[str, Any]:
        c = self.coverage
        return {"probe": self.probe, "determined": self.determined, "samples": self.n_samples,
                "reason": self.problem or None, "advice": self.advice or None,
                "centre_nT": None if self.centre_nT is None else [float(x) for x in self.centre_nT],
                "field_nT": self.field_nT, "cone": None if self.cone is None else self.cone.as_dict(),
                "coverage": {"fraction": c.fraction, "missing": c.missing, "condition": _finite(c.condition)}}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _split(problem: str) -> tuple[str, str]:
    """A refusal's sentence as (reason, advice): the advice is what follows its last ': turn' / '; turn' / ':
    leave' clause, else the coverage's advice is given by the caller."""
    for mark in ("; turn about", ": turn about", "; directions near", ": directions near", "; spread the samples",
                 "; rotate"):
        i = problem.rfind(mark)
        if i > 0:
            return problem[:i], problem[i + 2:]
    return problem, ""


def judge(raw_nT: np.ndarray, total_nT: Any = None, *, name: str = "s1", min_fraction: float = 0.0,
          max_condition: float = MAX_CONDITION, core: Any = None, maps: bool = True) -> Determinacy:
    """Whether the (N, 3) raw samples of one probe determine a calibration against total_nT (per sample (N,), a
    constant, or None: estimated): the module docstring's tests, in that order. Rows with a NaN are left out (with
    their reference). core: the judge's fit already made of these samples (ellipsoid.ellipsoid_core), not redone;
    maps: the coverage's text maps (the online gate, which shows none, asks without)."""
    from .ellipsoid import ellipsoid_core

    raw = np.asarray(raw_nT, float)
    ok = np.isfinite(raw).all(axis=1)
    total = total_nT
    if isinstance(total, np.ndarray) and total.ndim:
        ok &= np.isfinite(total)
        total = total if ok.all() else total[ok]
    raw = raw if ok.all() else raw[ok]                # no copy of hours of samples where every row is finite
    problem, cone, centre, field_nT = "", None, None, None
    if core is None:
        try:
            core = ellipsoid_core(raw, total, name=name, max_condition=max_condition)
        except CalibrationRefused as e:
            problem = str(e).removeprefix(f"{name}: ")
    if core is not None:
        cal = core.fit.calibration
        centre, cone, field_nT = cal.offset_nT, core.cone, float(np.sqrt(core.fit.f2_ref))
        problem = core.problem() or shape_problem(cal.matrix)
    cov = coverage(raw, centre_nT=centre, min_fraction=min_fraction, max_condition=max_condition, maps=maps)
    if not problem and not cov.usable:
        problem = cov.reason
    advice = _split(problem)[1] if problem else ""
    if problem and not advice:
        advice = cov.advice() or "turn the probe about at least two axes, so the field sweeps most directions"
        problem = f"{problem}; {advice}"
    return Determinacy(name, int(raw.shape[0]), problem, advice, cov, cone, centre, field_nT, core)


def judge_all(field_nT: np.ndarray, total_nT: Any, probe_names: Sequence[str], **kw: Any) -> list[Determinacy]:
    """judge() of every probe of (N, P, 3) samples, in order."""
    return [judge(field_nT[:, k], total_nT, name=name, **kw) for k, name in enumerate(probe_names)]


def refuse_undetermined(judgements: Sequence[Determinacy], *, then: str = "") -> None:
    """CalibrationRefused for the first probe whose samples do not determine a calibration: its message the probe's
    name, the problem and `then` (what the refusal costs); `reason` and `advice` as attributes (the JSON of a
    refusal), and `problem` (what is not determined, for advice that quotes it)."""
    for j in judgements:
        if not j.determined:
            refused = CalibrationRefused(f"{j.probe}: {j.problem}{then}")
            refused.problem = f"{j.probe}: {j.problem}"
            reason = j.problem[:-len(j.advice)].rstrip("; :") if j.advice and j.problem.endswith(j.advice) else j.problem
            refused.reason = f"{j.probe}: {reason}"
            refused.advice = j.advice
            raise refused


#: the share of directions seen about the judge's centre below which a field that is a field about zero but not about
#: that centre is said as directions that do not place the centre (above it: a unit or a gain)
WIDE_COVERAGE = 0.75
#: the RMS distance of the samples from the judge's fitted ellipsoid, as a share of its size, above which they lie on
#: no one ellipsoid: a cloud, not a shell, whatever share of directions its centre sees (measured 2026-12-07: the real
#: boards of ../shared/real-data turned by hand and a tumbled copter's log 0.3-2.9 %; seven public flight logs whose
#: compass hardly turned or turned in its platform's own field 13-36 %; one that never turned 44 %, every direction
#: "seen" about a centre inside the cloud)
SHELL_MAX = 0.1


def physical(j: Determinacy, raw_nT: np.ndarray, given_total_nT: Any = None, source: str = "") -> Determinacy:
    """The judgement `j` of (N, 3) raw samples, refused (problem and advice) where the field is physically absurd:
    with a reference (given_total_nT: per sample, or a constant; `source` says what it is) when the data's own size
    about the judge's centre is more than SITE_RATIO_MAX from it; without one, when the field the judge assumed lies
    outside the Earth's (EARTH_RANGE_NT). The samples' size about zero says whether their unit is wrong or the
    directions they span do not place the centre. A field in range is refused all the same where the samples lie on
    no one ellipsoid (a cloud: `cloud`). A judgement already refused, or without a centre, is returned."""
    if not j.determined or j.centre_nT is None:
        return j
    thick = shell_thickness(j, raw_nT)
    raw = np.asarray(raw_nT, float)[:, None, :]
    size = float(median_field(raw, [j.centre_nT])[0])
    about_zero = float(median_field(raw, [np.zeros(3)])[0])          # what the data read before any offset
    lo, hi = EARTH_RANGE_NT
    if given_total_nT is not None:
        ref = np.asarray(given_total_nT, float)
        ref = float(np.nanmedian(ref)) if ref.ndim else float(ref)
        if not np.isfinite(size) or size <= 0 or 1.0 / SITE_RATIO_MAX <= ref / size <= SITE_RATIO_MAX:
            return cloud(j, thick)
        fits_zero = 1.0 / SITE_RATIO_MAX <= ref / max(about_zero, 1e-300) <= SITE_RATIO_MAX
        given = f"the total field given ({ref:,.0f} nT, {source or 'given'})"
        r = max(ref / size, size / ref)
        problem = (f"the data's field about their fitted centre is {_nT(size)} nT (median), "
                   f"{f'{r:,.0f}' if r >= 10 else f'{r:.2g}'} times {'below' if ref > size else 'above'} {given}: the "
                   f"calibration would scale the sensor by that factor, which no sensor's gain is (accepted within "
                   f"{SITE_RATIO_MAX:g} times)")
        guess = unit_guess(size)
        last = f"or check {given}"
    else:
        field = j.field_nT if j.field_nT is not None else size
        if lo <= field <= hi:
            return cloud(j, thick)
        fits_zero = lo <= about_zero <= hi
        problem = (f"with no reference field, the fit assumes a total field of {_nT(field)} nT (the calibrated sphere "
                   f"has the raw ellipsoid's volume), outside the Earth's {lo:,.0f}-{hi:,.0f} nT: no magnetometer on "
                   f"Earth reads that")
        guess = unit_guess(field)
        last = ("or give the site's field (--site LAT,LON[,ALT], a ref_total column or estimator.total_nT) to have the "
                "fit scaled to it and checked against it")
    if thick is not None and thick > SHELL_MAX:       # the fitted size says nothing of the unit: no guess from it
        problem += (f"{f', while the samples read {about_zero:,.0f} nT about zero and' if fits_zero else ', and the samples'}"
                    f" {_on_no_ellipsoid(thick)}")
        advice = CLOUD_ADVICE
    elif fits_zero and j.coverage.fraction < WIDE_COVERAGE:
        problem += (f", while the samples read {about_zero:,.0f} nT about zero: the directions they span do not place "
                    f"the centre (one turn, or too small a part of the sphere)")
        advice = "turn the probe about at least two axes, so the field sweeps most directions"
    elif guess:
        advice = f"are the data in {guess}; the CSV contract is nT"
    else:
        advice = ("the data's scale is not a field in nT: check the unit and the gain, and that the compass is not in "
                  "a platform's own field")
    advice = f"{advice}; {last}"
    return replace(j, problem=f"{problem}; {advice}", advice=advice)


def cloud(j: Determinacy, thick: float | None) -> Determinacy:
    """The judgement `j`, refused where its samples lie on no one ellipsoid (their shell thickness above SHELL_MAX),
    whatever field they read: a calibration that leaves a tenth of the field as residual is no magnetometer's (a
    cloud of pure noise of 17,000 nT about zero was calibrated with exit 0, a residual of 6,663 nT)."""
    if thick is None or thick <= SHELL_MAX:
        return j
    problem = f"the samples {_on_no_ellipsoid(thick)}, or the data are no magnetometer's"
    return replace(j, problem=f"{problem}; {CLOUD_ADVICE}", advice=CLOUD_ADVICE)


#: what helps samples that lie on no one ellipsoid
CLOUD_ADVICE = ("turn the probe about at least two axes, so the field sweeps most directions, away from what moves the "
                "field about it (motors, currents, iron that turns with it)")


def _on_no_ellipsoid(thick: float) -> str:
    """The words for samples of shell thickness `thick` (above SHELL_MAX), after "the samples"."""
    return (f"lie on no one ellipsoid (their RMS distance from the fitted one is {thick:.0%} of its size; a sensor "
            f"turned in a steady field gives a few per cent): the probe hardly turned, or the field about it changed "
            f"as it turned (a platform's own field)")


def shell_thickness(j: Determinacy, raw_nT: np.ndarray) -> float | None:
    """The RMS distance of the (N, 3) raw samples from the judge's fitted ellipsoid, as a share of its size:
    rms(|M (r - o)| / median - 1) of the judge's calibration; None where the judge made no fit. Free of the data's
    unit and origin, and of the field the fit was scaled to."""
    if j.fit is None:
        return None
    cal = j.fit.fit.calibration
    raw = np.asarray(raw_nT, float)
    mags = [np.linalg.norm((raw[a:a + 65_536] - cal.offset_nT) @ cal.matrix.T, axis=1)  # no (N, 3) temporaries
            for a in range(0, raw.shape[0], 65_536)]
    mag = np.concatenate(mags) if mags else np.empty(0)
    mag = mag[np.isfinite(mag)]
    mid = float(np.median(mag)) if mag.size else 0.0
    if not mid > 0:
        return None
    return float(np.sqrt(np.mean((mag / mid - 1.0) ** 2)))


def _nT(x: float) -> str:
    """A field as said: 12,563 from 1,000 up, else three figures (52.5)."""
    return f"{x:,.0f}" if abs(x) >= 1000 else f"{x:.3g}"
