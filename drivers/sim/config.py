"""The [sim] section: the simulated unit's world (field, motion, probes, effects, faults), validated.

Every parameter is in physical units and named with its unit. `load_sim_config(table)` checks a
TOML table strictly (fluxcal.drivers.config): an unknown key or a bad value is a ConfigError naming the key.

    [sim]                  seed, rate_hz, duration_s, realtime, speed, lsb_nT, range_nT, seq_start, t_us_start, can_base_id
    [sim.field]            total_nT, inclination_deg, declination_deg, gradient_nT_m, drift_nT_per_h  (NED)
    [sim.reference]        enabled, noise_nT                  (scalar total-field reference, ref_total)
    [sim.track]            enabled, latitude_deg, longitude_deg, altitude_start_m, climb_m_s, year  (a platform that
                           climbs through the main field: the World Magnetic Model along it, and lat/lon/alt columns)
    [sim.motion]           kind = "static" | "turntable" | "tumble" | "grid", and its parameters
    [sim.temperature]      start_C, ramp_C_per_h, amplitude_C, period_s, reference_C
    [sim.faults]           wire faults (serial and CAN) and flagged samples
    [[sim.probes]]         one table per probe: position, paper-001 errors, noise, effect parameters

>>> cfg = load_sim_config({"rate_hz": 100.0, "probes": [{"position_m": [0.2, 0.0, 0.0]}]})
>>> cfg.rate_hz, len(cfg.probes), cfg.probes[0].name
(100.0, 1, 's1')
>>> load_sim_config({"probes": [{"scael": [1, 1, 1]}]})  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
fluxcal.drivers.errors.ConfigError: sim.probes[0].scael: unknown key (allowed: name, position_m, scale, nonorth_deg, ...)
"""

from __future__ import annotations

import copy
import warnings
from dataclasses import asdict, dataclass
from typing import Any

from ..config import load_section, spec
from ..errors import ConfigError
from ..icd import MAX_PROBES

AXES = ("x", "y", "z")
#: the most samples one run may have (duration_s x rate_hz): `fluxcal simulate` writes each as a line of a
#: file (about 100 bytes in a CSV), and the fault record keeps one number per fault
MAX_RUN_SAMPLES = 10**9
MOTION_KINDS = ("static", "turntable", "tumble", "grid")


def _zeros3() -> list[float]:
    return [0.0, 0.0, 0.0]


def _zeros33() -> list[list[float]]:
    return [[0.0, 0.0, 0.0] for _ in range(3)]


def _check_3x3(value: list[list[float]], key: str) -> None:
    if len(value) != 3 or any(len(row) != 3 for row in value):
        shape = f"{len(value)} rows of lengths {[len(r) for r in value]}"
        raise ConfigError(f"{key}: expected a 3x3 matrix (3 lists of 3 numbers), got {shape}")


@dataclass
class FieldConfig:
    """The ambient field at the site, in the earth frame NED (x north, y east, z down)."""

    total_nT: float = spec(50000.0, min=0.0, max=1.0e6, doc="total field |B| at the platform origin")
    inclination_deg: float = spec(60.0, min=-90.0, max=90.0, doc="dip below the horizontal, positive down")
    declination_deg: float = spec(0.0, min=-180.0, max=180.0, doc="east of true north")
    gradient_nT_m: list[list[float]] = spec(default_factory=_zeros33,
                                            doc="uniform site gradient G[i][j] = dB_j/dx_i, NED, nT/m")
    drift_nT_per_h: list[float] = spec(default_factory=_zeros3, length=3, doc="slow ambient change per NED axis")
    variation_nT: float = spec(0.0, min=0.0, max=1.0e5,
                               doc="ambient variation (geomagnetic activity, nearby traffic): RMS per NED axis of a "
                                   "random field change common to all probes, 1/f spectrum between the two periods")
    variation_min_period_s: float = spec(60.0, min=1e-3, max=1.0e7, doc="shortest period of the ambient variation")
    variation_max_period_s: float = spec(14400.0, min=1e-3, max=1.0e8, doc="longest period of the ambient variation")

    def validate(self, path: str) -> None:
        if self.variation_max_period_s <= self.variation_min_period_s:
            raise ConfigError(f"{path}.variation_max_period_s: {self.variation_max_period_s!r} is not allowed "
                              f"(allowed: longer than variation_min_period_s = {self.variation_min_period_s!r})")
        _check_3x3(self.gradient_nT_m, f"{path}.gradient_nT_m")
        g = self.gradient_nT_m
        scale = max(1.0, max(abs(v) for row in g for v in row))
        asym = max(abs(g[i][j] - g[j][i]) for i in range(3) for j in range(3))
        trace = g[0][0] + g[1][1] + g[2][2]
        if asym > 1e-6 * scale or abs(trace) > 1e-6 * scale:
            # Maxwell in a source-free region: curl B = 0 (symmetric) and div B = 0 (traceless)
            warnings.warn(f"{path}.gradient_nT_m is not symmetric and traceless (asymmetry {asym:g} nT/m, "
                          f"trace {trace:g} nT/m): no source-free field has such a gradient", UserWarning,
                          stacklevel=2)


