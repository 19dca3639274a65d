"""Gradiometer differences, gradient-tensor components and their invariants, over whole blocks.

Convention: G[i, j] = ∂B_j / ∂x_i ([FastRotation] eq. 1), in nT/m, platform frame, for corrected fields of
shape (N, P, 3); every function is vectorised over N and returns the shapes of
fluxcal.service.numerics.outputs.CorrectedBlock (diff (N, P−1, 3), tensor (N, 3, 3), centre (N, 3)).

From P probes at positions r_k the field differences obey B_k − B_0 = Gᵀ (r_k − r_0) to first
order; `tensor_from_positions` solves it by least squares about the centroid (B_0 the mean field,
r_0 the mean position). For [FastRotation]'s planar cross (probes 1, 3 on the x baseline, 2, 4 on the y
baseline, d apart in each pair) it reduces exactly to [FastRotation] eq. 2: row x = (B_1 − B_3)/d, row y =
(B_2 − B_4)/d. A planar array measures only the in-plane rows (six components; [FastRotation] keeps ∂B_y/∂x and
∂B_x/∂y as independent measurements); the out-of-plane row follows from a source-free field
(G symmetric and traceless): G[z, x] = G[x, z], G[z, y] = G[y, z], G[z, z] = −(G[x, x] + G[y, y]).
([FastRotation] eq. 2 as printed repeats the x-pair column in the third column; the paper's own Table 4 uses
∂B_z/∂x = (B_z1 − B_z3)/d there, as here.)
"""

from __future__ import annotations

import functools

import numpy as np

from fluxcal.drivers.errors import ConfigError

#: the six components a planar x-y array measures, as (row, column) of G, named as [FastRotation] Table 4 does:
#: Bxx = (Bx1−Bx3)/d, Bxy = (Bx2−Bx4)/d, Bxz = (Bz1−Bz3)/d, Byx = (By1−By3)/d, Byy = (By2−By4)/d,
#: Byz = (Bz2−Bz4)/d (checked: these reproduce its "before calibration" row exactly)
MEASURED_001 = {"Bxx": (0, 0), "Bxy": (1, 0), "Bxz": (0, 2), "Byx": (0, 1), "Byy": (1, 1), "Byz": (1, 2)}


def differences(corrected_nT: np.ndarray) -> np.ndarray:
    """Probe k minus probe 1, (N, P, 3) -> (N, P−1, 3) ([TwoFluxgate]'s gradiometer output, eq. 10)."""
    return corrected_nT[:, 1:] - corrected_nT[:, :1]


def center_field(corrected_nT: np.ndarray) -> np.ndarray:
    """B0, the field at the array centre: the mean of the probes ([FastRotation] eq. 3), (N, P, 3) -> (N, 3)."""
    return corrected_nT.mean(axis=1)


def cross_positions(baseline_m: float) -> np.ndarray:
    """Positions (4, 3) in m of [FastRotation]'s planar cross: probe 1 at +x, 2 at +y, 3 at −x, 4 at −y, each
    pair `baseline_m` apart (the baseline d of eq. 2)."""
    h = 0.5 * float(baseline_m)
    return np.array([[h, 0.0, 0.0], [0.0, h, 0.0], [-h, 0.0, 0.0], [0.0, -h, 0.0]])


@functools.lru_cache(maxsize=64)
def _geometry(shape: tuple[int, int], key: bytes) -> tuple[np.ndarray, bool]:
    """D⁺ (3, P) about the centroid and whether the array is planar, for positions given as bytes
    (computed once per geometry: the service calls the tensor block after block with the same one)."""
    r = np.frombuffer(key, float).reshape(shape)
    d = r - r.mean(axis=0)
    u, sv, vt = np.linalg.svd(d, full_matrices=False)
    rank = int(np.sum(sv > 1e-9 * max(sv[0], 1e-300)))
    if rank < 2:
        raise ConfigError("probes.position_m: the probes lie on one line (or one point); "
                          "a tensor needs at least a planar array")
    if rank == 2 and not np.isclose(abs(vt[2][2]), 1.0, atol=1e-9):
        raise ConfigError("probes.position_m: a planar array must lie in the platform x-y plane")
    pinv = np.linalg.pinv(d)
    pinv.flags.writeable = False
    return pinv, rank == 2


