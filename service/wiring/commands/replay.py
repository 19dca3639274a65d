"""`fluxcal replay REC.mcap [--config FILE] [--out OUT.mcap]`: a recording through the same pipeline.

The raw blocks are replayed exactly as they were recorded, and every command the live service
applied is applied again before the same sample, so the corrected output equals the live run's bit
for bit (given the same configuration: by default the one stored in the recording). Reports how
many corrected blocks were compared and whether they were identical.
"""

from __future__ import annotations

import os

# The estimator and the gate multiply many small matrices: idle OpenBLAS worker threads spin for the cores
# between them (measured, bench/bench_service.py with the other core busy: replay 5.8x slower). One thread
# unless the user says otherwise; this only takes effect when numpy is not loaded yet (the CLI).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json
import re
import sys
import time
from argparse import Namespace
from pathlib import Path

import numpy as np

from drivers.block import SampleBlock
from drivers.errors import RecordingError
from service.io.calfile import calibration_from_dict
from service.io.recordings.labdata import check_one_run
from service.io.recordings.reader import read_recording
from service.wiring.commands.notes import say_read_warnings
from service.wiring.config import config_from_dict, load_config, rate_stated
from service.wiring.daemon import build_pipeline
from service.wiring.progress import Progress


def continuation(path: Path, rec) -> str | None:
    """What to say when `path` is not the start of its run (a rotated file -0002, -0003, ..., or a directory
    starting with one): the pipeline's state when it began (the calibration learned, the commands applied) is
    in the earlier files, so its replay cannot match the live output; replay the run from its first file."""
    first = Path(rec.files[0]) if rec.files else path
    m = re.match(r"^.+-(\d{4})\.mcap$", first.name)
    index = int(m.group(1)) if m else int(rec.metadata.get("file_index", "1") or 1) if not path.is_dir() else 1
    if index <= 1:
        return None
    folder = path if path.is_dir() else path.parent
    starts = sorted(folder.glob("*-0001.mcap"))
    where = (f"`fluxcal replay {folder}` (the folder of that run's files)" if len(starts) == 1 else
             f"a folder holding that run's files, from its -0001 file on (`fluxcal replay FOLDER`)")
    return (f"{first.name} is file {index} of a run the service split into several files: it continues where "
            f"file {index - 1} stopped, and the state the live run had then (the calibration it had learned, the "
            f"commands applied) is in the earlier files, so a replay of it alone cannot give the live output; "
            f"replay the whole run: {where}")


#: the rate a serial source was taken to run at before source.rate_hz existed (the live run used it)
LEGACY_RATE_HZ = 200.0


def _with_rate(raw: dict, recording: str) -> dict:
    """A configuration stored before source.rate_hz existed (serial or replay source, no rate stated):
    the live run counted its estimator durations at 200 Hz, so replay must too, to give the same output;
    said, with how to replay at another rate."""
    if not rate_stated(raw):
        print(f"fluxcal replay: {recording}: its stored configuration names no source.rate_hz (it was recorded "
              f"before the key existed, when a serial source was taken to run at {LEGACY_RATE_HZ:g} Hz): replaying "
              f"at {LEGACY_RATE_HZ:g} Hz as the live run did; give --config with source.rate_hz for another rate",
              file=sys.stderr)
        raw = {**raw, "source": {**raw["source"], "rate_hz": LEGACY_RATE_HZ}}
    return raw


