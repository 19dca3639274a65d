"""`fluxcal replay REC.mcap [--config FILE] [--out OUT.mcap] [--ros2-out DIR]`: a recording through the same pipeline.

The raw blocks are replayed exactly as they were recorded, and every command the live service
applied is applied again before the same sample (given the same configuration: by default the one
stored in the recording). The corrected output is compared with the recording's, sample by sample:
bit for bit where the recording names this machine's arithmetic (its "fluxcal.arithmetic" record), else
within the tolerance rounding can reach through the estimator's conditioning (rounding_tolerance_nT,
docs/recording.md "Replay equality"), with the largest difference printed; the calibrations must be
replaced at the same samples as live. A hole (data lost from a damaged recording) is said as one, and
the samples after it, which the live estimator saw and the replay's cannot follow, are not compared.
"""

from __future__ import annotations

import os

# The estimator and the gate multiply many small matrices: idle OpenBLAS worker threads spin for the cores
# between them (measured, bench/bench_service.py with the other core busy: replay 5.8x slower). One thread
# unless the user says otherwise; this only takes effect when numpy is not loaded yet (the CLI).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import json
import re
import time
from argparse import Namespace
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import RecordingError
from fluxcal.service.io.calfile import calibration_from_dict
from fluxcal.service.io.recordings.gaps import RecorderGap
from fluxcal.service.io.recordings.labdata import check_one_run
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.io.recordings.repair import repair_notes
from fluxcal.service.wiring.commands.notes import check_output_file, check_output_folder
from fluxcal.service.wiring.commands.options import PATH, CommandHelp, fleet_help, fleet_options
from fluxcal.service.wiring.commands.replay_run import run_blocks
from fluxcal.service.wiring.config import config_from_dict, load_config, rate_stated
from fluxcal.service.wiring.daemon import build_pipeline
from fluxcal.service.wiring.prepare import say_read_warnings
from fluxcal.service.wiring.result import Result, Said, print_result, stderr_say
from fluxcal.service.wiring.sinks import McapSink, Sinks

HELP = CommandHelp("run a recording through the same pipeline and compare with its output",
                   "  fluxcal replay recordings/grad1-sim-30s.mcap\n  fluxcal replay rec.mcap --out again.mcap",
                   more=(" It compares the replay's corrected output with the recording's, sample by sample: exit 0 "
                   "when every one equals the live run's (bit for bit where the recording names this machine's "
                   "arithmetic, else within the rounding tolerance of its conditioning, printed with the largest "
                   "difference; or there was none to compare, which it says), 1 when any differs by more or a "
                   "calibration was replaced at other samples. The samples after a hole in a damaged recording "
                   "are not compared, which it says."))


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="REC.mcap", nargs="+",
                   help="an MCAP file, or a directory of one run's rotated files"
                   + fleet_help("--out", json_flag=False))
    p.add_argument("--config", metavar="FILE",
                   help="replay with this configuration (default: the one stored in the recording)")
    p.add_argument("--out", metavar="OUT.mcap", help="also record the replay here, with the initial calibration and "
                                                    "the commands, so it replays again (default: none)")
    p.add_argument("--ros2-out", dest="ros2_out", metavar="DIR",
                   help="also write the corrected vectors as sensor_msgs/msg/MagneticField in a ROS 2 bag, a new "
                        "folder DIR (MCAP storage, CDR; docs/ros2.md); stamps are the unit's time (default: none)")
    fleet_options(p)


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
             "a folder holding that run's files, from its -0001 file on (`fluxcal replay FOLDER`)")
    return (f"{first.name} is file {index} of a run the service split into several files: it continues where "
            f"file {index - 1} stopped, and the state the live run had then (the calibration it had learned, the "
            f"commands applied) is in the earlier files, so a replay of it alone cannot give the live output; "
            f"replay the whole run: {where}")


#: the rate a serial source was taken to run at before source.rate_hz existed (the live run used it)
LEGACY_RATE_HZ = 200.0


def _with_rate(raw: dict, recording: str, said: Said) -> dict:
    """A configuration stored before source.rate_hz existed (serial or replay source, no rate stated):
    the live run counted its estimator durations at 200 Hz, so replay must too, to give the same output;
    said, with how to replay at another rate."""
    if not rate_stated(raw):
        said("config", f"{recording}: its stored configuration names no source.rate_hz (it was recorded before the "
                       f"key existed, when a serial source was taken to run at {LEGACY_RATE_HZ:g} Hz): replaying at "
                       f"{LEGACY_RATE_HZ:g} Hz as the live run did; give --config with source.rate_hz for another rate",
             level="say")
        raw = {**raw, "source": {**raw["source"], "rate_hz": LEGACY_RATE_HZ}}
    return raw


