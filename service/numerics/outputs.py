"""What the pipeline produces for each SampleBlock: corrected vectors, differences, tensor.

The sinks (Zenoh, MCAP) and the replay comparison consume these; the numerics make them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CorrectedBlock:
    """Outputs for N samples of P probes, all in the common (platform) frame.

    t_s           (N,)         float64  unit time, s (same as the raw block)
    seq           (N,)         int64    unwrapped sample counter (same as the raw block)
    corrected_nT  (N, P, 3)    float64  calibrated, aligned field of every probe
    diff_nT       (N, P-1, 3)  float64  probe k minus probe 1 (gradiometer differences), None if P == 1
    tensor_nT_m   (N, 3, 3)    float64  gradient tensor G[i, j] = dB_j/dx_i, None unless geometry allows
    center_nT     (N, 3)       float64  field at the array centre (mean of probes, 001 eq. 3), None if P == 1
    cal_id        int                   which calibration produced it (increments when one is replaced)
    """

    t_s: np.ndarray
    seq: np.ndarray
    corrected_nT: np.ndarray
    diff_nT: np.ndarray | None
    tensor_nT_m: np.ndarray | None
    center_nT: np.ndarray | None
    cal_id: int

    @property
    def n_samples(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def n_probes(self) -> int:
        return int(self.corrected_nT.shape[1])
