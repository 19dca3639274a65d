"""Benchmarks (not tests) of the service, printed with the machine they ran on.

1. Replay throughput in probe-samples/s, including MCAP decode and write, of a 4-probe 1 kHz
   recording cut into the 20-sample blocks a live unit delivers, against the bare numerics
   (ICD parse + calibrate) of the same samples in the same run, and the floor: the parts of that replay no
   implementation with the same outputs can skip, each timed alone.
2. The live service (`fluxcal run` under a simulated unit on a pty) at 1, 2 and 5 kHz x 4 probes and 1 kHz x 8:
   its CPU time (process CPU, all threads, and by thread) as a share of one core, per probe-sample and against the
   bare numerics of the same samples timed in this process; latency from a frame written to the pty to its corrected
   Zenoh message received, p50 and p99. Each case several times (min and median). With --profile, first one run
   with the stages of the service's loop timed (bench/_stages.py): where each microsecond of a block goes.

Run by hand, under the shared lock:  flock /tmp/fluxcal-heavy.lock .venv/bin/python bench/bench_service.py [--profile]
(the replay runs with OPENBLAS_NUM_THREADS=1 unless set, as `fluxcal replay` does; the live service is
started with the environment this was given, as a user starts it)
"""

from __future__ import annotations

import os

_USER_BLAS_THREADS = os.environ.get("OPENBLAS_NUM_THREADS")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")        # before numpy loads: the replay CLI's setting

import argparse
import platform
import resource
import tempfile
import time
import zlib
from pathlib import Path

import numpy as np
from _live import SUBSCRIBED, bare_seconds, config_text, identity, make_samples, probes
from _machine import cpu_model

from fluxcal.drivers.block import SampleBlock
from fluxcal.service.io.calfile import load_calibration

N_PROBES, RATE = 4, 1000.0
PROBES = probes(N_PROBES)


def machine() -> str:
    return f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}"


def bench_replay(tmp: Path, seconds: float, repeat: int) -> None:
    import tomllib

    from fluxcal.service.io.recordings import files, writer
    from fluxcal.service.wiring import pipeline as pipeline_mod
    from fluxcal.service.wiring.config import config_from_dict

    s = make_samples(seconds, RATE, PROBES)
    block = s.to_block()
    log = writer.McapLogger(tmp / "rep", unit="bench", filename="in.mcap")
    for i in range(0, block.n_samples, 20):
        log.write_raw(block.slice(i, i + 20))
    log.close()
    initial = identity(tmp, PROBES)
    fcfg = config_from_dict(tomllib.loads(config_text(tmp, '[source]\nkind = "sim"', 7447, initial, PROBES, RATE)))
    start = load_calibration(initial)
    # the parts of the replay, each call's wall time added to its part (the pipeline's and the writer's)
    parts = {"gate": _timed(pipeline_mod.Pipeline, "_check_candidate"),
             "estimator": _timed(pipeline_mod.Pipeline, "_update_estimators"),
             "correction and products": _timed(pipeline_mod.Pipeline, "_correct"),
             "chunks (lz4, CRC, file)": _timed(files.McapFiles, "finish", _timed(files.McapFiles, "flush")),
             "10 Hz means": _timed(writer.Products, "corrected"), "their JSON": _timed(writer, "encode_json")}
    # replay path: MCAP decode -> pipeline (estimator, gate, correction) -> MCAP write; in one process, then with
    # the gate's checks worked out in a second (gate_ahead.py, as `fluxcal replay` does where that pays)
    runs: dict[str, tuple[list[float], list]] = {"one process": ([], []), "gate ahead": ([], [])}
    for rep in range(repeat):
        for mode, (times, phases) in runs.items():
            for spent in parts.values():
                spent.clear()
            times.append(_replay_once(tmp, fcfg, start, f"out{rep}.mcap", ahead=mode == "gate ahead", split=phases))
            phases[-1] = phases[-1] + ({k: (sum(v), len(v)) for k, v in parts.items()},)
    t_bare = bare_seconds(s, N_PROBES, time.perf_counter, runs=3)
    n = block.n_samples * N_PROBES
    print(f"bare parse + calibrate of {block.n_samples} samples x {N_PROBES} probes: {n / t_bare:,.0f} probe-samples/s "
          f"({t_bare * 1e3:.1f} ms)")
    for mode, (times, phases) in runs.items():
        t_replay = min(times)
        print(f"replay (MCAP decode + pipeline + MCAP write), {mode}: {n / t_replay:,.0f} probe-samples/s (best of "
              f"{repeat}; median {n / float(np.median(times)):,.0f}); ratio replay / bare: best {t_bare / t_replay:.3f}, "
              f"median {t_bare / float(np.median(times)):.3f} (OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')})")
        dec, pip, wri, (own, kids), split = phases[times.index(t_replay)]
        print(f"  best run: MCAP decode {dec * 1e3:.0f} ms, pipeline {pip * 1e3:.0f} ms, MCAP write {wri * 1e3:.0f} ms; "
              "of these: " + ", ".join(f"{k} {v * 1e3:.0f} ms ({c} calls)" for k, (v, c) in split.items()))
        cpus = [(o + c) for (*_, (o, c), _) in phases]
        print(f"  CPU: the replay's process {own * 1e3:.0f} ms, the second process {kids * 1e3:.0f} ms (best run); "
              f"both, median of the runs, {float(np.median(cpus)) * 1e3:.0f} ms: spread perfectly over "
              f"{_cores()} cores at best {t_bare * _cores() / float(np.median(cpus)):.3f}x")
    floor_parts(block, t_bare)