@dataclass
class ReplayOptions:
    config: str | None = field(default=None, metadata=PATH)  # replay with this configuration (default: the one stored)
    out: str | None = field(default=None, metadata=PATH)  # also record the replay here
    # also write the corrected vectors as a ROS 2 bag (a folder) here
    ros2_out: str | None = field(default=None, metadata=PATH)


@dataclass
class ReplayResult(Result):
    """A replay and its comparison with the live run: the figures, and the lines a person reads."""

    samples: int = 0
    probes: int = 0
    compared: int = 0
    identical: int = 0
    largest_nT: float | None = None
    tolerance_nT: float | None = None
    beyond: int = 0
    holes: int = 0
    same_arithmetic: bool | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    lines: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        """How the replay compares with the live run: the last line said on stdout, or, when the replay failed
        (status 1), the last error said of it (the one that sums the failure up)."""
        if self.status:
            errors = [n.text for n in self.notes if n.level == "error"]
            if errors:
                return errors[-1]
        return self.lines[-1] if self.lines else ""

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "samples": self.samples, "probes": self.probes, "compared": self.compared,
                "identical": self.identical, "largest_nT": self.largest_nT, "tolerance_nT": self.tolerance_nT,
                "beyond": self.beyond, "holes": self.holes, "same_arithmetic": self.same_arithmetic,
                "seconds": self.seconds, "verdict": self.verdict}

    def text(self) -> str:
        return "\n".join(self.lines)


def options(args: Namespace) -> ReplayOptions:
    return ReplayOptions(config=args.config, out=args.out, ros2_out=args.ros2_out)


def main(args: Namespace) -> int:
    """The command line: the replay's lines on stdout, what fails on stderr as it comes; exit 0 or 1."""
    result = execute(args.recording, options(args), Said("replay", stderr_say("replay")))
    print_result(result, False)
    return result.status


def execute(source: str, opts: ReplayOptions, said: Said, *, sinks: list[Any] | None = None) -> ReplayResult:
    """`fluxcal replay SOURCE`: read, replay through the pipeline, compare with the live run. The replay goes to
    `sinks` (fluxcal.service.wiring.sinks.Sink) as the live run went to the service's, and to a recording at opts.out."""
    t_start = time.perf_counter()
    if opts.out:
        check_output_file(opts.out, suffixes=(".mcap",), not_this=source)     # before any work
    if opts.ros2_out:
        check_output_folder(opts.ros2_out, "--ros2-out")
    if Path(source).is_dir():
        check_one_run(Path(source))           # a folder of one run (the reader's rule, as fit's)
    rec = read_recording(source)
    t_read = time.perf_counter() - t_start
    lost = [w for w in rec.report.problems if not w.endswith("nothing lost")]
    say_read_warnings(said, source, lost)
    for w in rec.report.problems:
        if w not in lost:
            said("read", w)
    for line in repair_notes(rec.report):
        said("read", line, level="say")
    later = continuation(Path(source), rec)
    if later:
        said("part-of-run", later, level="say")
    cfg = _configuration(source, rec, opts, said)
    initial, initial_event, commands = _initial_and_commands(rec)
    pipeline = build_pipeline(cfg, initial)
    outputs = Sinks([], lambda m: said("output", m, level="error"))
    blocks = _coalesce(rec.raw, [c["seq"] for c in commands])
    try:                                      # every output opened is closed, whichever fails to open
        recording = _recording(opts.out, cfg, rec, initial_event) if opts.out else None
        for sink in ([recording] if recording else []) + list(sinks or []):
            outputs.add(sink)
        if opts.ros2_out:
            from fluxcal.service.wiring.ros2_sink import replay_ros2_sink

            outputs.add(replay_ros2_sink(opts.ros2_out, cfg, say=lambda m: said("output", m, level="say")))
        t0 = time.perf_counter()
        samples, out_seq, out_vals, replaced = run_blocks(pipeline, cfg, blocks, commands, outputs)
    finally:
        outputs.close()
    t_pipe = time.perf_counter() - t0
    out = ReplayResult("replay", str(source), samples=samples, probes=cfg.unit.n_probes)
    if recording is not None and not _recorded(recording, opts.out, out, said):
        return out
    t1 = time.perf_counter()
    cut, holes = _first_hole(rec, rec.unit)
    cmp = _compare(rec.corrected_blocks, out_seq, out_vals, before=cut)
    t_all = time.perf_counter() - t_start
    p = cfg.unit.n_probes
    out.seconds = {"all": t_all, "reading": t_read, "setting_up": t0 - t_start - t_read, "pipeline": t_pipe,
                   "comparing": time.perf_counter() - t1}
    out.lines.append(f"replayed {samples} samples of {p} probe(s) in {t_all:.2f} s: reading the recording "
                     f"{t_read:.2f} s, setting up {t0 - t_start - t_read:.2f} s, the pipeline {t_pipe:.2f} s "
                     f"({samples * p / max(t_pipe, 1e-9):,.0f} probe-samples/s), comparing "
                     f"{time.perf_counter() - t1:.2f} s (the interpreter's start and imports before them not counted)"
                     + (f"; written to {opts.out}" if opts.out else "")
                     + (f"; ROS 2 bag written to {opts.ros2_out}" if opts.ros2_out else ""))
    out.status = _verdict(out, said, rec, out_seq, cmp, cut, holes, replaced, later)
    failed = {name: n for name, n in outputs.errors.items() if n}
    if failed:
        said("output", "an output failed, so what it holds is incomplete: "
             + ", ".join(f"{name} {n:,} time(s)" for name, n in failed.items()), level="error")
        out.status = 1
    out.notes = said.notes
    return out


