"""The simulated world: platform motion, the ambient field with its gradient and drift, and each probe's
forward model (paper 001) with the physical effects. Pure numpy over arrays of instants; no I/O.

Frames and conventions:

- earth frame NED: x north, y east, z down (the geomagnetic convention);
  B_earth = F (cos I cos D, cos I sin D, sin I), I inclination (positive down), D declination (east);
- platform frame: rigid with the platform; its attitude R(t) maps platform to earth, v_earth = R v_platform,
  and its body angular rate ω (platform frame, rad/s) satisfies dR/dt = R [ω]x;
- site gradient G[i, j] = dB_j/dx_i (001 eq. 1) in the earth frame, about the platform origin (the
  rotation centre): B_earth(r) = B0 + drift_nT_per_h·t/3600 + G^T r;
- probe (sensor) frame: the ideal orthogonal axes of probe k; 001 eq. 5: B_platform = Tα Tβ Tγ B_sensor,
  so B_sensor = (Tα Tβ Tγ)^T B_platform (heel α about x, pitch β about y, azimuth γ about z, eq. 4);
- output (001 eq. 11): raw = C A B_sensor + offset, C = diag(c_x, c_y, c_z),
  A = [[cosθcosφ, sinθcosφ, sinφ], [0, cosψ, sinψ], [0, 0, 1]];
- truth calibration: matrix = (C A (Tα Tβ Tγ)^T)^-1, so that matrix (raw - offset) = B_platform.

Effects (each off while its parameters are zero) act at four places of the chain, in this order:
sampling instant (lag), field at the probe (eddy), transfer u = C A B_sensor (temperature scale,
nonlinearity) and offset (temperature offset, drift). The site gradient and the ambient drift are
part of the field. Random numbers are addressed by sample index (ChunkedRandom), so a run cut into
blocks of any size gives the same samples.
"""

from __future__ import annotations

import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar, Iterable

import numpy as np

from .config import FieldConfig, MotionConfig, ProbeSimConfig, SimConfig, TemperatureConfig

# random streams (spawned from the seed, one per purpose, so one does not shift another)
STREAM_MOTION, STREAM_NOISE, STREAM_REF, STREAM_TEMP_INVALID, STREAM_SERIAL, STREAM_GARBAGE, STREAM_CAN = range(1, 8)
_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


# --- random numbers addressed by sample index -------------------------------------------------------

class ChunkedRandom:
    """Random numbers for samples [start, stop): chunk c of a stream comes from default_rng([seed, stream, c]).

    Any range gives the same numbers however the run is cut into blocks, and ranges can be asked for
    in any order (a reader that reconnects, a test that regenerates one stretch)."""

    CHUNK = 4096

    def __init__(self, seed: int, stream: int, per_sample: tuple[int, ...] = (), kind: str = "normal") -> None:
        if kind not in ("normal", "uniform", "bytes"):
            raise ValueError(f"kind: expected 'normal', 'uniform' or 'bytes', got {kind!r}")
        self.seed, self.stream, self.per_sample, self.kind = int(seed), int(stream), tuple(per_sample), kind
        self._cache: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()          # an emitter thread and its owner may both draw

    def _chunk(self, c: int) -> np.ndarray:
        with self._lock:
            return self._chunk_locked(c)

    def _chunk_locked(self, c: int) -> np.ndarray:
        got = self._cache.get(c)
        if got is None:
            rng = np.random.default_rng([self.seed, self.stream, c])
            shape = (self.CHUNK, *self.per_sample)
            if self.kind == "normal":
                got = rng.standard_normal(shape)
            elif self.kind == "uniform":
                got = rng.random(shape)
            else:
                got = rng.integers(0, 256, size=shape, dtype=np.uint8)
            if len(self._cache) >= 4:
                self._cache.pop(next(iter(self._cache)))
            self._cache[c] = got
        return got

    def draw(self, start: int, stop: int) -> np.ndarray:
        if stop <= start:
            return np.empty((0, *self.per_sample), dtype=np.uint8 if self.kind == "bytes" else np.float64)
        c0, c1 = start // self.CHUNK, (stop - 1) // self.CHUNK
        parts = [self._chunk(c) for c in range(c0, c1 + 1)]   # one numpy call per 4096 samples
        joined = parts[0] if len(parts) == 1 else np.concatenate(parts)
        base = c0 * self.CHUNK
        return joined[start - base:stop - base].copy()


# --- rotations --------------------------------------------------------------------------------------

