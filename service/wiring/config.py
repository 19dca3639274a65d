"""The service's TOML configuration: every section validated at start, strictly.

    [unit]        name, n_probes, lsb_nT
    [[probes]]    name, position_m (platform frame; needed for tensor components)
    [source]      kind (required in a file: a kind fluxcal.drivers.registry declares, docs/sources.md), then its keys
    [sim]         the simulated unit's world (fluxcal.drivers.sim.config)
    [estimator]   the online estimator and its quality gate
    [calibration] where the calibration persists, and an optional one to start from
    [zenoh]       session mode and endpoints (fluxcal.service.io.bus.ZenohConfig)
    [mcap]        recording directory, rotation, chunking

An error names the key, the value and what is allowed (fluxcal.drivers.config).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fluxcal.drivers.config import load_section, read_toml, spec
from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.registry import allowed, default_kind, source_kind
from fluxcal.service.numerics.calib.site import site_from_text

_UNIT_NAME = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")
_SERIAL = re.compile(r"^[A-Za-z0-9_.:/+\-]{0,64}$")


@dataclass
class UnitConfig:
    name: str = spec("unit1", doc="key segment in fluxcal/<unit>/...: letters, digits, _ and -")
    n_probes: int = spec(2, min=1, max=8)
    lsb_nT: float = spec(0.001, min=1e-9, max=1e3, doc="nT per ADC count")
    block_ms: float = spec(8.0, min=0.0, max=1000.0,
                           doc="input is gathered into blocks of about this long before it is processed, "
                               "recorded and published: latency against CPU")
    status_s: float = spec(10.0, min=0.1, max=3600.0, doc="`fluxcal run` says a status line on stderr this often")
    silence_s: float = spec(5.0, min=0.5, max=86400.0,
                            doc="nothing from the unit for this long is said (console, health, dashboard), and its end")
    duplicate: str = spec("refuse", choices=("refuse", "suffix"),
                          doc="when another live service holds this unit's name on the Zenoh network: refuse to "
                              "start, naming it, or serve as <name>-2, <name>-3, ...")

    def validate(self, path: str) -> None:
        if not _UNIT_NAME.match(self.name):
            raise ConfigError(f"{path}.name: {self.name!r} is not allowed (allowed: 1-64 letters, digits, '_' or '-')")


@dataclass
class ProbeConfig:
    name: str = spec("")
    position_m: list[float] = spec([0.0, 0.0, 0.0], length=3, min=-100.0, max=100.0)
    serial: str = spec("", doc="the probe's serial number: its calibrations carry it, and one made for another "
                               "probe is refused (letters, digits and . _ - : / +)")

    def validate(self, path: str) -> None:
        if not _SERIAL.match(self.serial):
            raise ConfigError(f"{path}.serial: {self.serial!r} is not allowed (allowed: up to 64 letters, digits "
                              f"and . _ - : / +)")


@dataclass
class EstimatorConfig:
    method: str = spec("rls", choices=("rls",))
    forgetting: float = spec(0.9995, min=0.9, max=1.0, doc="RLS forgetting factor per sample")
    total_nT: float | None = spec(None, min=1000.0, max=200000.0,
                                  doc="ambient total field (a coil system's too: up to 200,000 nT, where the Earth's "
                                      "is 22,000-67,000); omit to use ref_total from the source or estimate it")
    site: str | None = spec(None, doc="LAT,LON[,ALT_M[,DATE]]: the total field from the World Magnetic Model at the "
                                      "site, for a unit without a scalar magnetometer (instead of total_nT)")
    align: str = spec("rotation", choices=("rotation", "regression", "none"))
    min_samples: int = spec(2000, min=20, max=10**9)
    gate_coverage: float = spec(0.3, min=0.0, max=1.0, doc="fraction of direction bins that must be seen")
    gate_condition: float = spec(1e3, min=1.0)
    gate_rms_nT: float = spec(20.0, min=0.0, doc="largest scalar residual RMS accepted")
    update_every_s: float = spec(0.5, min=0.001, max=60.0,
                                 doc="the estimator takes samples in chunks this long (of data time)")
    check_every_s: float = spec(5.0, min=0.05, max=86400.0,
                                doc="how often the online estimate is checked against the gate")
    window_s: float = spec(60.0, min=1.0, doc="ring buffer length for alignment and the error metric; bounded by "
                                              "memory at the unit's rate and probe count (check_window_memory)")

    def validate(self, path: str) -> None:
        if self.site is None:
            return
        if self.total_nT is not None:
            raise ConfigError(f"{path}.site: {self.site!r} is not allowed beside {path}.total_nT (allowed: one of them)")
        self.total_nT = site_from_text(self.site, f"{path}.site").total_nT


@dataclass
class CalibrationConfig:
    file: str = spec("", doc="where the calibration in use persists (relative paths: to the configuration's "
                             "directory); default state/<unit>-<source kind>-cal.json")
    initial: str | None = spec(None, doc="start from this calibration file instead of learning from scratch (even "
                                         "one learned on another unit or source: you say so by naming it)")
    # what a calibration may be and still be applied, reloaded or started from (fluxcal.service.numerics.calib.plausible)
    max_offset_nT: float = spec(1e6, min=1.0, max=1e9, doc="largest offset a calibration may hold on any axis")
    max_condition: float = spec(10.0, min=1.0, max=1e6, doc="largest condition number of a calibration's matrix")
    max_scale: float = spec(2.0, min=1.0, max=100.0,
                            doc="a calibration's matrix may scale the field by 1/max_scale to max_scale")
    min_total_nT: float = spec(1000.0, min=0.0, max=1e7, doc="smallest total field a calibration may name")
    max_total_nT: float = spec(200000.0, min=1.0, max=1e9, doc="largest total field a calibration may name")
    max_offset_change_nT: float = spec(2000.0, min=1.0, max=1e9,
                                       doc="before the service has seen estimator.min_samples to judge an applied "
                                           "calibration on, one whose offsets differ from the calibration in use by "
                                           "more than this is refused (another unit's probes); after, the data judge")

    def validate(self, path: str) -> None:
        if not self.min_total_nT < self.max_total_nT:
            raise ConfigError(f"{path}.min_total_nT: {self.min_total_nT!r} is not allowed (allowed: below "
                              f"{path}.max_total_nT = {self.max_total_nT!r})")

    def limits(self):
        from fluxcal.service.numerics.calib.plausible import CalibrationLimits

        return CalibrationLimits(max_offset_nT=self.max_offset_nT, max_condition=self.max_condition,
                                 max_scale=self.max_scale, min_total_nT=self.min_total_nT,
                                 max_total_nT=self.max_total_nT)


@dataclass
class EffectsConfig:
    plugins: list[str] = spec(default_factory=list,
                              doc="effects of your own the service loads at start, as FILE.py:ClassName (relative "
                                  "paths: to the configuration's directory) or package.module:ClassName; those that "
                                  "act on each sample alone (per_sample) can then be added with add-effect")


@dataclass
class McapConfig:
    enabled: bool = spec(True)
    dir: str = spec("recordings/live")
    rotate_mb: float = spec(256.0, min=0.01, max=1.0e6)
    rotate_s: float = spec(3600.0, min=1.0, max=1.0e7)
    chunk_kb: int = spec(1024, min=4, max=65536)
    flush_s: float = spec(1.0, min=0.05, max=60.0)


@dataclass
class Ros2Config:
    enabled: bool = spec(False, doc="also write the corrected vectors as a ROS 2 bag (sensor_msgs/msg/MagneticField, "
                                    "MCAP storage, CDR; docs/ros2.md), a new folder under dir at each start")
    dir: str = spec("recordings/ros2", doc="where the bags go (relative paths: to the configuration's directory)")
    raw: bool = spec(False, doc="also write the raw (uncorrected) vectors, on topics of their own")


@dataclass
class FluxcalConfig:
    unit: UnitConfig
    probes: list[ProbeConfig]
    source: Any
    sim: Any
    estimator: EstimatorConfig
    calibration: CalibrationConfig
    zenoh: Any
    mcap: McapConfig
    effects: EffectsConfig = field(default_factory=EffectsConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)
    path: str = ""
    raw: dict = field(default_factory=dict)

    @property
    def probe_names(self) -> list[str]:
        return [p.name for p in self.probes]

    @property
    def positions_m(self) -> list[list[float]]:
        return [p.position_m for p in self.probes]

    @property
    def rate_hz(self) -> float | None:
        """The unit's sample rate, Hz: source.rate_hz, else the simulated unit's; None if neither is set.
        The estimator's durations (window_s, check_every_s, update_every_s) are counted in samples at it."""
        rate = getattr(self.source, "rate_hz", None) or getattr(self.sim, "rate_hz", None)
        return float(rate) if rate else None


