"""`fluxcal decode CAPTURE --probes N [--can] [--lsb-nT X] [--base-id ID] --out FILE.csv|FILE.mcap`:
turn a raw serial capture (ICD frames, possibly starting mid-frame, with noise) or a CAN log
(python-can formats by suffix) into data, with the same parsing and assembly as the live sources.

CSV columns: t, s1_x .. sN_z (nT), s1_temp .. sN_temp (degC), seq, flags. For serial captures t is
the unit clock (t_us unwrapped) in seconds with 6 decimals, i.e. exact microseconds; CAN carries no
unit clock, so there t = seq / rate with the rate estimated from the log's timestamps. Saturated
axes and invalid temperatures are written as nan (the flags column says why). The output is
written to a temporary file and renamed, so it is complete or absent. Counters go to stderr.

The capture must be a regular file (a FIFO or a device is refused before it is opened). A serial capture is
streamed, so any size is read (Ctrl-C or SIGTERM stop it between pieces); a CAN log is held whole, so it has
the size limit of fluxcal.drivers.inputs (FLUXCAL_MAX_INPUT_MB), and a text log the line-length limit.
"""

from __future__ import annotations

import argparse
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from fluxcal.drivers.assemble import FrameAssembler, SerialFramer, can_icd_counters, serial_icd_counters
from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError, DataError, FluxcalError
from fluxcal.drivers.icd import MAX_PROBES, frame_length, parse_serial
from fluxcal.drivers.inputs import check_size, not_regular, open_regular, scan_lines
from fluxcal.drivers.outputs import temp_beside
from fluxcal.drivers.source import Counters
from fluxcal.service.wiring.commands.options import CommandHelp, int_auto
from fluxcal.service.wiring.progress import Progress
from fluxcal.service.wiring.result import Result, Said, stderr_say

CHUNK_BYTES = 4 << 20          # serial captures are read in 4 MiB pieces: any size fits in memory
TEXT_CAN_LOGS = (".log", ".asc", ".csv")          # python-can's line-based formats (.blf is binary)


HELP = CommandHelp("turn a serial capture or CAN log into data (CSV or MCAP) for fit and diagnose",
                   "  fluxcal decode capture.bin --probes 2 --out data.csv\n"
                   "  fluxcal decode bus.log --can --probes 4 --base-id 0x200 --out data.mcap")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", metavar="CAPTURE", help="raw serial bytes, or a CAN log (.log, .asc, .blf) with --can")
    p.add_argument("--probes", type=int, required=True, metavar="N", help="probes in each frame (1..8; required)")
    p.add_argument("--can", action="store_true",
                   help="the capture is a CAN log (default: serial bytes). CAN frames carry no unit clock: t is "
                        "the sample counter over the rate estimated from the log's timestamps. Neither carries a "
                        "total field: give fit and diagnose --site or a config's total field")
    p.add_argument("--lsb-nT", dest="lsb_nT", type=float, default=0.001, metavar="X",
                   help="nT per ADC count (default: %(default)s)")
    p.add_argument("--base-id", dest="base_id", type=int_auto, default=0x200, metavar="ID",
                   help="first CAN identifier of the unit (default: 0x200)")
    p.add_argument("--out", required=True, metavar="FILE.csv|FILE.mcap", help="where to write the data")


@dataclass
class DecodeOptions:
    probes: int
    out: str
    can: bool = False
    lsb_nT: float = 0.001
    base_id: int = 0x200


@dataclass
class DecodeResult(Result):
    """A capture decoded into data: how many samples, and the parser's counters (what was lost and why)."""

    samples: int = 0
    counters: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "samples": self.samples, "counters": self.counters}


def options(args: argparse.Namespace) -> DecodeOptions:
    return DecodeOptions(probes=args.probes, out=args.out, can=args.can, lsb_nT=args.lsb_nT, base_id=args.base_id)


def main(args: argparse.Namespace) -> int:
    """The command line: what was written and the counters said on stderr (the data go to --out)."""
    return execute(args.capture, options(args), Said("decode", stderr_say("decode"))).status


