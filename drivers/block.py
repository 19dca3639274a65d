"""SampleBlock: the unit of data that flows through fluxcal, a block of N samples from P probes.

Every source (serial, CAN, simulated unit, MCAP replay, CSV) yields these; every stage
(ring buffer, estimator, corrector, sinks) consumes them. Arrays, never single samples.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

#: flags bits from the ICD
FLAG_SATURATED = 0x01
FLAG_TEMP_INVALID = 0x02
FLAG_CLOCK_RESYNC = 0x04
#: bits 3..7, which the ICD says are 0: a frame with any of them set is not to be trusted
FLAGS_RESERVED = 0xF8
#: set by the driver (not the unit) on a sample that failed a plausibility check: reserved flag bits,
#: a value beyond the configured full scale, a probe vector exactly zero, a temperature outside the
#: probe's range (drivers/assemble.py Plausibility). Recorded as it is; the pipeline and `fit` keep every
#: sample with any reserved bit set (this one included) out of the estimator and the corrected output.
FLAG_IMPLAUSIBLE = 0x80


class Timed:
    """Samples in time: `t_s` (N,) and an (N, P, ...) array per sample and probe, named by PROBE_ARRAY."""

    PROBE_ARRAY: ClassVar[str]

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_probes(self) -> int:
        return int(getattr(self, self.PROBE_ARRAY).shape[1])


@dataclass(frozen=True)
class SampleBlock(Timed):
    """N samples of P three-axis probes, already scaled to physical units.

    t_s       (N,)      float64  unit time in seconds, unwrapped (monotonic across clock wraps)
    seq       (N,)      int64    sample counter, unwrapped (monotonic across uint16 wraps)
    field_nT  (N, P, 3) float64  probe outputs in nT (counts x lsb_nT), NaN where an axis saturated
    temp_C    (N, P)    float64  probe temperatures in degC, NaN where invalid
    flags     (N,)      uint8    ICD flags
    """

    PROBE_ARRAY = "field_nT"

    t_s: np.ndarray
    seq: np.ndarray
    field_nT: np.ndarray
    temp_C: np.ndarray
    flags: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = self.t_s.shape[0]
        if self.field_nT.ndim != 3 or self.field_nT.shape[2] != 3 or self.field_nT.shape[0] != n:
            raise ValueError(f"field_nT: expected shape (N={n}, P, 3), got {self.field_nT.shape}")
        p = self.field_nT.shape[1]
        if self.temp_C.shape != (n, p):
            raise ValueError(f"temp_C: expected shape ({n}, {p}), got {self.temp_C.shape}")
        if self.seq.shape != (n,) or self.flags.shape != (n,):
            raise ValueError(f"seq/flags: expected shape ({n},), got {self.seq.shape}/{self.flags.shape}")


    def __len__(self) -> int:
        return self.n_samples

    @staticmethod
    def empty(n_probes: int) -> "SampleBlock":
        return SampleBlock(
            t_s=np.empty(0), seq=np.empty(0, np.int64), field_nT=np.empty((0, n_probes, 3)),
            temp_C=np.empty((0, n_probes)), flags=np.empty(0, np.uint8),
        )

    @staticmethod
    def concat(blocks: "list[SampleBlock]") -> "SampleBlock":
        if not blocks:
            raise ValueError("concat: no blocks")
        keys = set(blocks[0].extras)
        return SampleBlock(
            t_s=np.concatenate([b.t_s for b in blocks]),
            seq=np.concatenate([b.seq for b in blocks]),
            field_nT=np.concatenate([b.field_nT for b in blocks]),
            temp_C=np.concatenate([b.temp_C for b in blocks]),
            flags=np.concatenate([b.flags for b in blocks]),
            extras={k: np.concatenate([b.extras[k] for b in blocks]) for k in keys
                    if all(k in b.extras for b in blocks)},
        )

    def slice(self, start: int, stop: int) -> "SampleBlock":
        return self.rows(slice(start, stop))

    def excluded(self) -> np.ndarray:
        """(N,) bool: samples flagged implausible (any reserved flag bit, FLAG_IMPLAUSIBLE among them)."""
        return (self.flags & FLAGS_RESERVED) != 0

    def without_implausible(self) -> "SampleBlock":
        """This block with the field and temperatures of every sample flagged implausible set to NaN (as
        saturated axes are), so that no estimator, effect or corrected output uses them; the block itself
        when none is (the common case: one test, no copy)."""
        bad = self.excluded()
        if not bad.any():
            return self
        field_nT, temp_C = self.field_nT.copy(), self.temp_C.copy()
        field_nT[bad] = np.nan
        temp_C[bad] = np.nan
        return SampleBlock(t_s=self.t_s, seq=self.seq, field_nT=field_nT, temp_C=temp_C, flags=self.flags,
                           extras=self.extras)

    def rows(self, keep: "slice | np.ndarray") -> "SampleBlock":
        """The samples `keep` selects (a slice, indices or a boolean mask), every column alike."""
        return SampleBlock(t_s=self.t_s[keep], seq=self.seq[keep], field_nT=self.field_nT[keep],
                           temp_C=self.temp_C[keep], flags=self.flags[keep],
                           extras={k: v[keep] for k, v in self.extras.items()})


class Unwrapper:
    """Unwraps a wrapping unsigned counter (uint16 seq, uint32 microsecond clock) block by block.

    >>> u = Unwrapper(bits=16)
    >>> u.unwrap(np.array([65534, 65535, 0, 1])).tolist()
    [65534, 65535, 65536, 65537]
    >>> u.unwrap(np.array([2])).tolist()
    [65538]
    """

    def __init__(self, bits: int) -> None:
        self.modulus = 1 << bits
        self._last: int | None = None
        self._base = 0

    def unwrap(self, raw: np.ndarray) -> np.ndarray:
        raw = np.asarray(raw, dtype=np.int64)
        if raw.size == 0:
            return raw
        prev = np.empty_like(raw)
        prev[0] = raw[0] if self._last is None else self._last
        prev[1:] = raw[:-1]
        # a step backwards by more than half the range is a wrap forwards
        wraps = np.cumsum((raw - prev) < -(self.modulus // 2))
        out = raw + self._base + wraps * self.modulus
        self._base += int(wraps[-1]) * self.modulus
        self._last = int(raw[-1])
        return out