def main(args: Namespace) -> int:
    if args.out:
        from service.wiring.commands.notes import check_output_file

        check_output_file(args.out, suffixes=(".mcap",), not_this=args.recording)     # before any work
    if Path(args.recording).is_dir():
        check_one_run(Path(args.recording))     # a folder of one run (the reader's rule, as fit's)
    rec = read_recording(args.recording)
    say_read_warnings("replay", args.recording, rec.report.warnings)
    later = continuation(Path(args.recording), rec)
    if later:
        print(f"fluxcal replay: {later}", file=sys.stderr)
    if args.config:
        cfg = load_config(args.config)
    else:
        text = rec.metadata.get("config")
        if not text:
            raise RecordingError(f"{args.recording}: no configuration stored in the recording; give --config")
        cfg = config_from_dict(_with_rate(json.loads(text), args.recording), f"{args.recording} (stored configuration)")
    initial = None
    initial_event = {"kind": "initial", "seq": 0, "calibration": None}
    commands = []
    for ev in rec.events:
        if ev.get("kind") == "initial" and ev.get("calibration"):
            initial = calibration_from_dict(ev["calibration"], "recorded initial calibration")
            initial_event = ev
        elif ev.get("kind") == "command":
            commands.append(ev)
    commands.sort(key=lambda e: e["seq"])
    pipeline = build_pipeline(cfg, initial)
    logger = None
    if args.out:
        from service.io.recordings.writer import McapLogger

        out = Path(args.out)
        logger = McapLogger(out.parent, unit=cfg.unit.name, filename=out.name, rotate_mb=1e9, rotate_s=1e12,
                            metadata=dict(rec.metadata))
        # what a replay of this copy needs: the calibration it started from and the commands, where they acted
        logger.write_event(initial_event)
    blocks = _coalesce(rec.raw, [c["seq"] for c in commands])
    progress = Progress(sum(b.n_samples for b in blocks), "replay")
    samples = 0
    ci = 0
    out_seq, out_vals = [], []
    t0 = time.perf_counter()
    try:
        for block in blocks:
            while ci < len(commands) and block.n_samples and commands[ci]["seq"] <= int(block.seq[0]):
                c = commands[ci]
                payload = (calibration_from_dict(c["calibration"]) if c.get("name") == "apply"
                           else c.get("effect"))
                pipeline.command(c["name"], payload, seq=c["seq"], t_s=float("nan"))
                if c.get("name") == "apply" and "note" not in c:
                    pipeline.held = False     # recorded before applied calibrations were held: as that live run
                if logger is not None:
                    logger.write_event(c)
                ci += 1
            result = pipeline.process(block)
            samples += block.n_samples
            if logger is not None:
                logger.write_raw(block)
                if result.corrected is not None:
                    logger.write_corrected(result.corrected)
            if result.corrected is not None:
                out_seq.append(result.corrected.seq)
                out_vals.append(result.corrected.corrected_nT)
            progress.to(samples)
    finally:
        progress.close()
        if logger is not None:
            logger.close()
    if logger is not None and logger.dropped:
        print(f"fluxcal replay: {args.out}: the replay could not be written ({logger.last_error}); "
              f"{logger.dropped} message(s) lost", file=sys.stderr)
        return 1
    if logger is not None and logger.errors:
        print(f"fluxcal replay: {args.out}: {logger.errors} write error(s), retried; nothing was lost "
              f"(the last: {logger.last_error})", file=sys.stderr)
    compared, identical = _compare(rec.corrected_blocks, out_seq, out_vals)
    dt = time.perf_counter() - t0
    p = cfg.unit.n_probes
    uncorrected = samples - sum(int(s.size) for s in out_seq)
    print(f"replayed {samples} samples of {p} probe(s) in {dt:.2f} s ({samples * p / max(dt, 1e-9):,.0f} "
          f"probe-samples/s); corrected samples compared with the recording: {compared}, identical: {identical}"
          + (f" ({uncorrected} earlier sample(s) have no corrected output, live or replayed: no calibration was "
             f"usable yet)" if uncorrected > 0 and compared else "")
          + (f"; written to {args.out}" if args.out else ""))
    if compared and identical != compared:
        print(f"fluxcal replay: {compared - identical} corrected sample(s) differ from the live run"
              + (" (a continuation replayed alone: see above)" if later else ""), file=sys.stderr)
        return 1
    if not compared:
        live = sum(c.n_samples for c in rec.corrected_blocks)
        replayed = sum(int(s.size) for s in out_seq)
        if live:
            print(f"fluxcal replay: the live run has {live} corrected sample(s), the replay {replayed} at the same "
                  f"samples: they differ" + (" (a continuation replayed alone: see above)" if later else ""),
                  file=sys.stderr)
            return 1
        print("fluxcal replay: nothing to compare: the recording holds no corrected samples (its calibration was "
              f"not usable while it ran); the replay gave {replayed}", file=sys.stderr)
    return 0


def _coalesce(whole: SampleBlock, cut_seqs, max_samples: int = 20000):
    """Large blocks for speed (the pipeline's output does not depend on blocking), cut where a
    recorded command applies so it lands before the same sample as live."""
    cuts = sorted(set(int(s) for s in cut_seqs))
    edges = np.searchsorted(whole.seq, cuts)
    bounds = sorted(set([0, whole.n_samples, *edges.tolist(), *range(0, whole.n_samples, max_samples)]))
    return [whole.slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _compare(live_blocks, seqs, values) -> tuple[int, int]:
    """Samples of the live corrected stream compared with the replay's, matched by seq."""
    if not live_blocks or not seqs:
        return 0, 0
    live_seq = np.concatenate([c.seq for c in live_blocks])
    live_val = np.concatenate([c.corrected_nT for c in live_blocks])
    seq = np.concatenate(seqs)
    val = np.concatenate(values)
    common, il, ir = np.intersect1d(live_seq, seq, return_indices=True)
    a, b = live_val[il], val[ir]
    same = np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=(1, 2))
    return int(common.size), int(same.sum())
