"""`fluxcal replay REC.mcap [--config FILE] [--out OUT.mcap]`: a recording through the same pipeline.

The raw blocks are replayed exactly as they were recorded, and every command the live service
applied is applied again before the same sample, so the corrected output equals the live run's bit
for bit (given the same configuration: by default the one stored in the recording). Reports how
many corrected blocks were compared and whether they were identical.
"""

from __future__ import annotations

import json
import sys
import time
from argparse import Namespace
from pathlib import Path

import numpy as np

from drivers.errors import RecordingError
from service.calib.calfile import calibration_from_dict
from service.config import config_from_dict, load_config
from service.daemon import build_pipeline
from service.recording import read_recording


class Progress:
    """A progress bar on a terminal, nothing otherwise."""

    def __init__(self, total: int, label: str) -> None:
        self.total, self.label = max(total, 1), label
        self.tty = sys.stderr.isatty()
        self.last = 0.0

    def update(self, done: int) -> None:
        now = time.monotonic()
        if not self.tty or now - self.last < 0.1:
            return
        self.last = now
        frac = min(done / self.total, 1.0)
        bar = "#" * int(30 * frac)
        print(f"\r{self.label} [{bar:<30}] {frac:6.1%}", end="", file=sys.stderr, flush=True)

    def done(self) -> None:
        if self.tty:
            print("\r\033[K", end="", file=sys.stderr, flush=True)


def main(args: Namespace) -> int:
    rec = read_recording(args.recording)
    if args.config:
        cfg = load_config(args.config)
    else:
        text = rec.metadata.get("config")
        if not text:
            raise RecordingError(f"{args.recording}: no configuration stored in the recording; give --config")
        cfg = config_from_dict(json.loads(text), f"{args.recording} (stored configuration)")
    initial = None
    commands = []
    for ev in rec.events:
        if ev.get("kind") == "initial" and ev.get("calibration"):
            initial = calibration_from_dict(ev["calibration"], "recorded initial calibration")
        elif ev.get("kind") == "command":
            commands.append(ev)
    commands.sort(key=lambda e: e["seq"])
    pipeline = build_pipeline(cfg, initial)
    logger = None
    if args.out:
        from service.mcap_sink import McapLogger

        out = Path(args.out)
        logger = McapLogger(out.parent, unit=cfg.unit.name, filename=out.name, rotate_mb=1e9, rotate_s=1e12,
                            metadata=dict(rec.metadata))
    blocks = rec.raw_blocks
    live = {(int(c.seq[0]), int(c.seq[-1])): c for c in rec.corrected_blocks}
    progress = Progress(sum(b.n_samples for b in blocks), "replay")
    compared = identical = samples = 0
    ci = 0
    t0 = time.perf_counter()
    try:
        for block in blocks:
            while ci < len(commands) and block.n_samples and commands[ci]["seq"] <= int(block.seq[0]):
                c = commands[ci]
                payload = calibration_from_dict(c["calibration"]) if c.get("name") == "apply" else None
                pipeline.command(c["name"], payload, seq=c["seq"], t_s=float("nan"))
                ci += 1
            result = pipeline.process(block)
            samples += block.n_samples
            if logger is not None:
                logger.write_raw(block)
                if result.corrected is not None:
                    logger.write_corrected(result.corrected)
            if result.corrected is not None and block.n_samples:
                ref = live.get((int(block.seq[0]), int(block.seq[-1])))
                if ref is not None:
                    compared += 1
                    identical += int(np.array_equal(ref.corrected_nT, result.corrected.corrected_nT, equal_nan=True))
            progress.update(samples)
    finally:
        progress.done()
        if logger is not None:
            logger.close()
    dt = time.perf_counter() - t0
    p = cfg.unit.n_probes
    print(f"replayed {samples} samples of {p} probe(s) in {dt:.2f} s ({samples * p / max(dt, 1e-9):,.0f} "
          f"probe-samples/s); corrected blocks compared with the recording: {compared}, identical: {identical}"
          + (f"; written to {args.out}" if args.out else ""))
    if compared and identical != compared:
        print(f"fluxcal replay: {compared - identical} corrected block(s) differ from the live run", file=sys.stderr)
        return 1
    return 0