#: what the estimator's window and update chunk may take in memory (ring buffer and chunk buffers)
WINDOW_BUDGET_BYTES = 1 << 30


def sample_bytes(n_probes: int) -> int:
    """Bytes one sample of n_probes takes in the ring buffer (fluxcal.drivers.ringbuffer): t, seq, one extra such as
    ref_total (8 each), flags (1), and per probe three axes and a temperature (8 each)."""
    return 25 + 32 * n_probes


def check_window_memory(est: EstimatorConfig, rate_hz: float, n_probes: int) -> None:
    """The estimator's window (window_s) and update chunk (update_every_s) counted in samples at the unit's rate:
    at least one sample, and within WINDOW_BUDGET_BYTES together (window_s = 1e12 asked numpy for 1.42 PiB)."""
    per = sample_bytes(n_probes)
    budget = WINDOW_BUDGET_BYTES
    where = f"{n_probes} probe(s) at {rate_hz:g} Hz, {per} bytes a sample"
    chunk = max(1, int(round(est.update_every_s * rate_hz))) * per
    if chunk > budget // 2:
        top = budget // 2 // per / rate_hz
        raise ConfigError(f"estimator.update_every_s: {est.update_every_s:g} is not allowed: {_size(chunk)} a chunk "
                          f"for {where} (allowed: up to {top:.4g} s, a chunk within {_size(budget // 2)})")
    window = est.window_s * rate_hz                        # a float: window_s = 1e308 is no integer overflow
    if window < 1:
        raise ConfigError(f"estimator.window_s: {est.window_s:g} is not allowed: it holds no sample at {rate_hz:g} Hz "
                          f"(allowed: at least {1.0 / rate_hz:.4g} s at this rate)")
    if window * per + chunk > budget:
        top = (budget - chunk) // per / rate_hz
        size = f"{_size(window * per)} in memory" if math.isfinite(window) else "more than any memory holds"
        raise ConfigError(f"estimator.window_s: {est.window_s:g} is not allowed: {window:.4g} samples of {where}, "
                          f"{size} (allowed: up to {top:.6g} s at this rate and probe count: the window and the "
                          f"update chunk within {_size(budget)})")


