"""Benchmarks (not tests) of the service, printed with the machine they ran on.

1. Replay throughput in probe-samples/s, including MCAP decode and write, of a 4-probe 1 kHz
   recording cut into the 20-sample blocks a live unit delivers, against the bare numerics
   (ICD parse + calibrate) of the same samples in the same run, and the floor: the parts of that replay no
   implementation with the same outputs can skip, each timed alone.
2. Live latency from a frame written to the pty to its corrected Zenoh message received, p50 and
   p99, and the service's CPU use, at 1 kHz with 4 probes.

Run by hand:  .venv/bin/python bench/bench_service.py [--seconds 20]
(the replay runs with OPENBLAS_NUM_THREADS=1 unless set, as `fluxcal replay` does; the live service is
started with the environment this was given)
"""

from __future__ import annotations

import os

_USER_BLAS_THREADS = os.environ.get("OPENBLAS_NUM_THREADS")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")        # before numpy loads: the replay CLI's setting

import argparse
import json
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tty
from pathlib import Path

import numpy as np
from _machine import cpu_model

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.icd import encode_serial, parse_serial
from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.unit import Unit
from fluxcal.service.io.calfile import load_calibration, save_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration

N_PROBES, RATE = 4, 1000.0
PROBES = [{"name": f"s{k + 1}", "position_m": p, "offset_nT": [100.0 * k, -50.0, 30.0], "noise_nT": 0.5}
          for k, p in enumerate([[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]])]


def machine() -> str:
    return f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}"


def config_text(tmp: Path, source: str, port: int, initial: Path, block_ms: float | None = None) -> str:
    lines = ['[unit]', 'name = "bench"', f'n_probes = {N_PROBES}'] + ([f'block_ms = {block_ms}'] if block_ms else []) + ['']
    for p in PROBES:
        lines += ['[[probes]]', f'name = "{p["name"]}"', f'position_m = {p["position_m"]}', '']
    lines += [source, '', '[sim]', f'rate_hz = {RATE}', '[sim.reference]', 'enabled = false', '']
    for p in PROBES:
        lines += ['[[sim.probes]]'] + [f'{k} = {json.dumps(v)}' for k, v in p.items()] + ['']
    lines += ['[estimator]', 'total_nT = 52500.0', '[calibration]', f'file = "{tmp / "cal.json"}"',
              f'initial = "{initial}"', '[zenoh]', f'listen = ["tcp/127.0.0.1:{port}"]',
              '[mcap]', f'dir = "{tmp / "rec"}"', '']
    return "\n".join(lines)


def make_samples(seconds: float):
    cfg = load_sim_config({"rate_hz": RATE, "duration_s": seconds, "probes": PROBES})
    unit = Unit(cfg)
    return cfg, unit, unit.digitise(0, cfg.n_samples)


