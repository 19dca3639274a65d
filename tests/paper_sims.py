"""Forward simulations of the papers' own simulation setups, for tests (and anyone who needs them).

[TwoFluxgate] section 3 (two-fluxgate gradiometer, Xi'an): field (31653.3, −1968.8, 41810.1) nT, three
one-turn rotations by eq. 17 (about x: θ, about y: φ, about z: ψ), 10 points per turn 36° apart,
X_k = A_k⁻¹ B + E_k + ξ_k (eq. 18). Probe truth from Tables 1-2 as A = N K⁻¹, N the tables'
"non-orthogonality" matrix (columns normalised to unit length; the extracted text prints 1.027 in
N1[2, 2], which is 1 in the estimate column and must be 1 for a unit column), K = diag of the
sensitivities, so the raw output is X = K N⁻¹ B + E. Choices the paper leaves open, made here:
- the noise: "variance 3 nT" is read as E|ξ|² = 3 nT² (σ = 1 nT per axis). With σ = √3 per axis the
  peak-to-peak differences after calibration come out ~9.5 nT (median over seeds), against the
  paper's 5.4-5.9 nT (Table 3); with σ = 1 they come out 5.3-5.5 nT. `per_axis=True` gives the other
  reading.
- the total field: the printed components have |B| = 52477.5 nT, not the 52532.7 nT printed
  beside them; the components are simulated and their norm is the total field.

[FastRotation] section 5.1 (four-probe cross): TMI 60000 nT, inclination 57°, declination −5° (x north,
y east, z down), platform attitudes Tγ(30°·i) Tβ(30°·j) Tα(30°·k) B_geo, i (z) fastest, then j (y),
then k (x): 12³ = 1728 samples; the first twelve are one turn about z. Per probe q: the
misaligned ideal output B_c = T_qᵀ B_oc + ξ (T_q = Tα Tβ Tγ of Table 3, eq. 5-6; ξ ~ N(0, 1 nT²) per
axis, added to the misaligned output as the paper says) and the raw output
B_r = C A B_c + I (eq. 11) with Table 1's φ, θ, ψ, c, i. These conventions reproduce Table 2's
"before" TMI RMSE (8994.31, 6714.99, 9041.56, 8723.06 nT) and Table 4's "before" tensor RMSE
(52171, 28115, 42346, 53898, 21816, 30940 nT/m) to the printed digits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluxcal.service.numerics.calib.alignment import rotation_from_angles
from fluxcal.service.numerics.calib.model import sensing_matrix, triangular_matrix
from fluxcal.service.numerics.calib.tensor import cross_positions

# --- [TwoFluxgate] ---------------------------------------------------------------------------------

P000_FIELD_NT = np.array([31653.3, -1968.8, 41810.1])
P000_TOTAL_PRINTED_NT = 52532.7
P000_N1 = np.array([[0.9994, 0.0140, 0.0], [0.0, 0.9998, 0.0], [0.0349, -0.0175, 1.0]])
P000_K1 = np.array([0.9870, 1.0460, 1.0120])
P000_E1 = np.array([-30.0, 60.0, 110.0])
P000_N2 = np.array([[0.9988, 0.0331, -0.0209], [-0.0349, 0.9985, -0.0007], [0.0349, -0.0436, 0.9998]])
P000_K2 = np.array([0.9910, 0.9890, 1.0120])
P000_E2 = np.array([600.0, -70.0, 20.0])
#: Table 3, peak-to-peak nT: total-field error probe 1, probe 2, difference x, y, z
P000_TABLE3_BEFORE = np.array([3138.6, 2633.0, 2831.5, 5801.9, 2218.8])
P000_TABLE3_AFTER = np.array([4.6, 4.1, 5.4, 5.6, 5.9])


def rotation_000(theta: float, phi: float, psi: float) -> np.ndarray:
    """[TwoFluxgate] eq. 17: B = R B0 for rotations θ about x, φ about y, ψ about z (radians)."""
    ct, st, cp, sp, cs, ss = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi), np.cos(psi), np.sin(psi)
    return np.array([[cp * cs, st * sp * cs + ct * ss, -ct * sp * cs + st * ss],
                     [-cp * ss, -(st * sp * ss - ct * cs), ct * sp * ss + st * cs],
                     [sp, -st * cp, ct * cp]])


def _unit_columns(n: np.ndarray) -> np.ndarray:
    return n / np.linalg.norm(n, axis=0)


@dataclass
class Paper000:
    field_nT: np.ndarray          # (N, 3) true field in the reference frame Ouvw
    raw1_nT: np.ndarray           # (N, 3) probe 1 output
    raw2_nT: np.ndarray           # (N, 3) probe 2 output
    turn: np.ndarray              # (N,) 0: about x, 1: about y, 2: about z
    total_nT: float
    noise_nT: float               # σ per axis
    n1: np.ndarray = field(default_factory=lambda: _unit_columns(P000_N1))
    k1: np.ndarray = field(default_factory=lambda: P000_K1.copy())
    e1: np.ndarray = field(default_factory=lambda: P000_E1.copy())
    n2: np.ndarray = field(default_factory=lambda: _unit_columns(P000_N2))
    k2: np.ndarray = field(default_factory=lambda: P000_K2.copy())
    e2: np.ndarray = field(default_factory=lambda: P000_E2.copy())

    @property
    def a1(self) -> np.ndarray:
        """True A_1 (B = A_1 (X_1 − E_1)) = N_1 K_1⁻¹: [TwoFluxgate] eq. 8's zero pattern."""
        return self.n1 / self.k1

    @property
    def a2(self) -> np.ndarray:
        return self.n2 / self.k2