@dataclass
class ReferenceConfig:
    """A scalar magnetometer (proton / optically pumped) at the platform origin: ref_total."""

    enabled: bool = spec(False)
    noise_nT: float = spec(0.01, min=0.0, max=1.0e4, doc="Gaussian noise of the reference, 1 sigma")


@dataclass
class TrackConfig:
    """A platform climbing (or descending) straight up through the main field: the field at the platform origin is
    the World Magnetic Model (pygeomag) at its position and date, in place of [sim.field]'s total, inclination and
    declination (its gradient, drift and variation still add); the samples carry lat_deg, lon_deg, alt_m."""

    enabled: bool = spec(False)
    latitude_deg: float = spec(51.0, min=-89.0, max=89.0, doc="geodetic latitude of the climb")
    longitude_deg: float = spec(0.0, min=-180.0, max=180.0, doc="longitude of the climb")
    altitude_start_m: float = spec(0.0, min=-1000.0, max=800000.0, doc="height above the WGS84 ellipsoid at t = 0")
    climb_m_s: float = spec(0.0, min=-10000.0, max=10000.0, doc="rate of climb (negative: descent)")
    year: float = spec(2026.0, min=2010.0, max=2030.0, doc="decimal year of the flight (the model's date)")


@dataclass
class MotionConfig:
    """Platform attitude over time (the platform frame relative to NED)."""

    kind: str = spec("turntable", choices=MOTION_KINDS)
    initial_deg: list[float] = spec(default_factory=_zeros3, length=3, min=-360.0, max=360.0,
                                    doc="heel (about x), pitch (about y), azimuth (about z) at t = 0: "
                                        "R0 = Rz(azimuth) Ry(pitch) Rx(heel)")
    axes: list[str] = spec(["z", "y", "x"], choices=AXES,
                           doc="turntable: platform axes turned in sequence; grid: nesting, fastest first")
    rate_deg_s: float = spec(30.0, min=1e-6, max=36000.0, doc="turntable rate / tumbling angular rate")
    turns: int = spec(1, min=1, max=1000, doc="turntable: whole turns about each axis")
    dwell_s: float = spec(1.0, min=0.0, max=1.0e6, doc="turntable: pause before each axis' turns")
    ramp_s: float = spec(0.0, min=0.0, max=1.0e4, doc="turntable: raised-cosine speed ramp at start and stop")
    tumble_period_s: float = spec(10.0, min=0.01, max=1.0e6, doc="tumble: how fast the rotation wanders")
    steps_per_turn: int = spec(12, min=1, max=3600, doc="grid: attitudes per turn (12 = 30 degree steps)")
    hold_s: float = spec(0.5, min=1e-6, max=1.0e6, doc="grid: time at each attitude")

    def validate(self, path: str) -> None:
        if not self.axes:
            raise ConfigError(f"{path}.axes: expected at least one axis (allowed: 'x', 'y', 'z')")
        if self.kind == "turntable" and self.ramp_s > 0:
            turn_s = 360.0 * self.turns / self.rate_deg_s
            if turn_s < self.ramp_s:
                raise ConfigError(f"{path}.ramp_s: {self.ramp_s!r} is longer than one axis' turns "
                                  f"({turn_s:g} s at rate_deg_s = {self.rate_deg_s:g}); lower ramp_s")


@dataclass
class TemperatureConfig:
    """Platform temperature over time: start + ramp + sinusoid (each probe adds its temp_offset_C)."""

    start_C: float = spec(20.0, min=-100.0, max=200.0)
    ramp_C_per_h: float = spec(0.0, min=-1000.0, max=1000.0)
    amplitude_C: float = spec(0.0, min=0.0, max=200.0, doc="sinusoid amplitude")
    period_s: float = spec(600.0, min=1e-3, max=1.0e9, doc="sinusoid period")
    reference_C: float = spec(20.0, min=-100.0, max=200.0,
                              doc="temperature at which scale and offset take their nominal values")