def _replay_once(tmp: Path, fcfg, start, out_name: str, *, ahead: bool, split: list) -> float:
    """One replay of tmp/rep/in.mcap to out_name, timed; appends (decode, pipeline, write) seconds to `split`."""
    from fluxcal.service.io.recordings import writer
    from fluxcal.service.io.recordings.reader import read_recording
    from fluxcal.service.wiring.daemon import build_pipeline
    from fluxcal.service.wiring.gate_ahead import GateAhead

    own0, kids0 = _cpu(resource.RUSAGE_SELF), _cpu(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    whole = read_recording(tmp / "rep" / "in.mcap").raw     # every raw sample, as `fluxcal replay` takes them
    t_decode = time.perf_counter() - t0
    pipe = build_pipeline(fcfg, start)      # corrected from the first sample, as a recording's initial event does
    blocks = [whole.slice(i, i + 20000) for i in range(0, whole.n_samples, 20000)]
    second = GateAhead(pipe, lambda pl: [pl.process(b) for b in blocks]) if ahead else None
    t_pipe = time.perf_counter() - t0 - t_decode
    out = writer.McapLogger(tmp / "rep", unit="bench", filename=out_name)
    for b in blocks:
        t1 = time.perf_counter()
        r = pipe.process(b)
        t_pipe += time.perf_counter() - t1
        out.write_raw(b)
        if r.corrected is not None:
            out.write_corrected(r.corrected)
    out.close()
    t = time.perf_counter() - t0
    if second is not None:
        assert second.fallback is None, second.fallback
        second.close()                  # joined: its CPU is counted among the children's
    cpu = (_cpu(resource.RUSAGE_SELF) - own0, _cpu(resource.RUSAGE_CHILDREN) - kids0)
    split.append((t_decode, t_pipe, t - t_decode - t_pipe, cpu))
    return t


def _cpu(who: int) -> float:
    """User + system CPU seconds of this process (all its threads) or of its joined children."""
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _timed(owner, name: str, spent: list[float] | None = None) -> list[float]:
    """Wrap owner.name (a class's method or a module's function) to add each call's wall time to the list
    returned (`spent`, when given)."""
    spent = [] if spent is None else spent
    inner = getattr(owner, name)

    def wrapper(*a, **k):
        t0 = time.perf_counter()
        try:
            return inner(*a, **k)
        finally:
            spent.append(time.perf_counter() - t0)

    setattr(owner, name, wrapper)
    return spent


def floor_parts(block: SampleBlock, t_bare: float) -> None:
    """The work no replay with unchanged outputs can skip, each part timed alone on the same samples (best of 3):
    the input's lz4 frames decompressed, the estimator's normal equations accumulated in the pipeline's 0.5-s
    chunks, the correction with its differences and tensor, and the raw and corrected streams compressed with
    lz4 as the logger writes them. Their sum against the 2 x bare that a 0.5x ratio allows."""
    import lz4.frame

    from fluxcal.drivers.encoding import encode_raw
    from fluxcal.service.io.encoding import encode_corrected
    from fluxcal.service.numerics.calib.rls import RlsEllipsoid
    from fluxcal.service.numerics.outputs import products

    def best(f, k: int = 3) -> float:
        ts = []
        for _ in range(k):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        return min(ts)

    raw_bytes = encode_raw(block)
    packed = lz4.frame.compress(raw_bytes)
    m, o = np.stack([np.eye(3)] * N_PROBES), np.zeros((N_PROBES, 3))
    pos = np.array([p["position_m"] for p in PROBES], dtype=float)

    def rls() -> None:
        est = RlsEllipsoid(n_probes=N_PROBES)
        for i in range(0, block.n_samples, 500):
            est.partial_fit(block.field_nT[i:i + 500], total_nT=52500.0)

    def correct(lo: int = 0, hi: int | None = None):
        b = block.slice(lo, block.n_samples if hi is None else hi)
        d = b.field_nT - o[None]                     # the pipeline's element-by-element product
        c = d[..., 0:1] * m[None, :, :, 0] + d[..., 1:2] * m[None, :, :, 1] + d[..., 2:3] * m[None, :, :, 2]
        return products(b.t_s, b.seq, c, pos, 1)

    def correct_all() -> None:                       # in the pipeline's spans: one gate check (5 s) each
        for i in range(0, block.n_samples, 5000):
            correct(i, i + 5000)

    corrected_bytes = encode_corrected(correct())
    mb = 1 << 20                                     # the logger's chunks: 1 MiB before compression

    def compress() -> None:
        for data in (raw_bytes, corrected_bytes):
            for i in range(0, len(data), mb):
                lz4.frame.compress(data[i:i + mb])

    def crc() -> None:                               # each chunk's CRC, which the MCAP writer stores and readers check
        for data in (raw_bytes, corrected_bytes):
            for i in range(0, len(data), mb):
                zlib.crc32(data[i:i + mb])

    pack = "lz4 compress of raw + corrected out"
    parts = {"lz4 decompress of the input": best(lambda: lz4.frame.decompress(packed)),
             "RLS normal equations": best(rls),
             "correction, differences, tensor": best(correct_all),
             pack: best(compress), "CRC32 of the chunks": best(crc)}
    total = sum(parts.values())
    print("  floor, each part alone: " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in parts.items())
          + f"; sum {total * 1e3:.0f} ms against the {2e3 * t_bare:.0f} ms a 0.5x ratio allows "
          f"(at best {t_bare / total:.2f}x; {(len(raw_bytes) + len(corrected_bytes)) / 1e6:.1f} MB written; "
          f"written uncompressed, at best {t_bare / (total - parts[pack]):.2f}x)")
    cores = os.cpu_count() or 1
    print(f"  spread perfectly over all {cores} cores (no part waiting for another): at best "
          f"{t_bare * cores / total:.2f}x, uncompressed {t_bare * cores / (total - parts[pack]):.2f}x, "
          f"before the gate's checks that the same outputs need (above)")
    compression_choices(raw_bytes + corrected_bytes, best)