def _size(n: float) -> str:
    for unit, shift in (("EiB", 60), ("PiB", 50), ("TiB", 40), ("GiB", 30), ("MiB", 20), ("kiB", 10)):
        if n >= 1 << shift:
            return f"{n / (1 << shift):.3g} {unit}"
    return f"{n:.0f} bytes"


_SECTIONS = ("unit", "probes", "source", "sim", "estimator", "calibration", "zenoh", "mcap", "effects", "ros2")

RATE_MISSING = ("source.rate_hz: missing (allowed: the unit's sample rate in Hz, 0.001 to 100000; the estimator's "
                "window_s, check_every_s and update_every_s are counted in samples at this rate)")


def rate_stated(raw: dict) -> bool:
    """Whether a raw configuration states its unit's sample rate where its source kind needs it (its declaration's
    needs_rate): in source.rate_hz or a [sim] rate_hz."""
    src, sim = raw.get("source"), raw.get("sim")
    try:
        kind = source_kind(src.get("kind", default_kind().name) if isinstance(src, dict) else default_kind().name)
    except ConfigError:
        return True                     # an unknown kind is said where the [source] table is read
    if not kind.needs_rate:
        return True
    return (isinstance(src, dict) and "rate_hz" in src) or (isinstance(sim, dict) and "rate_hz" in sim)