def tensor_operator(positions_m: np.ndarray, n_probes: int) -> tuple[np.ndarray, bool]:
    """(D⁺ (3, P) about the centroid, planar) of the probe positions (P, 3) in m, checked: what the tensor of every
    block of one array needs, computed once."""
    r = np.ascontiguousarray(positions_m, float)
    if r.ndim != 2 or r.shape[1] != 3 or r.shape[0] != n_probes:
        raise ConfigError(f"probes.position_m: expected ({n_probes}, 3) positions in m, got {r.shape}")
    return _geometry(r.shape, r.tobytes())


def tensor_from_positions(corrected_nT: np.ndarray, positions_m: np.ndarray) -> np.ndarray:
    """(N, P, 3) corrected fields at probe positions (P, 3) -> (N, 3, 3) tensor G (least squares)."""
    pinv, planar = tensor_operator(positions_m, corrected_nT.shape[1])
    return tensor_about_centre(corrected_nT - corrected_nT.mean(axis=1, keepdims=True), pinv, planar)


def tensor_about_centre(db: np.ndarray, pinv: np.ndarray, planar: bool) -> np.ndarray:
    """G = D⁺ ΔB from the fields about the array's mean field, db (N, P, 3), and tensor_operator's (D⁺, planar).
    Summed probe by probe, in probe order (a reduction over the outer axis adds its rows one after another): the
    same rounding whatever the block length (replay = live)."""
    n, p = db.shape[0], db.shape[1]
    terms = np.multiply(pinv.T[:, None, :, None], db.transpose(1, 0, 2)[:, :, None, :],
                        out=np.empty((p, n, 3, 3)))           # (P, N, 3, 3) in C order: term k = D⁺[:, k] ΔB_k
    g = np.add.reduce(terms, axis=0)                          # ((t_0 + t_1) + t_2) + ...
    if planar:
        _complete_planar(g)
    return g


def _complete_planar(g: np.ndarray) -> None:
    """Row z of a planar (x-y) array's tensor from symmetry and zero trace, in place."""
    g[:, 2, :2] = g[:, :2, 2]                         # G[z, x] = G[x, z], G[z, y] = G[y, z]
    zz = g[:, 2, 2]
    np.add(g[:, 0, 0], g[:, 1, 1], out=zz)
    np.negative(zz, out=zz)                           # G[z, z] = −(G[x, x] + G[y, y])


def tensor_from_cross(corrected_nT: np.ndarray, baseline_m: float) -> np.ndarray:
    """[FastRotation] eq. 2 for the cross (probes 1, 3 on +x, −x and 2, 4 on +y, −y; `cross_positions`):
    (N, 4, 3) corrected fields -> (N, 3, 3), G[x, :] = (B_1 − B_3)/d, G[y, :] = (B_2 − B_4)/d."""
    b = np.asarray(corrected_nT, float)
    if b.ndim != 3 or b.shape[1:] != (4, 3):
        raise ValueError(f"corrected_nT: expected shape (N, 4, 3), got {b.shape}")
    g = np.empty((b.shape[0], 3, 3))
    g[:, 0, :] = (b[:, 0] - b[:, 2]) / baseline_m
    g[:, 1, :] = (b[:, 1] - b[:, 3]) / baseline_m
    _complete_planar(g)
    return g


tensor_cross = tensor_from_cross        # the name the first version used


def measured_components(g: np.ndarray) -> dict[str, np.ndarray]:
    """The six measured components of a planar-cross tensor, named as in [FastRotation] Table 4, each (N,)."""
    return {name: g[:, i, j] for name, (i, j) in MEASURED_001.items()}


def invariants(g: np.ndarray) -> dict[str, np.ndarray]:
    """Rotation invariants of (N, 3, 3) tensors: I0 (trace), I1, I2 (det), Frobenius norm, and the
    eigenvalues of the symmetric part (N, 3), ascending."""
    tr = np.trace(g, axis1=1, axis2=2)
    i1 = 0.5 * (tr ** 2 - np.einsum("nij,nji->n", g, g))
    sym = 0.5 * (g + np.swapaxes(g, 1, 2))
    return {"I0": tr, "I1": i1, "I2": np.linalg.det(g), "frobenius": np.sqrt(np.einsum("nij,nij->n", g, g)),
            "eigenvalues": np.linalg.eigvalsh(sym)}
