"""The platform's motion and the frames of the simulated world: rotations, attitudes, the [FastRotation]
misalignment and non-orthogonality matrices, the geomagnetic field, and the motions a run can make.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from .config import MotionConfig
from .streams import STREAM_MOTION

_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


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
    """Tα of [FastRotation] eq. 4: [[1, 0, 0], [0, cosα, sinα], [0, -sinα, cosα]]."""
    c, s = math.cos(alpha_rad), math.sin(alpha_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])


def pitch_matrix(beta_rad: float) -> np.ndarray:
    """Tβ of [FastRotation] eq. 4: [[cosβ, 0, -sinβ], [0, 1, 0], [sinβ, 0, cosβ]]."""
    c, s = math.cos(beta_rad), math.sin(beta_rad)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def azimuth_matrix(gamma_rad: float) -> np.ndarray:
    """Tγ of [FastRotation] eq. 4: [[cosγ, sinγ, 0], [-sinγ, cosγ, 0], [0, 0, 1]]."""
    c, s = math.cos(gamma_rad), math.sin(gamma_rad)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def misalignment_matrix(alpha_rad: float, beta_rad: float, gamma_rad: float) -> np.ndarray:
    """T = Tα Tβ Tγ ([FastRotation] eq. 5): B_platform = T B_sensor."""
    return heel_matrix(alpha_rad) @ pitch_matrix(beta_rad) @ azimuth_matrix(gamma_rad)


def nonorthogonality_matrix(phi_rad: float, theta_rad: float, psi_rad: float) -> np.ndarray:
    """A of [FastRotation] eq. 11: [[cosθcosφ, sinθcosφ, sinφ], [0, cosψ, sinψ], [0, 0, 1]]."""
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

    def table(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What a turntable controller logs: the table angle (deg, 0 at the start of each turn) and which
        body axis it turns about (0 x, 1 y, 2 z; -1 in the dwell before a turn)."""
        seg, u = self._local(t_s)
        angle, _ = self._angle_rate(u)
        axis = np.array([_AXIS_INDEX[a] for a in self.axes])[seg]
        return np.degrees(angle), np.where(u > 0, axis, -1)


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
        # attitude and rate are asked for at the same instants one after the other: the angles of the last
        # instants asked for are kept (a third of a simulation's time)
        last = getattr(self, "_last", None)
        if last is not None and last[0].shape == np.shape(t_s) and np.array_equal(last[0], t_s):
            return last[1], last[2]
        angle, rate = self._euler_at(t_s)
        self._last = (np.array(t_s, dtype=np.float64, copy=True), angle, rate)
        return angle, rate

    def _euler_at(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    """Static attitudes on a nested grid ([FastRotation] section 5.1: 12 per turn, z fastest, then y, then x:
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
