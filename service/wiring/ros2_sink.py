"""The service's corrected (and, if asked, raw) vectors as a ROS 2 bag beside its own recording: a Sink
(sinks.py) around fluxcal.service.io.recordings.ros2_writer.Ros2BagWriter, for the live service and `replay --out`.

    sink = Ros2BagSink.open("run_ros2", unit=cfg.unit.name, probe_names=cfg.probe_names)
    ...                                   # the daemon (or replay) tells it on_raw / on_corrected
    sink.close()                          # writes metadata.yaml: then `ros2 bag info run_ros2` and rosbags read it
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError, RecordingError
from fluxcal.service.io.recordings.ros2_writer import Ros2BagWriter
from fluxcal.service.numerics.outputs import CorrectedBlock

from .sinks import Sink


class Ros2BagSink(Sink):
    """sensor_msgs/msg/MagneticField per probe and sample into a rosbag2 directory (MCAP storage, CDR)."""

    name = "ros2-bag"

    def __init__(self, writer: Ros2BagWriter, *, raw: bool = False, wall_clock: bool = False,
                 say: Callable[[str], None] | None = None) -> None:
        self.writer = writer
        self.raw = raw
        self.wall_clock = wall_clock          # stamps: the wall clock at the first block, then the unit's clock on
        self.say = say                        # where the bag's account is said when it closes

    @classmethod
    def live(cls, cfg: Any, say: Callable[[str], None] | None = None) -> "Ros2BagSink | None":
        """The bag of the running service's [ros2] section (None when disabled): a new folder under ros2.dir named
        after the unit and the start's UTC time; stamps in UNIX time, the unit's clock set against the wall clock
        at the first block."""
        r = cfg.ros2
        if not r.enabled:
            return None
        import time as _time

        folder = Path(r.dir) / f"{cfg.unit.name}-{_time.strftime('%Y%m%dT%H%M%S', _time.gmtime())}"
        sink = cls.open(folder, unit=cfg.unit.name, probe_names=list(cfg.probe_names), raw=r.raw, key="ros2.dir")
        sink.wall_clock, sink.say = True, say
        return sink

    @classmethod
    def open(cls, path: str | Path, *, unit: str, probe_names: list[str], raw: bool = False,
             stamp_origin_ns: int | None = None, key: str = "--ros2-out") -> "Ros2BagSink":
        """A new bag at path (a directory that must not exist or be empty). stamp_origin_ns: UNIX time of the unit's
        t = 0 in ns, added to every sample time to make its header stamp (None: 0, the unit's own clock as the stamps;
        a live run gives time.time_ns() minus its first block's t_s). ConfigError naming `key` when no bag can be
        written there."""
        origin = int(stamp_origin_ns) if stamp_origin_ns is not None else 0
        try:
            return cls(Ros2BagWriter(Path(path), unit=unit, probe_names=list(probe_names), stamp_origin_ns=origin),
                       raw=raw)
        except (OSError, RecordingError) as e:
            raise ConfigError(f"{key}: {str(path)!r}: cannot write a ROS 2 bag there ({e}; allowed: a new or empty "
                              f"directory this user can create)") from None

    def on_raw(self, block: SampleBlock) -> None:
        if self.wall_clock and block.n_samples:     # the first block: the unit's t_s against the wall clock
            import time as _time

            self.writer.stamp_origin_ns = _time.time_ns() - int(round(float(block.t_s[0]) * 1e9))
            self.wall_clock = False
        if self.raw:
            self.writer.write_raw(block)

    def on_corrected(self, block: CorrectedBlock) -> None:
        self.writer.write_corrected(block)

    def status(self) -> dict[str, Any] | None:
        return None            # the recorder's status is the MCAP recording's (Sinks.recording takes the first)

    def close(self) -> None:
        """Finish the bag and say what it holds, and what it could not hold (a sample with a non-finite axis, such
        as a saturated probe's, or stamped before 1970: sensor_msgs has no place for either)."""
        self.writer.close()
        if self.say is not None:
            w = self.writer
            left = (f"; {w.skipped:,} probe-sample(s) not written (a non-finite axis, or a stamp before the UNIX "
                    f"epoch: sensor_msgs has no place for either)") if w.skipped else ""
            self.say(f"ROS 2 bag {w.path}: {w.message_count:,} message(s) on {len(w.status()['topics'])} "
                     f"topic(s){left}")


def replay_ros2_sink(out: str | Path, cfg: Any, *, raw: bool = False, origin_unix_s: float | None = None,
                     say: Callable[[str], None] | None = None) -> Ros2BagSink:
    """The sink `replay --ros2-out DIR` tells of every replayed block (on_raw, on_corrected) and closes at the end:
    stamps are the unit's sample times plus origin_unix_s (the recording's start in UNIX time where it is known;
    else the unit's clock as it is, said by the stamps starting near 0)."""
    origin = None if origin_unix_s is None else int(round(origin_unix_s * 1e9))
    sink = Ros2BagSink.open(out, unit=cfg.unit.name, probe_names=list(cfg.probe_names), raw=raw,
                            stamp_origin_ns=origin)
    sink.say = say
    return sink
