"""The simulated unit (drivers/sim/): its samples straight from the simulated world in process ("direct"), or
through another kind's transport (a pty, a CAN bus), where that kind's driver reads it and keeps its counters."""

from __future__ import annotations

from ..declare import Counted, SourceKind, Transport
from ._icd import icd_samples, picked

KIND = SourceKind(
    "sim", "the simulated unit, its world in the [sim] section",
    config="fluxcal.drivers.sim.source:SimSourceConfig",
    factory="fluxcal.drivers.sim.source:open_source",
    opener="fluxcal.drivers.sim.source:open_configured",
    counters=(Counted("frames_accepted", "samples the simulated unit gave (one frame each)", decoded=True,
                      what="{n:,} sample(s) the simulated unit gave"),)
    + picked(icd_samples(""), "saturated_axes", "temp_invalid"),
    transports=(Transport("direct", "the simulated unit's samples in process: no wire, no wire faults"),),
    unit_clock=True,
    runs_world=True,
    default=True,
)
