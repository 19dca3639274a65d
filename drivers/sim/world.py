"""The simulated world: platform motion, the ambient field with its gradient and drift, and each probe's
forward model ([FastRotation]) with the physical effects. Pure numpy over arrays of instants; no I/O.

Frames and conventions:

- earth frame NED: x north, y east, z down (the geomagnetic convention);
  B_earth = F (cos I cos D, cos I sin D, sin I), I inclination (positive down), D declination (east);
- platform frame: rigid with the platform; its attitude R(t) maps platform to earth, v_earth = R v_platform,
  and its body angular rate ω (platform frame, rad/s) satisfies dR/dt = R [ω]x;
- site gradient G[i, j] = dB_j/dx_i ([FastRotation] eq. 1) in the earth frame, about the platform origin (the
  rotation centre): B_earth(r) = B0 + drift_nT_per_h·t/3600 + G^T r;
- probe (sensor) frame: the ideal orthogonal axes of probe k; [FastRotation] eq. 5: B_platform = Tα Tβ Tγ B_sensor,
  so B_sensor = (Tα Tβ Tγ)^T B_platform (heel α about x, pitch β about y, azimuth γ about z, eq. 4);
- output ([FastRotation] eq. 11): raw = C A B_sensor + offset, C = diag(c_x, c_y, c_z),
  A = [[cosθcosφ, sinθcosφ, sinφ], [0, cosψ, sinψ], [0, 0, 1]];
- truth calibration: matrix = (C A (Tα Tβ Tγ)^T)^-1, so that matrix (raw - offset) = B_platform.

Effects (each off while its parameters are zero) act at four places of the chain, in this order:
sampling instant (lag), field at the probe (eddy), transfer u = C A B_sensor (temperature scale,
nonlinearity) and offset (temperature offset, drift). The site gradient and the ambient drift are
part of the field. Random numbers are addressed by sample index (ChunkedRandom), so a run cut into
blocks of any size gives the same samples."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from .config import FieldConfig, ProbeSimConfig, SimConfig, TemperatureConfig, TrackConfig
from .motion import (
    GridMotion,
    Motion,
    StaticMotion,
    TumbleMotion,
    TurntableMotion,
    attitude_from_euler_deg,
    azimuth_matrix,
    geomagnetic_field_nT,
    heel_matrix,
    make_motion,
    misalignment_matrix,
    nonorthogonality_matrix,
    pitch_matrix,
    rotation,
)
from .physics import (
    EFFECTS,
    EddyEffect,
    Effect,
    EffectContext,
    LagEffect,
    NonlinearityEffect,
    OffsetDriftEffect,
    TemperatureEffect,
)
from .streams import STREAM_AMBIENT, STREAM_NOISE, STREAM_PINK, STREAM_REF, ChunkedRandom, OneOverF, PinkNoise

#: 1/f probe noise from this frequency up to the Nyquist frequency, Hz
PINK_F_LO_HZ = 1e-4


class ClimbTrack:
    """[sim.track]: the platform's position at world time t (straight up or down from one place) and the main field
    there, NED, from pygeomag's own GeoMag.calculate at heights TRACK_GRID_M apart, linear between them (the field's
    curvature with height, about 12 F / R^2 = 1.5e-8 nT/m^2, makes that at most 5e-6 nT off)."""

    def __init__(self, cfg: TrackConfig, duration_s: float) -> None:
        from pygeomag import GeoMag

        self.cfg = cfg
        lo, hi = sorted((cfg.altitude_start_m, cfg.altitude_start_m + cfg.climb_m_s * max(duration_s, 0.0)))
        heights = np.arange(lo - TRACK_GRID_M, hi + 2 * TRACK_GRID_M, TRACK_GRID_M)
        model = GeoMag()
        res = [model.calculate(glat=cfg.latitude_deg, glon=cfg.longitude_deg, alt=h / 1000.0, time=cfg.year)
               for h in heights]
        self.heights_m = heights
        self.ned_nT = np.array([[r.x, r.y, r.z] for r in res])
        self.model = str(model.model)

    def altitude_m(self, t_s: np.ndarray) -> np.ndarray:
        return self.cfg.altitude_start_m + self.cfg.climb_m_s * np.asarray(t_s, np.float64)

    def field_nT(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3) NED at the platform origin at world times t."""
        h = self.altitude_m(t_s)
        return np.stack([np.interp(h, self.heights_m, self.ned_nT[:, a]) for a in range(3)], axis=-1)

    def rate_nT_s(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3) d/dt of field_nT: the climb rate times the slope with height."""
        h = self.altitude_m(t_s)
        slope = np.diff(self.ned_nT, axis=0) / TRACK_GRID_M
        i = np.clip(np.searchsorted(self.heights_m, h, side="right") - 1, 0, slope.shape[0] - 1)
        return self.cfg.climb_m_s * slope[i]

    def position(self, t_s: np.ndarray) -> dict[str, np.ndarray]:
        t = np.asarray(t_s, np.float64)
        return {"lat_deg": np.full(t.shape, self.cfg.latitude_deg), "lon_deg": np.full(t.shape, self.cfg.longitude_deg),
                "alt_m": self.altitude_m(t)}


#: heights between the track's model evaluations, m
TRACK_GRID_M = 50.0


@dataclass(frozen=True)
class AmbientField:
    """B_earth(t, r) = B0 + drift_nT_per_h t / 3600 + v(t) + G^T r, NED, r from the platform origin in m;
    v(t) the ambient variation (1/f, common to all probes), or none."""

    vector_nT: np.ndarray          # (3,) B0
    gradient_nT_m: np.ndarray      # (3, 3) G[i, j] = dB_j/dx_i
    drift_nT_per_h: np.ndarray     # (3,)
    variation: OneOverF | None = None
    track: ClimbTrack | None = None

    @staticmethod
    def from_config(cfg: FieldConfig, seed: int = 0, track: ClimbTrack | None = None) -> "AmbientField":
        variation = None
        if cfg.variation_nT > 0:
            f_lo, f_hi = 1.0 / cfg.variation_max_period_s, 1.0 / cfg.variation_min_period_s
            density = cfg.variation_nT / np.sqrt(np.log(f_hi / f_lo))        # so that the RMS is variation_nT
            variation = OneOverF(seed, STREAM_AMBIENT, np.full(3, density), f_lo, f_hi)
        return AmbientField(vector_nT=geomagnetic_field_nT(cfg.total_nT, cfg.inclination_deg, cfg.declination_deg),
                            gradient_nT_m=np.array(cfg.gradient_nT_m, dtype=np.float64),
                            drift_nT_per_h=np.array(cfg.drift_nT_per_h, dtype=np.float64), variation=variation,
                            track=track)

    def at_origin(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3) B0 + drift t + v(t); B0 the model along [sim.track] where it is on."""
        b0 = self.vector_nT if self.track is None else self.track.field_nT(t_s)
        b = b0 + self.drift_nT_per_h * (np.asarray(t_s)[..., None] / 3600.0)
        return b if self.variation is None else b + self._variation(t_s, False)

    def rate_at(self, t_s: np.ndarray) -> np.ndarray:
        """(..., 3) dB/dt at the origin, nT/s."""
        r = np.broadcast_to(self.rate_nT_s, (*np.shape(t_s), 3))
        if self.track is not None:
            r = r + self.track.rate_nT_s(t_s)
        return r if self.variation is None else r + self._variation(t_s, True)

    def _variation(self, t_s: np.ndarray, derivative: bool) -> np.ndarray:
        """v(t) or dv/dt; instants (N, P) that are the same for every probe (no lag) are evaluated once."""
        assert self.variation is not None
        t = np.asarray(t_s, dtype=np.float64)
        if t.ndim == 2 and t.shape[1] > 1 and np.array_equal(t, np.broadcast_to(t[:, :1], t.shape)):
            one = self.variation.at(t[:, 0], derivative)
            return np.broadcast_to(one[:, None, :], (*t.shape, 3))
        return self.variation.at(t, derivative)

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

    def core(self, t_s: np.ndarray, tau_s: np.ndarray) -> np.ndarray:
        """T_c(t): the temperature of a core that follows T with time constant tau (dT_c/dt = (T - T_c) / tau,
        T_c(0) = T(0)), exactly: the steady response to the ramp and the sinusoid plus the transient."""
        c = self.cfg
        t = np.asarray(t_s, dtype=np.float64)
        tau = np.broadcast_to(np.asarray(tau_s, dtype=np.float64), t.shape)
        w = 2.0 * math.pi / c.period_s
        r = c.ramp_C_per_h / 3600.0

        def steady(tt: np.ndarray) -> np.ndarray:
            return (c.start_C + r * (tt - tau) + c.amplitude_C / np.sqrt(1.0 + (w * tau) ** 2)
                    * np.sin(w * tt - np.arctan(w * tau)))

        lagged = steady(t) + (self.at(0.0) - steady(np.zeros_like(t))) * np.exp(-t / np.where(tau > 0, tau, 1.0))
        return np.where(tau > 0, lagged, self.at(t))


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
        """(P, 3, 3) A of [FastRotation] eq. 11."""
        return np.stack([nonorthogonality_matrix(*np.radians(a)) for a in self.nonorth_deg])

    @property
    def misalign(self) -> np.ndarray:
        """(P, 3, 3) T = Tα Tβ Tγ of [FastRotation] eq. 5 (B_platform = T B_sensor)."""
        return np.stack([misalignment_matrix(*np.radians(a)) for a in self.misalign_deg])

    @property
    def forward_matrix(self) -> np.ndarray:
        """(P, 3, 3) F = C A T^T: raw - offset = F B_platform when no effect acts."""
        return self.scale[:, :, None] * self.nonorth @ np.swapaxes(self.misalign, 1, 2)

    @property
    def truth_matrix(self) -> np.ndarray:
        """(P, 3, 3) F^-1: matrix (raw - offset) = B_platform (the `matrix` of docs/contracts.md)."""
        f = self.forward_matrix
        return np.linalg.solve(f, np.broadcast_to(np.eye(3), f.shape))


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


