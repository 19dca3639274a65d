"""Replay: the raw blocks a fluxcal MCAP recording holds, bit for bit (drivers/mcap_source.py), counted as the live
source counted them."""

from __future__ import annotations

from ..declare import Counted, SourceKind
from ._icd import icd_samples, picked

KIND = SourceKind(
    "replay", "a fluxcal MCAP recording (a file, or a folder of rotated files), its raw blocks as recorded",
    config="fluxcal.drivers.mcap_source:ReplayConfig",
    factory="fluxcal.drivers.mcap_source:open_source",
    counters=(Counted("frames_accepted", "recorded samples read", decoded=True, what="{n:,} recorded sample(s) read"),)
    + picked(icd_samples(""), "seq_gaps", "samples_missed", "saturated_axes", "temp_invalid"),
    path_keys=("path",),
    unit_clock=True,
    needs_rate=True,
)