def load_config(path: str | Path, *, source_required: bool = True) -> FluxcalConfig:
    """The configuration of a TOML file; its relative paths (calibration.file, calibration.initial, mcap.dir,
    a replay source's path) are taken relative to the file's directory, not the working directory.
    source_required: a configuration that runs a unit must name its source (require_source); one that only
    describes an array for fit (probe positions, the total field) need not, but must not be empty."""
    raw = read_toml(path)
    if source_required:
        require_source(raw, str(path))
    else:
        require_content(raw, str(path))
    cfg = config_from_dict(raw, str(path))
    base = Path(path).resolve().parent

    def here(p: str) -> str:
        return os.path.normpath(base / p)          # absolute paths stay as they are

    cfg.calibration.file = here(cfg.calibration.file)
    check_state_file(cfg.calibration.file, f"{path}: calibration.file")
    if cfg.calibration.initial:
        cfg.calibration.initial = here(cfg.calibration.initial)
    cfg.mcap.dir = here(cfg.mcap.dir)
    cfg.ros2.dir = here(cfg.ros2.dir)
    for key in source_kind(cfg.source.kind).path_keys:
        setattr(cfg.source, key, here(getattr(cfg.source, key)))
    cfg.effects.plugins = [here(p.rpartition(":")[0]) + ":" + p.rpartition(":")[2] if p.rpartition(":")[0].endswith(".py")
                           else p for p in cfg.effects.plugins]
    return cfg


def check_state_file(file: str, key: str) -> None:
    """Where the calibration in use persists must be a file's path: a folder there, or a file where a folder of
    the path should be, is a ConfigError at start (it failed every save, said every 5 s, and the summary at stop
    said no fault)."""
    p = Path(file)
    if p.is_dir():
        raise ConfigError(f"{key}: {file!r} is a folder (allowed: a file's path, e.g. {str(p / 'cal.json')!r}; "
                          f"the calibration in use persists there)")
    for parent in p.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ConfigError(f"{key}: {file!r} is not allowed: {str(parent)!r} is a file, not a folder")
            break


def require_source(raw: dict, path: str) -> None:
    """A configuration file must name its source: an emptied or cut file (or one missing its [source]) is an
    error, never a simulated unit publishing data on the default port. (A dict built in code, such as the
    configuration a recording stores, still defaults to the simulator: config_from_dict.)"""
    src = raw.get("source")
    if isinstance(src, dict) and "kind" in src:
        return
    what = ("the file is empty" if not raw else
            "it has no [source] section" if src is None else "its [source] names no kind")
    raise ConfigError(f"{path}: [source] kind is required (allowed: {allowed()}): {what}; a configuration must say "
                      f"where the data come from (kind = {default_kind().name!r} for {default_kind().doc}; see "
                      f"configs/*.toml and docs/sources.md)")


def require_content(raw: dict, path: str) -> None:
    """A configuration that only describes an array (fit's and diagnose's --config) needs no source, but an
    emptied file gives nothing and is refused, not taken as no configuration."""
    if not raw:
        raise ConfigError(f"{path}: the file is empty (or only comments): --config gives the probe positions "
                          f"([[probes]] position_m) and the total field ([estimator] total_nT); give a configuration "
                          f"that has them, or leave --config out")