def _attitudes(motion, t: np.ndarray, t_np: np.ndarray) -> tuple[np.ndarray, ...]:
    """Attitude and angular rate at the unit's instants t (N,) and at each probe's t_np (N, P): the same
    arrays broadcast when every probe samples at the unit's instant (no effect moved them)."""
    r0, w0 = motion.attitude(t), motion.angular_rate(t)
    if np.array_equal(t_np, np.broadcast_to(t[:, None], t_np.shape)):
        n, p = t_np.shape
        return r0, w0, np.broadcast_to(r0[:, None], (n, p, 3, 3)), np.broadcast_to(w0[:, None], (n, p, 3))
    return r0, w0, motion.attitude(t_np), motion.angular_rate(t_np)


class World:
    """The simulated world of one [sim] configuration: evaluate it at sample indices or at any instants."""

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        self.rate_hz = config.rate_hz
        self.n_probes = config.n_probes
        self.n_samples = config.n_samples
        self.motion = make_motion(config.motion, config.seed)
        self.track = ClimbTrack(config.track, config.duration_s) if config.track.enabled else None
        self.field = AmbientField.from_config(config.field, config.seed, self.track)
        self.probes = ProbeArray.from_config(config.probes)
        self.temperature = TemperatureProfile(config.temperature)
        self.effects: list[Effect] = [cls.from_config(config) for cls in EFFECTS]
        self._forward = self.probes.forward_matrix
        self._nonorth_scaled = self.probes.scale[:, :, None] * self.probes.nonorth    # C A
        self._to_sensor = np.swapaxes(self.probes.misalign, 1, 2)                      # T^T
        self._noise = ChunkedRandom(config.seed, STREAM_NOISE, (self.n_probes, 3))
        self._ref_noise = ChunkedRandom(config.seed, STREAM_REF, ())
        self._temp_lag_s = np.array([p.temp_lag_s for p in config.probes], dtype=np.float64)
        pink = np.array([p.pink_nT_rtHz for p in config.probes], dtype=np.float64).reshape(self.n_probes, 3)
        self._pink = (PinkNoise(config.seed, STREAM_PINK, pink, PINK_F_LO_HZ, 0.5 * self.rate_hz, self.rate_hz)
                      if np.any(pink > 0) else None)

    # -- what is on ----------------------------------------------------------------------------------
    @property
    def active_effects(self) -> list[str]:
        """Names of the effects with non-zero parameters (the `--effects` names of docs/effects.md, plus 'gradient')."""
        names = [e.name for e in self.effects if e.active()]
        if np.any(self.field.drift_nT_per_h) and "drift" not in names:
            names.append("drift")
        if np.any(self.field.gradient_nT_m):
            names.append("gradient")
        if self.field.variation is not None:
            names.append("ambient")
        if np.any(self._temp_lag_s) and "temperature" in names:
            names.append("thermal")
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
            if self._pink is not None:
                out.noise_nT += self._pink.draw(start, stop)
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
        r0, w0, r, w = _attitudes(self.motion, t, t_np)                      # (N, 3, 3), (N, 3), per probe
        pos = self.probes.position_m                                          # (P, 3)
        r_earth = np.einsum("npij,pj->npi", r, pos)
        b_platform = np.einsum("npji,npj->npi", r, self.field.at(t_np, r_earth))
        # d/dt R^T b = -ω x (R^T b) + R^T (db/dt + G^T R (ω x r_k))
        grad_term = np.einsum("ji,npj->npi", self.field.gradient_nT_m,
                              np.einsum("npij,npj->npi", r, np.cross(w, pos)))
        db_platform = -np.cross(w, b_platform) + np.einsum("npji,npj->npi", r, self.field.rate_at(t_np) + grad_term)

        b_sensor = np.einsum("pij,npj->npi", self._to_sensor, b_platform)   # B_s = T^T B_p
        db_sensor = np.einsum("pij,npj->npi", self._to_sensor, db_platform)
        temp = self.temperature.at(t_np) + self.probes.temp_offset_C
        # the effects act on the core's temperature, which lags the probe's (logged) one by temp_lag_s
        core = (temp if not np.any(self._temp_lag_s) else
                self.temperature.core(t_np, self._temp_lag_s) + self.probes.temp_offset_C)
        ctx = EffectContext(t_s=t_np, temp_C=core, dsensor_dt_nT_s=db_sensor)

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

        b_earth0 = self.field.at_origin(t)
        ref = np.linalg.norm(b_earth0, axis=-1) if self.config.reference.enabled else None
        return WorldSamples(
            index=np.full(n, -1, np.int64), t_s=t, t_probe_s=t_np, attitude=r0,
            angular_rate_rad_s=w0, field_earth_nT=b_earth0,
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
                "pink_nT_rtHz": list(cfg.probes[k].pink_nT_rtHz),
                "temp_offset_C": float(pr.temp_offset_C[k]),
                "temp_lag_s": float(self._temp_lag_s[k]),
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
                "variation_nT": cfg.field.variation_nT,
                "variation_periods_s": [cfg.field.variation_min_period_s, cfg.field.variation_max_period_s],
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
