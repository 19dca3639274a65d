"""The one pipeline that live input, replay and `fit --method rls` share.

    SampleBlock -> correct with the calibration in use -> differences, centre field, tensor
               -> ring buffer -> online RLS ellipsoid per probe (unless frozen)
               -> every check interval of *data* time: candidate = RLS estimate aligned over the
                  ring buffer; it replaces the calibration in use only if it passes the gate.

Nothing depends on the wall clock or on how the input is cut into blocks: the estimator takes
samples in fixed chunks (`chunk_samples`), the gate is checked every `check_every_samples`, and a
new calibration applies from the sample after the check. So a replay that reads the recording in
large blocks (and applies the recorded commands at their seq) gives the live run's corrected output
bit for bit. No I/O here: the daemon and the commands feed it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.block import SampleBlock
from drivers.errors import CalibrationRefused, DataError, FluxcalError
from drivers.ringbuffer import RingBuffer

from service.numerics.calib import alignment, coverage as coverage_mod, tensor as tensor_mod
from service.numerics.calib.model import ArrayCalibration
from service.numerics.calib.rls import RlsEllipsoid
from service.numerics.engine.channels import channel_names
from service.numerics.outputs import CorrectedBlock


@dataclass
class GateResult:
    usable: bool
    reasons: list[str]
    coverage: float
    condition: float
    rms_nT: list[float]


@dataclass
class PipelineEvent:
    """Something the sinks should record: calibration replaced, gate failed, command applied."""

    kind: str                 # "calibration", "gate", "command"
    seq: int                  # the first sample seq this applies from
    t_s: float
    detail: dict[str, Any] = field(default_factory=dict)


@dataclass
class Processed:
    corrected: CorrectedBlock | None
    error: dict[str, float]           # model-vs-measurement metric of this block, per channel, nT
    events: list[PipelineEvent]


def _apply(m: np.ndarray, d: np.ndarray) -> np.ndarray:
    """b[n, p, i] = Σ_j m[p, i, j] d[n, p, j], element by element: the same rounding whatever N is
    (a BLAS product may sum differently for different block sizes, and replay must equal live)."""
    return d[..., 0:1] * m[None, :, :, 0] + d[..., 1:2] * m[None, :, :, 1] + d[..., 2:3] * m[None, :, :, 2]


def _rows(b: SampleBlock, keep: np.ndarray) -> SampleBlock:
    return SampleBlock(t_s=b.t_s[keep], seq=b.seq[keep], field_nT=b.field_nT[keep], temp_C=b.temp_C[keep],
                       flags=b.flags[keep], extras={k: v[keep] for k, v in b.extras.items()})


def _join(pieces: list[CorrectedBlock]) -> CorrectedBlock | None:
    """One CorrectedBlock from consecutive pieces (cal_id: the one in use at the block's end)."""
    if not pieces:
        return None
    if len(pieces) == 1:
        return pieces[0]

    def cat(name: str):
        arrays = [getattr(p, name) for p in pieces]
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    return CorrectedBlock(t_s=cat("t_s"), seq=cat("seq"), corrected_nT=cat("corrected_nT"), diff_nT=cat("diff_nT"),
                          tensor_nT_m=cat("tensor_nT_m"), center_nT=cat("center_nT"), cal_id=pieces[-1].cal_id)


def _rms_over_rows(x: np.ndarray) -> np.ndarray:
    """RMS over axis 0 ignoring NaN (a saturated axis); NaN where a column has no finite value. The same
    arithmetic as np.nanmean, without its warning (and without a warnings context per block)."""
    ok = np.isfinite(x)
    n = ok.sum(axis=0)
    return np.sqrt(np.sum(np.where(ok, x * x, 0.0), axis=0) / np.where(n > 0, n, np.nan))


class Pipeline:
    """Stateful block processor. `process(block)` is the only hot path."""

    def __init__(self, *, n_probes: int, probe_names: list[str], positions_m: np.ndarray | None,
                 forgetting: float = 0.9995, total_nT: float | None = None, align: str = "rotation",
                 min_samples: int = 2000, gate_coverage: float = 0.3, gate_condition: float = 1e3,
                 gate_rms_nT: float = 20.0, check_every_samples: int = 400, window_samples: int = 12000,
                 chunk_samples: int = 100, initial: ArrayCalibration | None = None) -> None:
        self.n_probes = n_probes
        self.probe_names = list(probe_names)
        self.positions_m = None if positions_m is None else np.asarray(positions_m, float)
        self.total_nT = total_nT
        self.align = align
        self.forgetting = forgetting
        self.min_samples = min_samples
        self.gate_coverage = gate_coverage
        self.gate_condition = gate_condition
        self.gate_rms_nT = gate_rms_nT
        self.chunk = int(chunk_samples)
        self.check_every_chunks = max(1, int(round(check_every_samples / self.chunk))) \
            if np.isfinite(check_every_samples) else None
        self._fill = 0                    # samples buffered towards the next chunk
        self._chunks = 0                  # chunks fed since the last check
        self._buf_field = np.empty((self.chunk, n_probes, 3))
        self._buf_ref = np.empty(self.chunk)
        self.ring = RingBuffer(capacity=window_samples, n_probes=n_probes)
        self.frozen = False
        self.calibration: ArrayCalibration | None = None
        self.cal_id = 0
        self.last_gate: GateResult | None = None
        self.next_seq = 0                 # seq of the first sample the next block will bring
        self.refusal: str | None = None   # why the last check found no candidate
        self.effects: list[str] = []      # effect terms in the calibration in use (added at runtime)
        self.effect_fit = None            # their fit (service.numerics.effects), applied in _correct
        self._last_temp_C = np.full(n_probes, np.nan)   # each probe's latest valid temperature
        self._estimators = self._new_estimators()
        if initial is not None:
            self.set_calibration(initial)

    # --- state ---------------------------------------------------------------------------

    def _new_estimators(self) -> list[RlsEllipsoid]:
        return [RlsEllipsoid(forgetting=self.forgetting) for _ in range(self.n_probes)]

    def set_calibration(self, cal: ArrayCalibration) -> None:
        if len(cal.probes) != self.n_probes:
            raise DataError(f"calibration has {len(cal.probes)} probes, the unit has {self.n_probes}")
        self.calibration = cal
        self.cal_id += 1
        m = np.stack([p.matrix for p in cal.probes])
        o = np.stack([p.offset_nT for p in cal.probes])
        self._matrices, self._offsets = m, o

    def reset(self) -> None:
        self._estimators = self._new_estimators()
        self._fill = 0
        self._chunks = 0

    def command(self, name: str, payload: Any, seq: int, t_s: float) -> PipelineEvent:
        """Apply a runtime command between blocks; the event records where it took effect."""
        if name == "freeze":
            self.frozen = True
        elif name == "unfreeze":
            self.frozen = False
        elif name == "reset":
            self.reset()
        elif name == "apply":
            if not isinstance(payload, ArrayCalibration):
                raise DataError("apply: expected a calibration")
            self.effects, self.effect_fit = [], None
            self.set_calibration(payload)
        elif name == "add-effect":
            self.add_effect(str(payload or "").strip())
        else:
            raise FluxcalError(f"unknown command {name!r} (allowed: freeze, unfreeze, reset, apply, add-effect)")
        detail = {"name": name, "cal_id": self.cal_id}
        if name == "add-effect":
            detail["effect"] = str(payload or "").strip()
        return PipelineEvent("command", seq, t_s, detail)

    #: effects the running service can add: they act sample by sample, so correcting block by block
    #: gives the same numbers however the input is cut (replay = live). Effects on dB/dt or time
    #: shifts (eddy, lag) need samples across block edges: fit them offline (`fluxcal fit --effects`).
    LIVE_EFFECTS = ("temperature", "drift", "nonlinearity")

    def add_effect(self, name: str) -> None:
        """Refit the calibration with one more effect over the ring buffer and correct with it from
        now on. The online estimator keeps learning, but its linear-only candidates no longer replace
        a calibration with effects (freeze/reset/apply still work)."""
        from service.numerics.engine import fit_with_effects

        if name not in self.LIVE_EFFECTS:
            raise FluxcalError(f"add-effect: {name!r} cannot be added to the running service (allowed: "
                               f"{', '.join(self.LIVE_EFFECTS)}); fit it offline with `fluxcal fit --effects {name}`")
        if self.calibration is None:
            raise FluxcalError("add-effect: no calibration in use yet; wait until it is usable")
        names = [e for e in self.effects if e != name] + [name]
        window = self.ring.view()
        ok = np.isfinite(window.field_nT).all(axis=(1, 2))
        data = window if ok.all() else window.slice(0, 0) if not ok.any() else _rows(window, ok)
        if data.n_samples < 200:
            raise FluxcalError(f"add-effect: only {data.n_samples} samples in the window; wait for more data")
        ef, _ = fit_with_effects(data, names, self.calibration, total_nT=self.total_nT)
        params = [p for p in ef.parameters if p.term == name]
        ratios = [abs(p.value) / p.stderr for p in params if p.stderr and p.stderr > 0]
        if params and (len(ratios) < len(params) or max(ratios) < 3.0):
            # an effect the data do not show would only add noise, and a drift would be extrapolated
            worst = f"largest |value| / standard error {max(ratios):.1f}" if ratios else "not determined"
            raise FluxcalError(f"add-effect: the {data.n_samples} samples in the window do not show {name}: none of "
                               f"its {len(params)} parameters is 3 standard errors from zero ({worst}); not added. "
                               f"`fluxcal diagnose` on the recording ranks what is missing")
        cal = ef.calibration()
        cal.method, cal.align = self.calibration.method, self.calibration.align
        self.effect_fit = ef
        self.effects = names
        self.set_calibration(cal)

    # --- hot path --------------------------------------------------------------------------

    def process(self, block: SampleBlock) -> Processed:
        events: list[PipelineEvent] = []
        n = block.n_samples
        if n:
            self.next_seq = int(block.seq[-1]) + 1
        pieces: list[CorrectedBlock] = []
        start = 0
        while start < n:
            stop = min(n, start + self.chunk - self._fill)       # up to the next chunk boundary
            seg = block.slice(start, stop)
            c = self._correct(seg)
            if c is not None:
                pieces.append(c)
            self._note_temperature(seg.temp_C)
            self.ring.append(seg)
            if not self.frozen:
                self._buf_field[self._fill:self._fill + stop - start] = seg.field_nT
                ref = self._reference_total(seg)
                self._buf_ref[self._fill:self._fill + stop - start] = ref if ref is not None else np.nan
                self._fill += stop - start
                if self._fill == self.chunk:
                    self._fill = 0
                    self._update_estimators(self._buf_field, self._buf_ref)
                    self._chunks += 1
                    if self.check_every_chunks and self._chunks >= self.check_every_chunks:
                        self._chunks = 0
                        ev = self._check_candidate(int(seg.seq[-1]) + 1, float(seg.t_s[-1]))
                        if ev is not None:
                            events.append(ev)
            start = stop
        corrected = _join(pieces)
        error = self._error_metric(block.slice(n - corrected.n_samples, n), corrected) if corrected else {}
        return Processed(corrected=corrected, error=error, events=events)

    def _note_temperature(self, temp_C: np.ndarray) -> None:
        """Remember each probe's latest valid (finite) temperature."""
        if temp_C.shape[0] and np.isfinite(temp_C[-1]).all():
            self._last_temp_C[:] = temp_C[-1]             # the usual case: the last sample's are all valid
            return
        ok = np.isfinite(temp_C)
        last = np.where(ok, np.arange(temp_C.shape[0])[:, None], -1).max(axis=0, initial=-1)
        have = np.flatnonzero(last >= 0)
        self._last_temp_C[have] = temp_C[last[have], have]

    def _filled_temperature(self, temp_C: np.ndarray) -> np.ndarray:
        """Invalid (NaN) temperatures replaced by the probe's latest valid one before them: causal, so
        the same however the input is cut into blocks."""
        ok = np.isfinite(temp_C)
        if ok.all():
            return temp_C
        idx = np.maximum.accumulate(np.where(ok, np.arange(temp_C.shape[0])[:, None], -1), axis=0)
        cols = np.arange(temp_C.shape[1])[None, :]
        return np.where(idx >= 0, temp_C[np.maximum(idx, 0), cols], self._last_temp_C[None, :])

    def _correct_with_effects(self, block: SampleBlock) -> np.ndarray:
        """Linear part and the (sample-by-sample) effects. The effects' evaluator wants at least 30
        samples; a shorter piece is padded with copies of its last sample, which cannot change the
        others since every live effect acts on each sample alone. For the same reason a probe with a
        saturated (NaN) axis is evaluated at a stand-in value and comes out NaN, as without effects
        (the evaluator drops rows holding NaN); an invalid temperature is the probe's latest valid one."""
        n = block.n_samples
        sat = ~np.isfinite(block.field_nT).all(axis=2)                   # (N, P)
        field = np.where(sat[..., None], self._offsets[None], block.field_nT) if sat.any() else block.field_nT
        extras = block.extras
        ref = extras.get("ref_total")
        if ref is not None and not np.isfinite(ref).all():
            # a missing reference reading: it enters the fit's comparison, never the corrected vector, but
            # the evaluator would drop its row; a stand-in keeps the row (and the layout of the fit's terms)
            ok = np.isfinite(ref)
            stand_in = float(np.median(ref[ok])) if ok.any() else float(self.total_nT or 0.0)
            extras = {**extras, "ref_total": np.where(ok, ref, stand_in)}
        block = SampleBlock(t_s=block.t_s, seq=block.seq, field_nT=field,
                            temp_C=self._filled_temperature(block.temp_C), flags=block.flags, extras=extras)
        with np.errstate(divide="ignore", invalid="ignore"):       # a stand-in may sit at the centre
            if n >= 30:
                c = self.effect_fit.correct(block)
            else:
                idx = np.r_[np.arange(n), np.full(30 - n, n - 1)]
                t = block.t_s[idx].copy()
                t[n:] = t[n - 1] + 1e-6 * np.arange(1, 31 - n)
                padded = SampleBlock(t_s=t, seq=block.seq[idx], field_nT=block.field_nT[idx],
                                     temp_C=block.temp_C[idx], flags=block.flags[idx],
                                     extras={k: v[idx] for k, v in block.extras.items()})
                c = self.effect_fit.correct(padded)[:n]
        c[sat] = np.nan
        return c

    def flush_estimator(self) -> None:
        """Feed a partly filled chunk to the estimator (end of a batch; the service never needs it)."""
        if self._fill and not self.frozen:
            self._update_estimators(self._buf_field[:self._fill], self._buf_ref[:self._fill])
        self._fill = 0

    def _correct(self, block: SampleBlock) -> CorrectedBlock | None:
        if self.calibration is None:
            return None
        if self.effect_fit is not None and block.n_samples:
            c = self._correct_with_effects(block)
        else:
            # b_k = M_k (raw_k - o_k) for every sample and probe at once
            c = _apply(self._matrices, block.field_nT - self._offsets[None])
        diff = c[:, 1:] - c[:, :1] if self.n_probes > 1 else None
        center = c.mean(axis=1) if self.n_probes > 1 else None
        tens = None
        if self.positions_m is not None and self.n_probes >= 4:
            tens = tensor_mod.tensor_from_positions(c, self.positions_m)
        return CorrectedBlock(t_s=block.t_s, seq=block.seq, corrected_nT=c, diff_nT=diff, tensor_nT_m=tens,
                              center_nT=center, cal_id=self.cal_id)

    def _reference_total(self, block: SampleBlock) -> np.ndarray | float | None:
        ref = block.extras.get("ref_total")
        return ref if ref is not None else self.total_nT

    def _update_estimators(self, field_nT: np.ndarray, ref: np.ndarray) -> None:
        ok_rows = np.isfinite(field_nT).all(axis=2)                       # (N, P)
        have_ref = bool(np.isfinite(ref).all())
        for k, est in enumerate(self._estimators):
            rows = ok_rows[:, k]
            if not rows.any():
                continue
            r = ref[rows] if have_ref else self.total_nT
            est.partial_fit(field_nT[rows, k], total_nT=r)

    def _error_metric(self, block: SampleBlock, corrected: CorrectedBlock | None) -> dict[str, float]:
        if corrected is None or block.n_samples == 0:
            return {}
        ref = self._reference_total(block)
        out: dict[str, float] = {}
        names = channel_names(self.probe_names)                           # scalars, then differences
        mag = np.linalg.norm(corrected.corrected_nT, axis=2)              # (N, P)
        if ref is not None:
            res = mag - (ref[:, None] if isinstance(ref, np.ndarray) else ref)
            out.update(zip(names[:self.n_probes], map(float, _rms_over_rows(res))))
        if corrected.diff_nT is not None and self.positions_m is None:
            d = _rms_over_rows(corrected.diff_nT)                          # (P-1, 3)
            out.update(zip(names[self.n_probes:], map(float, d.reshape(-1))))
        return out

    # --- the gate ----------------------------------------------------------------------------

    def _check_candidate(self, seq: int, t_s: float) -> PipelineEvent | None:
        cand = self.candidate()
        if cand is None:
            if self.refusal is None:
                return None                   # too few samples yet: nothing to say
            return PipelineEvent("gate", seq, t_s, {"usable": False, "reasons": [self.refusal]})
        gate = self.evaluate(cand)
        self.last_gate = gate
        if self.effects:
            return None                       # a linear-only candidate never replaces effects
        if not gate.usable:
            return PipelineEvent("gate", seq, t_s, {"usable": False, "reasons": gate.reasons})
        first = self.calibration is None
        self.set_calibration(cand)
        return PipelineEvent("calibration", seq, t_s, {"cal_id": self.cal_id, "first_usable": first,
                                                        "coverage": gate.coverage, "condition": gate.condition,
                                                        "rms_nT": gate.rms_nT})

    def _window(self, max_samples: int = 600) -> SampleBlock:
        """The ring buffer, thinned to at most `max_samples` evenly spaced samples: directions and
        residuals change slowly, and the gate runs often."""
        n = len(self.ring)
        step = max(1, -(-n // max_samples))
        return self.ring.take(np.arange(0, n, step))         # only the rows kept: no copy of the whole ring

    def candidate(self) -> ArrayCalibration | None:
        """The online estimate, aligned over the ring buffer, or None if not yet determined (then
        `refusal` says why, once there are enough samples to ask)."""
        self.refusal = None
        if any(est.n_samples_ < self.min_samples for est in self._estimators):
            return None
        try:
            probes = [est.snapshot(name=name) for est, name in zip(self._estimators, self.probe_names)]
        except (CalibrationRefused, FluxcalError) as e:
            self.refusal = str(e)
            return None
        window = self._window()
        if self.n_probes > 1 and self.align != "none" and window.n_samples >= 3:
            probes = alignment.align_probes(probes, window.field_nT, method=self.align)
        return ArrayCalibration(method="rls", align=None if self.n_probes == 1 else self.align, probes=probes,
                                total_nT=self.total_nT, effects=[], diagnostics={},
                                span=(float(window.t_s[0]) if window.n_samples else 0.0,
                                      float(window.t_s[-1]) if window.n_samples else 0.0,
                                      int(self._estimators[0].n_samples_)))

    def evaluate(self, cal: ArrayCalibration) -> GateResult:
        """The quality gate: coverage, conditioning and residual over the ring buffer window."""
        window = self._window()
        reasons: list[str] = []
        covs, conds, rmss = [], [], []
        ref = self._reference_total(window)
        for k, (p, est) in enumerate(zip(cal.probes, self._estimators)):
            raw = window.field_nT[:, k]
            raw = raw[np.isfinite(raw).all(axis=1)]
            cov = coverage_mod.coverage(raw)
            covs.append(cov.fraction)
            conds.append(float(est.condition_))
            corr = p.apply(raw)
            if ref is None:
                mag = np.linalg.norm(corr, axis=1)
                rms = float(np.std(mag))
            else:
                r = ref[np.isfinite(window.field_nT[:, k]).all(axis=1)] if isinstance(ref, np.ndarray) else ref
                rms = float(np.sqrt(np.mean((np.linalg.norm(corr, axis=1) - r) ** 2)))
            rmss.append(rms)
            name = self.probe_names[k]
            if cov.fraction < self.gate_coverage:
                reasons.append(f"{name}: {cov.reason or 'coverage too small'}")
            if not np.isfinite(conds[-1]) or conds[-1] > self.gate_condition:
                reasons.append(f"{name}: ill-conditioned fit (condition {conds[-1]:.3g})")
            if not np.isfinite(rms) or rms > self.gate_rms_nT:
                reasons.append(f"{name}: residual {rms:.3g} nT above the gate {self.gate_rms_nT} nT")
            if not (np.all(np.isfinite(p.matrix)) and np.all(np.isfinite(p.offset_nT))):
                reasons.append(f"{name}: non-finite parameters")
        return GateResult(usable=not reasons, reasons=reasons, coverage=float(min(covs)),
                          condition=float(max(conds)), rms_nT=rmss)

    def state(self) -> dict[str, Any]:
        """The calibration state for publishing (JSON-ready)."""
        cal = self.calibration
        g = self.last_gate
        return {
            "cal_id": self.cal_id,
            "usable": cal is not None,
            "frozen": self.frozen,
            "method": None if cal is None else cal.method,
            "effects": list(self.effects),
            "probes": [] if cal is None else [
                {"name": p.name, "offset_nT": p.offset_nT.tolist(), "matrix": p.matrix.tolist(),
                 "offset_se_nT": np.nan_to_num(p.offset_se_nT, nan=-1).tolist()} for p in cal.probes],
            "gate": None if g is None else {"usable": g.usable, "reasons": g.reasons, "coverage": g.coverage,
                                            "condition": g.condition, "rms_nT": g.rms_nT},
            "samples_seen": int(min(est.n_samples_ for est in self._estimators)),
        }