def _recorded(recording: McapSink, path: str, out: ReplayResult, said: Said) -> bool:
    """Whether the replay's own recording was written whole (said when not, the result then failed)."""
    logger = recording.logger
    if logger.dropped:
        said("output", f"{path}: the replay could not be written ({logger.last_error}); {logger.dropped} message(s) "
                       f"lost", level="error")
        out.status, out.notes = 1, said.notes
        return False
    if logger.errors:
        said("output", f"{path}: {logger.errors} write error(s), retried; nothing was lost (the last: "
                       f"{logger.last_error})", level="say")
    out.written.append(str(path))
    return True


def _configuration(source: str, rec, opts: ReplayOptions, said: Said):
    """The configuration to replay with: --config, else the one the recording stores (the live run's)."""
    if opts.config:
        return load_config(opts.config)
    text = rec.metadata.get("config")
    if not text:
        raise RecordingError(f"{source}: no configuration stored in the recording; give --config")
    return config_from_dict(_with_rate(json.loads(text), source, said), f"{source} (stored configuration)")


def _initial_and_commands(rec) -> tuple[Any, dict, list[dict]]:
    """The calibration the live run started from (and its event), and the commands it applied, in seq order."""
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
    return initial, initial_event, commands


def _recording(path: str, cfg, rec, initial_event: dict) -> McapSink:
    """The replay recorded at `path`, with the initial calibration and the commands, where they acted: what a
    replay of this copy needs."""
    from fluxcal.service.io.recordings.writer import McapLogger

    out = Path(path)
    logger = McapLogger(out.parent, unit=cfg.unit.name, filename=out.name, rotate_mb=1e9, rotate_s=1e12,
                        metadata=dict(rec.metadata))
    logger.write_event(initial_event)
    return McapSink(logger)


