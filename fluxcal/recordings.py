"""Recordings (docs/recording.md): read one whole (its raw and corrected streams, commands, health), repair one a
killed writer left without its footer, decode its channels with the mcap package, load any file into samples.

>>> from fluxcal.recordings import read_recording
>>> read_recording("recordings/grad1-sim-30s.mcap").raw_blocks[0].n_probes
2
"""

from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.io.recordings.reader import FluxcalDecoderFactory, read_recording
from fluxcal.service.io.recordings.repair import repair_recording
from fluxcal.service.io.recordings.ros2 import Ros2Mapping
from fluxcal.service.io.recordings.writer import write_recording

__all__ = ["FluxcalDecoderFactory", "Ros2Mapping", "load_data", "read_recording", "repair_recording",
           "write_recording"]