def paper000(seed: int = 0, *, noise_var_nT2: float = 3.0, per_axis: bool = False,
             points_per_turn: int = 10) -> Paper000:
    """[TwoFluxgate] section 3's simulation (see the module docstring for the readings chosen)."""
    rng = np.random.default_rng(seed)
    sigma = np.sqrt(noise_var_nT2) if per_axis else np.sqrt(noise_var_nT2 / 3.0)
    ang = 2 * np.pi * np.arange(points_per_turn) / points_per_turn
    rots = ([rotation_000(a, 0.0, 0.0) for a in ang] + [rotation_000(0.0, a, 0.0) for a in ang]
            + [rotation_000(0.0, 0.0, a) for a in ang])
    b = np.array([r @ P000_FIELD_NT for r in rots])
    sim = Paper000(b, b, b, np.repeat([0, 1, 2], points_per_turn), float(np.linalg.norm(P000_FIELD_NT)), sigma)
    # eq. 18: X = A⁻¹ B + E + ξ
    sim.raw1_nT = np.linalg.solve(sim.a1, b.T).T + sim.e1 + rng.normal(0.0, sigma, b.shape)
    sim.raw2_nT = np.linalg.solve(sim.a2, b.T).T + sim.e2 + rng.normal(0.0, sigma, b.shape)
    return sim


# --- [FastRotation] --------------------------------------------------------------------------------

P001_TOTAL_NT = 60000.0
P001_INCLINATION_DEG = 57.0
P001_DECLINATION_DEG = -5.0
P001_BASELINE_M = 0.4
#: Table 1, per probe: φ, θ, ψ (deg), c_x, c_y, c_z, i_x, i_y, i_z (nT)
P001_TABLE1 = np.array([[3.56, -1.85, 2.27, 1.253, 1.175, 0.859, 357.0, 160.0, -213.0],
                        [-2.74, 3.11, 1.66, 0.951, 1.202, 1.105, -253.0, 183.0, 97.0],
                        [1.86, -2.95, 3.02, 1.110, 0.799, 1.308, 169.0, -364.0, 245.0],
                        [-3.28, 2.44, -1.88, 0.853, 1.235, 1.186, 256.0, 169.0, -166.0]])
#: Table 3 preset misalignment, per probe α (heel), β (pitch), γ (azimuth), rad
P001_TABLE3_RAD = np.array([[-0.383449, 0.224798, 0.238063],
                            [0.218341, -0.069115, 0.373850],
                            [-0.205425, 0.130202, -0.227416],
                            [0.212407, 0.233700, 0.168250]])
P001_TABLE2_BEFORE_NT = np.array([8994.31, 6714.99, 9041.56, 8723.06])
P001_TABLE4_BEFORE = {"Bxx": 52171, "Bxy": 28115, "Bxz": 42346, "Byx": 53898, "Byy": 21816, "Byz": 30940}
P001_TABLE4_AFTER = {"Bxx": 3.7537, "Bxy": 3.4655, "Bxz": 3.8518, "Byx": 3.9604, "Byy": 3.5570, "Byz": 3.5281}


