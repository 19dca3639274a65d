"""Benchmark (not a test) of MCAP logging and replay, printed with the machine it ran on.

Throughput of raw SampleBlocks of 4 probes x 50 samples (1 kHz, random fields, a NaN per block and a
"ref_total" extra column) in probe-samples/s, through:

    baseline      encode_raw, decode_raw, and both, of every block: the bare encoding, no MCAP
    write         McapLogger.write_raw of every block + close (chunked, compressed, on disk); ratio to encode
    read          McapSource (the replay source) draining the same file(s); ratio to decode
    write+read    both, the round trip a record-then-replay does; ratio to encode+decode

for each chunk compression the installed mcap writer supports (lz4, zstd, none), and the file size
per sample. Ratios are rates against the baseline measured in the same process (best of
--repeat rounds; each round runs every case), so another job on the machine moves both.
A ratio of 0.5 means MCAP halves the throughput of the bare encoding.

Run by hand:  .venv/bin/python bench/bench_mcap.py [--blocks 4000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import mcap
import numpy as np

from drivers.block import SampleBlock
from drivers.mcap_source import McapSource
from service.encoding import decode_raw, encode_raw
from service.mcap_sink import McapLogger

N_PROBES, N_SAMPLES, RATE_HZ = 4, 50, 1000.0
COMPRESSIONS = ("lz4", "zstd", "none")


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    try:
        mcap_version = mcap.__version__
    except AttributeError:
        from importlib.metadata import version

        mcap_version = version("mcap")
    return (f"{cpu}, {os.cpu_count()} cores, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}, numpy {np.__version__}, mcap {mcap_version}")


def make_blocks(n_blocks: int, seed: int = 0) -> list[SampleBlock]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_blocks):
        k = i * N_SAMPLES + np.arange(N_SAMPLES)
        f = rng.normal(0, 3e4, (N_SAMPLES, N_PROBES, 3))
        f[7, 1, 2] = np.nan
        out.append(SampleBlock(t_s=k / RATE_HZ, seq=k.astype(np.int64), field_nT=f,
                               temp_C=rng.normal(20, 2, (N_SAMPLES, N_PROBES)),
                               flags=np.zeros(N_SAMPLES, np.uint8), extras={"ref_total": rng.normal(5e4, 1, N_SAMPLES)}))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", type=int, default=4000, help="blocks of 4 x 50 samples (default 4000)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds of every measurement; the best is kept")
    args = ap.parse_args()

    blocks = make_blocks(args.blocks)
    payloads = [encode_raw(b) for b in blocks]
    probe_samples = args.blocks * N_SAMPLES * N_PROBES
    print(f"machine: {machine()}")
    print(f"{args.blocks} blocks of {N_PROBES} probes x {N_SAMPLES} samples = {probe_samples:,} probe-samples, "
          f"best of {args.repeat} rounds (each round runs every case, so a busy machine slows all alike)")

    tmp = Path(tempfile.mkdtemp(prefix="bench_mcap_"))

    def encode() -> None:
        for b in blocks:
            encode_raw(b)

    def decode() -> None:
        for d in payloads:
            decode_raw(d)

    def write(compression: str) -> None:
        out = tmp / compression
        shutil.rmtree(out, ignore_errors=True)
        log = McapLogger(out, unit="bench", compression=compression, flush_interval_s=1.0)
        for b in blocks:
            log.write_raw(b)
        log.close()
        assert log.errors == 0, log.last_error

    def read(compression: str) -> None:
        src = McapSource(tmp / compression)
        n = 0
        while not src.exhausted:
            n += src.read(0.0).n_samples
        src.close()
        assert n == args.blocks * N_SAMPLES, n

    cases: dict[str, Callable[[], None]] = {"encode": encode, "decode": decode}
    for c in COMPRESSIONS:
        cases[f"{c} write"] = lambda c=c: write(c)
        cases[f"{c} read"] = lambda c=c: read(c)
    times = dict.fromkeys(cases, float("inf"))
    try:
        for _ in range(args.repeat):
            for name, fn in cases.items():
                t0 = time.perf_counter()
                fn()
                times[name] = min(times[name], time.perf_counter() - t0)
        sizes = {c: sum(f.stat().st_size for f in (tmp / c).glob("*.mcap")) for c in COMPRESSIONS}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    def line(label: str, t: float, base_t: float, base: str) -> None:
        rate = probe_samples / t
        print(f"{label:<24} {rate / 1e6:7.2f} M probe-samples/s  {base_t / t:5.2f} x {base}")

    line("encode (baseline)", times["encode"], times["encode"], "encode")
    line("decode (baseline)", times["decode"], times["decode"], "decode")
    t_bare = times["encode"] + times["decode"]
    line("encode+decode (baseline)", t_bare, t_bare, "encode+decode")
    for c in COMPRESSIONS:
        line(f"{c} MCAP write", times[f"{c} write"], times["encode"], "encode")
        line(f"{c} MCAP read (replay)", times[f"{c} read"], times["decode"], "decode")
        line(f"{c} MCAP write+read", times[f"{c} write"] + times[f"{c} read"], t_bare, "encode+decode")
        print(f"{c + ' file':<24} {sizes[c] / 1e6:7.2f} MB, {sizes[c] / (args.blocks * N_SAMPLES):.1f} bytes/sample "
              f"(encoded payload {len(payloads[0]) / N_SAMPLES:.1f} bytes/sample)")


if __name__ == "__main__":
    main()