@dataclass
class FaultConfig:
    """Faults injected on the wire (serial bytes, CAN frames) and flagged samples; all off by default.

    Each fraction is the probability per frame (per CAN frame for can_drop_fraction), drawn
    reproducibly from the seed. The emitters keep a record of exactly what they corrupted."""

    garbage_fraction: float = spec(0.0, min=0.0, max=1.0, doc="serial: random bytes inserted after a frame")
    garbage_max_bytes: int = spec(16, min=1, max=4096)
    bitflip_fraction: float = spec(0.0, min=0.0, max=1.0, doc="serial: one bit of the frame flipped")
    drop_byte_fraction: float = spec(0.0, min=0.0, max=1.0, doc="serial: one byte of the frame lost")
    drop_frame_fraction: float = spec(0.0, min=0.0, max=1.0, doc="serial: whole frame never sent")
    can_drop_fraction: float = spec(0.0, min=0.0, max=1.0, doc="CAN: one axis frame never sent")
    outage_at_s: list[float] = spec(default_factory=list, min=0.0,
                                    doc="times (s from start) the port closes (pty closed, CAN silent)")
    outage_s: float = spec(1.0, min=0.0, max=1.0e6, doc="how long each outage lasts")
    temp_invalid_fraction: float = spec(0.0, min=0.0, max=1.0, doc="samples flagged temperature-invalid")
    duplicate_fraction: float = spec(0.0, min=0.0, max=1.0, doc="serial: a frame sent twice, bit for bit")
    stale_fraction: float = spec(0.0, min=0.0, max=1.0,
                                 doc="serial: after a frame, the one stale_frames before it sent again (the "
                                     "counter and clock step back)")
    stale_frames: int = spec(5, min=1, max=1000, doc="how far back a stale frame is")
    restart_at_s: list[float] = spec(default_factory=list, min=0.0,
                                     doc="times (s from start) the unit restarts: counter and clock back to 0")
    silence_at_s: list[float] = spec(default_factory=list, min=0.0,
                                     doc="times (s from start) the unit falls silent, the port staying open")
    silence_s: float = spec(1.0, min=0.0, max=1.0e6, doc="how long each silence lasts")
    wrong_baud_at_s: list[float] = spec(default_factory=list, min=0.0,
                                        doc="serial: times the bytes start arriving garbled, as read at a wrong "
                                            "baud rate (no frame decodes)")
    wrong_baud_s: float = spec(1.0, min=0.0, max=1.0e6, doc="how long each such stretch lasts")
    reserved_flag_fraction: float = spec(0.0, min=0.0, max=1.0,
                                         doc="samples with flag bit 3 set, which the ICD says is 0")
    full_scale_fraction: float = spec(0.0, min=0.0, max=1.0,
                                      doc="samples whose probe-1 x reads one count inside the positive rail")
    zero_vector_fraction: float = spec(0.0, min=0.0, max=1.0, doc="samples whose last probe reads (0, 0, 0)")
    temp_rail_fraction: float = spec(0.0, min=0.0, max=1.0,
                                     doc="samples whose probe-1 temperature reads the int16 rail, 327.67 degC")

    def validate(self, path: str) -> None:
        for key, length in (("outage_at_s", "outage_s"), ("silence_at_s", "silence_s"),
                            ("wrong_baud_at_s", "wrong_baud_s")):
            at, span = getattr(self, key), getattr(self, length)
            if any(b <= a for a, b in zip(at, at[1:])):
                raise ConfigError(f"{path}.{key}: {at!r} must be increasing")
            if any(a + span > b for a, b in zip(at, at[1:])):
                raise ConfigError(f"{path}.{key}: stretches of {length} = {span:g} s overlap")
        if any(b <= a for a, b in zip(self.restart_at_s, self.restart_at_s[1:])):
            raise ConfigError(f"{path}.restart_at_s: {self.restart_at_s!r} must be increasing")