def execute(source: str, opts: DecodeOptions, said: Said) -> DecodeResult:
    """`fluxcal decode SOURCE`: the capture's frames through the live parser into a CSV or an MCAP recording."""
    n = opts.probes
    if not 1 <= n <= MAX_PROBES:
        raise ConfigError(f"--probes: {n} is not allowed (allowed: 1..{MAX_PROBES}, the unit's number of probes)")
    if not (math.isfinite(opts.lsb_nT) and opts.lsb_nT > 0):
        raise ConfigError(f"--lsb-nT: {opts.lsb_nT!r} is not allowed (allowed: a positive number of nT per count)")
    capture = Path(source)
    out = Path(opts.out)
    suffix = out.suffix.lower()
    if suffix not in (".csv", ".mcap"):
        raise ConfigError(f"--out: {out} must end in .csv or .mcap")
    try:
        refused = not_regular(capture, os.stat(capture).st_mode)  # a FIFO or a device: refused before any open
    except FileNotFoundError:
        raise DataError(f"{capture}: capture file not found") from None
    except OSError as e:
        raise DataError(f"{capture}: cannot read ({e.strerror})") from None
    if refused:
        raise refused
    if out.exists() and out.resolve() == capture.resolve():
        raise ConfigError(f"--out: {out} is the capture itself; choose another output file")
    if not out.parent.resolve().is_dir():
        raise ConfigError(f"--out: directory {out.parent} does not exist")

    counters = can_icd_counters() if opts.can else serial_icd_counters()
    if opts.can:
        from fluxcal.drivers.can_source import check_base_id

        check_base_id(opts.base_id, n, "--base-id")
        blocks, t_format = _can_blocks(capture, n, opts.base_id, opts.lsb_nT, counters, said), "%.9f"
    else:
        blocks, t_format = _serial_blocks(capture, n, opts.lsb_nT, counters), "%.6f"

    counted = _Counted(blocks)
    if suffix == ".csv":
        _write_csv(out, n, t_format, counted, capture, opts, counters)
    else:
        _write_mcap(out, n, counted, capture, opts, counters)
    said("written", f"{counted.samples} samples -> {out}", level="say")
    said("counters", _counters_line(counters, opts.can), level="say")
    return DecodeResult("decode", str(source), notes=said.notes, written=[str(out)], samples=counted.samples,
                        counters=dict(counters.as_dict()))


def _counters_line(c: Counters, can_log: bool) -> str:
    parts = [f"frames accepted {c.frames_accepted}"]
    if can_log:
        parts += [f"wrong length {c.wrong_length}", f"remote frames {c.remote_frames}",
                  f"other nodes' frames {c.foreign_frames}"]
    else:
        parts += [f"CRC failures {c.crc_failures}", f"bytes skipped {c.bytes_skipped}"]
    parts.append(f"sequence gaps {c.seq_gaps} ({c.samples_missed} samples missed)")
    if can_log:
        parts.append(f"incomplete CAN samples {c.can_incomplete}")
    parts += [f"saturated axes {c.saturated_axes}", f"invalid temperatures {c.temp_invalid}"]
    return "counters: " + ", ".join(parts)


def _serial_blocks(capture: Path, n: int, lsb_nT: float, counters: Counters) -> Iterator[SampleBlock]:
    framer = SerialFramer(n, counters)
    assembler = FrameAssembler(n, lsb_nT, counters)
    progress = Progress(capture.stat().st_size, "decode", unit="B")
    f = open_regular(capture, "a capture")         # streamed in CHUNK_BYTES pieces: no size limit is needed
    with f, progress:
        while True:
            chunk = f.read(CHUNK_BYTES)
            counters.bytes_received += len(chunk)
            frames = framer.feed(chunk) if chunk else framer.finish()
            if len(frames):
                yield assembler.block(frames)
            if not chunk:
                return
            progress.to(framer.bytes_fed)


def _can_blocks(capture: Path, n: int, base_id: int, lsb_nT: float, counters: Counters,
                said: Said) -> Iterator[SampleBlock]:
    from fluxcal.drivers.assemble import SeqGapCounter
    from fluxcal.drivers.can_source import estimate_rate_hz, read_can_log

    # a CAN log is held whole (its samples), and python-can reads a text log line by line: both bounded first
    check_size(capture, capture.stat().st_size, "a CAN log")
    if capture.suffix.lower() in TEXT_CAN_LOGS:
        scan_lines(capture, "a CAN log")
    samples, _ = read_can_log(capture, n, base_id=base_id, counters=counters)
    if len(samples) == 0:
        return
    rate = estimate_rate_hz(samples)
    if rate is None:
        said("clock", "CAN carries no unit clock and the log's timestamps do not give the rate: t is the sample "
                       "counter", level="say")
        rate = 1.0
    else:
        said("clock", f"CAN carries no unit clock: t = seq / {rate:.6g} Hz, the rate estimated from the log's "
                      f"timestamps", level="say")
    SeqGapCounter().update(samples.seq, counters)
    yield samples.to_block(rate_hz=rate, lsb_nT=lsb_nT, counters=counters)


