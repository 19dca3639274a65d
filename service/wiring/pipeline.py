"""The one pipeline that live input, replay and `fit --method rls` share.

    SampleBlock -> correct with the calibration in use -> differences, centre field, tensor
               -> ring buffer -> online RLS ellipsoid, every probe in one estimator (unless frozen)
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

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import DataError, FluxcalError
from fluxcal.drivers.ringbuffer import RingBuffer
from fluxcal.service.numerics.calib.model import ArrayCalibration, apply_columns, matrix_columns
from fluxcal.service.numerics.calib.rls import RlsEllipsoid
from fluxcal.service.numerics.calib.rls_info import finite_rows
from fluxcal.service.numerics.channels import BlockError
from fluxcal.service.numerics.outputs import CorrectedBlock, Derived, join_corrected

from .gate import Gate, GateResult, reference_total
from .live_effects import LiveEffects


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


def _rows(block: SampleBlock, start: int, stop: int) -> SampleBlock:
    """block.slice(start, stop), the block itself when that is all of it (the usual live block: no copy)."""
    return block if start == 0 and stop == block.n_samples else block.slice(start, stop)


def _reference_tail(block: SampleBlock, n: int, total_nT: float | None) -> np.ndarray | float | None:
    """reference_total of the block's last n samples."""
    ref = block.extras.get("ref_total")
    return total_nT if ref is None else ref[ref.shape[0] - n:]


#: an apply event's note (its presence also tells replay that the live run held the applied calibration)
APPLIED_NOTE = ("in use until `reset`: the online estimate keeps learning and the gate judging it, but it does not "
                "replace an applied calibration")


class _ChunkFeed:
    """The estimators' side of the pipeline: samples gathered into fixed chunks of `chunk` samples, each full chunk
    given to every probe's estimator at once (Pipeline's state: _buf_field, _buf_ref, _fill, _chunks, _rls)."""

    chunk: int
    total_nT: float | None
    frozen: bool

    def _buffer(self, seg: SampleBlock) -> bool:
        """The segment into the chunk being filled (it ends at the chunk's end at most); a full chunk goes to the
        estimators. Whether it did."""
        fill, k = self._fill, seg.n_samples
        self._buf_field[fill:fill + k] = seg.field_nT
        ref = reference_total(seg, self.total_nT)
        self._buf_ref[fill:fill + k] = ref if ref is not None else np.nan
        self._fill += k
        if self._fill < self.chunk:
            return False
        self._fill = 0
        self._update_estimators(self._buf_field, self._buf_ref)
        self._chunks += 1
        return True

    def flush_estimator(self) -> None:
        """Feed a partly filled chunk to the estimator (end of a batch; the service never needs it)."""
        if self._fill and not self.frozen:
            self._update_estimators(self._buf_field[:self._fill], self._buf_ref[:self._fill])
        self._fill = 0

    def _update_estimators(self, field_nT: np.ndarray, ref: np.ndarray) -> None:
        ok_rows = finite_rows(field_nT)                                   # (N, P)
        have_ref = bool(np.isfinite(ref).all())
        if ok_rows.all():       # every probe at once: bit for bit the per-probe updates below
            self._rls.partial_fit(field_nT, total_nT=ref if have_ref else self.total_nT)
            return
        for k, est in enumerate(self._estimators):             # a probe's NaN rows dropped (RlsProbe)
            rows = ok_rows[:, k]
            if rows.any():
                est.partial_fit(field_nT[rows, k], total_nT=ref[rows] if have_ref else self.total_nT)


