"""The one noise estimate: a robust white-noise sigma from second differences, per series or per channel.

Second differences remove offsets and slow trends (anything linear over three samples), and the
median absolute deviation ignores steps and spikes, so the figure is the noise floor whatever model
the residual comes from.
"""

from __future__ import annotations

import numpy as np


def robust_noise(x: np.ndarray) -> float:
    """White-noise sigma of a series from its second differences: 1.4826 MAD(d2) / sqrt(6).

    >>> rng = np.random.default_rng(0)
    >>> round(robust_noise(rng.standard_normal(100000) * 2.0), 1)
    2.0
    """
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size < 5:
        return float("nan")
    d2 = x[2:] - 2.0 * x[1:-1] + x[:-2]
    # var(d2) = (1 + 4 + 1) sigma^2 for white noise
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def channel_noise(values: np.ndarray) -> np.ndarray:
    """Noise floor per channel (columns of values): std of second differences / sqrt(6), robust."""
    return np.array([robust_noise(values[:, c]) for c in range(values.shape[1])])
