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



def products(t_s: np.ndarray, seq: np.ndarray, corrected_nT: np.ndarray, positions_m: np.ndarray | None,
             cal_id: int) -> CorrectedBlock:
    """Everything the pipeline derives from corrected vectors (N, P, 3): each probe minus probe 1, the
    array centre, and with four or more positioned probes the gradient tensor."""
    c = corrected_nT
    n_probes = c.shape[1]
    diff = c[:, 1:] - c[:, :1] if n_probes > 1 else None
    center = c.mean(axis=1) if n_probes > 1 else None
    tens = None
    if positions_m is not None and n_probes >= 4:
        from .calib.tensor import tensor_from_positions

        tens = tensor_from_positions(c, positions_m)
    return CorrectedBlock(t_s=t_s, seq=seq, corrected_nT=c, diff_nT=diff, tensor_nT_m=tens, center_nT=center,
                          cal_id=cal_id)