class Pipeline(_ChunkFeed):
    """Stateful block processor. `process(block)` is the only hot path."""

    CORRECT_BY_CHUNK = False          # True: correct chunk by chunk, as before the spans (the tests' reference)

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
        self.chunk = int(chunk_samples)
        self.check_every_chunks = max(1, int(round(check_every_samples / self.chunk))) \
            if np.isfinite(check_every_samples) else None
        self._buf_field = np.empty((self.chunk, n_probes, 3))
        self._buf_ref = np.empty(self.chunk)
        self.ring = RingBuffer(capacity=window_samples, n_probes=n_probes)
        self.frozen = False
        self.held = False                 # a calibration applied by command: online candidates do not replace it
        self.corrects = True              # False: estimators, gate and commands only (gate_ahead's second process)
        self.calibration: ArrayCalibration | None = None
        self.cal_id = 0
        self.last_gate: GateResult | None = None
        self.next_seq = 0                 # seq of the first sample the next block will bring
        self.live = LiveEffects(n_probes, total_nT)
        self._derive = Derived(self.positions_m, n_probes)        # differences, centre, tensor of each block
        self._error = BlockError(self.probe_names, differences=self.positions_m is None)
        self.gate = Gate(probe_names=self.probe_names, align=align, min_samples=min_samples, coverage=gate_coverage,
                         condition=gate_condition, rms_nT=gate_rms_nT, total_nT=total_nT)
        self.reset()                      # the estimators, the chunk being filled, chunks since the last check
        # a calibration not judged on this unit's data (the one started from, one applied before there were samples
        # to judge it on) is judged once there are: another unit's was used for good on a static platform
        self.on_trial = initial is not None
        if initial is not None:
            self.set_calibration(initial)

    # --- state ---------------------------------------------------------------------------

    def set_calibration(self, cal: ArrayCalibration) -> None:
        if len(cal.probes) != self.n_probes:
            raise DataError(f"calibration has {len(cal.probes)} probes, the unit has {self.n_probes}")
        self.calibration = cal
        self.cal_id += 1
        m = np.stack([p.matrix for p in cal.probes])
        o = np.stack([p.offset_nT for p in cal.probes])
        self._matrices, self._offsets = m, o
        self._columns, self._offset_rows = matrix_columns(m), o[None]

    def reset(self) -> None:
        """Forget what the online estimators learned (the `reset` command)."""
        self._rls = RlsEllipsoid(forgetting=self.forgetting, n_probes=self.n_probes)   # one for every probe
        self._estimators = self._rls.probes()     # each probe as an estimator of its own (the gate reads them)
        self._fill = 0                    # samples buffered towards the next chunk
        self._chunks = 0                  # chunks fed since the last check
        self.last_gate = None             # no check since: the state says none, not the one before

    def command(self, name: str, payload: Any, seq: int, t_s: float) -> PipelineEvent:
        """Apply a runtime command between blocks; the event records where it took effect."""
        if name == "freeze":
            self.frozen = True
        elif name == "unfreeze":
            self.frozen = False
        elif name == "reset":
            self.reset()
            self.held = False             # learn again: the next usable candidate replaces what is in use
        elif name == "apply":
            if not isinstance(payload, ArrayCalibration):
                raise DataError("apply: expected a calibration")
            self.live.clear()
            self.set_calibration(payload)
            self.held = True              # it stays: the online estimate keeps learning, the gate judging it
            self.on_trial = len(self.ring) < self.gate.min_samples
        elif name == "add-effect":
            self.add_effect(str(payload or "").strip())
        else:
            raise FluxcalError(f"unknown command {name!r} (allowed: freeze, unfreeze, reset, apply, add-effect)")
        detail = {"name": name, "cal_id": self.cal_id, **({"note": APPLIED_NOTE} if name == "apply" else {}),
                  **({"effect": str(payload or "").strip()} if name == "add-effect" else {})}
        return PipelineEvent("command", seq, t_s, detail)

    # --- hot path --------------------------------------------------------------------------

    def process(self, block: SampleBlock) -> Processed:
        events: list[PipelineEvent] = []
        block = block.without_implausible()     # flagged by the driver: no estimator, effect or output uses them
        n = block.n_samples
        if n:
            self.next_seq = int(block.seq[-1]) + 1
        pieces: list[CorrectedBlock | None] = []
        # corrected in spans of one calibration, up to each check (the products round alike whatever the span);
        # with live effects chunk by chunk, before each chunk's temperatures are noted
        by_chunk = self.CORRECT_BY_CHUNK or self.live.fit is not None
        start = span = 0
        while start < n:
            stop = min(n, start + self.chunk - self._fill)       # up to the next chunk boundary
            seg = _rows(block, start, stop)
            if by_chunk:
                pieces.append(self._correct(seg))
            self.live.note_temperature(seg.temp_C)
            self.ring.append(seg)
            if not self.frozen and self._buffer(seg):
                if self.check_every_chunks and self._chunks >= self.check_every_chunks:
                    self._chunks = 0
                    if not by_chunk:                          # with the calibration in use until here
                        pieces.append(self._correct(_rows(block, span, stop)))
                        span = stop
                    ev = self._check_candidate(int(seg.seq[-1]) + 1, float(seg.t_s[-1]))
                    if ev is not None:
                        events.append(ev)
            start = stop
        if not by_chunk and span < n:
            pieces.append(self._correct(_rows(block, span, n)))
        corrected = join_corrected([c for c in pieces if c is not None])
        error = {} if corrected is None else self._error(corrected, _reference_tail(block, corrected.n_samples,
                                                                                    self.total_nT))
        return Processed(corrected=corrected, error=error, events=events)

    def _correct(self, block: SampleBlock) -> CorrectedBlock | None:
        if self.calibration is None or not self.corrects:
            return None
        if self.live.fit is not None and block.n_samples:
            c = self.live.correct(block, self._offsets)
        else:
            # b_k = M_k (raw_k - o_k) for every sample and probe at once
            c = apply_columns(self._columns, block.field_nT - self._offset_rows)
        return self._derive(block.t_s, block.seq, c, self.cal_id)

    # --- the gate (gate.py) and live effects (live_effects.py) -------------------------------------

    @property
    def effects(self) -> list[str]:
        """Effect terms in the calibration in use (added at runtime)."""
        return self.live.names

    @property
    def effect_fit(self):
        return self.live.fit

    def candidate(self) -> ArrayCalibration | None:
        """The online estimate, aligned over the ring buffer, or None if not yet determined (then
        `gate.refusal` says why, once there are enough samples to ask)."""
        return self.gate.candidate(self._estimators, self.ring)

    def evaluate(self, cal: ArrayCalibration) -> GateResult:
        """The quality gate: coverage, conditioning and residual over the ring buffer window."""
        return self.gate.evaluate(cal, self._estimators, self.ring)

    def add_effect(self, name: str) -> None:
        """Refit the calibration with one more effect over the ring buffer and correct with it from
        now on. The online estimator keeps learning, but its linear-only candidates no longer replace
        a calibration with effects (freeze/reset/apply still work)."""
        self.set_calibration(self.live.add(name, self.ring.view(), self.calibration))

    def _check_candidate(self, seq: int, t_s: float) -> PipelineEvent | None:
        doubted = _on_trial(self, seq, t_s)
        if doubted is not None:
            return doubted
        cand = self.candidate()
        if cand is None:
            if self.gate.refusal is None:
                return None                   # too few samples yet: nothing to say
            self.last_gate = GateResult(False, [self.gate.refusal], float("nan"), float("nan"), [])
            return PipelineEvent("gate", seq, t_s, {"usable": False, "reasons": [self.gate.refusal]})
        gate = self.evaluate(cand)
        self.last_gate = gate
        if self.effects or self.held:
            return None                       # a linear-only candidate never replaces effects, nor an applied one
        if not gate.usable:
            return PipelineEvent("gate", seq, t_s, {"usable": False, "reasons": gate.reasons})
        first = self.calibration is None
        self.set_calibration(cand)
        return PipelineEvent("calibration", seq, t_s, {"cal_id": self.cal_id, "first_usable": first,
                                                        "coverage": gate.coverage, "condition": gate.condition,
                                                        "rms_nT": gate.rms_nT})

    def state(self) -> dict[str, Any]:
        """The calibration state for publishing (JSON-ready)."""
        return _state(self)


