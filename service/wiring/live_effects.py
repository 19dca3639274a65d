"""Effects added to the running service (`add-effect`): refitted over the ring buffer, then applied
sample by sample, so correcting block by block gives the same numbers however the input is cut."""

from __future__ import annotations

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import FluxcalError
from fluxcal.service.numerics.calib.model import ArrayCalibration


class LiveEffects:
    """The effect terms in the calibration in use, their fit, and each probe's latest valid temperature."""

    @staticmethod
    def allowed() -> list[str]:
        """The effects the running service can add (EffectTerm.per_sample: temperature, drift, nonlinearity, and
        effects of your own loaded at start from [effects] plugins that say so): they act sample by sample, so
        correcting block by block gives the same numbers however the input is cut (replay = live). Effects on
        dB/dt or time shifts (eddy, lag) need samples across block edges: fit them offline."""
        from fluxcal.service.numerics.effects import known_effects

        return [n for n, cls in known_effects().items() if getattr(cls, "per_sample", False)]

    def __init__(self, n_probes: int, total_nT: float | None) -> None:
        self.total_nT = total_nT
        self.names: list[str] = []        # effect terms in the calibration in use (added at runtime)
        self.fit = None                   # their fit (fluxcal.service.numerics.engine.EffectsFit)
        self._last_temp_C = np.full(n_probes, np.nan)   # each probe's latest valid temperature

    def clear(self) -> None:
        self.names, self.fit = [], None

    def add(self, name: str, window: SampleBlock, calibration: ArrayCalibration | None) -> ArrayCalibration:
        """The calibration refitted with one more effect over the window (the ring buffer); it corrects
        from now on. FluxcalError when it cannot be added, or the window's data do not show it."""
        from fluxcal.service.numerics.engine import fit_with_effects

        allowed = self.allowed()
        if not isinstance(name, str) or len(name) > 64:       # the bus refuses these first; said short anyway
            shown = repr(name)[:40] + ("..." if len(repr(name)) > 40 else "")
            raise FluxcalError(f"add-effect: {shown} is not an effect name (allowed: {', '.join(allowed)})")
        if name not in allowed:
            from fluxcal.service.numerics.effects import known_effects

            offline = (f"; fit it offline with `fluxcal fit --effects {name}`" if name in known_effects() else
                       f"; {name!r} is not an effect at all (the catalogue: {', '.join(known_effects())}; effects "
                       f"of your own are loaded at start from the configuration's [effects] plugins)")
            raise FluxcalError(f"add-effect: {name!r} cannot be added to the running service (allowed: "
                               f"{', '.join(allowed)}){offline}")
        if calibration is None:
            raise FluxcalError("add-effect: no calibration in use yet; wait until it is usable")
        names = [e for e in self.names if e != name] + [name]
        ok = np.isfinite(window.field_nT).all(axis=(1, 2))
        data = window if ok.all() else window.slice(0, 0) if not ok.any() else window.rows(ok)
        if data.n_samples < 200:
            raise FluxcalError(f"add-effect: only {data.n_samples} samples in the window; wait for more data")
        ef, _ = fit_with_effects(data, names, calibration, total_nT=self.total_nT)
        why = ef.not_shown(name)
        if why:
            raise FluxcalError(f"add-effect: the {data.n_samples} samples in the window do not show {name}: {why}; "
                               f"not added. `fluxcal diagnose` on the recording ranks what is missing")
        cal = ef.calibration()
        cal.method, cal.align = calibration.method, calibration.align
        self.fit = ef
        self.names = names
        return cal

    def note_temperature(self, temp_C: np.ndarray) -> None:
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

    def correct(self, block: SampleBlock, offsets: np.ndarray) -> np.ndarray:
        """Linear part and the (sample-by-sample) effects. The effects' evaluator wants at least 30
        samples; a shorter piece is padded with copies of its last sample, which cannot change the
        others since every live effect acts on each sample alone. For the same reason a probe with a
        saturated (NaN) axis is evaluated at a stand-in value and comes out NaN, as without effects
        (the evaluator drops rows holding NaN); an invalid temperature is the probe's latest valid one."""
        n = block.n_samples
        sat = ~np.isfinite(block.field_nT).all(axis=2)                   # (N, P)
        field = np.where(sat[..., None], offsets[None], block.field_nT) if sat.any() else block.field_nT
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
                c = self.fit.correct(block)
            else:
                idx = np.r_[np.arange(n), np.full(30 - n, n - 1)]
                t = block.t_s[idx].copy()
                t[n:] = t[n - 1] + 1e-6 * np.arange(1, 31 - n)
                padded = SampleBlock(t_s=t, seq=block.seq[idx], field_nT=block.field_nT[idx],
                                     temp_C=block.temp_C[idx], flags=block.flags[idx],
                                     extras={k: v[idx] for k, v in block.extras.items()})
                c = self.fit.correct(padded)[:n]
        c[sat] = np.nan
        return c

