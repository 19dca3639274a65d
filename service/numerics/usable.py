"""The samples a fit can use: a saturated (ICD flag bit0, NaN) or otherwise non-finite probe axis, or a missing
scalar reference, never enters a fit as a number; what is left out is counted per probe and said.

>>> import numpy as np
>>> from fluxcal.drivers.block import SampleBlock
>>> f = np.ones((4, 2, 3)); f[1, 0, 2] = np.nan; f[2, 1, 0] = np.inf
>>> b = SampleBlock(t_s=np.arange(4.0), seq=np.arange(4), field_nT=f, temp_C=np.zeros((4, 2)),
...                 flags=np.array([0, 1, 0, 0], np.uint8))
>>> u = usable_samples(b, ["s1", "s2"])
>>> u.keep.tolist(), u.notes[:2]
([True, False, False, True], ['s1: 1 saturated sample left out', 's2: 1 sample with a non-finite axis left out'])
>>> u.notes[2]
'2 of 4 samples left out in all: a sample left out for one probe is left out for every probe (the array is aligned and compared sample by sample)'
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from fluxcal.drivers.block import FLAG_SATURATED, SampleBlock


@dataclass(frozen=True)
class Usable:
    """keep (N,) bool: the samples every probe and the reference can give; notes: what was left out, per probe."""

    keep: np.ndarray
    notes: list[str] = field(default_factory=list)
    #: per probe name: samples left out for that probe's own axes (saturated or not finite)
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def n_dropped(self) -> int:
        return int(self.keep.size - np.count_nonzero(self.keep))


def _samples(n: int) -> str:
    return f"{n} sample" + ("" if n == 1 else "s")


def usable_samples(block: SampleBlock, probe_names: Sequence[str]) -> Usable:
    """The samples where every probe axis (and ref_total, when the data carry one) is a finite number.

    A probe's sample with a NaN or inf axis is 'saturated' when the sample is flagged so (ICD bit0; decoders
    write a saturated axis as NaN) and 'with a non-finite axis' otherwise. The probes are aligned and compared
    sample by sample, so a sample left out for one probe is left out for all; the notes say so when it matters."""
    n = block.n_samples
    keep = np.ones(n, bool)
    notes: list[str] = []
    dropped: dict[str, int] = {}
    flagged = (np.asarray(block.flags) & FLAG_SATURATED) != 0
    for k, name in enumerate(probe_names):
        bad = ~np.isfinite(block.field_nT[:, k]).all(axis=1)
        keep &= ~bad
        dropped[name] = m = int(np.count_nonzero(bad))
        if not m:
            continue
        sat = int(np.count_nonzero(bad & flagged))
        if sat == m:
            notes.append(f"{name}: {m} saturated sample{'' if m == 1 else 's'} left out")
        elif sat == 0:
            notes.append(f"{name}: {_samples(m)} with a non-finite axis left out")
        else:
            notes.append(f"{name}: {_samples(m)} left out ({sat} saturated, {m - sat} with a non-finite axis)")
    ref = block.extras.get("ref_total")
    if ref is not None:
        bad = ~np.isfinite(ref)
        if bad.any():
            notes.append(f"ref_total: {_samples(int(np.count_nonzero(bad)))} without a finite reference left out")
        keep &= ~bad
    left = int(n - np.count_nonzero(keep))
    if left and len(probe_names) > 1:
        notes.append(f"{left} of {n} samples left out in all: a sample left out for one probe is left out for "
                     f"every probe (the array is aligned and compared sample by sample)")
    return Usable(keep=keep, notes=notes, dropped=dropped)


def refuse_stuck(field_nT: np.ndarray, probe_names: Sequence[str]) -> None:
    """DataError for a probe whose every sample (N, P, 3) is the same vector: the sensor did not measure (stuck, or
    not there). fit and diagnose ask it before fitting (a real ArduPilot log's compass, 784 identical rows, crashed
    diagnose and was called 'a single-axis turn' by fit)."""
    from fluxcal.drivers.errors import DataError

    for k, name in enumerate(probe_names):
        raw = field_nT[:, k, :]
        if raw.shape[0] and not np.ptp(raw, axis=0).any():
            v = ", ".join(f"{x:.6g}" for x in raw[0])
            others = [n for n in probe_names if n != name]
            what = ("leave its columns out (a PX4 or ArduPilot log: --mags with the other compasses' instances)"
                    if others else "the file holds no other probe: check that the sensor is powered, connected and "
                                   "enabled")
            raise DataError(f"{name}: all {raw.shape[0]:,} samples are the same vector ({v} nT): the sensor did not "
                            f"measure (stuck, or not there); nothing to calibrate: {what}")


def temperature_notes(block: SampleBlock | np.ndarray, probe_names: Sequence[str]) -> list[str]:
    """Per probe with some but not all temperatures invalid (NaN, or ICD bit1): how many, and what the
    temperature terms do with them (they take the temperature interpolated in time from the valid ones).
    block: a SampleBlock or its (N, P) temperatures."""
    temp = np.asarray(block.temp_C if isinstance(block, SampleBlock) else block, float)
    out = []
    for k, name in enumerate(probe_names):
        bad = int(np.count_nonzero(~np.isfinite(temp[:, k])))
        if 0 < bad < temp.shape[0]:
            out.append(f"{name}_temp: {_samples(bad)} without a valid temperature: the temperature terms take "
                       f"{name}'s temperature there interpolated in time from the valid ones")
    return out