def bench_replay(tmp: Path, seconds: float) -> None:
    import tomllib

    from fluxcal.service.io.recordings.reader import read_recording
    from fluxcal.service.io.recordings.writer import McapLogger
    from fluxcal.service.wiring.config import config_from_dict
    from fluxcal.service.wiring.daemon import build_pipeline

    cfg, unit, s = make_samples(seconds)
    block = s.to_block()
    log = McapLogger(tmp / "rep", unit="bench", filename="in.mcap")
    for i in range(0, block.n_samples, 20):
        log.write_raw(block.slice(i, i + 20))
    log.close()
    initial = tmp / "identity.json"
    save_calibration(ArrayCalibration("ellipsoid", None, [ProbeCalibration(p["name"], np.zeros(3), np.eye(3))
                                                          for p in PROBES]), initial)
    fcfg = config_from_dict(tomllib.loads(config_text(tmp, '[source]\nkind = "sim"', 7447, initial)))
    start = load_calibration(initial)
    # replay path: MCAP decode -> pipeline (estimator, gate, correction) -> MCAP write; best of 3
    times, phases = [], []
    for rep in range(3):
        t0 = time.perf_counter()
        rec = read_recording(tmp / "rep" / "in.mcap")
        whole = rec.raw                          # every raw sample, as `fluxcal replay` takes them
        t_decode = time.perf_counter() - t0
        pipe = build_pipeline(fcfg, start)      # corrected from the first sample, as a recording's initial event does
        t_pipe = time.perf_counter() - t0 - t_decode
        checks = _timed(pipe, "_check_candidate")
        out = McapLogger(tmp / "rep", unit="bench", filename=f"out{rep}.mcap")
        for i in range(0, whole.n_samples, 20000):
            b = whole.slice(i, i + 20000)
            t1 = time.perf_counter()
            r = pipe.process(b)
            t_pipe += time.perf_counter() - t1
            out.write_raw(b)
            if r.corrected is not None:
                out.write_corrected(r.corrected)
        out.close()
        times.append(time.perf_counter() - t0)
        phases.append((t_decode, t_pipe, times[-1] - t_decode - t_pipe, sum(checks), len(checks)))
    t_replay = min(times)
    # bare numerics: parse the ICD bytes and apply a calibration, same samples
    data = encode_serial(s.seq_raw, s.t_us_raw, s.counts, s.temp_raw, s.flags)
    m = np.stack([np.eye(3)] * N_PROBES)
    o = np.zeros((N_PROBES, 3))
    bare = []
    for _ in range(3):
        t0 = time.perf_counter()
        p = parse_serial(data, N_PROBES, final=True)
        f = p.frames.counts * 0.001
        np.einsum("pij,npj->npi", m, f - o[None])
        bare.append(time.perf_counter() - t0)
    t_bare = min(bare)
    n = whole.n_samples * N_PROBES
    print(f"replay (MCAP decode + pipeline + MCAP write), {whole.n_samples} samples x {N_PROBES} probes: "
          f"{n / t_replay:,.0f} probe-samples/s (best of 3; median {n / sorted(times)[1]:,.0f})")
    print(f"bare parse + calibrate of the same samples:                         {n / t_bare:,.0f} probe-samples/s")
    print(f"ratio replay / bare: {t_bare / t_replay:.3f} "
          f"(OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')})")
    dec, pip, wri, chk, n_chk = phases[times.index(t_replay)]
    print(f"  best run: MCAP decode {dec * 1e3:.0f} ms, pipeline {pip * 1e3:.0f} ms (of which the gate's {n_chk} checks "
          f"{chk * 1e3:.0f} ms), MCAP write {wri * 1e3:.0f} ms; bare {t_bare * 1e3:.1f} ms")
    floor_parts(block, t_bare)


