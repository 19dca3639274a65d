"""Gradiometer differences, gradient-tensor components and their invariants, over whole blocks.

Convention: G[i, j] = ∂B_j / ∂x_i (001 eq. 1), in nT/m, platform frame. From P probes at positions
r_k the field differences obey B_k − B̄ = Gᵀ (r_k − r̄); the least-squares G of a planar cross
reduces to 001 eq. 2 (rows x and y are the pair differences over the baseline d). A planar array
measures only the in-plane rows; the out-of-plane row follows from a source-free field
(G symmetric and traceless), which 001 uses too.
"""

from __future__ import annotations

import numpy as np

from drivers.errors import ConfigError


def differences(corrected_nT: np.ndarray) -> np.ndarray:
    """Probe k minus probe 1, (N, P, 3) -> (N, P−1, 3) (000's gradiometer output)."""
    return corrected_nT[:, 1:] - corrected_nT[:, :1]


def center_field(corrected_nT: np.ndarray) -> np.ndarray:
    """B0, the field at the array centre: the mean of the probes (001 eq. 3)."""
    return corrected_nT.mean(axis=1)


def tensor_from_positions(corrected_nT: np.ndarray, positions_m: np.ndarray) -> np.ndarray:
    """(N, P, 3) corrected fields at probe positions (P, 3) -> (N, 3, 3) tensor G."""
    r = np.asarray(positions_m, float)
    d = r - r.mean(axis=0)
    u, sv, vt = np.linalg.svd(d, full_matrices=False)
    rank = int(np.sum(sv > 1e-9 * max(sv[0], 1e-300)))
    if rank < 2:
        raise ConfigError("probes.position_m: the probes lie on one line (or one point); "
                          "a tensor needs at least a planar array")
    db = corrected_nT - corrected_nT.mean(axis=1, keepdims=True)
    pinv = np.linalg.pinv(d)                                      # (3, P)
    g = np.einsum("ip,npj->nij", pinv, db)                        # G = D⁺ ΔB
    if rank == 3:
        return g
    normal = vt[2]
    if not np.isclose(abs(normal[2]), 1.0, atol=1e-9):
        raise ConfigError("probes.position_m: a planar array must lie in the platform x-y plane")
    # planar in x-y: rows x and y are measured; row z from symmetry and zero trace
    g[:, 2, 0] = g[:, 0, 2]
    g[:, 2, 1] = g[:, 1, 2]
    g[:, 2, 2] = -(g[:, 0, 0] + g[:, 1, 1])
    return g


def tensor_cross(corrected_nT: np.ndarray, baseline_m: float) -> np.ndarray:
    """001 eq. 2 for the cross: probes 1, 3 on +x, −x and 2, 4 on +y, −y, baseline d between pairs."""
    b = corrected_nT
    g = np.empty((b.shape[0], 3, 3))
    g[:, 0, :] = (b[:, 0] - b[:, 2]) / baseline_m
    g[:, 1, :] = (b[:, 1] - b[:, 3]) / baseline_m
    g[:, 2, 0] = g[:, 0, 2]
    g[:, 2, 1] = g[:, 1, 2]
    g[:, 2, 2] = -(g[:, 0, 0] + g[:, 1, 1])
    return g


def invariants(g: np.ndarray) -> dict[str, np.ndarray]:
    """Rotation invariants of (N, 3, 3) tensors: I0 (trace), I1, I2 (det), Frobenius norm."""
    tr = np.trace(g, axis1=1, axis2=2)
    i1 = 0.5 * (tr ** 2 - np.einsum("nij,nji->n", g, g))
    return {"I0": tr, "I1": i1, "I2": np.linalg.det(g), "frobenius": np.sqrt(np.einsum("nij,nij->n", g, g))}