def _no_frames_message(capture: Path, n: int, opts: DecodeOptions, c: Counters) -> str:
    if opts.can:
        lo, hi = opts.base_id, opts.base_id + 4 * n - 1
        if c.frames_accepted == 0:
            return (f"{capture}: no CAN frame with the ids of a {n}-probe unit ({lo:#x}..{hi:#x}); check --probes, "
                    f"--base-id and that the file is a CAN log")
        return (f"{capture}: {c.frames_accepted} frames but no complete sample ({c.can_incomplete} incomplete); "
                f"check --probes: a {n}-probe sample needs {3 * n} frames")
    size = capture.stat().st_size
    if size == 0:
        return f"{capture}: the capture is empty"
    hint = ""
    with capture.open("rb") as f:
        head = f.read(CHUNK_BYTES)
    others = [m for m in range(1, MAX_PROBES + 1) if m != n and len(parse_serial(head, m, final=True).frames)]
    if others:
        hint = f"; it holds {others[0]}-probe frames: use --probes {others[0]}"
    return (f"{capture}: no intact {n}-probe ICD frame ({frame_length(n)} bytes, sync a5 5a) in {size} bytes"
            f" ({c.crc_failures} failed their CRC){hint or '; check --probes, and use --can for a CAN log'}")


class _AtomicFile:
    """A temporary file beside the target, renamed onto it on commit and removed on abort."""

    def __init__(self, path: Path, mode: str) -> None:
        self.path = path
        self.tmp = temp_beside(path)                  # never a link planted at the name: renamed onto `path`
        self.file = open(self.tmp, mode)

    def commit(self) -> None:
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()
        os.replace(self.tmp, self.path)

    def abort(self) -> None:
        if not self.file.closed:
            self.file.close()
        self.tmp.unlink(missing_ok=True)


class _CsvWriter:
    """The columns of docs/csv.md plus seq and flags, rows written block by block."""

    def __init__(self, path: Path, n: int, t_format: str) -> None:
        self.n = n
        header = ["t"] + [f"s{k}_{a}" for k in range(1, n + 1) for a in "xyz"]
        header += [f"s{k}_temp" for k in range(1, n + 1)] + ["seq", "flags"]
        # nT with 12 significant digits: counts x lsb_nT come back to the count for any lsb_nT;
        # temperatures are whole hundredths of a degree
        self.fmt = ",".join([t_format] + ["%.12g"] * (3 * n) + ["%.2f"] * n + ["%d", "%d"])
        self.out = _AtomicFile(path, "w")
        self.out.file.write(",".join(header) + "\n")

    def write(self, b: SampleBlock) -> None:
        table = np.column_stack([b.t_s, b.field_nT.reshape(len(b), -1), b.temp_C, b.seq, b.flags])
        np.savetxt(self.out.file, table, fmt=self.fmt)

    def commit(self) -> None:
        self.out.commit()

    def abort(self) -> None:
        self.out.abort()


class _Counted:
    """Passes blocks through and counts their samples."""

    def __init__(self, blocks: Iterator[SampleBlock]) -> None:
        self.blocks = blocks
        self.samples = 0

    def __iter__(self) -> Iterator[SampleBlock]:
        for b in self.blocks:
            self.samples += b.n_samples
            yield b


def _write_csv(out: Path, n: int, t_format: str, blocks: _Counted, capture: Path, opts: DecodeOptions,
               counters: Counters) -> None:
    try:
        writer = _CsvWriter(out, n, t_format)
    except OSError as e:
        raise ConfigError(f"--out: cannot write {out} ({e.strerror})") from None
    try:
        for block in blocks:
            writer.write(block)
        if blocks.samples == 0:
            raise DataError(_no_frames_message(capture, n, opts, counters))
        writer.commit()
    except OSError as e:
        writer.abort()
        raise FluxcalError(f"writing {out} failed ({e}); nothing was written") from e
    except BaseException:
        writer.abort()
        raise


def _write_mcap(out: Path, n: int, blocks: _Counted, capture: Path, opts: DecodeOptions,
                counters: Counters) -> None:
    """Through fluxcal.service.io.recordings.writer.write_recording(path, blocks, unit=, probe_names=), the MCAP logger's
    whole-file entry point, into a temporary file renamed on success."""
    from fluxcal.service.io.recordings.writer import write_recording

    unit = re.sub(r"[^A-Za-z0-9_\-]", "_", capture.stem)[:64] or "unit1"
    tmp = temp_beside(out)
    try:
        write_recording(tmp, blocks, unit=unit, probe_names=[f"s{k}" for k in range(1, n + 1)])
        if blocks.samples == 0:
            raise DataError(_no_frames_message(capture, n, opts, counters))
        os.replace(tmp, out)
    except OSError as e:
        raise FluxcalError(f"writing {out} failed ({e}); nothing was written") from e
    finally:
        tmp.unlink(missing_ok=True)
