"""The configuration `fit` and `diagnose` take the total field and probe positions from: --config, else the one
a service recording stores (the configuration it ran with, as `replay` uses), said in their header line."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.config import load_section
from drivers.errors import ConfigError

#: the header's words for a configuration taken from the recording
FROM_RECORDING = "configuration from the recording"


@dataclass(frozen=True)
class DataConfig:
    """What fit and diagnose take from a configuration; `origin` None: there was none."""

    total_nT: float | None = None
    positions_m: np.ndarray | None = None
    origin: str | None = None           # FROM_RECORDING, or "configuration from FILE" (--config)
    warning: str | None = None          # a stored configuration that could not be used, and why


def geometry(raw: dict[str, Any], n_probes: int) -> tuple[np.ndarray | None, float | None]:
    """Probe positions (P, 3) and the total field of a raw configuration. The sections used are validated
    strictly ([unit], [[probes]], [estimator], [sim]); the others need not describe a runnable source, but
    unknown section names are still errors (ConfigError, without the file's name)."""
    from service.wiring.config import _SECTIONS, EstimatorConfig, ProbeConfig, UnitConfig

    for key in raw:
        if key not in _SECTIONS:
            raise ConfigError(f"{key}: unknown section (allowed: {', '.join(_SECTIONS)})")
    unit = load_section(UnitConfig, raw.get("unit", {}), "unit")
    total = load_section(EstimatorConfig, raw.get("estimator", {}), "estimator").total_nT
    tables = raw.get("probes", [])
    if not isinstance(tables, list):
        raise ConfigError("probes: expected an array of tables [[probes]]")
    probes = [load_section(ProbeConfig, t, f"probes[{i}]") for i, t in enumerate(tables)]
    positions = None
    if probes:
        if "unit" in raw and len(probes) != unit.n_probes:
            raise ConfigError(f"probes: {len(probes)} [[probes]] tables but unit.n_probes = {unit.n_probes}")
        positions = np.array([p.position_m for p in probes], dtype=np.float64)
    elif "sim" in raw:
        from drivers.sim.config import load_sim_config

        positions = np.array([p.position_m for p in load_sim_config(raw["sim"]).probes], dtype=np.float64)
    if positions is not None and positions.shape[0] != n_probes:
        raise ConfigError(f"probes: {positions.shape[0]} probe positions but the data have {n_probes} probes")
    return positions, total


def stored_config(metadata: dict[str, str], where: str, n_probes: int) -> DataConfig:
    """The total field and probe positions of the configuration a service recording stores (its "fluxcal"
    metadata record's `config`). None of it when the recording stores none (a CSV, `simulate`'s recordings);
    a stored configuration that cannot be read is a warning saying so (the caller says it and counts it), and
    the data are then used as without one."""
    text = metadata.get("config")
    if not text:
        return DataConfig()
    try:
        raw = json.loads(text)
        if not isinstance(raw, dict):
            raise ConfigError(f"expected a table, got {type(raw).__name__}")
        positions, total = geometry(raw, n_probes)
    except (ValueError, ConfigError) as e:
        return DataConfig(warning=f"{where}: its stored configuration cannot be used ({e}): the total field and "
                                  f"probe positions are not taken from it; give them with --config FILE")
    return DataConfig(total, positions, FROM_RECORDING)


def spread(positions_m: Any) -> np.ndarray | None:
    """Probe positions that tell the probes apart (None when there are none, or all are at one point)."""
    if positions_m is None:
        return None
    pos = np.asarray(positions_m, float)
    return pos if np.ptp(pos, axis=0).any() else None
