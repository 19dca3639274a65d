"""The quality gate of the online calibration: the candidate (the online estimate aligned over the ring
buffer) and whether it may replace the calibration in use (coverage, conditioning, residual)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import CalibrationRefused, FluxcalError
from fluxcal.drivers.ringbuffer import RingBuffer
from fluxcal.service.numerics.calib import alignment
from fluxcal.service.numerics.calib.determinacy import judge, physical
from fluxcal.service.numerics.calib.misfit import add_direction_spread, add_time_spread
from fluxcal.service.numerics.calib.model import ArrayCalibration
from fluxcal.service.numerics.calib.rls import RlsEllipsoid


@dataclass
class GateResult:
    usable: bool
    reasons: list[str]
    coverage: float
    condition: float
    rms_nT: list[float]


class Gate:
    """Settings and verdicts of the gate (EstimatorConfig's gate_* keys)."""

    def __init__(self, *, probe_names: Sequence[str], align: str, min_samples: int, coverage: float,
                 condition: float, rms_nT: float, total_nT: float | None) -> None:
        self.probe_names = list(probe_names)
        self.align, self.min_samples, self.total_nT = align, min_samples, total_nT
        self.coverage, self.condition, self.rms_nT = coverage, condition, rms_nT
        self.refusal: str | None = None   # why the last check found no candidate
        self.asked = 0                      # estimators the last candidate() asked for a snapshot (each solved)
        # the candidate's errors at least the ring buffer's spread in time and direction (_add_spreads); off for
        # a caller that adds its own (`fit --method rls`: the coloured-noise and direction errors)
        self.spread_errors = True
        self._window: SampleBlock | None = None
        self._window_key: tuple | None = None   # (ring, samples appended, length, max_samples) it was taken at

    def window(self, ring: RingBuffer, max_samples: int = 600) -> SampleBlock:
        """The ring buffer, thinned to at most `max_samples` evenly spaced samples: directions and
        residuals change slowly, and the gate runs often. Taken once per state of the ring (the candidate
        and its evaluation at one check share it)."""
        key = (ring, ring.total_appended, len(ring), max_samples)
        last = self._window_key
        if last is None or last[0] is not ring or last[1:] != key[1:]:
            n = len(ring)
            step = max(1, -(-n // max_samples))
            self._window = ring.take(np.arange(0, n, step))    # only the rows kept: no copy of the whole ring
            self._window_key = key
        assert self._window is not None
        return self._window

    def candidate(self, estimators: Sequence[RlsEllipsoid], ring: RingBuffer) -> ArrayCalibration | None:
        """The online estimate, aligned over the ring buffer, or None if not yet determined (then
        `refusal` says why, once there are enough samples to ask)."""
        self.refusal, self.asked = None, 0
        if any(est.n_samples_ < self.min_samples for est in estimators):
            return None
        probes = []
        try:
            for est, name in zip(estimators, self.probe_names):
                self.asked += 1                 # the estimators solved: the snapshots taken, and the one refused
                probes.append(est.snapshot(name=name))
        except (CalibrationRefused, FluxcalError) as e:
            self.refusal = str(e)
            return None
        if self.spread_errors:
            self._add_spreads(probes, ring)
        window = self.window(ring)
        if len(estimators) > 1 and self.align != "none" and window.n_samples >= 3:
            probes = alignment.align_probes(probes, window.field_nT, method=self.align)
        return ArrayCalibration(method="rls", align=None if len(estimators) == 1 else self.align, probes=probes,
                                total_nT=self.total_nT, effects=[], diagnostics={},
                                span=_span(ring))

    #: samples of the ring buffer (evenly spaced) over which the candidate's errors are checked (time, direction)
    SPREAD_SAMPLES = 4000

    def _add_spreads(self, probes: list, ring: RingBuffer) -> None:
        """Each probe's errors at least those of leaving one stretch of the ring buffer out, and one region of
        field direction, where its residual differs between them beyond chance for white noise (misfit: as the
        batch fit's): the estimator's own errors are white-noise ones, and a real board's offsets were 4-7 of
        them from those its authors published. The fits left out are unconstrained by the total field, as the
        estimator is (a configured or logged total sets only its scale: coloured_fit._fitted_total); the rows are
        those the estimator took (a logged total that is not finite drops a row)."""
        n = len(ring)
        w = ring.take(np.arange(0, n, max(1, -(-n // self.SPREAD_SAMPLES))))
        ref = reference_total(w, self.total_nT)
        for k, p in enumerate(probes):
            raw = w.field_nT[:, k]
            ok = np.isfinite(raw).all(axis=1)
            if isinstance(ref, np.ndarray):
                ok &= np.isfinite(ref)
            if np.count_nonzero(ok) >= 200 and p.offset_se_nT is not None and p.matrix_se is not None:
                add_time_spread(p, "full", raw[ok], None, p.name)
                add_direction_spread(p, "full", raw[ok], None, p.name)

    def evaluate(self, cal: ArrayCalibration, estimators: Sequence[RlsEllipsoid], ring: RingBuffer) -> GateResult:
        """The quality gate: coverage, conditioning, residual and one turn's wobble over the ring buffer window."""
        window = self.window(ring)
        reasons: list[str] = []
        covs, conds, rmss = [], [], []
        ref = reference_total(window, self.total_nT)
        for k, (p, est) in enumerate(zip(cal.probes, estimators)):
            raw = window.field_nT[:, k]
            # the one determinacy gate (determinacy.judge), asked of the window's samples as fit asks it of a file's:
            # enough samples, not one plane, conditioned, not one cone, the share of directions; one verdict, one cone;
            # and as fit, inspect and diagnose ask it, physical: a field no magnetometer reads, samples on no one
            # ellipsoid (a static platform's noise, 100 % of the directions "seen" about a centre inside it)
            judged = physical(judge(raw, ref, name=self.probe_names[k], min_fraction=self.coverage,
                                    max_condition=self.condition, maps=False), raw, ref,
                              "the ref_total column" if isinstance(ref, np.ndarray) else "estimator.total_nT")
            covs.append(judged.coverage.fraction)
            conds.append(float(est.condition_))
            _, rms = scalar_residual(p, window, k, ref)
            rmss.append(rms)
            name = self.probe_names[k]
            if not judged.determined:           # (a real hand turn was accepted 63,000 nT off before the cone test)
                reasons.append(f"{name}: {judged.problem}")
            if not np.isfinite(conds[-1]) or conds[-1] > self.condition:
                reasons.append(f"{name}: ill-conditioned fit (condition {conds[-1]:.3g})")
            if not np.isfinite(rms) or rms > self.rms_nT:
                reasons.append(f"{name}: residual {rms:.3g} nT above the gate {self.rms_nT} nT")
            if not (np.all(np.isfinite(p.matrix)) and np.all(np.isfinite(p.offset_nT))):
                reasons.append(f"{name}: non-finite parameters")
        return GateResult(usable=not reasons, reasons=reasons, coverage=float(min(covs)),
                          condition=float(max(conds)), rms_nT=rmss)

    def fails_on_data(self, cal: ArrayCalibration, ring: RingBuffer, in_use: ArrayCalibration | None = None) -> str:
        """"" where `cal` leaves on the ring's window a residual the gate accepts, or not far above what the calibration
        in use leaves (DATA_JUMP times); else the figures, naming the probe: the data check of identity.judge_on_data
        (which refuses), and of the calibration a service starts from once it has the samples (which says it)."""
        window = self.window(ring)
        ref = reference_total(window, self.total_nT)
        for k, probe in enumerate(cal.probes):
            _, rms = scalar_residual(probe, window, k, ref)
            now = scalar_residual(in_use.probes[k], window, k, ref)[1] if in_use is not None else None
            if not np.isfinite(rms) or (rms > self.rms_nT and (now is None or rms > DATA_JUMP * now)):
                span = window.t_s[-1] - window.t_s[0] if window.n_samples else 0.0
                used = f"the calibration in use leaves {now:.3g} nT, " if now is not None else ""
                shown = f"{rms:,.0f}" if rms >= 1000 else f"{rms:.4g}"
                return (f"{probe.name}: on this unit's last {span:.0f} s of data it leaves a residual of {shown} nT "
                        f"rms ({used}the gate accepts at most {self.rms_nT:g} nT: estimator.gate_rms_nT)")
        return ""


#: a calibration that leaves more than this times the residual of the one in use (and more than the gate allows) is
#: refused on the data (Gate.fails_on_data)
DATA_JUMP = 4.0


def scalar_residual(p, window: SampleBlock, k: int, ref: np.ndarray | float | None) -> tuple[np.ndarray, float]:
    """Probe k's corrected vectors over the window (its finite samples) by calibration `p`, and the RMS of
    |corrected| - the reference total (its spread about the mean without one): the gate's residual."""
    ok = np.isfinite(window.field_nT[:, k]).all(axis=1)
    corr = p.apply(window.field_nT[ok, k])
    mag = np.linalg.norm(corr, axis=1)
    if ref is None:
        return corr, float(np.std(mag))
    r = ref[ok] if isinstance(ref, np.ndarray) else ref
    return corr, float(np.sqrt(np.mean((mag - r) ** 2)))


def _span(ring: RingBuffer) -> tuple[float, float, int]:
    """(t0_s, t1_s, n_samples) of the ring buffer: its first and last instants and the samples between."""
    n = len(ring)
    if not n:
        return 0.0, 0.0, 0
    ends = ring.take(np.array([0, n - 1]))
    return float(ends.t_s[0]), float(ends.t_s[-1]), n


def reference_total(block: SampleBlock, total_nT: float | None) -> np.ndarray | float | None:
    """The total field the scalar residual is taken against: the block's ref_total, else the configured one."""
    ref = block.extras.get("ref_total")
    return ref if ref is not None else total_nT