def compression_choices(data: bytes, best) -> None:
    """The logger's chunk size and compression by measurement: lz4 of the replay's output in chunks of 64 KiB to
    4 MiB, and at its faster levels, with the size each leaves (best of 3)."""
    import lz4.frame

    def rate(size: int, level: int = 0) -> tuple[float, float]:
        pieces = [data[i:i + size] for i in range(0, len(data), size)]
        out: list[int] = []
        t = best(lambda: out.append(sum(len(lz4.frame.compress(p, compression_level=level)) for p in pieces)))
        return len(data) / t / 1e6, out[-1] / len(data)

    sizes = ", ".join("{} KiB {:.0f} MB/s".format(k >> 10, rate(k)[0]) for k in (64 << 10, 256 << 10, 1 << 20, 4 << 20))
    levels = ", ".join("level {} {:.0f} MB/s to {:.2f} of the size".format(lv, *rate(1 << 20, lv))
                       for lv in (0, -1, -4))
    print(f"  lz4 of the output by chunk size: {sizes}; by level (1 MiB chunks): {levels}")


def _stats(values) -> str:
    v = sorted(values)
    return f"{v[0]:.1f}" if len(v) == 1 else f"min {v[0]:.1f}, median {float(np.median(v)):.1f}"


def print_profile(run) -> None:
    """Where the CPU time of one live block goes: the stages of the service's loop (thread CPU time, inclusive, and
    each stage's own), and the process's threads (from /proc over the run)."""
    st, blocks = run.stages, max(run.stages["blocks"], 1)
    rows = {label: (ns, calls) for label, ns, calls in st["stages"]}
    print(f"  profile of one live block ({run.n_probes} probes at {run.rate:.0f} Hz, {blocks} blocks of "
          f"{run.rate * run.seconds / blocks:.1f} samples; thread CPU per block, us; own = the stage less those "
          f"indented under it):")
    for label, (ns, calls) in rows.items():
        children = [lb for lb in rows if lb.startswith(label + "/") and "/" not in lb[len(label) + 1:]]
        own = ns - sum(rows[c][0] for c in children)
        depth = label.count("/")
        name = label.rsplit("/", 1)[-1]
        print(f"    {'  ' * depth}{name:<{44 - 2 * depth}} {ns / 1e3 / blocks:8.1f}"
              + (f"  own {own / 1e3 / blocks:7.1f}" if children else " " * 13) + f"   {calls / blocks:6.2f} calls")
    per = {k: v * 1e6 / blocks for k, v in run.groups.items()}
    print("    threads (/proc schedstat): " + ", ".join(f"{k} {v:.0f}" for k, v in per.items())
          + f"; all {run.cpu_s * 1e6 / blocks:.0f} us per block ({100 * run.core:.1f} % of a core with the timers)")


