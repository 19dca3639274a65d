"""What the pipeline produces for each SampleBlock: corrected vectors, differences, tensor.

The sinks (Zenoh, MCAP) and the replay comparison consume these; the numerics make them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluxcal.drivers.block import Timed


@dataclass(frozen=True)
class CorrectedBlock(Timed):
    """Outputs for N samples of P probes, all in the common (platform) frame.

    t_s           (N,)         float64  unit time, s (same as the raw block)
    seq           (N,)         int64    unwrapped sample counter (same as the raw block)
    corrected_nT  (N, P, 3)    float64  calibrated, aligned field of every probe
    diff_nT       (N, P-1, 3)  float64  probe k minus probe 1 (gradiometer differences), None if P == 1
    tensor_nT_m   (N, 3, 3)    float64  gradient tensor G[i, j] = dB_j/dx_i, None unless geometry allows
    center_nT     (N, 3)       float64  field at the array centre (mean of probes, [FastRotation] eq. 3), None if P == 1
    cal_id        int                   which calibration produced it (increments when one is replaced)
    """

    PROBE_ARRAY = "corrected_nT"

    t_s: np.ndarray
    seq: np.ndarray
    corrected_nT: np.ndarray
    diff_nT: np.ndarray | None
    tensor_nT_m: np.ndarray | None
    center_nT: np.ndarray | None
    cal_id: int


def join_corrected(pieces: list[CorrectedBlock]) -> CorrectedBlock | None:
    """One CorrectedBlock from consecutive pieces (cal_id: the one in use at the last piece), None from none."""
    if not pieces:
        return None
    if len(pieces) == 1:
        return pieces[0]

    def cat(name: str):
        arrays = [getattr(p, name) for p in pieces]
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    return CorrectedBlock(t_s=cat("t_s"), seq=cat("seq"), corrected_nT=cat("corrected_nT"), diff_nT=cat("diff_nT"),
                          tensor_nT_m=cat("tensor_nT_m"), center_nT=cat("center_nT"), cal_id=pieces[-1].cal_id)


def products(t_s: np.ndarray, seq: np.ndarray, corrected_nT: np.ndarray, positions_m: np.ndarray | None,
             cal_id: int) -> CorrectedBlock:
    """Everything the pipeline derives from corrected vectors (N, P, 3): each probe minus probe 1, the
    array centre, and with four or more positioned probes the gradient tensor."""
    return Derived(positions_m, corrected_nT.shape[1])(t_s, seq, corrected_nT, cal_id)


class Derived:
    """`products` for one array (P probes at positions_m, or None), block after block: what depends only on the
    array (the tensor's D⁺) is computed once, the centre field once per block for the centre and the tensor."""

    def __init__(self, positions_m: np.ndarray | None, n_probes: int) -> None:
        from .calib.tensor import tensor_operator

        self.n_probes = n_probes
        self.tensor = None if positions_m is None or n_probes < 4 else tensor_operator(positions_m, n_probes)

    def __call__(self, t_s: np.ndarray, seq: np.ndarray, c: np.ndarray, cal_id: int) -> CorrectedBlock:
        from .calib.tensor import tensor_about_centre

        diff = center = tens = None
        if self.n_probes > 1:
            diff = c[:, 1:] - c[:, :1]
            center = np.add.reduce(c, axis=1)
            center /= self.n_probes              # c.mean(axis=1): the sum over the probes, then / P
            if self.tensor is not None:
                tens = tensor_about_centre(c - center[:, None, :], *self.tensor)
        return CorrectedBlock(t_s=t_s, seq=seq, corrected_nT=c, diff_nT=diff, tensor_nT_m=tens, center_nT=center,
                              cal_id=cal_id)
