"""The 10-Hz means of a long block (replay hands the writer 20,000 samples at once) are computed for all its
whole intervals together; they equal, bit for bit, the interval-by-interval means of the same blocks."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.service.numerics.decimate import VectorMeans
from fluxcal.service.numerics.outputs import products

POSITIONS = np.array([[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]])


class OneByOne(VectorMeans):
    """Every interval on its own, as before the batch."""

    BATCH = 10 ** 9


def blocks(seed: int, n_probes: int, rate_hz: float):
    """Corrected blocks of random sizes (one sample to 5,000), jittered clocks, NaN rows, a NaN time, a
    calibration change, -0.0 values, and white or 1/f-like (integrated) noise."""
    rng = np.random.default_rng(seed)
    n = 30000
    t = np.arange(n) / rate_hz + rng.normal(scale=0.1 / rate_hz, size=n)
    noise = rng.normal(size=(n, n_probes, 3))
    if seed % 2:
        noise = np.cumsum(noise, axis=0) * 0.05
    c = 50000.0 * rng.normal(size=(1, n_probes, 3)) / 1.7 + noise
    c[rng.random(n) < 0.01, rng.integers(0, n_probes)] = np.nan
    c[rng.random(n) < 0.001] = -0.0
    t[1234] = np.nan
    pos = POSITIONS if n_probes == 4 else None
    i, cal = 0, 1
    while i < n:
        m = int(rng.choice([1, 7, 20, 333, 2000, 5000]))
        if i > n // 2 and cal == 1:
            cal = 2
        yield products(t[i:i + m], np.arange(i, i + m, dtype=np.int64), c[i:i + m], pos, cal)
        i += m


def same(a, b) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if isinstance(a, tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and bool(np.all((a == b) | (np.isnan(a) & np.isnan(b)))) and \
        bool(np.array_equal(np.signbit(a), np.signbit(b)))


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
@pytest.mark.parametrize("n_probes, rate_hz", [(1, 200.0), (2, 1000.0), (3, 333.0), (4, 1000.0)])
def test_long_blocks_give_the_interval_by_interval_means_bit_for_bit(seed, n_probes, rate_hz):
    new, old = VectorMeans(0.1), OneByOne(0.1)
    got, want = [], []
    for b in blocks(seed, n_probes, rate_hz):
        got += new.add(b)
        want += old.add(b)
    got += new.flush()
    want += old.flush()
    assert len(got) == len(want) > 200
    for g, w in zip(got, want):
        assert g.keys() == w.keys()
        for k in g:
            assert same(g[k], w[k]), (k, g[k], w[k])