def bench_live(cases: list[tuple[float, int]], seconds: float, repeat: int, block_ms: float | None,
               profile: bool, subscribe: str = "corrected") -> None:
    from _live import live_floor, live_run

    if profile:
        print_profile(live_run(cases[0][0], cases[0][1], seconds, block_ms, _USER_BLAS_THREADS, profile=True, subscribe=subscribe))
    base = None
    for rate, n_probes in cases:
        runs = [live_run(rate, n_probes, seconds, block_ms, _USER_BLAS_THREADS, subscribe=subscribe)
                for _ in range(repeat)]
        core = [100 * r.core for r in runs]
        us_ps = [r.cpu_s * 1e6 / r.probe_samples for r in runs]
        ratio = [r.cpu_s / r.bare_s for r in runs]
        groups = {k: [100 * r.groups[k] / r.wall_s for r in runs] for k in runs[0].groups}
        p50 = [float(np.percentile(r.lat_ms, 50)) for r in runs]
        p99 = [float(np.percentile(r.lat_ms, 99)) for r in runs]
        p99o = [float(np.percentile(r.lat_oldest_ms, 99)) for r in runs]
        if base is None:
            base = float(np.median(core))
        floor_us, floor_core = live_floor(rate, n_probes, seconds, block_ms or 8.0)
        print(f"live, {n_probes} probes at {rate:.0f} Hz over a pty, block_ms {block_ms or 'default'}, heard: "
              f"{', '.join(SUBSCRIBED[subscribe])}, {repeat} x "
              f"{seconds:.0f} s: service CPU % of one core {_stats(core)} (all threads; "
              + ", ".join(f"{k} {_stats(v)}" for k, v in groups.items())
              + f"); {_stats(us_ps)} us per probe-sample, {_stats(ratio)} x the bare parse + calibrate of the same "
              f"samples in this process ({runs[0].bare_s * 1e3:.1f} ms); median {float(np.median(core)) / base:.2f} x "
              f"the first case's CPU. Latency frame written -> corrected message received, newest frame of each "
              f"block: p50 {_stats(p50)} ms, p99 {_stats(p99)} ms; oldest frame p99 {_stats(p99o)} ms. The floor: what "
              f"no service with these outputs can skip (read, parse, scale, correct with differences and tensor, "
              f"encode, nine Zenoh puts, two MCAP messages), in one thread paced as the service: {floor_us:.0f} us a "
              f"block, {100 * floor_core:.1f} % of one core; the service "
              f"{float(np.median(core)) / 100 / floor_core:.2f} x that")


