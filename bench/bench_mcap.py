"""Benchmark (not a test): MCAP logging and replay throughput of raw blocks, in probe-samples/s.

Run by hand:  .venv/bin/python bench/bench_mcap.py [--seconds 60] [--block 50] [--runs 3]

Data: the simulated unit, 4 probes at 1 kHz, quantised to the ADC step (lsb 0.001 nT) like the
serial source's output, cut into blocks of 50 samples (one block = one MCAP message). Measured in
one process, best of `--runs`:

    bare encode / decode       encode_raw / decode_raw of every block, no MCAP (the baseline)
    MCAP write  (lz4|zstd|none) McapLogger.write_raw of every block + close (encoding included)
    MCAP read                  McapSource over the file until exhausted (decoding included)
    service write              write_raw + write_corrected (+ the 10 Hz vectors) per block, lz4

Each MCAP figure is printed with its ratio against the bare encode (writes) or decode (reads) of
the same blocks, and the file size per probe-sample.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.block import SampleBlock  # noqa: E402
from drivers.mcap_source import McapSource  # noqa: E402
from drivers.sim.config import load_sim_config  # noqa: E402
from drivers.sim.world import World  # noqa: E402
from service.encoding import decode_raw, encode_raw  # noqa: E402
from service.mcap_sink import McapLogger  # noqa: E402
from service.outputs import CorrectedBlock  # noqa: E402


def cpu_model() -> str:
    name = platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            name = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), name)
    except OSError:
        pass
    return name or platform.machine()


def best_of(runs: int, fn) -> float:
    best = float("inf")
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


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
          f"{n_ps:,} probe-samples; best of {args.runs}")

    payloads: list[bytes] = []

    def enc() -> None:
        payloads[:] = [encode_raw(b) for b in blocks]

    def dec() -> None:
        for p in payloads:
            decode_raw(p)

    t_enc = best_of(args.runs, enc)
    t_dec = best_of(args.runs, dec)
    raw_bytes = sum(len(p) for p in payloads)
    print(f"{'bare encode_raw':<28}{n_ps / t_enc:>14,.0f} probe-samples/s   ({raw_bytes / n_ps:.1f} B/probe-sample)")
    print(f"{'bare decode_raw':<28}{n_ps / t_dec:>14,.0f} probe-samples/s")

    tmp = Path(tempfile.mkdtemp(prefix="bench_mcap_"))
    try:
        for compression in ("lz4", "zstd", "none"):
            path = tmp / f"{compression}.mcap"

            def write() -> None:
                with McapLogger(path, unit="bench", compression=compression) as log:
                    for b in blocks:
                        log.write_raw(b)

            def read() -> None:
                src = McapSource(path)
                while not src.exhausted:
                    src.read()

            t_w = best_of(args.runs, write)
            t_r = best_of(args.runs, read)
            size = path.stat().st_size
            print(f"{'MCAP write, ' + compression:<28}{n_ps / t_w:>14,.0f} probe-samples/s   "
                  f"{t_enc / t_w:5.2f}x bare encode   file {size / n_ps:5.2f} B/probe-sample "
                  f"({size / raw_bytes:.0%} of the payloads)")
            print(f"{'MCAP read (replay), ' + compression:<28}{n_ps / t_r:>14,.0f} probe-samples/s   "
                  f"{t_dec / t_r:5.2f}x bare decode")

        cors = [CorrectedBlock(b.t_s, b.seq, b.field_nT * 1.0001, b.field_nT[:, 1:] - b.field_nT[:, :1], None,
                               b.field_nT.mean(axis=1), 1) for b in blocks]

        def service_write() -> None:
            with McapLogger(tmp / "svc.mcap", unit="bench") as log:
                for b, c in zip(blocks, cors):
                    log.write_raw(b)
                    log.write_corrected(c)

        t_s = best_of(args.runs, service_write)
        print(f"{'service write, lz4':<28}{n_ps / t_s:>14,.0f} probe-samples/s   "
              f"{t_enc / t_s:5.2f}x bare encode of the raw blocks alone "
              f"(raw + corrected + 10 Hz vectors; {args.seconds / t_s:,.0f}x real time)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
