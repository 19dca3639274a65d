"""Forward simulations of [SineFit] and [TwoStep]'s own setups, for their tests.

[SineFit] section 3 (non-orthogonality from a turntable rotation): α = 1.5°, β = 32.5°, γ = 1.7°,
B = 52000 nT, I = 47°, the probe level on a turntable turning about its z axis, raw = S B (eq. 1,
no scale or offset errors). Choices the paper leaves open, made here:
- the initial phase: θ_x0 = 91°, which makes the noise-free data give exactly the fitted curves the
  paper prints in section 3.1 (x = 35463.9 sin(t + 91), y = 35463.9 sin(t + 179.5),
  z = … sin(t + 123.5) + 38013.7);
- the samples: one full turn, one sample per degree (360), θ = t in degrees as in those curves;
- the noise: "noise n nT" is read as Gaussian per axis with σ = n/2 (i.e. ±n holds 95 % of it). The
  paper's σ column (15.7, 24.0, 52.5 nT at 30, 50, 100 nT) is what that reading gives (~n/2: the
  error of |B| is the noise along B); with σ = n per axis it comes out ≈ n, not "below the noise
  level". `noise_sd_per_level=1.0` gives the other reading.

[TwoStep] section 4 (two-step heading calibration, a manual three-axis turntable): tilt states level,
roll ±30°, ±60°, +90°, pitch ±30°, ±60°, +90°; headings 0°…330° every 30° in each (11 × 12 = 132
points). Attitude R = Rz(heading) Ry(pitch) Rx(roll) (NED, x forward, z down), h_b = Rᵀ h_n.
Step 1 uses all 132 points, step 2 the level (a turn about body z), roll +90° (about body y) and
pitch +90° (about body x) sweeps; heading errors are evaluated on the 108 points of level,
roll ±30/±60 and pitch ±30/±60 (the paper's figures 3-5). The paper gives no simulation; choices:
- site field: Beijing, 54500 nT, inclination 59.5°, heading counted from magnetic north;
- the sensor (a Mag-03 class fluxgate on a platform with some iron): h_s = M h_b + b + noise with
  M = soft-iron · scale · non-orthogonality · mounting misalignment; scale errors ~1-3 %, axes a
  few tenths of a degree out of square, mounted 1-3° off the platform axes, soft iron of a few
  percent, hard-iron offsets of a few hundred nT, noise 2 nT per axis;
- the turntable (0.1° scale): every set angle (heading per point, roll and pitch per state) is off
  by a uniform error within ±0.05°, and a per-point wobble of the axis during a sweep (σ
  `wobble_deg`, larger in the roll/pitch +90° states where the gimbal is locked by hand) makes
  the single-axis turns "non-ideal" ([TwoStep] section 3.2 item 2): that is what leaves V̂ non-orthogonal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# --- [SineFit] -------------------------------------------------------------------------------------

P003_ALPHA_DEG, P003_BETA_DEG, P003_GAMMA_DEG = 1.5, 32.5, 1.7
P003_TOTAL_NT, P003_INCLINATION_DEG = 52000.0, 47.0
#: [SineFit] Table 1: noise nT -> α, β, γ, φ, η (deg), σ (nT)
P003_TABLE1 = {0: (1.500, 32.500, 1.700, 88.566, 89.050, 0.000),
               30: (1.500, 32.599, 1.713, 88.557, 89.040, 15.729),
               50: (1.500, 32.258, 1.485, 88.744, 89.175, 23.986),
               100: (1.500, 32.160, 1.528, 88.707, 89.153, 52.452)}
#: [SineFit] section 3.1, the fitted curves of the noise-free simulation: amplitude, phase (deg), mean
P003_CURVES = {"x": (35463.9, 91.0, 0.0), "y": (35463.9, 179.5, 0.0), "z": (10520.8, 123.5, 38013.7)}


def s_matrix_003(alpha_deg: float, beta_deg: float, gamma_deg: float) -> np.ndarray:
    """[SineFit] eq. 1: raw = S B; rows are the unit sensing axes in O_XYZ."""
    a, b, g = np.radians([alpha_deg, beta_deg, gamma_deg])
    return np.array([[1.0, 0.0, 0.0],
                     [np.sin(a), np.cos(a), 0.0],
                     [np.cos(b) * np.sin(g), np.sin(b) * np.sin(g), np.cos(g)]])


@dataclass
class Paper003:
    theta_rad: np.ndarray        # (N,) table angle
    t_s: np.ndarray              # (N,) time at 1°/s
    field_nT: np.ndarray         # (N, 3) true field in O_XYZ
    raw_nT: np.ndarray           # (N, 3) probe output
    alpha_deg: float
    beta_deg: float
    gamma_deg: float
    total_nT: float
    inclination_deg: float
    offset_nT: np.ndarray
    scale: np.ndarray

    @property
    def phi_deg(self) -> float:
        b, g = np.radians([self.beta_deg, self.gamma_deg])
        return float(np.degrees(np.arccos(np.cos(b) * np.sin(g))))

    @property
    def eta_deg(self) -> float:
        a, b, g = np.radians([self.alpha_deg, self.beta_deg, self.gamma_deg])
        return float(np.degrees(np.arccos(np.sin(a + b) * np.sin(g))))


def paper003(noise_nT: float = 0.0, seed: int = 0, *, n_samples: int = 360, noise_sd_per_level: float = 0.5,
             theta0_deg: float = 91.0, offset_nT=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0),
             alpha_deg: float = P003_ALPHA_DEG, beta_deg: float = P003_BETA_DEG,
             gamma_deg: float = P003_GAMMA_DEG) -> Paper003:
    """One full turn in n_samples equal steps; raw = diag(scale) S B + offset + noise."""
    theta = np.radians(np.arange(n_samples) * 360.0 / n_samples)
    incl = np.radians(P003_INCLINATION_DEG)
    bxy, bz = P003_TOTAL_NT * np.cos(incl), P003_TOTAL_NT * np.sin(incl)
    th0 = np.radians(theta0_deg)
    # [SineFit] eq. 3 and 5: B_X = B_xy sin(θ + θ_x0), B_Y = B_xy cos(θ + θ_x0) (a turn about +Z)
    field = np.column_stack([bxy * np.sin(theta + th0), bxy * np.cos(theta + th0), np.full(n_samples, bz)])
    s = s_matrix_003(alpha_deg, beta_deg, gamma_deg)
    k = np.asarray(scale, float)
    o = np.asarray(offset_nT, float)
    raw = field @ (np.diag(k) @ s).T + o
    raw = raw + np.random.default_rng(seed).normal(0.0, noise_sd_per_level * noise_nT, raw.shape)
    return Paper003(theta, np.degrees(theta), field, raw, alpha_deg, beta_deg, gamma_deg, P003_TOTAL_NT,
                    P003_INCLINATION_DEG, o, k)


# --- [TwoStep] -------------------------------------------------------------------------------------

P004_TOTAL_NT, P004_INCLINATION_DEG = 54500.0, 59.5
P004_HEADINGS_DEG = np.arange(0.0, 360.0, 30.0)
#: (roll, pitch) of the tilt states in the paper's order; the last three are not in the heading figures
P004_TILTS_DEG = [(0.0, 0.0), (30.0, 0.0), (-30.0, 0.0), (60.0, 0.0), (-60.0, 0.0),
                  (0.0, 30.0), (0.0, -30.0), (0.0, 60.0), (0.0, -60.0), (90.0, 0.0), (0.0, 90.0)]
#: [TwoStep] section 4.1.2: heading error after calibration, max and RMS (deg)
P004_RESULTS = {"two-step": (0.40, 0.21), "no-sign": (180.00, 102.90), "no-orth": (1.39, 0.62),
                "dot-product": (0.42, 0.20)}


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def attitude(roll_rad: float, pitch_rad: float, heading_rad: float) -> np.ndarray:
    """R_nb = Rz(ψ) Ry(θ) Rx(φ): body to NED."""
    return rz(heading_rad) @ ry(pitch_rad) @ rx(roll_rad)


def tilt_compensated_heading_deg(b_body: np.ndarray, roll_deg: np.ndarray, pitch_deg: np.ndarray) -> np.ndarray:
    """The standard tilt-compensated compass: level the body vector with the known roll φ and pitch θ,
    H = Ry(θ) Rx(φ) b, ψ = atan2(−H_y, H_x) (NED; 0 = magnetic north, positive to the east)."""
    b = np.atleast_2d(b_body)
    ph, th = np.radians(roll_deg), np.radians(pitch_deg)
    hx = b[:, 0] * np.cos(th) + b[:, 1] * np.sin(ph) * np.sin(th) + b[:, 2] * np.cos(ph) * np.sin(th)
    hy = b[:, 1] * np.cos(ph) - b[:, 2] * np.sin(ph)
    return np.degrees(np.arctan2(-hy, hx))


def heading_error_deg(heading_deg: np.ndarray, truth_deg: np.ndarray) -> np.ndarray:
    return (np.asarray(heading_deg) - np.asarray(truth_deg) + 180.0) % 360.0 - 180.0


@dataclass
class Paper004:
    raw_nT: np.ndarray           # (132, 3) sensor output
    roll_deg: np.ndarray         # (132,) nominal turntable readings
    pitch_deg: np.ndarray
    heading_deg: np.ndarray
    state: np.ndarray            # (132,) index into P004_TILTS_DEG
    m_true: np.ndarray           # h_s = M h_b + b
    b_true_nT: np.ndarray
    field_ned_nT: np.ndarray

    def sweep(self, roll: float, pitch: float) -> np.ndarray:
        return self.raw_nT[(self.roll_deg == roll) & (self.pitch_deg == pitch)]

    def turns(self) -> list[np.ndarray]:
        """Step 2's three single-axis turns: about body x (pitch +90°), y (roll +90°), z (level)."""
        return [self.sweep(0.0, 90.0), self.sweep(90.0, 0.0), self.sweep(0.0, 0.0)]

    @property
    def evaluated(self) -> np.ndarray:
        """The 108 points of the paper's heading figures (no ±90° state)."""
        return (np.abs(self.roll_deg) < 89.0) & (np.abs(self.pitch_deg) < 89.0)


