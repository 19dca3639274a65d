"""Whether a calibration may be this unit's, beyond its physics (fluxcal.service.numerics.calib.plausible): who it was made
for, what this unit's calibrations have been, and what it does to this unit's own data.

    unit         the unit's name it carries ("unit", or the unit a service learned it on) is this one's
    probe serial the serial numbers it carries for the probes are this unit's ([[probes]] serial)
    history      without data to judge it yet, its offsets are within calibration.max_offset_change_nT of the
                 calibration in use: the offsets of a unit's calibrations are its probes' fingerprint where no
                 serial number says (another unit's probes sit thousands of nT away)
    data         on the service's window it leaves a residual the gate would accept (estimator.gate_rms_nT), or at
                 least not far above what the calibration in use leaves: the gate's own figures

The red team's case: another unit's calibration (the same probe names, as every example configuration has; offsets
5,000 nT away; "unit": "grad2") was applied, held, persisted and reloaded; the error went from 0.75 to ~8,000 nT.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from fluxcal.service.numerics.calib.plausible import ImplausibleCalibration

from .config import FluxcalConfig


def unit_identity(cfg: FluxcalConfig) -> dict[str, Any]:
    """What a calibration made by or for this unit carries: its name and its probes' serial numbers (if given)."""
    serials = {p.name: p.serial for p in cfg.probes if p.serial}
    return {"name": cfg.unit.name, **({"probes": serials} if serials else {})}


def made_for(cal: Any) -> dict[str, Any]:
    """The unit a calibration says it was made for: its "unit", else the unit a service learned it on."""
    if cal.unit:
        return dict(cal.unit)
    learned = cal.diagnostics.get("learned_on")
    return {"name": str(learned["unit"])} if isinstance(learned, dict) and learned.get("unit") else {}


def check_identity(cal: Any, cfg: FluxcalConfig) -> None:
    """ImplausibleCalibration naming the unit or the probe a calibration was made for, when not this unit's."""
    theirs, ours = made_for(cal), unit_identity(cfg)
    name = theirs.get("name")
    if name and name != ours["name"]:
        raise ImplausibleCalibration("unit", f"it was made for unit {name!r}, this is unit {ours['name']!r} (to use "
                                             f"another unit's calibration knowingly, remove its \"unit\" first)")
    for probe, serial in (theirs.get("probes") or {}).items():
        mine = ours.get("probes", {}).get(probe)
        if mine and serial != mine:
            raise ImplausibleCalibration("probe serial", f"{probe}: it was made for the probe with serial "
                                                         f"{serial!r}, this unit's {probe} is {mine!r} "
                                                         f"([[probes]] serial)")


def recording_identity(metadata: dict[str, str]) -> dict[str, Any]:
    """The unit a fluxcal recording was made by (its "fluxcal" metadata: the unit, the stored configuration's probe
    serial numbers), for the calibration fitted on it; {} for data that do not say (a CSV, a foreign log)."""
    name = metadata.get("unit")
    if not name:
        return {}
    try:
        probes = json.loads(metadata.get("config") or "{}").get("probes") or []
        serials = {str(p["name"]): str(p["serial"]) for p in probes if isinstance(p, dict) and p.get("serial")}
    except (ValueError, AttributeError, KeyError, TypeError):
        serials = {}
    return {"name": str(name), **({"probes": serials} if serials else {})}


def judge_on_data(cal: Any, pipeline: Any, cfg: FluxcalConfig) -> str:
    """Refuse (ImplausibleCalibration "data" or "history") a calibration that the service's own data, or without
    enough of them its calibration in use, say is not this unit's; else what it was judged on."""
    ring, gate, in_use = pipeline.ring, pipeline.gate, pipeline.calibration
    if len(ring) < cfg.estimator.min_samples:
        if in_use is not None:
            jump = np.abs(cal.offsets() - in_use.offsets()).max(axis=1)
            k = int(np.argmax(jump))
            limit = cfg.calibration.max_offset_change_nT
            if jump[k] > limit:
                raise ImplausibleCalibration("history", f"{cal.probes[k].name}: its offsets differ from the "
                                             f"calibration in use by {jump[k]:.4g} nT (at most {limit:g} nT "
                                             f"without data to judge it: calibration.max_offset_change_nT); the "
                                             f"service has {len(ring)} of the {cfg.estimator.min_samples} samples "
                                             f"it judges a calibration on: apply it again once it has them")
        return f"not judged on data yet ({len(ring)} of the {cfg.estimator.min_samples} samples needed)"
    why = gate.fails_on_data(cal, ring, in_use)
    if why:
        raise ImplausibleCalibration("data", f"{why}: not this unit's")
    return f"judged on the last {len(ring)} samples"