@dataclass
class ProbeSimConfig:
    """One three-axis probe: where it sits, its paper-001 errors, its noise and its effect parameters.

    Forward model ([FastRotation] eq. 4, 5, 11): raw = C A (Tα Tβ Tγ)^T B_platform + offset, with
    C = diag(scale), A from nonorth_deg = [φ, θ, ψ], Tα/Tβ/Tγ from misalign_deg = [α, β, γ].
    """

    name: str = spec("", doc="defaults to s<k>")
    position_m: list[float] = spec(default_factory=_zeros3, length=3, min=-100.0, max=100.0,
                                   doc="probe centre in the platform frame")
    scale: list[float] = spec([1.0, 1.0, 1.0], length=3, min=0.01, max=100.0,
                               doc="c_x, c_y, c_z ([FastRotation] eq. 11)")
    nonorth_deg: list[float] = spec(default_factory=_zeros3, length=3, min=-45.0, max=45.0,
                                    doc="φ, θ, ψ non-orthogonality angles ([FastRotation] eq. 11)")
    misalign_deg: list[float] = spec(default_factory=_zeros3, length=3, min=-180.0, max=180.0,
                                     doc="α heel (x), β pitch (y), γ azimuth (z) ([FastRotation] eq. 4-5)")
    offset_nT: list[float] = spec(default_factory=_zeros3, length=3, min=-1.0e6, max=1.0e6)
    noise_nT: list[float] | float = spec(0.0, length=3, min=0.0, max=1.0e5,
                                         doc="Gaussian noise per axis, 1 sigma; one number or three")
    pink_nT_rtHz: list[float] | float = spec(0.0, length=3, min=0.0, max=1.0e5,
                                             doc="1/f noise per axis: its density at 1 Hz, nT/sqrt(Hz), from 0.1 mHz "
                                                 "to the Nyquist frequency (fluxgates: 0.005-0.1); one number or three")
    temp_offset_C: float = spec(0.0, min=-100.0, max=100.0, doc="this probe's temperature minus the profile")
    temp_lag_s: float = spec(0.0, min=0.0, max=1.0e5,
                             doc="thermal lag: the core follows this probe's temperature with this time constant, s "
                                 "(the temperature effect acts on the core's; the logged one is the probe's)")
    temp_offset_nT_per_C: list[float] = spec(default_factory=_zeros3, length=3, min=-1.0e4, max=1.0e4,
                                             doc="temperature effect: offset change per degC")
    temp_scale_ppm_per_C: list[float] = spec(default_factory=_zeros3, length=3, min=-1.0e5, max=1.0e5,
                                             doc="temperature effect: scale-factor change per degC")
    eddy_s: list[list[float]] = spec(default_factory=_zeros33, min=-10.0, max=10.0,
                                     doc="eddy effect: 3x3 matrix on dB/dt in the probe frame")
    lag_s: float = spec(0.0, min=-10.0, max=10.0, doc="lag effect: the probe is sampled at t + lag_s")
    nonlin_quadratic_per_nT: list[float] = spec(default_factory=_zeros3, length=3, min=-1.0, max=1.0,
                                                doc="nonlinearity: q in u + q u^2 + c u^3, u in nT")
    nonlin_cubic_per_nT2: list[float] = spec(default_factory=_zeros3, length=3, min=-1.0, max=1.0,
                                             doc="nonlinearity: c in u + q u^2 + c u^3, u in nT")
    drift_offset_nT_per_h: list[float] = spec(default_factory=_zeros3, length=3, min=-1.0e6, max=1.0e6,
                                              doc="drift effect: offset change per hour")

    def validate(self, path: str) -> None:
        _check_3x3(self.eddy_s, f"{path}.eddy_s")
        if not isinstance(self.noise_nT, list):
            self.noise_nT = [float(self.noise_nT)] * 3
        if not isinstance(self.pink_nT_rtHz, list):
            self.pink_nT_rtHz = [float(self.pink_nT_rtHz)] * 3


def _default_probes() -> list[ProbeSimConfig]:
    probes = [ProbeSimConfig(name="s1", position_m=[-0.25, 0.0, 0.0]),
              ProbeSimConfig(name="s2", position_m=[0.25, 0.0, 0.0])]
    for p in probes:
        p.validate("")
    return probes