def config_from_dict(raw: dict, path: str = "<config>") -> FluxcalConfig:
    def err(msg: str) -> ConfigError:
        return ConfigError(f"{path}: {msg}")

    for key in raw:
        if key not in _SECTIONS:
            raise err(f"{key}: unknown section (allowed: {', '.join(_SECTIONS)})")
    try:
        unit = load_section(UnitConfig, raw.get("unit", {}), "unit")
        probes_raw = raw.get("probes", [])
        if not isinstance(probes_raw, list):
            raise ConfigError("probes: expected an array of tables [[probes]]")
        probes = [load_section(ProbeConfig, t, f"probes[{i}]") for i, t in enumerate(probes_raw)]
        if probes and len(probes) != unit.n_probes:
            raise ConfigError(f"probes: {len(probes)} [[probes]] tables but unit.n_probes = {unit.n_probes}")
        if not probes:
            probes = [ProbeConfig(name=f"s{k + 1}") for k in range(unit.n_probes)]
        for k, pr in enumerate(probes):
            if not pr.name:
                pr.name = f"s{k + 1}"
        names = [p.name for p in probes]
        if len(set(names)) != len(names):
            raise ConfigError(f"probes: names must differ, got {names}")

        src = raw.get("source", {"kind": default_kind().name})   # a recording's stored configuration of an older run
        if not isinstance(src, dict):
            raise ConfigError("source: expected a table")
        decl = source_kind(src.get("kind", default_kind().name))
        source = decl.load(src, "source")
        kind = decl.name
        for attr in ("n_probes",):
            if hasattr(source, attr) and getattr(source, attr) != unit.n_probes:
                raise ConfigError(f"source.{attr}: {getattr(source, attr)!r} differs from unit.n_probes = {unit.n_probes}")

        if not rate_stated(raw):
            raise ConfigError(RATE_MISSING)
        sim = None
        if "sim" in raw or decl.runs_world:
            from fluxcal.drivers.sim.config import load_sim_config

            sim = load_sim_config(raw.get("sim", {}))
            n_sim = len(sim.probes)
            if n_sim != unit.n_probes:
                raise ConfigError(f"sim.probes: {n_sim} simulated probes but unit.n_probes = {unit.n_probes}")
        src_rate = getattr(source, "rate_hz", None)
        if sim is not None and src_rate is not None and abs(src_rate - sim.rate_hz) > 1e-9 * sim.rate_hz:
            raise ConfigError(f"source.rate_hz: {src_rate!r} differs from sim.rate_hz = {sim.rate_hz!r} (allowed: "
                              f"the same rate, or leave source.rate_hz out)")
        estimator = load_section(EstimatorConfig, raw.get("estimator", {}), "estimator")
        rate = src_rate or (sim.rate_hz if sim is not None else None)
        if rate:
            check_window_memory(estimator, float(rate), unit.n_probes)
        calibration = load_section(CalibrationConfig, raw.get("calibration", {}), "calibration")
        if not calibration.file:
            # one file per unit and source kind: a calibration learned on the simulator never meets hardware
            calibration.file = f"state/{unit.name}-{kind}-cal.json"
        from fluxcal.service.io.bus import ZenohConfig

        zenoh_cfg = load_section(ZenohConfig, raw.get("zenoh", {}), "zenoh")
        mcap = load_section(McapConfig, raw.get("mcap", {}), "mcap")
        effects = load_section(EffectsConfig, raw.get("effects", {}), "effects")
        ros2 = load_section(Ros2Config, raw.get("ros2", {}), "ros2")
    except ConfigError as e:
        raise err(str(e)) from None
    return FluxcalConfig(unit=unit, probes=probes, source=source, sim=sim, estimator=estimator,
                         calibration=calibration, zenoh=zenoh_cfg, mcap=mcap, effects=effects, ros2=ros2, path=path,
                         raw=raw)