def bench_against(code: Path, rate: float, n_probes: int, seconds: float, pairs: int, block_ms: float | None,
                  subscribe: str = "corrected") -> None:
    """The service of another checkout (`code`: main before a change) and this one's, run by turns in pairs, so that
    what else the machine does weighs on both alike: each pair's CPU ratio, and latency."""
    from _live import live_run

    ratios, cores = [], {"other": [], "this": []}
    p99 = {"other": [], "this": []}
    for _ in range(pairs):
        a = live_run(rate, n_probes, seconds, block_ms, _USER_BLAS_THREADS, code=code, subscribe=subscribe)
        b = live_run(rate, n_probes, seconds, block_ms, _USER_BLAS_THREADS, subscribe=subscribe)
        ratios.append(b.core / a.core)
        for key, r in (("other", a), ("this", b)):
            cores[key].append(100 * r.core)
            p99[key].append(float(np.percentile(r.lat_ms, 99)))
    print(f"live, {n_probes} probes at {rate:.0f} Hz, heard: {', '.join(SUBSCRIBED[subscribe])}, {pairs} pairs of "
          f"{seconds:.0f} s runs by turns: service CPU % of "
          f"one core {code}: {_stats(cores['other'])}; this checkout: {_stats(cores['this'])}; this / that in each "
          f"pair: {_stats(ratios)} ({', '.join(f'{r:.2f}' for r in ratios)}); latency p99 (newest frame) "
          f"{_stats(p99['other'])} against {_stats(p99['this'])} ms")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=30.0, help="of each live run")
    ap.add_argument("--repeat", type=int, default=3, help="runs of each live case")
    ap.add_argument("--cases", default="1000x4,2000x4,5000x4,1000x8",
                    help="live cases, RATExPROBES, comma-separated (the first is the one profiled)")
    ap.add_argument("--profile", action="store_true", help="first, one live run with the stages timed")
    ap.add_argument("--against", type=Path, default=None, metavar="CHECKOUT",
                    help="only: the first live case with this checkout's service and this one's by turns, in pairs")
    ap.add_argument("--live-only", action="store_true", help="skip the replay benchmark")
    ap.add_argument("--replay-only", action="store_true", help="skip the live benchmark")
    ap.add_argument("--subscribe", choices=sorted(SUBSCRIBED), default="corrected",
                    help="what a client hears in the live runs: the corrected stream (timed), or every stream")
    ap.add_argument("--block-ms", type=float, default=None,
                    help="[unit] block_ms of the live service (default: its default)")
    args = ap.parse_args()
    cases = [(float(c.split("x")[0]), int(c.split("x")[1])) for c in args.cases.split(",")]
    print("machine:", machine())
    if args.against is not None:
        bench_against(args.against, cases[0][0], cases[0][1], args.seconds, args.repeat, args.block_ms,
                      args.subscribe)
        return
    with tempfile.TemporaryDirectory() as d:
        if not args.live_only:
            bench_replay(Path(d), 60.0, args.repeat)
    if not args.replay_only:
        bench_live(cases, args.seconds, args.repeat, args.block_ms, args.profile, args.subscribe)


if __name__ == "__main__":
    main()
