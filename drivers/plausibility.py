"""What a frame that passed its CRC may still not hold: reserved flag bits, values beyond full scale, exactly-zero
vectors, temperatures outside the probe's range (flagged FLAG_IMPLAUSIBLE, counted, kept out of the estimator),
and the [source] keys that set the limits."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .block import FLAG_IMPLAUSIBLE, FLAGS_RESERVED
from .config import spec
from .errors import ConfigError
from .source import Counters


@dataclass(frozen=True)
class Plausibility:
    """What a frame that passed its CRC may still not hold. A sample is flagged FLAG_IMPLAUSIBLE (kept, recorded,
    kept out of the estimator) when its flags have a bit the ICD says is 0, an axis not at a rail reads beyond
    `full_scale_nT`, a probe's vector is exactly (0, 0, 0) (an ADC that stopped converting), or a probe's
    temperature not flagged invalid lies outside [temp_min_C, temp_max_C].

    The defaults are wide on purpose: 1,000,000 nT (1 mT) is the largest range of common fluxgate families
    (the Earth's field is below 70,000 nT), so only values no fluxgate gives are caught, such as
    2,147,483.646 nT, one count inside the int32 rail at 0.001 nT per count; -100..200 degC is the simulated
    unit's range, and the int16 temperature rails are +-327.68 degC. Configure the probe's own range."""

    full_scale_nT: float = 1_000_000.0
    temp_min_C: float = -100.0
    temp_max_C: float = 200.0

    def flag(self, field_nT: np.ndarray, saturated: np.ndarray | None, counts: np.ndarray, temp_C: np.ndarray,
             temp_bad: np.ndarray | None, flags: np.ndarray, counters: Counters | None, *,
             field_range_nT: tuple[float, float] | None = None) -> np.ndarray:
        """flags with FLAG_IMPLAUSIBLE set where a check fails (a new array only then); counts the reasons.
        saturated (N, P, 3) and temp_bad (N,): None when none is; field_range_nT: the field's least and
        greatest value, when the caller knows them."""
        lo, hi = field_range_nT if field_range_nT is not None else (float(field_nT.min()), float(field_nT.max()))
        zero = not counts.any(axis=2).all()
        high = max(-lo, hi) > self.full_scale_nT
        hot = float(temp_C.min()) < self.temp_min_C or float(temp_C.max()) > self.temp_max_C
        if not (high or hot or zero or (flags & FLAGS_RESERVED).any()):
            return flags                       # the common case: a few reductions, no array of its own
        zero = ~counts.any(axis=2)                                                 # (N, P)
        reserved = (flags & FLAGS_RESERVED) != 0                                   # (N,)
        beyond = np.abs(field_nT) > self.full_scale_nT                             # (N, P, 3)
        if saturated is not None:
            beyond &= ~saturated
        temp_out = ~((temp_C >= self.temp_min_C) & (temp_C <= self.temp_max_C))
        if temp_bad is not None:
            temp_out &= ~temp_bad[:, None]
        bad = reserved | beyond.any(axis=(1, 2)) | zero.any(axis=1) | temp_out.any(axis=1)
        if not bad.any():
            return flags
        if counters is not None:
            counters.implausible_samples += int(np.count_nonzero(bad))
            counters.reserved_flags += int(np.count_nonzero(reserved))
            counters.beyond_full_scale += int(np.count_nonzero(beyond))
            counters.zero_vectors += int(np.count_nonzero(zero))
            counters.temp_out_of_range += int(np.count_nonzero(temp_out))
        return np.where(bad, flags | FLAG_IMPLAUSIBLE, flags).astype(np.uint8)


def plausibility_spec() -> dict:
    """The [source] keys of the plausibility checks (Plausibility), shared by the serial and CAN configs."""
    return {
        "full_scale_nT": spec(Plausibility().full_scale_nT, min=1.0, max=1e12,
                              doc="the probes' full scale: a larger |axis| not at a rail flags the sample "
                                  "implausible (kept out of the estimator)"),
        "temp_min_C": spec(Plausibility().temp_min_C, min=-327.68, max=327.67,
                           doc="the lowest plausible probe temperature"),
        "temp_max_C": spec(Plausibility().temp_max_C, min=-327.68, max=327.67,
                           doc="the highest plausible probe temperature"),
    }


def check_temp_range(temp_min_C: float, temp_max_C: float, path: str) -> None:
    """ConfigError naming the key unless temp_min_C < temp_max_C."""
    if not temp_min_C < temp_max_C:
        raise ConfigError(f"{path}.temp_max_C: {temp_max_C!r} is not allowed (allowed: above "
                          f"{path}.temp_min_C = {temp_min_C!r})")