def _coalesce(whole: SampleBlock, cut_seqs, max_samples: int = 20000):
    """Large blocks for speed (the pipeline's output does not depend on blocking), cut where a
    recorded command applies so it lands before the same sample as live."""
    cuts = sorted(set(int(s) for s in cut_seqs))
    edges = np.searchsorted(whole.seq, cuts)
    bounds = sorted(set([0, whole.n_samples, *edges.tolist(), *range(0, whole.n_samples, max_samples)]))
    return [whole.slice(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


#: the unit roundoff of IEEE double precision: one correctly rounded operation errs by at most this, relatively
UNIT_ROUNDOFF = 2.0 ** -53


def rounding_tolerance_nT(largest_nT: float, condition: float, n_samples: int) -> float:
    """The most rounding can make the corrected output of two machines differ when their arithmetic differs
    (docs/recording.md, "Replay equality"): the estimator's information is a sum over the n samples it saw, and
    two orders of summing n terms differ by at most n·u of the sum of their magnitudes, at most n·u relative to
    the normal matrix's column scaling; its solve turns that into at most κ²·n·u in the parameters (κ the
    condition number of the column-scaled design, which the gate reports; κ² that of the normal matrix), and the
    corrected vector y = M (x − c) inherits it in proportion to the field, |y|."""
    return float(largest_nT) * max(float(condition), 1.0) ** 2 * max(int(n_samples), 1) * UNIT_ROUNDOFF


@dataclass
class Compared:
    """The live corrected stream against the replay's, matched by seq (before `before`, a hole's first sample)."""

    n: int = 0
    identical: int = 0
    diff_nT: np.ndarray = field(default_factory=lambda: np.empty(0))   # per sample, the largest component's
    seq: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    field_nT: float = 0.0                                               # the largest |y| compared
    live: int = 0                                                       # live corrected samples (before `before`)
    replayed: int = 0

    @property
    def largest(self) -> tuple[float, int | None]:
        if not self.diff_nT.size:
            return 0.0, None
        k = int(np.argmax(self.diff_nT))
        return float(self.diff_nT[k]), int(self.seq[k])


def _compare(live_blocks, seqs, values, before: int | None = None) -> Compared:
    """Samples of the live corrected stream compared with the replay's, matched by seq; a NaN where the other
    has a number is an infinite difference."""
    if not live_blocks or not seqs:
        live = sum(c.n_samples for c in live_blocks) if live_blocks else 0
        return Compared(live=live, replayed=sum(int(s.size) for s in seqs))
    live_seq = np.concatenate([c.seq for c in live_blocks])
    live_val = np.concatenate([c.corrected_nT for c in live_blocks])
    seq = np.concatenate(seqs)
    val = np.concatenate(values)
    if before is not None:
        keep_l, keep_r = live_seq < before, seq < before
        live_seq, live_val, seq, val = live_seq[keep_l], live_val[keep_l], seq[keep_r], val[keep_r]
    common, il, ir = np.intersect1d(live_seq, seq, return_indices=True)
    a, b = live_val[il], val[ir]
    both_nan = np.isnan(a) & np.isnan(b)
    d = np.where(both_nan, 0.0, np.abs(a - b))
    d = np.where(np.isnan(d), np.inf, d)
    same = np.all((a == b) | both_nan, axis=(1, 2))
    mag = np.linalg.norm(a, axis=-1)
    size = float(np.max(mag[np.isfinite(mag)])) if np.isfinite(mag).any() else 0.0
    return Compared(int(common.size), int(same.sum()), d.max(axis=(1, 2)) if d.size else np.empty(0), common,
                    size, int(live_seq.size), int(seq.size))


def _first_hole(rec, unit: str | None) -> tuple[int | None, list]:
    """The first sample seq `unit`'s raw stream lost (-1: the recording's start), to a hole (damage) or a recorder
    gap (io/recordings/gaps: a full disk, from the recording's own health), and what lost them, said as each is."""
    holes = [h for h in rec.holes if h.seq_span(unit) is not None]
    firsts = [(-1 if h.seq_span(unit)[0] is None else h.seq_span(unit)[0]) for h in holes]
    gaps = rec.gaps                                    # found as the recording was read (io/recordings/gaps)
    firsts += [g.seq_before + 1 for g in gaps]
    return (min(firsts) if firsts else None), [(h, h.describe(unit)) for h in holes] + [(g, g.describe()) for g in gaps]


def _arithmetic_said(recorded: dict[str, str]) -> tuple[str, bool]:
    """What replay says of the arithmetic the recording was made with, and whether it is this machine's."""
    from fluxcal.service.io.recordings.arithmetic import (
        another_instruction_set,
        arithmetic_differences,
        machine_arithmetic,
    )

    here = machine_arithmetic()
    diffs = arithmetic_differences(recorded, here)
    if not diffs:
        return "recorded with this machine's arithmetic", True
    if not recorded:
        return (f"the arithmetic it was recorded with: unknown (recorded before fluxcal named it; here: numpy "
                f"{here.get('numpy')}, CPU features {here.get('numpy_simd')}, {here.get('numpy_blas')} "
                f"({here.get('numpy_blas_core') or 'kernels not said'}))"), False
    what = "on another instruction set" if another_instruction_set(recorded, here) else "with other library versions"
    return f"recorded {what} ({'; '.join(diffs)})", False


def _verdict(out: ReplayResult, said: Said, rec, out_seq, cmp: Compared, cut: int | None, holes: list, replaced,
             later: str | None) -> int:
    """Compare, print the verdict (stdout's last line) and what fails (stderr); the exit status: 0 when the replay
    equals the live run (bit for bit on this machine's arithmetic, else within the rounding tolerance) as far as
    the recording allows, 1 when it does not."""
    continued = " (a continuation replayed alone: see above)" if later else ""
    samples = out.samples
    out.holes = len(holes)
    for h, said_as in holes:
        said("gap" if isinstance(h, RecorderGap) else "hole", said_as, level="say")
    if cut is not None:
        after = sum(int(np.count_nonzero(c.seq >= cut)) for c in rec.corrected_blocks)
        said("hole", f"the live run's estimator saw the samples the recording lost and the replay's did not, so the "
                     f"replay cannot follow the live run past them: the {after} corrected sample(s) from seq "
                     f"{max(cut, 0)} on are not compared; those before are", level="say")
    uncorrected = samples - sum(int(s.size) for s in out_seq)
    note = (f" ({uncorrected} earlier sample(s) have no corrected output, live or replayed: no calibration was "
            f"usable yet)" if uncorrected > 0 and cmp.n else "")
    if not cmp.n:
        if cmp.live:
            said("differ", f"the live run has {cmp.live} corrected sample(s), the replay {cmp.replayed} at the same "
                           f"samples: they differ{continued}", level="error")
            return 1
        said("compare", "nothing to compare: the recording holds no corrected samples"
             + (" before its first hole" if cut is not None else " (its calibration was not usable while it ran)")
             + f"; the replay gave {cmp.replayed}", level="say")
        return 0
    arith, same = _arithmetic_said(rec.arithmetic)
    before = [r for r in replaced if cut is None or r[0] < cut]
    kappa = max([r[2] for r in before if np.isfinite(r[2])], default=1.0)
    n_seen = samples if cut is None else int(np.count_nonzero(rec.raw.seq < cut))
    tol = 0.0 if same else rounding_tolerance_nT(cmp.field_nT, kappa, n_seen)
    largest, at = cmp.largest
    beyond = int(np.count_nonzero(cmp.diff_nT > tol))
    out.compared, out.identical, out.same_arithmetic = cmp.n, cmp.identical, same
    out.largest_nT, out.tolerance_nT, out.beyond = float(largest), float(tol), beyond
    head = f"corrected samples compared with the recording: {cmp.n}, bit-identical: {cmp.identical}"
    if cmp.identical == cmp.n:
        out.lines.append(f"{head}{note} — {arith}")
    elif not beyond:
        out.lines.append(f"{head}, equal within {largest:.2g} nT (the largest difference, at seq {at}; tolerance "
                         f"{tol:.2g} nT: rounding amplified by the estimator's conditioning, condition {kappa:.3g} over "
                         f"{n_seen} samples, docs/recording.md){note} — {arith}")
    else:
        why = ("recorded with this machine's arithmetic, where the replay is bit for bit" if same else
               f"tolerance {tol:.2g} nT: rounding amplified by the estimator's conditioning, condition {kappa:.3g} "
               f"over {n_seen} samples")
        out.lines.append(f"{head}, {beyond} beyond the tolerance (the largest difference {largest:.3g} nT at seq "
                         f"{at}; {why}){note} — {arith}")
        said("differ", f"{beyond} corrected sample(s) differ from the live run by more than rounding can explain (the "
                       f"largest by {largest:.3g} nT at seq {at}; " + ("bit for bit expected" if same else
                                                                       f"tolerance {tol:.2g} nT") + f"){continued}",
             level="error")
    status = 1 if beyond else 0
    live_events = [(int(e["seq"]), int(e.get("cal_id", -1))) for e in rec.calibration if e.get("kind") == "calibration"
                   and isinstance(e.get("seq"), int) and (cut is None or e["seq"] < cut)]
    ours = [(r[0], r[1]) for r in before if r[3] == "calibration"]
    if rec.calibration and live_events != ours:
        said("differ", f"the calibration was replaced at other samples than in the live run: live (seq, cal_id) "
                       f"{live_events}, replayed {ours}{continued}", level="error")
        status = 1
    return status
