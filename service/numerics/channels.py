"""The one naming of the residual channels (docs/contracts.md): s<k>.scalar, s<k>-s1.<axis>, s<k>-ref.<axis>;
and the model-vs-measurement error of a block in those channels. Light: the pipeline imports it."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .outputs import CorrectedBlock

AXES = ("x", "y", "z")


def channel_names(probe_names: Sequence[str], vector: bool = False) -> list[str]:
    """['s1.scalar', ..., 's2-s1.x', 's2-s1.y', 's2-s1.z', ...] and, with a reference vector, 's1-ref.x', ...

    >>> channel_names(["s1", "s2"])
    ['s1.scalar', 's2.scalar', 's2-s1.x', 's2-s1.y', 's2-s1.z']
    >>> channel_names(["s1"], vector=True)
    ['s1.scalar', 's1-ref.x', 's1-ref.y', 's1-ref.z']
    """
    names = [f"{p}.scalar" for p in probe_names]
    for p in probe_names[1:]:
        names += [f"{p}-{probe_names[0]}.{a}" for a in AXES]
    if vector:
        for p in probe_names:
            names += [f"{p}-ref.{a}" for a in AXES]
    return names


def _rms_over_rows(x: np.ndarray) -> np.ndarray:
    """RMS over axis 0 ignoring NaN (a saturated axis); NaN where a column has no finite value. The same
    arithmetic as np.nanmean, without its warning (and without a warnings context per block)."""
    ok = np.isfinite(x)
    if ok.all():                      # the usual block: the same sums and quotient, without the masks
        return np.sqrt(np.add.reduce(x * x, axis=0) / x.shape[0])
    n = ok.sum(axis=0)
    return np.sqrt(np.sum(np.where(ok, x * x, 0.0), axis=0) / np.where(n > 0, n, np.nan))


def block_error_rms(probe_names: Sequence[str], corrected: CorrectedBlock, reference_nT: np.ndarray | float | None, *,
                    differences: bool = True) -> dict[str, float]:
    """The model-vs-measurement error of one block: RMS of each residual channel (channel_names) over
    its samples; scalar channels only with a reference total field, differences only when asked."""
    return BlockError(probe_names, differences=differences)(corrected, reference_nT)


class BlockError:
    """block_error_rms of one unit's blocks, one after another (its channels named once)."""

    def __init__(self, probe_names: Sequence[str], *, differences: bool = True) -> None:
        self.n_probes = len(probe_names)
        self.names = channel_names(probe_names)                      # scalars, then differences
        self.differences = differences

    def __call__(self, corrected: CorrectedBlock, reference_nT: np.ndarray | float | None) -> dict[str, float]:
        if corrected.n_samples == 0:
            return {}
        out: dict[str, float] = {}
        names, n_probes = self.names, self.n_probes
        if reference_nT is not None:
            c = corrected.corrected_nT
            mag = np.sqrt(np.add.reduce(c * c, axis=2))               # |B| (N, P), as np.linalg.norm(c, axis=2)
            res = mag - (reference_nT[:, None] if isinstance(reference_nT, np.ndarray) else reference_nT)
            out.update(zip(names[:n_probes], _rms_over_rows(res).tolist()))
        if corrected.diff_nT is not None and self.differences:
            d = _rms_over_rows(corrected.diff_nT)                      # (P-1, 3)
            out.update(zip(names[n_probes:], d.reshape(-1).tolist()))
        return out
