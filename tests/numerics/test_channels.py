"""The error metric of a block in the residual channels (fluxcal.service.numerics.channels), as the pipeline takes it
block after block: each channel's RMS over the block's samples, a NaN (a saturated axis) left out of its own
channel only."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.service.numerics.channels import BlockError, block_error_rms, channel_names
from fluxcal.service.numerics.outputs import products


@pytest.mark.parametrize("n_probes", [1, 2, 4])
@pytest.mark.parametrize("with_nan", [False, True])
def test_block_error_is_each_channels_rms_over_the_block(n_probes, with_nan):
    rng = np.random.default_rng(n_probes + 7 * with_nan)
    c = 50000.0 * rng.normal(size=(1, n_probes, 3)) / 1.7 + rng.normal(0, 2.0, (30, n_probes, 3))
    if with_nan:
        c[4, 0, 1] = np.nan
    block = products(np.arange(30.0), np.arange(30), c, None, 1)
    ref = 52500.0 + rng.normal(0, 1.0, 30)
    names = [f"s{k + 1}" for k in range(n_probes)]
    got = BlockError(names)(block, ref)
    assert got == block_error_rms(names, block, ref) and list(got) == channel_names(names)
    with np.errstate(invalid="ignore"):
        scalar = np.sqrt(np.nanmean((np.linalg.norm(c, axis=2) - ref[:, None]) ** 2, axis=0))
        diff = np.sqrt(np.nanmean((c[:, 1:] - c[:, :1]) ** 2, axis=0)).ravel()
    want = np.concatenate([scalar, diff])
    assert np.allclose([got[k] for k in got], want, rtol=1e-14, atol=0)
    assert all(type(v) is float and np.isfinite(v) for v in got.values())        # a NaN costs one sample only
    if with_nan:                                    # the channels without the NaN: the plain RMS, bit for bit
        clean = products(np.arange(30.0), np.arange(30), np.where(np.isnan(c), 0.0, c), None, 1)
        other = BlockError(names)(clean, ref)
        untouched = [k for k in got if not (k == "s1.scalar" or k.endswith("-s1.y"))]
        assert (untouched or n_probes == 1) and all(got[k] == other[k] for k in untouched)
    assert BlockError(names, differences=False)(block, None) == {}
