"""Where each microsecond of one live block goes: `fluxcal run` with timers around the stages of its loop.

bench_service.py --profile starts the service through this module (python bench/_stages.py OUT.json run --config
...): the named methods below are wrapped, at class level, to add the thread CPU time (CLOCK_THREAD_CPUTIME_ID,
so not the wall clock, and not other threads' work) of each call to its stage; at exit the stages and their calls
are written to OUT.json. The service is otherwise the one users start.
"""

from __future__ import annotations

import os

# as `fluxcal run` sets it before numpy loads (service/wiring/commands/run.py): this module loads numpy first
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import atexit  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402
from pathlib import Path  # noqa: E402

#: (stage label, "module:Class.method" or "module:function", or several such separated by "|": the first that
#: exists, so that one list times the code before and after a change) in the order they are printed; a label's
#: parent is the label before its last "/". Inclusive times: a parent's own time is its total minus its children's.
STAGES = (
    ("loop", "fluxcal.service.wiring.daemon:Daemon._loop"),
    ("loop/commands", "fluxcal.service.io.bus.server:ServiceBus.pending_commands"),
    ("loop/read", "fluxcal.service.wiring.input:BatchReader.read"),
    ("loop/read/port", "fluxcal.drivers.serial_source:SerialSource._pull"),
    ("loop/read/parse", "fluxcal.drivers.assemble:SerialFramer.feed"),
    ("loop/read/assemble", "fluxcal.drivers.assemble:FrameAssembler.block"),
    ("loop/rate check", "fluxcal.service.wiring.daemon:Daemon._check_rate"),
    ("loop/raw: recording", "fluxcal.service.wiring.sinks:McapSink.on_raw"),
    ("loop/raw: bus", "fluxcal.service.wiring.sinks:BusSink.on_raw"),
    ("loop/pipeline", "fluxcal.service.wiring.daemon:Daemon._process"),
    ("loop/pipeline/ring", "fluxcal.drivers.ringbuffer:RingBuffer.append"),
    ("loop/pipeline/estimator", "fluxcal.service.wiring.pipeline:Pipeline._update_estimators"),
    ("loop/pipeline/gate", "fluxcal.service.wiring.pipeline:Pipeline._check_candidate"),
    ("loop/pipeline/correct", "fluxcal.service.wiring.pipeline:Pipeline._correct"),
    ("loop/pipeline/correct/products", "fluxcal.service.numerics.outputs:Derived.__call__|fluxcal.service.wiring.pipeline:products"),
    ("loop/pipeline/error", "fluxcal.service.numerics.channels:BlockError.__call__|fluxcal.service.wiring.pipeline:block_error_rms"),
    ("loop/status", "fluxcal.service.wiring.status:StatusLog.block"),
    ("loop/corrected: recording", "fluxcal.service.wiring.sinks:McapSink.on_corrected"),
    ("loop/recording: gathered messages", "fluxcal.service.wiring.sinks:McapSink.write_gathered"),
    ("loop/recording: gathered messages/10 Hz products", "fluxcal.service.io.foxglove_schemas:Products.corrected"),
    ("loop/bus: send", "fluxcal.service.wiring.sinks:BusSink.on_flush"),
    ("loop/corrected: bus", "fluxcal.service.wiring.sinks:BusSink.on_corrected"),
    ("loop/error: recording", "fluxcal.service.wiring.sinks:McapSink.on_error"),
    ("loop/error: bus", "fluxcal.service.wiring.sinks:BusSink.on_error"),
    ("loop/events", "fluxcal.service.wiring.daemon:Daemon._on_event"),
    ("loop/health (1 Hz)", "fluxcal.service.wiring.daemon:Daemon._tick_health"),
    ("loop/status line (1 Hz)", "fluxcal.service.wiring.status:StatusLog.tick"),
    ("loop/state (1 Hz)", "fluxcal.service.wiring.pipeline:Pipeline.state"),
)
#: the stage whose calls count the blocks
BLOCK_STAGE = "loop/pipeline"
#: recording chunks (lz4 and the file write): inside whichever stage wrote the message that filled one
CHUNK = ("recording chunk (lz4 + write)", "fluxcal.service.io.recordings.writer:ChunkedLog._flush")


class Timers:
    def __init__(self) -> None:
        self.ns: dict[str, int] = defaultdict(int)
        self.calls: dict[str, int] = defaultdict(int)
        self.thread = threading.get_ident()      # the service's thread (the stages run on it)

    def wrap(self, label: str, targets: str) -> None:
        for target in targets.split("|"):
            module_name, name = target.split(":")
            module = importlib.import_module(module_name)
            owner, attr = (getattr(module, name.split(".")[0], None), name.split(".")[1]) if "." in name \
                else (module, name)
            inner = getattr(owner, attr, None)
            if inner is not None:
                break
        else:
            return                                   # not in this version of the code: the stage reads 0
        ns, calls, clock = self.ns, self.calls, time.thread_time_ns

        def timed(*a, **k):
            t0 = clock()
            try:
                return inner(*a, **k)
            finally:
                ns[label] += clock() - t0
                calls[label] += 1

        setattr(owner, attr, timed)
        if owner is not module:
            return
        for m in list(sys.modules.values()):     # a function imported by name elsewhere (pipeline's block_error_rms)
            if getattr(m, "__name__", "").startswith("fluxcal.") and getattr(m, attr, None) is inner:
                setattr(m, attr, timed)


def main(out_path: str, argv: list[str]) -> int:
    timers = Timers()
    for label, target in STAGES + (CHUNK,):
        timers.wrap(label, target)

    def dump() -> None:
        Path(out_path).write_text(json.dumps({
            "stages": [[label, timers.ns[label], timers.calls[label]] for label, _ in STAGES + (CHUNK,)],
            "blocks": timers.calls[BLOCK_STAGE]}))

    atexit.register(dump)
    from fluxcal.service.wiring.cli import main as cli_main
    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2:]))