def sensor_matrix_004(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A Mag-03 class sensor on a platform: M = soft iron · scale · non-orthogonality · misalignment."""
    soft = np.eye(3) + rng.uniform(-0.03, 0.03, (3, 3))
    soft = 0.5 * (soft + soft.T)                            # induced magnetisation: symmetric
    scale = np.diag(1.0 + rng.uniform(-0.03, 0.03, 3))
    e = np.radians(rng.uniform(-0.5, 0.5, 3))              # axes out of square
    nonorth = np.array([[1.0, 0.0, 0.0], [np.sin(e[0]), np.cos(e[0]), 0.0],
                        [np.sin(e[1]), np.sin(e[2]), np.sqrt(1 - np.sin(e[1]) ** 2 - np.sin(e[2]) ** 2)]])
    mis = attitude(*np.radians(rng.uniform(-3.0, 3.0, 3)))  # mounting, 1-3°
    m = soft @ scale @ nonorth @ mis.T
    b = rng.uniform(-400.0, 400.0, 3)
    return m, b


def paper004(seed: int = 0, *, noise_nT: float = 2.0, reading_deg: float = 0.05,
             wobble_deg: tuple[float, float, float] = (0.02, 0.3, 0.3)) -> Paper004:
    """The 132 calibration points of [TwoStep] section 4.1.1.

    reading_deg: half-width of the uniform error of every set angle (the 0.1° scale).
    wobble_deg: σ of the per-point tilt of the turn axis during the sweeps, for (level and tilted
      states, roll +90°, pitch +90°)."""
    rng = np.random.default_rng(seed)
    m, b = sensor_matrix_004(rng)
    incl = np.radians(P004_INCLINATION_DEG)
    h_n = P004_TOTAL_NT * np.array([np.cos(incl), 0.0, np.sin(incl)])
    raw, rolls, pitches, heads, states = [], [], [], [], []
    for si, (roll, pitch) in enumerate(P004_TILTS_DEG):
        r_set = roll + rng.uniform(-reading_deg, reading_deg)
        p_set = pitch + rng.uniform(-reading_deg, reading_deg)
        wob = wobble_deg[1] if roll == 90.0 else wobble_deg[2] if pitch == 90.0 else wobble_deg[0]
        for h in P004_HEADINGS_DEG:
            h_set = h + rng.uniform(-reading_deg, reading_deg)
            dr, dp = rng.normal(0.0, wob, 2)
            r_nb = attitude(np.radians(r_set + dr), np.radians(p_set + dp), np.radians(h_set))
            h_b = r_nb.T @ h_n
            raw.append(m @ h_b + b + rng.normal(0.0, noise_nT, 3))
            rolls.append(roll)
            pitches.append(pitch)
            heads.append(h)
            states.append(si)
    return Paper004(np.array(raw), np.array(rolls), np.array(pitches), np.array(heads), np.array(states),
                    m, b, h_n)
