"""Benchmark (not a test): MCAP logging and replay throughput of raw blocks, in probe-samples/s.

Run by hand:  .venv/bin/python bench/bench_mcap.py [--seconds 60] [--block 50] [--runs 3]

Data: the simulated unit, 4 probes at 1 kHz, quantised to the ADC step (lsb 0.001 nT) like the
serial source's output, cut into blocks of 50 samples (one block = one MCAP message). Measured in
one process, best of `--runs`:

    bare encode / decode       encode_raw / decode_raw of every block, no MCAP (the baseline)
    MCAP write  (lz4|zstd|none) McapLogger.write_raw of every block + close (encoding included)
    MCAP read                  McapSource over the file until exhausted (decoding included)
    MCAP write + read          the round trip of a record-then-replay
    read_recording / read_samples   replay's and fit's / diagnose's readers of the lz4 file, whole
    service write              write_raw + write_corrected (+ the 10 Hz vectors) per block, lz4

Each MCAP figure is printed with its ratio against the bare encode (writes), decode (reads) or
encode + decode (round trip) of the same blocks, and the file size per probe-sample. Every round
runs every case, so another job on the machine slows baseline and MCAP alike.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _machine import cpu_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluxcal.drivers.block import SampleBlock  # noqa: E402
from fluxcal.drivers.mcap_source import McapSource  # noqa: E402
from fluxcal.drivers.sim.config import load_sim_config  # noqa: E402
from fluxcal.drivers.sim.world import World  # noqa: E402
from fluxcal.service.io.encoding import decode_raw, encode_raw  # noqa: E402
from fluxcal.service.io.recordings.reader import read_recording, read_samples  # noqa: E402
from fluxcal.service.io.recordings.writer import McapLogger  # noqa: E402
from fluxcal.service.numerics.outputs import CorrectedBlock  # noqa: E402


def make_blocks(seconds: float, block: int, n_probes: int = 4, rate_hz: float = 1000.0) -> list[SampleBlock]:
    probes = [{"offset_nT": [100.0 * k, -50.0, 30.0], "noise_nT": 0.5} for k in range(n_probes)]
    cfg = load_sim_config({"duration_s": seconds, "rate_hz": rate_hz, "probes": probes})
    raw = World(cfg).samples(0, cfg.n_samples).raw_nT                      # (N, P, 3)
    field = np.round(raw / 0.001) * 0.001                                  # counts x lsb_nT, like the unit
    n = field.shape[0]
    temp = np.round((20.0 + 0.01 * np.arange(n)[:, None] / rate_hz + np.zeros((1, n_probes))) / 0.01) * 0.01
    t = np.arange(n) / rate_hz
    seq = np.arange(n, dtype=np.int64)
    flags = np.zeros(n, np.uint8)
    return [SampleBlock(t_s=t[i:i + block], seq=seq[i:i + block], field_nT=field[i:i + block],
                        temp_C=temp[i:i + block], flags=flags[i:i + block]) for i in range(0, n, block)]


COMPRESSIONS = ("lz4", "zstd", "none")


def make_cases(blocks: list[SampleBlock], payloads: list[bytes], tmp: Path, n_ps: int) -> dict[str, Callable[[], None]]:
    """Every measured case by name (see the module docstring) over the blocks and their encoded payloads, its
    files written to and read from `tmp`."""
    cors = [CorrectedBlock(b.t_s, b.seq, b.field_nT * 1.0001, b.field_nT[:, 1:] - b.field_nT[:, :1], None,
                           b.field_nT.mean(axis=1), 1) for b in blocks]

    def encode() -> None:
        for b in blocks:
            encode_raw(b)

    def decode() -> None:
        for p in payloads:
            decode_raw(p)

    def write(compression: str) -> None:
        with McapLogger(tmp / f"{compression}.mcap", unit="bench", compression=compression) as log:
            for b in blocks:
                log.write_raw(b)
        assert log.errors == 0, log.last_error

    def read(compression: str) -> None:
        src = McapSource(tmp / f"{compression}.mcap")
        n = 0
        while not src.exhausted:
            n += src.read().n_samples
        assert n * 4 == n_ps

    def service_write() -> None:
        with McapLogger(tmp / "svc.mcap", unit="bench") as log:
            for b, c in zip(blocks, cors):
                log.write_raw(b)
                log.write_corrected(c)

    def whole(reader) -> None:
        n = reader(tmp / "lz4.mcap").raw.n_samples
        assert n * 4 == n_ps

    cases = {"encode": encode, "decode": decode, "service": service_write}
    for c in COMPRESSIONS:
        cases[f"{c} write"] = lambda c=c: write(c)
        cases[f"{c} read"] = lambda c=c: read(c)
    cases["read_recording"] = lambda: whole(read_recording)
    cases["read_samples"] = lambda: whole(read_samples)
    return cases


def best_times(cases: dict[str, Callable[[], None]], runs: int) -> dict[str, float]:
    """The best wall time of each case over `runs` rounds, each round running every case."""
    best = dict.fromkeys(cases, float("inf"))
    for _ in range(runs):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            fn()
            best[name] = min(best[name], time.perf_counter() - t0)
    return best


def print_results(best: dict[str, float], n_ps: int, raw_bytes: int, sizes: dict[str, int], seconds: float) -> None:
    """One line per case: probe-samples/s, the ratio against the bare encode / decode, the file size."""
    def line(label: str, t: float, ratio: str = "", extra: str = "") -> None:
        print(f"{label:<30}{n_ps / t:>14,.0f} probe-samples/s  {ratio:<26}{extra}")

    t_enc, t_dec = best["encode"], best["decode"]
    line("bare encode_raw", t_enc, "", f"{raw_bytes / n_ps:.1f} B/probe-sample")
    line("bare decode_raw", t_dec)
    line("bare encode + decode", t_enc + t_dec)
    for c in COMPRESSIONS:
        t_w, t_r = best[f"{c} write"], best[f"{c} read"]
        line(f"MCAP write, {c}", t_w, f"{t_enc / t_w:5.2f}x bare encode",
             f"file {sizes[c] / n_ps:5.2f} B/probe-sample ({sizes[c] / raw_bytes:.0%} of the payloads)")
        line(f"MCAP read (replay), {c}", t_r, f"{t_dec / t_r:5.2f}x bare decode")
        line(f"MCAP write + read, {c}", t_w + t_r, f"{(t_enc + t_dec) / (t_w + t_r):5.2f}x bare encode + decode")
    for name, what in (("read_recording", "replay's"), ("read_samples", "fit's, diagnose's")):
        line(f"{name} (lz4, {what})", best[name], f"{t_dec / best[name]:5.2f}x bare decode",
             "the whole recording into one block")
    t_s = best["service"]
    line("service write, lz4", t_s, f"{t_enc / t_s:5.2f}x bare encode (raw)",
         f"raw + corrected + 10 Hz vectors; {seconds / t_s:,.0f}x real time")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--block", type=int, default=50)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()

    import mcap

    blocks = make_blocks(args.seconds, args.block)
    n_ps = sum(b.n_samples * b.n_probes for b in blocks)
    print(f"machine: {cpu_model()} ({platform.machine()}), os.cpu_count() = {os.cpu_count()}, "
          f"Python {platform.python_version()}, numpy {np.__version__}, mcap {getattr(mcap, '__version__', '?')}")
    print(f"data: {len(blocks)} blocks of {args.block} samples x 4 probes ({args.seconds:.0f} s at 1 kHz), "
          f"{n_ps:,} probe-samples; best of {args.runs} rounds, each round runs every case (a busy machine "
          f"slows all alike)")
    payloads = [encode_raw(b) for b in blocks]
    raw_bytes = sum(len(p) for p in payloads)
    tmp = Path(tempfile.mkdtemp(prefix="bench_mcap_"))
    try:
        best = best_times(make_cases(blocks, payloads, tmp, n_ps), args.runs)
        sizes = {c: (tmp / f"{c}.mcap").stat().st_size for c in COMPRESSIONS}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print_results(best, n_ps, raw_bytes, sizes, args.seconds)


if __name__ == "__main__":
    main()
