"""Gradient tensor, differences, centre field and invariants against fields whose gradient is known."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.numerics.calib.tensor import (
    center_field,
    cross_positions,
    differences,
    invariants,
    measured_components,
    tensor_from_cross,
    tensor_from_positions,
)
from fluxcal.service.numerics.outputs import CorrectedBlock


def source_free_gradient(rng: np.random.Generator) -> np.ndarray:
    """A random symmetric, traceless G (nT/m), as any field outside its sources has."""
    a = rng.normal(0, 50, (3, 3))
    g = 0.5 * (a + a.T)
    return g - np.trace(g) / 3 * np.eye(3)


def linear_field(b0: np.ndarray, g: np.ndarray, positions_m: np.ndarray) -> np.ndarray:
    """B(r) = B0 + Gᵀ r at each position, for each of N samples: (N, P, 3) from b0 (N, 3), g (N, 3, 3)."""
    return b0[:, None, :] + np.einsum("nij,pi->npj", g, positions_m)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31), baseline=st.floats(0.05, 2.0))
def test_cross_recovers_a_source_free_linear_field_exactly(seed, baseline):
    rng = np.random.default_rng(seed)
    n = 7
    g = np.stack([source_free_gradient(rng) for _ in range(n)])
    b0 = rng.normal(0, 40000, (n, 3))
    pos = cross_positions(baseline)
    b = linear_field(b0, g, pos)
    assert np.allclose(tensor_from_cross(b, baseline), g, atol=1e-6)
    assert np.allclose(tensor_from_positions(b, pos), g, atol=1e-6)
    assert np.allclose(center_field(b), b0, atol=1e-6)          # eq. 3: the mean is the centre field


def test_cross_is_001_eq2_with_the_third_column_corrected():
    rng = np.random.default_rng(1)
    b = rng.normal(0, 100, (3, 4, 3))
    d = 0.4
    g = tensor_from_cross(b, d)
    # rows x and y: the pair differences of all three components (B1 − B3, B2 − B4)
    assert np.allclose(g[:, 0], (b[:, 0] - b[:, 2]) / d) and np.allclose(g[:, 1], (b[:, 1] - b[:, 3]) / d)
    # the third column is ∂Bz/∂x, ∂Bz/∂y (eq. 2 prints the x-pair column again)
    assert np.allclose(g[:, 0, 2], (b[:, 0, 2] - b[:, 2, 2]) / d)
    assert np.allclose(g[:, 2, 2], -(g[:, 0, 0] + g[:, 1, 1]))
    comp = measured_components(g)
    assert np.allclose(comp["Bxy"], (b[:, 1, 0] - b[:, 3, 0]) / d)     # Table 4's Bxy = (Bx2 − Bx4)/d
    assert np.allclose(comp["Byx"], (b[:, 0, 1] - b[:, 2, 1]) / d)     # Byx = (By1 − By3)/d
    assert np.allclose(comp["Byz"], (b[:, 1, 2] - b[:, 3, 2]) / d)


def test_general_positions_recover_the_full_tensor_without_symmetry():
    # five probes not in one plane measure all nine components, symmetric or not
    rng = np.random.default_rng(4)
    pos = np.array([[0.3, 0, 0], [0, 0.3, 0], [-0.3, 0, 0], [0, -0.3, 0], [0, 0, 0.25]]) + [0.1, -0.2, 0.05]
    g = rng.normal(0, 30, (4, 3, 3))
    b = linear_field(rng.normal(0, 30000, (4, 3)), g, pos)
    assert np.allclose(tensor_from_positions(b, pos), g, atol=1e-8)


def test_uniform_field_gives_zero_and_the_noise_floor():
    # [FastRotation]'s check: a uniform field has G = 0; noise σ per probe gives √2 σ / d per component
    rng = np.random.default_rng(5)
    b = np.array([30000.0, -2000.0, 45000.0]) + rng.normal(0, 1.0, (20000, 4, 3))
    g = tensor_from_cross(b, 0.4)
    rms = {k: np.sqrt(np.mean(v ** 2)) for k, v in measured_components(g).items()}
    assert all(abs(v - np.sqrt(2) / 0.4) < 0.08 for v in rms.values()), rms


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_invariants_do_not_change_with_the_frame(seed):
    rng = np.random.default_rng(seed)
    g = rng.normal(0, 20, (5, 3, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    g_rot = np.einsum("ij,njk,lk->nil", q, g, q)                 # G' = Q G Qᵀ
    a, b = invariants(g), invariants(g_rot)
    for key in ("I0", "I1", "I2", "frobenius", "eigenvalues"):
        assert np.allclose(a[key], b[key], rtol=1e-9, atol=1e-9), key
    sym = g[0] + g[0].T
    assert np.allclose(a["eigenvalues"][0], np.linalg.eigvalsh(0.5 * sym))


def test_shapes_match_the_corrected_block():
    rng = np.random.default_rng(6)
    c = rng.normal(0, 1000, (11, 4, 3))
    block = CorrectedBlock(t_s=np.arange(11.0), seq=np.arange(11), corrected_nT=c, diff_nT=differences(c),
                           tensor_nT_m=tensor_from_positions(c, cross_positions(0.4)), center_nT=center_field(c),
                           cal_id=1)
    assert block.diff_nT.shape == (11, 3, 3) and np.allclose(block.diff_nT[:, 0], c[:, 1] - c[:, 0])
    assert block.tensor_nT_m.shape == (11, 3, 3) and block.center_nT.shape == (11, 3)
    assert all(v.shape == (11,) for v in invariants(block.tensor_nT_m).values() if v.ndim == 1)


def test_bad_geometry_is_a_config_error():
    b = np.zeros((2, 4, 3))
    with pytest.raises(ConfigError, match="one line"):
        tensor_from_positions(b, np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]]))
    with pytest.raises(ConfigError, match="x-y plane"):
        tensor_from_positions(b, np.array([[0.2, 0, 0], [0, 0, 0.2], [-0.2, 0, 0], [0, 0, -0.2]]))
    with pytest.raises(ConfigError, match=r"expected \(4, 3\) positions"):
        tensor_from_positions(b, np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"expected shape \(N, 4, 3\)"):
        tensor_from_cross(np.zeros((2, 3, 3)), 0.4)


@pytest.mark.parametrize("n_probes", [4, 5, 8])
@pytest.mark.parametrize("planar", [True, False])
def test_a_block_derives_what_its_samples_derive_one_by_one(n_probes, planar):
    """Differences, centre and tensor of a block (outputs.Derived, the pipeline's) equal, bit for bit, those of
    each of its samples alone and products' of the block: the same sums in the same order whatever the block's
    length, so live blocks and replay's long ones agree; a NaN stays in its own sample."""
    from fluxcal.service.numerics.outputs import Derived, products

    rng = np.random.default_rng(n_probes + 10 * planar)
    pos = rng.normal(0, 0.2, (n_probes, 3))
    if planar:
        pos[:, 2] = 0.0
    c = 50000.0 * rng.normal(size=(1, n_probes, 3)) + rng.normal(0, 30, (40, n_probes, 3))
    c[7, 1, 2] = np.nan
    derive = Derived(pos, n_probes)
    whole = derive(np.arange(40.0), np.arange(40), c, 3)
    rows = [derive(np.arange(k, k + 1.0), np.arange(k, k + 1), c[k:k + 1], 3) for k in range(40)]
    once = products(np.arange(40.0), np.arange(40), c, pos, 3)
    for name in ("diff_nT", "center_nT", "tensor_nT_m"):
        one_by_one = np.concatenate([getattr(r, name) for r in rows])
        for got in (getattr(whole, name), getattr(once, name)):
            assert np.array_equal(got.view(np.int64), one_by_one.view(np.int64)), name
    assert np.isnan(whole.tensor_nT_m[7]).any() and np.isfinite(np.delete(whole.tensor_nT_m, 7, axis=0)).all()
    assert np.array_equal(whole.center_nT, c.mean(axis=1), equal_nan=True)            # the mean of the probes
