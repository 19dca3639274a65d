"""Benchmark: serial ICD parsing of 4-probe frames, frames per second, as a ratio against a
straightforward frame-by-frame parser (struct.unpack, resync on the sync word, byte-wise CRC) run in
the same process on the same bytes. Run by hand:

    .venv/bin/python bench/bench_parse.py [--frames 50000] [--repeat 5]

Acceptance target: >= 1,000,000 frames/s for the vectorised parser.
"""

from __future__ import annotations

import argparse
import os
import platform
import struct
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluxcal.drivers import icd  # noqa: E402
from fluxcal.drivers.assemble import SerialFramer  # noqa: E402

N_PROBES = 4


def baseline_parse(buf: bytes, n: int) -> int:
    """One frame at a time: find the sync, check version, n and CRC, unpack with struct."""
    fl = icd.frame_length(n)
    body = struct.Struct(f"<BBHI{3 * n}i{n}hB")
    crc_field = struct.Struct("<H")
    found, i = 0, 0
    while True:
        i = buf.find(b"\xa5\x5a", i)
        if i < 0 or i + fl > len(buf):
            return found
        if buf[i + 2] == icd.VERSION and buf[i + 3] == n:
            (crc,) = crc_field.unpack_from(buf, i + fl - 2)
            if icd.crc16_ccitt_false(buf[i + 2:i + fl - 2]) == crc:
                body.unpack_from(buf, i + 2)
                found += 1
                i += fl
                continue
        i += 1


def make_stream(frames: int, noise: bool, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    k = np.arange(frames)
    # field-like counts: 50 uT with a slow rotation and noise, at 0.001 nT per count
    phase = 2 * np.pi * k / 2000.0
    base = np.stack([np.cos(phase), np.sin(phase), 0.5 * np.ones_like(phase)], axis=1) * 5e7
    counts = (base[:, None, :] + rng.normal(0, 500, (frames, N_PROBES, 3))).astype(np.int32)
    temp = (2500 + rng.normal(0, 10, (frames, N_PROBES))).astype(np.int16)
    buf = icd.encode_serial(k, k * 1000, counts, temp, np.zeros(frames, np.uint8))
    if not noise:
        return buf
    # line noise: a burst of random bytes after about one frame in a thousand
    fl = icd.frame_length(N_PROBES)
    out, last = bytearray(), 0
    for at in np.sort(rng.choice(frames, frames // 1000, replace=False)):
        out += buf[last:at * fl] + rng.integers(0, 256, 20, dtype=np.uint8).tobytes()
        last = at * fl
    out += buf[last:]
    return bytes(out)


def best_of(fn, repeat: int) -> tuple[float, int]:
    times, result = [], 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return min(times), result


def framer_parse(buf: bytes, chunk: int) -> int:
    framer = SerialFramer(N_PROBES)
    for i in range(0, len(buf), chunk):
        framer.feed(buf[i:i + chunk])
    framer.finish()
    return framer.counters.frames_accepted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50_000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()

    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, Python {platform.python_version()}, numpy {np.__version__}")
    print(f"{args.frames} frames of {N_PROBES} probes ({icd.frame_length(N_PROBES)} bytes each), best of {args.repeat}")
    for noise in (False, True):
        buf = make_stream(args.frames, noise)
        t_base, n_base = best_of(lambda: baseline_parse(buf, N_PROBES), 1)
        rate_base = n_base / t_base
        label = "with line noise" if noise else "clean"
        print(f"\n[{label}: {len(buf) / 2**20:.1f} MiB]")
        print(f"  baseline struct parser     {rate_base:12,.0f} frames/s   1.0x")
        cases = [("parse_serial, whole buffer", lambda: len(icd.parse_serial(buf, N_PROBES, final=True).frames))]
        for chunk in (4 << 20, 64 << 10, 4 << 10):
            cases.append((f"SerialFramer, {chunk >> 10} KiB chunks", lambda c=chunk: framer_parse(buf, c)))
        for name, fn in cases:
            t, n = best_of(fn, args.repeat)
            assert n == n_base, f"{name}: {n} frames, baseline {n_base}"
            print(f"  {name:<26} {n / t:12,.0f} frames/s {n / t / rate_base:6.1f}x")


if __name__ == "__main__":
    main()