def rotation(axis: str, angle_rad: np.ndarray | float) -> np.ndarray:
    """Active right-handed rotation about a coordinate axis, for any array of angles: (..., 3, 3).

    >>> np.round(rotation("z", np.pi / 2) @ [1.0, 0.0, 0.0], 12).tolist()
    [0.0, 1.0, 0.0]
    """
    a = np.asarray(angle_rad, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "x":
        rows = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == "y":
        rows = [[c, z, s], [z, o, z], [-s, z, c]]
    elif axis == "z":
        rows = [[c, -s, z], [s, c, z], [z, z, o]]
    else:
        raise ValueError(f"axis: expected 'x', 'y' or 'z', got {axis!r}")
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def attitude_from_euler_deg(heel_deg: float, pitch_deg: float, azimuth_deg: float) -> np.ndarray:
    """Platform attitude R = Rz(azimuth) Ry(pitch) Rx(heel) (aerospace z-y-x order), platform -> NED."""
    h, p, a = np.radians([heel_deg, pitch_deg, azimuth_deg])
    return rotation("z", a) @ rotation("y", p) @ rotation("x", h)


def heel_matrix(alpha_rad: float) -> np.ndarray:
    """Tα of 001 eq. 4: [[1, 0, 0], [0, cosα, sinα], [0, -sinα, cosα]]."""
    c, s = math.cos(alpha_rad), math.sin(alpha_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def pitch_matrix(beta_rad: float) -> np.ndarray:
    """Tβ of 001 eq. 4: [[cosβ, 0, -sinβ], [0, 1, 0], [sinβ, 0, cosβ]]."""
    c, s = math.cos(beta_rad), math.sin(beta_rad)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def azimuth_matrix(gamma_rad: float) -> np.ndarray:
    """Tγ of 001 eq. 4: [[cosγ, sinγ, 0], [-sinγ, cosγ, 0], [0, 0, 1]]."""
    c, s = math.cos(gamma_rad), math.sin(gamma_rad)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def misalignment_matrix(alpha_rad: float, beta_rad: float, gamma_rad: float) -> np.ndarray:
    """T = Tα Tβ Tγ (001 eq. 5): B_platform = T B_sensor."""
    return heel_matrix(alpha_rad) @ pitch_matrix(beta_rad) @ azimuth_matrix(gamma_rad)


def nonorthogonality_matrix(phi_rad: float, theta_rad: float, psi_rad: float) -> np.ndarray:
    """A of 001 eq. 11: [[cosθcosφ, sinθcosφ, sinφ], [0, cosψ, sinψ], [0, 0, 1]]."""
    cf, sf = math.cos(phi_rad), math.sin(phi_rad)
    ct, st = math.cos(theta_rad), math.sin(theta_rad)
    cp, sp = math.cos(psi_rad), math.sin(psi_rad)
    return np.array([[ct * cf, st * cf, sf], [0.0, cp, sp], [0.0, 0.0, 1.0]])


def geomagnetic_field_nT(total_nT: float, inclination_deg: float, declination_deg: float) -> np.ndarray:
    """The field vector in NED: F (cos I cos D, cos I sin D, sin I).

    >>> np.round(geomagnetic_field_nT(50000.0, 90.0, 0.0), 6).tolist()
    [0.0, 0.0, 50000.0]
    """
    i, d = math.radians(inclination_deg), math.radians(declination_deg)
    return total_nT * np.array([math.cos(i) * math.cos(d), math.cos(i) * math.sin(d), math.sin(i)])


# --- platform motion ---------------------------------------------------------------------------------

class Motion(ABC):
    """Attitude R(t) (platform -> NED) and body angular rate ω(t) (platform frame, rad/s) at any instants."""

    def __init__(self, initial: np.ndarray) -> None:
        self.initial = np.asarray(initial, dtype=np.float64)   # R0

    @abstractmethod
    def attitude(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3, 3) for t of shape (...)."""

    @abstractmethod
    def angular_rate(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3) rad/s in the platform frame: dR/dt = R [ω]x."""

    def describe(self) -> dict[str, Any]:
        return {}


class StaticMotion(Motion):
    """The platform holds its initial attitude."""

    def attitude(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=np.float64)
        return np.broadcast_to(self.initial, (*t.shape, 3, 3)).copy()

    def angular_rate(self, t_s: np.ndarray) -> np.ndarray:
        return np.zeros((*np.shape(t_s), 3))


class TurntableMotion(Motion):
    """Whole turns about platform axes in sequence (each after a dwell), repeating: R = R0 R_axis(angle(t)).

    With ramp_s > 0 the speed rises and falls as a raised cosine over ramp_s, so the angular
    acceleration stays finite (a turn of Θ at rate ω then lasts Θ/ω + ramp_s)."""

    def __init__(self, initial: np.ndarray, axes: list[str], rate_deg_s: float, turns: int, dwell_s: float,
                 ramp_s: float = 0.0) -> None:
        super().__init__(initial)
        self.axes = list(axes)
        self.rate_rad_s = math.radians(rate_deg_s)
        self.turn_rad = 2.0 * math.pi * turns
        self.dwell_s = dwell_s
        self.ramp_s = ramp_s
        self.move_s = self.turn_rad / self.rate_rad_s + ramp_s
        self.segment_s = dwell_s + self.move_s
        self.period_s = self.segment_s * len(self.axes)

    def _local(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.mod(np.asarray(t_s, dtype=np.float64), self.period_s)
        seg = np.minimum((s // self.segment_s).astype(np.int64), len(self.axes) - 1)
        return seg, s - seg * self.segment_s - self.dwell_s       # time into the moving part

    def _angle_rate(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Angle and rate at time u into the move (u < 0: dwell, angle 0; u > move: angle Θ)."""
        w, tau, total, d = self.rate_rad_s, self.ramp_s, self.turn_rad, self.move_s
        u = np.clip(u, 0.0, d)
        if tau <= 0:
            return w * u, np.where((u > 0) & (u < d), w, 0.0)

        def up(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            # rate w (1 - cos(pi x / tau)) / 2 -> angle w/2 (x - tau/pi sin(pi x / tau))
            x = np.minimum(x, tau)
            return (0.5 * w * (x - tau / math.pi * np.sin(math.pi * x / tau)),
                    0.5 * w * (1.0 - np.cos(math.pi * x / tau)))

        a_up, r_up = up(u)
        a_dn, r_dn = up(d - u)
        cruise = 0.5 * w * tau + w * (u - tau)
        angle = np.where(u < tau, a_up, np.where(u > d - tau, total - a_dn, cruise))
        rate = np.where(u < tau, r_up, np.where(u > d - tau, r_dn, w))
        return angle, rate

    def attitude(self, t_s: np.ndarray) -> np.ndarray:
        seg, u = self._local(t_s)
        angle, _ = self._angle_rate(u)
        out = np.empty((*seg.shape, 3, 3))
        for j, axis in enumerate(self.axes):             # a loop over the (few) axes, not samples
            m = seg == j
            out[m] = self.initial @ rotation(axis, angle[m])
        return out

    def angular_rate(self, t_s: np.ndarray) -> np.ndarray:
        seg, u = self._local(t_s)
        _, rate = self._angle_rate(u)
        out = np.zeros((*seg.shape, 3))
        for j, axis in enumerate(self.axes):
            m = seg == j
            out[m, _AXIS_INDEX[axis]] = rate[m]
        return out

    def describe(self) -> dict[str, Any]:
        return {"period_s": self.period_s, "move_s": self.move_s}


class TumbleMotion(Motion):
    """Smooth random tumbling: z-y-x Euler angles that each advance at a random steady rate plus a
    few random sinusoids (periods around tumble_period_s), R = R0 Rz(ψ) Ry(θ) Rx(φ).

    Closed form in t, so attitude and rate are exact at any instant (lag, eddy need both)."""

    N_WOBBLE = 3

    def __init__(self, initial: np.ndarray, rate_deg_s: float, tumble_period_s: float, seed: int) -> None:
        super().__init__(initial)
        rng = np.random.default_rng([seed, STREAM_MOTION])
        w = math.radians(rate_deg_s)
        self.angle0 = rng.uniform(-math.pi, math.pi, 3)
        # steady Euler rates: random signs, no component near zero, about 0.8 of the rate in all
        u = rng.choice([-1.0, 1.0], 3) * rng.uniform(0.6, 1.0, 3)
        self.steady = 0.8 * w * u / np.linalg.norm(u)
        self.freq_hz = rng.uniform(0.5, 1.5, (3, self.N_WOBBLE)) / tumble_period_s
        self.phase = rng.uniform(0.0, 2.0 * math.pi, (3, self.N_WOBBLE))
        self.amp_rad_s = 0.35 * w / math.sqrt(self.N_WOBBLE) * rng.uniform(0.5, 1.0, (3, self.N_WOBBLE))

    def _euler(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(t_s, dtype=np.float64)[..., None, None]
        arg = 2.0 * math.pi * self.freq_hz * t + self.phase                     # (..., 3, K)
        # e_i(t) = e0_i + w_i t + sum_k a_ik / (2 pi f_ik) sin(2 pi f_ik t + p_ik)
        angle = self.angle0 + self.steady * t[..., 0] + np.sum(
            self.amp_rad_s / (2.0 * math.pi * self.freq_hz) * np.sin(arg), axis=-1)
        rate = self.steady + np.sum(self.amp_rad_s * np.cos(arg), axis=-1)
        return angle, rate

    def attitude(self, t_s: np.ndarray) -> np.ndarray:
        e, _ = self._euler(t_s)
        return self.initial @ rotation("z", e[..., 0]) @ rotation("y", e[..., 1]) @ rotation("x", e[..., 2])

    def angular_rate(self, t_s: np.ndarray) -> np.ndarray:
        e, de = self._euler(t_s)
        th, ph = e[..., 1], e[..., 2]
        dpsi, dth, dph = de[..., 0], de[..., 1], de[..., 2]
        # body rates of z-y-x Euler angles: p = φ' - ψ' sinθ, q = θ' cosφ + ψ' cosθ sinφ,
        # r = -θ' sinφ + ψ' cosθ cosφ
        return np.stack([dph - dpsi * np.sin(th),
                         dth * np.cos(ph) + dpsi * np.cos(th) * np.sin(ph),
                         -dth * np.sin(ph) + dpsi * np.cos(th) * np.cos(ph)], axis=-1)


class GridMotion(Motion):
    """Static attitudes on a nested grid (001 section 5.1: 12 per turn, z fastest, then y, then x:
    12^3 attitudes), each held hold_s: R = R0 R_{axes[-1]}(a) ... R_{axes[0]}(b); ω = 0 while held."""

    def __init__(self, initial: np.ndarray, axes: list[str], steps_per_turn: int, hold_s: float) -> None:
        super().__init__(initial)
        self.axes = list(axes)
        self.steps = steps_per_turn
        self.hold_s = hold_s
        self.n_attitudes = steps_per_turn ** len(axes)
        self.period_s = hold_s * self.n_attitudes

    def index(self, t_s: np.ndarray) -> np.ndarray:
        # the small nudge keeps t = k * hold_s (computed as i / rate_hz) in attitude k
        return np.floor(np.asarray(t_s, dtype=np.float64) / self.hold_s + 1e-9).astype(np.int64) % self.n_attitudes

    def attitude(self, t_s: np.ndarray) -> np.ndarray:
        j = self.index(t_s)
        out = np.broadcast_to(self.initial, (*j.shape, 3, 3))
        step = 2.0 * math.pi / self.steps
        for m in reversed(range(len(self.axes))):       # slowest axis first, on the left
            digit = (j // self.steps ** m) % self.steps
            out = out @ rotation(self.axes[m], digit * step)
        return np.array(out)

    def angular_rate(self, t_s: np.ndarray) -> np.ndarray:
        return np.zeros((*np.shape(t_s), 3))

    def describe(self) -> dict[str, Any]:
        return {"n_attitudes": self.n_attitudes, "period_s": self.period_s}


def make_motion(cfg: MotionConfig, seed: int) -> Motion:
    """The Motion a [sim.motion] table describes."""
    r0 = attitude_from_euler_deg(*cfg.initial_deg)
    if cfg.kind == "static":
        return StaticMotion(r0)
    if cfg.kind == "turntable":
        return TurntableMotion(r0, cfg.axes, cfg.rate_deg_s, cfg.turns, cfg.dwell_s, cfg.ramp_s)
    if cfg.kind == "tumble":
        return TumbleMotion(r0, cfg.rate_deg_s, cfg.tumble_period_s, seed)
    if cfg.kind == "grid":
        return GridMotion(r0, cfg.axes, cfg.steps_per_turn, cfg.hold_s)
    raise ValueError(f"motion kind {cfg.kind!r}")


# --- ambient field, temperature -----------------------------------------------------------------------

@dataclass(frozen=True)
class AmbientField:
    """B_earth(t, r) = B0 + drift_nT_per_h t / 3600 + G^T r, NED, r from the platform origin in m."""

    vector_nT: np.ndarray          # (3,) B0
    gradient_nT_m: np.ndarray      # (3, 3) G[i, j] = dB_j/dx_i
    drift_nT_per_h: np.ndarray     # (3,)

    @staticmethod
    def from_config(cfg: FieldConfig) -> "AmbientField":
        return AmbientField(vector_nT=geomagnetic_field_nT(cfg.total_nT, cfg.inclination_deg, cfg.declination_deg),
                            gradient_nT_m=np.array(cfg.gradient_nT_m, dtype=np.float64),
                            drift_nT_per_h=np.array(cfg.drift_nT_per_h, dtype=np.float64))

    def at_origin(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3) B0 + drift t."""
        return self.vector_nT + self.drift_nT_per_h * (np.asarray(t_s)[..., None] / 3600.0)

    def at(self, t_s: np.ndarray, r_earth_m: np.ndarray) -> np.ndarray:
        """(..., 3) at earth-frame offsets r (..., 3) from the origin: B0 + drift t + G^T r."""
        return self.at_origin(t_s) + np.einsum("ji,...j->...i", self.gradient_nT_m, r_earth_m)

    @property
    def rate_nT_s(self) -> np.ndarray:
        return self.drift_nT_per_h / 3600.0


@dataclass(frozen=True)
class TemperatureProfile:
    """T(t) = start + ramp t / 3600 + amplitude sin(2 pi t / period), plus each probe's offset."""

    cfg: TemperatureConfig

    def at(self, t_s: np.ndarray) -> np.ndarray:
        c = self.cfg
        t = np.asarray(t_s, dtype=np.float64)
        return c.start_C + c.ramp_C_per_h * t / 3600.0 + c.amplitude_C * np.sin(2.0 * math.pi * t / c.period_s)


# --- probes -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class ProbeArray:
    """The P probes' paper-001 parameters stacked for array work."""

    names: list[str]
    position_m: np.ndarray     # (P, 3) platform frame
    scale: np.ndarray          # (P, 3) c_x, c_y, c_z
    nonorth_deg: np.ndarray    # (P, 3) φ, θ, ψ
    misalign_deg: np.ndarray   # (P, 3) α, β, γ
    offset_nT: np.ndarray      # (P, 3)
    noise_nT: np.ndarray       # (P, 3) 1 sigma
    temp_offset_C: np.ndarray  # (P,)

    @staticmethod
    def from_config(probes: list[ProbeSimConfig]) -> "ProbeArray":
        def arr(attr: str) -> np.ndarray:
            return np.array([getattr(p, attr) for p in probes], dtype=np.float64)

        return ProbeArray(names=[p.name for p in probes], position_m=arr("position_m"), scale=arr("scale"),
                          nonorth_deg=arr("nonorth_deg"), misalign_deg=arr("misalign_deg"),
                          offset_nT=arr("offset_nT"), noise_nT=arr("noise_nT"), temp_offset_C=arr("temp_offset_C"))

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def nonorth(self) -> np.ndarray:
        """(P, 3, 3) A of 001 eq. 11."""
        return np.stack([nonorthogonality_matrix(*np.radians(a)) for a in self.nonorth_deg])

    @property
    def misalign(self) -> np.ndarray:
        """(P, 3, 3) T = Tα Tβ Tγ of 001 eq. 5 (B_platform = T B_sensor)."""
        return np.stack([misalignment_matrix(*np.radians(a)) for a in self.misalign_deg])

    @property
    def forward_matrix(self) -> np.ndarray:
        """(P, 3, 3) F = C A T^T: raw - offset = F B_platform when no effect acts."""
        return self.scale[:, :, None] * self.nonorth @ np.swapaxes(self.misalign, 1, 2)

    @property
    def truth_matrix(self) -> np.ndarray:
        """(P, 3, 3) F^-1: matrix (raw - offset) = B_platform (CONTRACTS.md section 3's `matrix`)."""
        f = self.forward_matrix
        return np.linalg.solve(f, np.broadcast_to(np.eye(3), f.shape))


# --- effects ------------------------------------------------------------------------------------------

@dataclass
class EffectContext:
    """What effects may look at, for N instants and P probes."""

    t_s: np.ndarray                # (N, P) the instants the probes were sampled
    temp_C: np.ndarray             # (N, P) probe temperatures
    dsensor_dt_nT_s: np.ndarray    # (N, P, 3) dB_sensor/dt from rotation, drift and gradient


class Effect:
    """One physical term of the forward model, with per-probe parameters in physical units.

    Override only the hooks the effect acts at; the world calls them in this order:
    sample_time (instant), sensor_field (field at the probe, sensor frame), transfer (u = C A B_sensor),
    offset. `active` is False while every parameter is zero."""

    name: ClassVar[str] = ""

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "Effect":
        raise NotImplementedError

    def active(self) -> bool:
        return False

    def params(self, k: int) -> dict[str, Any]:
        """Probe k's parameters for the truth file."""
        return {}

    def sample_time(self, t_s: np.ndarray) -> np.ndarray:
        return t_s

    def sensor_field(self, ctx: EffectContext, b_nT: np.ndarray) -> np.ndarray:
        return b_nT

    def transfer(self, ctx: EffectContext, u_nT: np.ndarray) -> np.ndarray:
        return u_nT

    def offset(self, ctx: EffectContext, offset_nT: np.ndarray) -> np.ndarray:
        return offset_nT


def _stack(cfg: SimConfig, attr: str) -> np.ndarray:
    return np.array([getattr(p, attr) for p in cfg.probes], dtype=np.float64)


class LagEffect(Effect):
    """A probe sampled lag_s after the unit's instant: it sees the attitude (and field) of t + lag_s."""

    name = "lag"

    def __init__(self, lag_s: np.ndarray) -> None:
        self.lag_s = np.asarray(lag_s, dtype=np.float64)          # (P,)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "LagEffect":
        return cls(_stack(cfg, "lag_s"))

    def active(self) -> bool:
        return bool(np.any(self.lag_s))

    def params(self, k: int) -> dict[str, Any]:
        return {"lag_s": float(self.lag_s[k])}

    def sample_time(self, t_s: np.ndarray) -> np.ndarray:
        return t_s + self.lag_s                                   # t_k = t + lag_k


class EddyEffect(Effect):
    """Fields induced by changing flux: B_sensor += E dB_sensor/dt, E (3x3, s) per probe."""

    name = "eddy"

    def __init__(self, matrix_s: np.ndarray) -> None:
        self.matrix_s = np.asarray(matrix_s, dtype=np.float64)    # (P, 3, 3)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "EddyEffect":
        return cls(_stack(cfg, "eddy_s"))

    def active(self) -> bool:
        return bool(np.any(self.matrix_s))

    def params(self, k: int) -> dict[str, Any]:
        return {"matrix_s": self.matrix_s[k].tolist()}

    def sensor_field(self, ctx: EffectContext, b_nT: np.ndarray) -> np.ndarray:
        return b_nT + np.einsum("pij,npj->npi", self.matrix_s, ctx.dsensor_dt_nT_s)


class TemperatureEffect(Effect):
    """Scale and offset follow the probe temperature: u (1 + ppm 1e-6 ΔT), offset + k ΔT, ΔT = T - reference."""

    name = "temperature"

    def __init__(self, offset_nT_per_C: np.ndarray, scale_ppm_per_C: np.ndarray, reference_C: float) -> None:
        self.offset_nT_per_C = np.asarray(offset_nT_per_C, dtype=np.float64)   # (P, 3)
        self.scale_ppm_per_C = np.asarray(scale_ppm_per_C, dtype=np.float64)   # (P, 3)
        self.reference_C = reference_C

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "TemperatureEffect":
        return cls(_stack(cfg, "temp_offset_nT_per_C"), _stack(cfg, "temp_scale_ppm_per_C"),
                   cfg.temperature.reference_C)

    def active(self) -> bool:
        return bool(np.any(self.offset_nT_per_C) or np.any(self.scale_ppm_per_C))

    def params(self, k: int) -> dict[str, Any]:
        return {"offset_nT_per_C": self.offset_nT_per_C[k].tolist(),
                "scale_ppm_per_C": self.scale_ppm_per_C[k].tolist(), "reference_C": self.reference_C}

    def transfer(self, ctx: EffectContext, u_nT: np.ndarray) -> np.ndarray:
        dt = (ctx.temp_C - self.reference_C)[..., None]
        return u_nT * (1.0 + 1e-6 * self.scale_ppm_per_C * dt)

    def offset(self, ctx: EffectContext, offset_nT: np.ndarray) -> np.ndarray:
        return offset_nT + self.offset_nT_per_C * (ctx.temp_C - self.reference_C)[..., None]


class NonlinearityEffect(Effect):
    """Per-axis transfer non-linearity: out = u + q u^2 + c u^3 on the field term u = C A B_sensor (nT)."""

    name = "nonlinearity"

    def __init__(self, quadratic_per_nT: np.ndarray, cubic_per_nT2: np.ndarray) -> None:
        self.quadratic_per_nT = np.asarray(quadratic_per_nT, dtype=np.float64)   # (P, 3)
        self.cubic_per_nT2 = np.asarray(cubic_per_nT2, dtype=np.float64)         # (P, 3)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "NonlinearityEffect":
        return cls(_stack(cfg, "nonlin_quadratic_per_nT"), _stack(cfg, "nonlin_cubic_per_nT2"))

    def active(self) -> bool:
        return bool(np.any(self.quadratic_per_nT) or np.any(self.cubic_per_nT2))

    def params(self, k: int) -> dict[str, Any]:
        return {"quadratic_per_nT": self.quadratic_per_nT[k].tolist(),
                "cubic_per_nT2": self.cubic_per_nT2[k].tolist()}

    def transfer(self, ctx: EffectContext, u_nT: np.ndarray) -> np.ndarray:
        return u_nT + self.quadratic_per_nT * u_nT ** 2 + self.cubic_per_nT2 * u_nT ** 3


class OffsetDriftEffect(Effect):
    """Slow offset drift per probe and axis: offset + d t / 3600 (the ambient drift is in the field)."""

    name = "drift"

    def __init__(self, offset_nT_per_h: np.ndarray) -> None:
        self.offset_nT_per_h = np.asarray(offset_nT_per_h, dtype=np.float64)     # (P, 3)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "OffsetDriftEffect":
        return cls(_stack(cfg, "drift_offset_nT_per_h"))

    def active(self) -> bool:
        return bool(np.any(self.offset_nT_per_h))

    def params(self, k: int) -> dict[str, Any]:
        return {"offset_nT_per_h": self.offset_nT_per_h[k].tolist()}

    def offset(self, ctx: EffectContext, offset_nT: np.ndarray) -> np.ndarray:
        return offset_nT + self.offset_nT_per_h * (ctx.t_s / 3600.0)[..., None]


#: the catalogue, in the order the world applies them; adding an effect is adding a class here
EFFECTS: tuple[type[Effect], ...] = (LagEffect, EddyEffect, TemperatureEffect, NonlinearityEffect, OffsetDriftEffect)


# --- the world ----------------------------------------------------------------------------------------

@dataclass
class WorldSamples:
    """Everything the world knows about N instants (arrays of N samples, P probes)."""

    index: np.ndarray                  # (N,) int64 sample index (-1 when evaluated at free instants)
    t_s: np.ndarray                    # (N,) world time, s from the start
    t_probe_s: np.ndarray              # (N, P) the instants each probe was sampled (t + lag)
    attitude: np.ndarray               # (N, 3, 3) R at t: platform -> NED
    angular_rate_rad_s: np.ndarray     # (N, 3) ω at t, platform frame
    field_earth_nT: np.ndarray         # (N, 3) at the platform origin at t, NED
    field_origin_nT: np.ndarray        # (N, 3) the same in the platform frame: R^T B_earth
    field_platform_nT: np.ndarray      # (N, P, 3) at each probe position and instant, platform frame
    field_sensor_nT: np.ndarray        # (N, P, 3) in each probe's ideal frame, before effects
    dsensor_dt_nT_s: np.ndarray        # (N, P, 3) its time derivative
    temp_C: np.ndarray                 # (N, P)
    output_nT: np.ndarray              # (N, P, 3) the probes' noise-free outputs
    noise_nT: np.ndarray               # (N, P, 3)
    ref_total_nT: np.ndarray | None    # (N,) scalar reference with its noise, or None

    @property
    def raw_nT(self) -> np.ndarray:
        """(N, P, 3) what the probes put out, before the ADC: output + noise."""
        return self.output_nT + self.noise_nT

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


class World:
    """The simulated world of one [sim] configuration: evaluate it at sample indices or at any instants."""

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        self.rate_hz = config.rate_hz
        self.n_probes = config.n_probes
        self.n_samples = config.n_samples
        self.motion = make_motion(config.motion, config.seed)
        self.field = AmbientField.from_config(config.field)
        self.probes = ProbeArray.from_config(config.probes)
        self.temperature = TemperatureProfile(config.temperature)
        self.effects: list[Effect] = [cls.from_config(config) for cls in EFFECTS]
        self._forward = self.probes.forward_matrix
        self._nonorth_scaled = self.probes.scale[:, :, None] * self.probes.nonorth    # C A
        self._to_sensor = np.swapaxes(self.probes.misalign, 1, 2)                      # T^T
        self._noise = ChunkedRandom(config.seed, STREAM_NOISE, (self.n_probes, 3))
        self._ref_noise = ChunkedRandom(config.seed, STREAM_REF, ())

    # -- what is on ----------------------------------------------------------------------------------
    @property
    def active_effects(self) -> list[str]:
        """Names of the effects with non-zero parameters (CONTRACTS.md names, plus 'gradient')."""
        names = [e.name for e in self.effects if e.active()]
        if np.any(self.field.drift_nT_per_h) and "drift" not in names:
            names.append("drift")
        if np.any(self.field.gradient_nT_m):
            names.append("gradient")
        return names

    def effect(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(name)

    # -- evaluation --------------------------------------------------------------------------------
    def times(self, start: int, stop: int) -> np.ndarray:
        """World time of samples [start, stop): i / rate_hz."""
        return np.arange(start, stop, dtype=np.float64) / self.rate_hz

    def samples(self, start: int, stop: int, *, effects: bool | Iterable[str] = True,
                noise: bool = True) -> WorldSamples:
        """Samples [start, stop) with their noise (the same numbers however the run is cut)."""
        if not 0 <= start <= stop:
            raise ValueError(f"samples: expected 0 <= start <= stop, got {start}, {stop}")
        out = self.evaluate(self.times(start, stop), effects=effects)
        out.index = np.arange(start, stop, dtype=np.int64)
        if noise:
            out.noise_nT = self._noise.draw(start, stop) * self.probes.noise_nT
            if out.ref_total_nT is not None:
                out.ref_total_nT = out.ref_total_nT + self.config.reference.noise_nT * self._ref_noise.draw(start, stop)
        return out

    def evaluate(self, t_s: np.ndarray, *, effects: bool | Iterable[str] = True) -> WorldSamples:
        """The noise-free world at instants t (N,) (world time, s). `effects`: all, none, or these names."""
        t = np.asarray(t_s, dtype=np.float64).reshape(-1)
        n, p = t.shape[0], self.n_probes
        if effects is True:
            on = [e for e in self.effects if e.active()]
        elif effects is False:
            on = []
        else:
            wanted = set(effects)
            on = [e for e in self.effects if e.name in wanted and e.active()]

        t_np = np.broadcast_to(t[:, None], (n, p)).copy()
        for e in on:
            t_np = e.sample_time(t_np)

        # field at each probe, at its instant: B_p = R^T (B0 + drift t + G^T R r_k)
        r = self.motion.attitude(t_np)                                        # (N, P, 3, 3)
        w = self.motion.angular_rate(t_np)                                    # (N, P, 3)
        pos = self.probes.position_m                                          # (P, 3)
        r_earth = np.einsum("npij,pj->npi", r, pos)
        b_platform = np.einsum("npji,npj->npi", r, self.field.at(t_np, r_earth))
        # d/dt R^T b = -ω x (R^T b) + R^T (db/dt + G^T R (ω x r_k))
        grad_term = np.einsum("ji,npj->npi", self.field.gradient_nT_m,
                              np.einsum("npij,npj->npi", r, np.cross(w, pos)))
        db_platform = -np.cross(w, b_platform) + np.einsum("npji,npj->npi", r, self.field.rate_nT_s + grad_term)

        b_sensor = np.einsum("pij,npj->npi", self._to_sensor, b_platform)   # B_s = T^T B_p
        db_sensor = np.einsum("pij,npj->npi", self._to_sensor, db_platform)
        temp = self.temperature.at(t_np) + self.probes.temp_offset_C
        ctx = EffectContext(t_s=t_np, temp_C=temp, dsensor_dt_nT_s=db_sensor)

        b_eff = b_sensor
        for e in on:
            b_eff = e.sensor_field(ctx, b_eff)
        u = np.einsum("pij,npj->npi", self._nonorth_scaled, b_eff)          # u = C A B_s
        for e in on:
            u = e.transfer(ctx, u)
        offset = np.broadcast_to(self.probes.offset_nT, (n, p, 3))
        for e in on:
            offset = e.offset(ctx, offset)
        output = u + offset                                                   # raw = C A B_s + offset

        r0 = self.motion.attitude(t)                                          # (N, 3, 3) at the unit's instant
        b_earth0 = self.field.at_origin(t)
        ref = np.linalg.norm(b_earth0, axis=-1) if self.config.reference.enabled else None
        return WorldSamples(
            index=np.full(n, -1, np.int64), t_s=t, t_probe_s=t_np, attitude=r0,
            angular_rate_rad_s=self.motion.angular_rate(t), field_earth_nT=b_earth0,
            field_origin_nT=np.einsum("nji,nj->ni", r0, b_earth0), field_platform_nT=b_platform,
            field_sensor_nT=b_sensor, dsensor_dt_nT_s=db_sensor, temp_C=temp, output_nT=output,
            noise_nT=np.zeros((n, p, 3)), ref_total_nT=ref)

    # -- truth ---------------------------------------------------------------------------------------
    def rms_rate_deg_s(self, max_s: float = 600.0) -> float:
        """RMS angular rate of the motion over the run (at most max_s, sampled at 20 Hz)."""
        span = self.config.duration_s if self.config.duration_s > 0 else max_s
        t = np.arange(0.0, min(span, max_s), 0.05)
        if t.size == 0:
            return 0.0
        return float(np.degrees(np.sqrt(np.mean(np.sum(self.motion.angular_rate(t) ** 2, axis=-1)))))

    def truth(self) -> dict[str, Any]:
        """Every parameter of the world, per-probe truth calibration included, as plain JSON types."""
        cfg = self.config
        pr = self.probes
        matrix, forward = pr.truth_matrix, pr.forward_matrix
        sensors = []
        for k in range(pr.n):
            sensors.append({
                "name": pr.names[k],
                "position_m": pr.position_m[k].tolist(),
                "scale": pr.scale[k].tolist(),
                "nonorth_deg": pr.nonorth_deg[k].tolist(),
                "misalign_deg": pr.misalign_deg[k].tolist(),
                "offset_nT": pr.offset_nT[k].tolist(),
                "matrix": matrix[k].tolist(),
                "forward_matrix": forward[k].tolist(),
                "noise_nT": pr.noise_nT[k].tolist(),
                "temp_offset_C": float(pr.temp_offset_C[k]),
                "effects": {e.name: e.params(k) for e in self.effects},
            })
        motion = {**_plain(cfg.motion.__dict__), **self.motion.describe(), "rms_rate_deg_s": self.rms_rate_deg_s()}
        return {
            "format": "fluxcal-sim-truth",
            "version": 1,
            "conventions": {
                "earth_frame": "NED: x north, y east, z down",
                "attitude": "R(t) maps platform to earth: v_earth = R v_platform; "
                            "R0 = Rz(azimuth) Ry(pitch) Rx(heel) from motion.initial_deg",
                "gradient": "G[i][j] = dB_j/dx_i in the earth frame; B(r) = B0 + G^T r, r from the platform origin",
                "probe_model": "raw = C A (Ta Tb Tg)^T B_platform + offset (paper 001 eq. 4, 5, 11); "
                               "C = diag(scale), A from nonorth_deg = [phi, theta, psi], "
                               "Ta Tb Tg from misalign_deg = [alpha heel x, beta pitch y, gamma azimuth z]",
                "matrix": "matrix (raw - offset_nT) = B_platform at the probe, before any effect term; "
                          "forward_matrix = C A (Ta Tb Tg)^T = inverse of matrix",
                "effects_order": "lag (instant) -> eddy (B_sensor += E dB_sensor/dt) -> "
                                 "temperature scale, nonlinearity (on u = C A B_sensor) -> "
                                 "offset + temperature offset + drift",
                "time": "world time t = sample index / rate_hz; CSV t = t + t_us_start / 1e6",
            },
            "seed": cfg.seed,
            "rate_hz": cfg.rate_hz,
            "duration_s": cfg.duration_s,
            "n_samples": self.n_samples,
            "lsb_nT": cfg.lsb_nT,
            "range_nT": cfg.range_nT,
            "seq_start": cfg.seq_start,
            "t_us_start": cfg.t_us_start,
            "can_base_id": cfg.can_base_id,
            "field": {
                "frame": "NED",
                "total_nT": cfg.field.total_nT,
                "inclination_deg": cfg.field.inclination_deg,
                "declination_deg": cfg.field.declination_deg,
                "vector_nT": self.field.vector_nT.tolist(),
                "gradient_nT_m": self.field.gradient_nT_m.tolist(),
                "drift_nT_per_h": self.field.drift_nT_per_h.tolist(),
            },
            "reference": {"enabled": cfg.reference.enabled, "noise_nT": cfg.reference.noise_nT,
                          "position_m": [0.0, 0.0, 0.0]},
            "motion": motion,
            "temperature": _plain(cfg.temperature.__dict__),
            "effects": self.active_effects,
            "sensors": sensors,
            "faults": _plain(cfg.faults.__dict__),
            "config": cfg.as_dict(),
        }


def _plain(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in d.items()}


__all__ = [
    "World", "WorldSamples", "Motion", "StaticMotion", "TurntableMotion", "TumbleMotion", "GridMotion",
    "make_motion", "AmbientField", "TemperatureProfile", "ProbeArray", "Effect", "EffectContext", "EFFECTS",
    "LagEffect", "EddyEffect", "TemperatureEffect", "NonlinearityEffect", "OffsetDriftEffect", "ChunkedRandom",
    "rotation", "attitude_from_euler_deg", "heel_matrix", "pitch_matrix", "azimuth_matrix",
    "misalignment_matrix", "nonorthogonality_matrix", "geomagnetic_field_nT",
]