def _timed(obj, name: str) -> list[float]:
    """Wrap obj.name (on the instance) to add each call's duration to the list returned."""
    spent: list[float] = []
    inner = getattr(obj, name)

    def wrapper(*a, **k):
        t0 = time.perf_counter()
        try:
            return inner(*a, **k)
        finally:
            spent.append(time.perf_counter() - t0)

    setattr(obj, name, wrapper)
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

    pack = "lz4 compress of raw + corrected out"
    parts = {"lz4 decompress of the input": best(lambda: lz4.frame.decompress(packed)),
             "RLS normal equations": best(rls),
             "correction, differences, tensor": best(correct_all),
             pack: best(compress)}
    total = sum(parts.values())
    print("  floor, each part alone: " + ", ".join(f"{k} {v * 1e3:.0f} ms" for k, v in parts.items())
          + f"; sum {total * 1e3:.0f} ms against the {2e3 * t_bare:.0f} ms a 0.5x ratio allows "
          f"(at best {t_bare / total:.2f}x; {(len(raw_bytes) + len(corrected_bytes)) / 1e6:.1f} MB written; "
          f"written uncompressed, at best {t_bare / (total - parts[pack]):.2f}x)")
    cores = os.cpu_count() or 1
    print(f"  spread perfectly over all {cores} cores (no part waiting for another): at best "
          f"{t_bare * cores / total:.2f}x, uncompressed {t_bare * cores / (total - parts[pack]):.2f}x, "
          f"before the gate's checks that the same outputs need (above)")


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def bench_live(tmp: Path, seconds: float, block_ms: float | None = None) -> None:
    from fluxcal.service.io.bus import BusClient, ZenohConfig

    cfg, unit, s = make_samples(seconds + 10)
    master, slave = os.openpty()
    tty.setraw(master)
    port_path = os.ttyname(slave)
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        port = sk.getsockname()[1]
    initial = tmp / "identity.json"
    save_calibration(ArrayCalibration("ellipsoid", None, [ProbeCalibration(p["name"], np.zeros(3), np.eye(3))
                                                          for p in PROBES]), initial)
    src = (f'[source]\nkind = "serial"\nport = "{port_path}"\nn_probes = {N_PROBES}\nrate_hz = {RATE}')
    cfg_path = tmp / "live.toml"
    full = config_text(tmp, src, port, initial, block_ms)            # the serial unit is real here: no [sim] sections
    cfg_path.write_text(full.split("\n[sim]")[0] + "\n[estimator]" + full.split("[estimator]", 1)[1])
    prof = os.environ.get("FLUXCAL_PROFILE")
    cmd = [sys.executable] + (["-m", "cProfile", "-o", prof] if prof else []) + ["-m", "fluxcal.service.wiring.cli", "run", "--config", str(cfg_path)]
    env = dict(os.environ)
    if _USER_BLAS_THREADS is None:
        env.pop("OPENBLAS_NUM_THREADS", None)                  # the live service as a user starts it
    proc = subprocess.Popen(cmd, env=env,
                            stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)
    client = BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "bench", streams=["corrected"])
    frames = encode_serial(s.seq_raw, s.t_us_raw, s.counts, s.temp_raw, s.flags)
    fl = len(frames) // len(s.seq_raw)
    sent_at = np.zeros(len(s.seq_raw))
    lat, lat_oldest = [], []
    stop = threading.Event()

    def receive():
        while not stop.is_set():
            msg = client.recv(timeout=0.2)
            if msg is None:
                continue
            now = time.perf_counter()
            seq, first = int(msg.value.seq[-1]), int(msg.value.seq[0])
            if seq < len(sent_at) and sent_at[seq] > 0 and sent_at[first] > 0:
                lat.append(now - sent_at[seq])
                lat_oldest.append(now - sent_at[first])

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    n = int(seconds * RATE)
    cpu0 = cpu_seconds(proc.pid)
    t_start = time.perf_counter()
    for i in range(n):
        target = t_start + i / RATE
        while time.perf_counter() < target:
            time.sleep(0.0002)
        os.write(master, frames[i * fl:(i + 1) * fl])
        sent_at[i] = time.perf_counter()
    wall = time.perf_counter() - t_start
    cpu = cpu_seconds(proc.pid) - cpu0
    time.sleep(1.0)
    stop.set()
    th.join()
    client.close()
    proc.send_signal(signal.SIGTERM)
    proc.wait(20)
    os.close(master)
    a = np.array(lat[len(lat) // 10:]) * 1e3          # skip the first tenth (start-up)
    b = np.array(lat_oldest[len(lat_oldest) // 10:]) * 1e3
    print(f"live, {N_PROBES} probes at {RATE:.0f} Hz over a pty, block_ms {block_ms or 'default'}, {seconds:.0f} s: latency frame written -> "
          f"corrected message received p50 {np.percentile(a, 50):.2f} ms, p99 {np.percentile(a, 99):.2f} ms "
          f"({a.size} messages; newest frame of each block), oldest frame of each block p50 "
          f"{np.percentile(b, 50):.2f} ms, p99 {np.percentile(b, 99):.2f} ms; service CPU {100 * cpu / wall:.1f} % "
          f"of one core")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--live-only", action="store_true", help="skip the replay benchmark")
    ap.add_argument("--replay-only", action="store_true", help="skip the live benchmark")
    ap.add_argument("--block-ms", type=float, default=None, help="[unit] block_ms of the live service (default: its default)")
    args = ap.parse_args()
    print("machine:", machine())
    with tempfile.TemporaryDirectory() as d:
        if not args.live_only:
            bench_replay(Path(d), 60.0)
        if not args.replay_only:
            bench_live(Path(d), args.seconds, args.block_ms)


if __name__ == "__main__":
    main()
