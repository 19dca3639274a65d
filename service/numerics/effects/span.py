"""The readings a fit saw, per probe and axis, about each probe's offset: what an effect's physics is judged over
(EffectTerm.rules_out_over; the nonlinearity term rules out a transfer that folds back within them)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class ReadingSpan:
    """The readings a fit saw, per probe and axis, about the probe's offset (nT): what a term's physics is judged
    over (EffectTerm.rules_out_over)."""

    probe_names: list[str]
    low_nT: np.ndarray                    # (P, 3)
    high_nT: np.ndarray                   # (P, 3)

    @classmethod
    def of(cls, data: Any, offsets_nT: np.ndarray) -> ReadingSpan:
        """The span of `data`'s raw readings about `offsets_nT` (P, 3), non-finite samples left out."""
        centred = data.raw_nT - np.asarray(offsets_nT, dtype=np.float64)[None]
        return cls(list(data.probe_names), np.nanmin(centred, axis=0), np.nanmax(centred, axis=0))