@dataclass
class SimConfig:
    """The whole simulated unit: sampling, digitisation, world and probes."""

    seed: int = spec(1, min=0, max=2**63 - 1, doc="every random number derives from it")
    rate_hz: float = spec(200.0, min=0.01, max=100000.0, doc="sample rate")
    duration_s: float = spec(60.0, min=0.0, max=1.0e9, doc="length of the run; 0 = until closed")
    realtime: bool = spec(False, doc="pace by the wall clock (true) or as fast as possible (false)")
    speed: float = spec(1.0, min=0.001, max=1.0e4,
                        doc="with realtime: seconds of the unit's time per second of the wall clock (a demo at 3)")
    lsb_nT: float = spec(0.001, min=1e-9, max=1e3, doc="nT per ADC count; must equal unit.lsb_nT")
    range_nT: float | None = spec(None, min=1.0, max=1.0e9,
                                  doc="probe range: beyond it an axis saturates (omit: int32 limits only)")
    seq_start: int = spec(0, min=0, max=65535, doc="first frame's seq (to force a wrap early)")
    t_us_start: int = spec(0, min=0, max=2**32 - 1, doc="unit clock at the first sample, us")
    can_base_id: int = spec(0x200, min=0, max=0x7FF, doc="CAN base identifier B (ids B + 4k + axis)")
    field: FieldConfig = spec(default_factory=FieldConfig)
    reference: ReferenceConfig = spec(default_factory=ReferenceConfig)
    track: TrackConfig = spec(default_factory=TrackConfig)
    motion: MotionConfig = spec(default_factory=MotionConfig)
    temperature: TemperatureConfig = spec(default_factory=TemperatureConfig)
    faults: FaultConfig = spec(default_factory=FaultConfig)
    probes: list[ProbeSimConfig] = spec(default_factory=_default_probes)

    def validate(self, path: str) -> None:
        if self.duration_s * self.rate_hz > MAX_RUN_SAMPLES:
            n, top = self.duration_s * self.rate_hz, MAX_RUN_SAMPLES / self.rate_hz
            raise ConfigError(f"{path}.duration_s: {self.duration_s:g} is not allowed: {n:.3g} samples at rate_hz = "
                              f"{self.rate_hz:g} (allowed: up to {top:.6g} s at this rate, at most "
                              f"{MAX_RUN_SAMPLES:.0e} samples a run; 0 runs until stopped)")
        n = len(self.probes)
        if not 1 <= n <= MAX_PROBES:
            raise ConfigError(f"{path}.probes: {n} [[{path}.probes]] tables (allowed: 1..{MAX_PROBES})")
        for k, p in enumerate(self.probes):
            if not p.name:
                p.name = f"s{k + 1}"
        names = [p.name for p in self.probes]
        if len(set(names)) != n:
            raise ConfigError(f"{path}.probes: names must differ, got {names}")
        top_id = self.can_base_id + 4 * (n - 1) + 2
        if top_id > 0x7FF:
            raise ConfigError(f"{path}.can_base_id: {self.can_base_id:#x} with {n} probes needs id {top_id:#x}, "
                              f"beyond the 11-bit limit 0x7ff; lower can_base_id")

    @property
    def n_probes(self) -> int:
        return len(self.probes)

    @property
    def n_samples(self) -> int | None:
        """Samples in the run, or None when it runs until closed (duration_s = 0)."""
        if self.duration_s == 0:
            return None
        return max(1, int(round(self.duration_s * self.rate_hz)))

    def as_dict(self) -> dict[str, Any]:
        """The configuration as a plain table that `load_sim_config` accepts again (None keys left out)."""
        return _drop_none(asdict(self))


def _drop_none(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _drop_none(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [_drop_none(v) for v in obj]
    return obj


def load_sim_config(table: Any, path: str = "sim") -> SimConfig:
    """Build a SimConfig from the [sim] TOML table; ConfigError names the key, value and what is allowed."""
    return load_section(SimConfig, copy.deepcopy(table), path)


#: the built-in world of `fluxcal simulate` without --config; configs/sim-gradiometer.toml has the same
#: [sim] tables with every key commented (tests/wiring/test_simulate_cli.py checks they agree)
GRADIOMETER: dict[str, Any] = {
    "seed": 2024,
    "rate_hz": 200.0,
    "duration_s": 60.0,
    "realtime": True,
    "lsb_nT": 0.001,
    "field": {"total_nT": 52500.0, "inclination_deg": 52.8, "declination_deg": -3.6,
              "gradient_nT_m": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]],
              "drift_nT_per_h": [0.0, 0.0, 0.0]},
    "reference": {"enabled": True, "noise_nT": 0.05},
    "motion": {"kind": "tumble", "rate_deg_s": 20.0, "tumble_period_s": 8.0},
    "temperature": {"start_C": 22.0, "ramp_C_per_h": 0.0, "amplitude_C": 0.0, "reference_C": 20.0},
    "probes": [
        {"name": "s1", "position_m": [-0.25, 0.0, 0.0], "scale": [1.021, 0.984, 1.012],
         "nonorth_deg": [0.8, -1.4, 2.1], "misalign_deg": [1.5, -2.2, 3.1],
         "offset_nT": [215.0, -340.0, 120.0], "noise_nT": 0.6},
        {"name": "s2", "position_m": [0.25, 0.0, 0.0], "scale": [0.973, 1.035, 0.991],
         "nonorth_deg": [-1.1, 0.6, -2.7], "misalign_deg": [-2.4, 1.8, -1.2],
         "offset_nT": [-180.0, 265.0, 390.0], "noise_nT": 0.8},
    ],
}