def _t_alpha(a: float) -> np.ndarray:
    return rotation_from_angles(a, 0.0, 0.0)


def _t_beta(b: float) -> np.ndarray:
    return rotation_from_angles(0.0, b, 0.0)


def _t_gamma(g: float) -> np.ndarray:
    return rotation_from_angles(0.0, 0.0, g)


@dataclass
class Probe001:
    nonorth_deg: np.ndarray       # φ, θ, ψ
    scale: np.ndarray             # c_x, c_y, c_z
    offset_nT: np.ndarray         # i_x, i_y, i_z
    misalign_rad: np.ndarray      # α, β, γ
    matrix: np.ndarray            # M = (C A)⁻¹, eq. 12
    rotation: np.ndarray          # T = Tα Tβ Tγ: platform = T · probe


@dataclass
class Paper001:
    platform_nT: np.ndarray       # (1728, 3) B_oc, the platform's ideal output
    ideal_nT: np.ndarray          # (1728, 4, 3) each probe's misaligned ideal output, with noise
    raw_nT: np.ndarray            # (1728, 4, 3) each probe's raw output
    steps: np.ndarray             # (1728, 3) attitude steps (x, y, z) of 30°
    probes: list[Probe001]
    positions_m: np.ndarray       # (4, 3)
    baseline_m: float = P001_BASELINE_M
    total_nT: float = P001_TOTAL_NT

    @staticmethod
    def index(x_step: int, y_step: int, z_step: int) -> int:
        """Sample index of the attitude (x, y, z) in 30° steps (z fastest)."""
        return int(x_step * 144 + y_step * 12 + z_step)

    def first_turn(self) -> np.ndarray:
        """The first turn about z: 12 samples 30° apart (coplanar in every probe frame)."""
        return np.arange(12)

    def spread(self, n: int = 10) -> np.ndarray:
        """n samples spread over the sphere of field directions: farthest-point selection over the
        platform directions, starting at the first sample (deterministic; several rotation axes)."""
        u = self.platform_nT / np.linalg.norm(self.platform_nT, axis=1, keepdims=True)
        sel = [0]
        d = 1.0 - u @ u[0]
        for _ in range(n - 1):
            k = int(np.argmax(d))
            sel.append(k)
            d = np.minimum(d, 1.0 - u @ u[k])
        return np.array(sel)


def geomagnetic_001() -> np.ndarray:
    i, d = np.radians(P001_INCLINATION_DEG), np.radians(P001_DECLINATION_DEG)
    return P001_TOTAL_NT * np.array([np.cos(i) * np.cos(d), np.cos(i) * np.sin(d), np.sin(i)])


def paper001(seed: int = 0, *, noise_nT: float = 1.0) -> Paper001:
    """[FastRotation] section 5.1's simulation (see the module docstring)."""
    rng = np.random.default_rng(seed)
    b_geo = geomagnetic_001()
    step = np.radians(30.0)
    steps = np.array([(k, j, i) for k in range(12) for j in range(12) for i in range(12)])
    rots = np.array([_t_gamma(i * step) @ _t_beta(j * step) @ _t_alpha(k * step) for k, j, i in steps])
    platform = rots @ b_geo
    probes, ideal, raw = [], [], []
    for row, mis in zip(P001_TABLE1, P001_TABLE3_RAD):
        t = rotation_from_angles(*mis)
        ca = sensing_matrix(row[:3], row[3:6])
        b_c = platform @ t + rng.normal(0.0, noise_nT, platform.shape)       # Tᵀ B_oc + ξ (eq. 6)
        ideal.append(b_c)
        raw.append(b_c @ ca.T + row[6:9])                                    # C A B_c + I (eq. 11)
        probes.append(Probe001(row[:3].copy(), row[3:6].copy(), row[6:9].copy(), mis.copy(),
                               triangular_matrix(row[:3], row[3:6]), t))
    return Paper001(platform, np.stack(ideal, axis=1), np.stack(raw, axis=1), steps, probes,
                    cross_positions(P001_BASELINE_M))