def _on_trial(pl: Pipeline, seq: int, t_s: float) -> PipelineEvent | None:
    """The calibration in use judged on the unit's data once, where it was not yet and now can be (Pipeline.on_trial):
    a "data check" event where it fails, else None. It stays in use: a residual against the total field also grows
    where that field is off (a site's model, a field that changes), and on a platform that does not turn no
    calibration can be learned to replace it; the event says which two things the figures cannot tell apart (another
    unit's calibration reloaded on a static platform corrected with errors of 5,000 nT for a whole run, said usable,
    with no word: a field trial)."""
    if not (pl.on_trial and pl.calibration is not None and len(pl.ring) >= pl.gate.min_samples):
        return None
    pl.on_trial = False
    why = pl.gate.fails_on_data(pl.calibration, pl.ring)
    if not why:
        return None
    why = (f"the calibration in use, not judged on this unit's data until now, fails the data check: {why}: it is "
           f"another unit's or far off, or the total field it is judged against is; it stays in use ("
           f"`fluxcal command reset` learns anew, `apply` gives another)")
    return PipelineEvent("data check", seq, t_s, {"passed": False, "reasons": [why], "cal_id": pl.cal_id})


def _state(pl: Pipeline) -> dict[str, Any]:
    cal = pl.calibration
    g = pl.last_gate
    return {
        "cal_id": pl.cal_id,
        "usable": cal is not None,
        "frozen": pl.frozen,
        "held": pl.held,
        "method": None if cal is None else cal.method,
        "align": None if cal is None else cal.align,
        "total_nT": None if cal is None or cal.total_nT is None else float(cal.total_nT),
        "span": None if cal is None else [float(cal.span[0]), float(cal.span[1]), int(cal.span[2])],
        "effects": list(pl.effects),
        "probes": [] if cal is None else [
            {"name": p.name, "offset_nT": p.offset_nT.tolist(), "matrix": p.matrix.tolist(),
             "offset_se_nT": np.nan_to_num(p.offset_se_nT, nan=-1).tolist(),
             "matrix_se": p.matrix_se.tolist(), "params": p.params} for p in cal.probes],
        "gate": None if g is None else {"usable": g.usable, "reasons": g.reasons, "coverage": g.coverage,
                                        "condition": g.condition, "rms_nT": g.rms_nT},
        "samples_seen": int(min(est.n_samples_ for est in pl._estimators)),
    }
