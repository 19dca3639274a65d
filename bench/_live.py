"""The live service under a simulated unit on a pty, for bench_service.py: one run of `fluxcal run` at a given rate
and probe count, its CPU time (all threads, and by thread) over the run, the latency from a frame written to its
corrected Zenoh message received, and the bare numerics of the same samples timed in this process."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluxcal.drivers.icd import encode_serial, parse_serial
from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.unit import Unit
from fluxcal.service.io.calfile import save_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration

BENCH = Path(__file__).resolve().parent
#: probe positions: a cross in the plane for 4 probes, two crosses 0.2 m apart in z for 8
_CROSS = [[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]]


def probes(n: int) -> list[dict]:
    pos = _CROSS if n <= 4 else [[x, y, z] for z in (-0.1, 0.1) for x, y, _ in _CROSS]
    return [{"name": f"s{k + 1}", "position_m": pos[k], "offset_nT": [100.0 * k, -50.0, 30.0], "noise_nT": 0.5}
            for k in range(n)]


def config_text(tmp: Path, source: str, port: int, initial: Path, plist: list[dict], rate: float,
                block_ms: float | None = None, sim: bool = True) -> str:
    lines = ['[unit]', 'name = "bench"', f'n_probes = {len(plist)}']
    lines += ([f'block_ms = {block_ms}'] if block_ms else []) + ['']
    for p in plist:
        lines += ['[[probes]]', f'name = "{p["name"]}"', f'position_m = {p["position_m"]}', '']
    lines += [source, '']
    if sim:
        lines += ['[sim]', f'rate_hz = {rate}', '[sim.reference]', 'enabled = false', '']
        for p in plist:
            lines += ['[[sim.probes]]'] + [f'{k} = {json.dumps(v)}' for k, v in p.items()] + ['']
    lines += ['[estimator]', 'total_nT = 52500.0', '[calibration]', f'file = "{tmp / "cal.json"}"',
              f'initial = "{initial}"', '[zenoh]', f'listen = ["tcp/127.0.0.1:{port}"]',
              '[mcap]', f'dir = "{tmp / "rec"}"', '']
    return "\n".join(lines)


def make_samples(seconds: float, rate: float, plist: list[dict], n: int | None = None):
    """The simulated unit's first n samples (all of `seconds` by default), digitised as its frames carry them."""
    cfg = load_sim_config({"rate_hz": rate, "duration_s": seconds, "probes": plist})
    return Unit(cfg).digitise(0, cfg.n_samples if n is None else n)


def identity(tmp: Path, plist: list[dict]) -> Path:
    path = tmp / "identity.json"
    save_calibration(ArrayCalibration("ellipsoid", None, [ProbeCalibration(p["name"], np.zeros(3), np.eye(3))
                                                          for p in plist]), path)
    return path


def bare_seconds(s, n_probes: int, clock=time.process_time, runs: int = 5) -> float:
    """Seconds (by `clock`: this process's CPU time, or a wall clock) of the bare numerics of the samples: parse
    their ICD bytes in one go and apply a calibration; the least of `runs`."""
    data = encode_serial(s.seq_raw, s.t_us_raw, s.counts, s.temp_raw, s.flags)
    m, o = np.stack([np.eye(3)] * n_probes), np.zeros((n_probes, 3))
    best = float("inf")
    for _ in range(runs):
        t0 = clock()
        f = parse_serial(data, n_probes, final=True).frames.counts * 0.001
        np.einsum("pij,npj->npi", m, f - o[None])
        best = min(best, clock() - t0)
    return best


def _tasks(pid: int) -> dict[int, tuple[str, float]]:
    """Every thread of `pid`: its name (comm) and CPU seconds so far (schedstat: the scheduler's own count, ns)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            comm = (task / "comm").read_text().strip()
            ns = int((task / "schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            continue
        out[int(task.name)] = (comm, ns / 1e9)
    return out


def process_cpu_s(pid: int) -> float:
    """CPU seconds of the process so far, all threads, those that ended included (its stat: clock ticks)."""
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def thread_groups(pid: int, before: dict, after: dict) -> dict[str, float]:
    """CPU seconds between two _tasks snapshots by group: the service's thread (the process's first), the other
    Python threads (the bus's sender, the desk), and Zenoh's runtime threads (named by zenoh)."""
    groups = {"service thread": 0.0, "other Python threads": 0.0, "zenoh threads": 0.0}
    for tid, (comm, cpu) in after.items():
        spent = cpu - before.get(tid, (comm, 0.0))[1]
        key = ("service thread" if tid == pid else "other Python threads" if comm.startswith("python")
               else "zenoh threads")
        groups[key] += spent
    return groups


@dataclass
class LiveRun:
    rate: float
    n_probes: int
    seconds: float
    block_ms: float | None
    cpu_s: float = 0.0                 # the service's process, all threads, over the frames' writing
    wall_s: float = 0.0
    groups: dict[str, float] = field(default_factory=dict)
    lat_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))        # newest frame of each block
    lat_oldest_ms: np.ndarray = field(default_factory=lambda: np.zeros(0))
    bare_s: float = 0.0                # bare numerics of the same samples, CPU s in this process
    stages: dict | None = None

    @property
    def core(self) -> float:
        return self.cpu_s / self.wall_s

    @property
    def probe_samples(self) -> int:
        return int(self.seconds * self.rate) * self.n_probes


def _feed(master: int, frames: bytes, fl: int, n: int, rate: float, sent_at: np.ndarray) -> float:
    """Write frame i at t0 + i / rate (all the frames due at each wake-up); returns the wall time it took."""
    t_start = time.perf_counter()
    i = 0
    while i < n:
        due = min(n, int((time.perf_counter() - t_start) * rate) + 1)
        if due > i:
            os.write(master, frames[i * fl:due * fl])
            sent_at[i:due] = time.perf_counter()
            i = due
        time.sleep(0.0002)
    return time.perf_counter() - t_start


#: what a client hears in a live run: the corrected stream (the latency is timed on it), or every data stream
SUBSCRIBED = {"corrected": ("corrected",),
              "all": ("corrected", "raw", "diff", "tensor", "error", "health", "calibration", "corrected/<probe>")}


def _python(code: Path | None) -> str:
    """The interpreter that runs a checkout's service: another checkout's own environment where it has one (an
    editable install maps the package to its own tree whatever PYTHONPATH says), else this one."""
    return str(code / ".venv" / "bin" / "python") if code is not None and (code / ".venv").is_dir() else sys.executable


def _other_client(port: int, subscribe: str, plist: list[dict]):
    """The streams heard besides `corrected` (SUBSCRIBED), by a client that keeps the newest (it never holds the
    service back); None when only `corrected` is."""
    from fluxcal.service.io.bus import BusClient, ZenohConfig

    if subscribe == "corrected":
        return None
    streams = [s for s in SUBSCRIBED[subscribe][1:] if "<" not in s] + [f"corrected/{p['name']}" for p in plist]
    return BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "bench", lossless=False, streams=streams)


def live_run(rate: float, n_probes: int, seconds: float, block_ms: float | None = None, blas_threads: str | None = None,
             profile: bool = False, code: Path | None = None, subscribe: str = "corrected") -> LiveRun:
    """One run of the service; `blas_threads`: OPENBLAS_NUM_THREADS for it (None: unset, as a user starts it);
    `code`: a checkout whose service runs (another revision, for a comparison in one run), else this one's."""
    from fluxcal.service.io.bus import BusClient, ZenohConfig

    run = LiveRun(rate, n_probes, seconds, block_ms)
    plist = probes(n_probes)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        s = make_samples(seconds + 10, rate, plist)
        master, slave = os.openpty()
        tty.setraw(master)
        with socket.socket() as sk:
            sk.bind(("127.0.0.1", 0))
            port = sk.getsockname()[1]
        src = f'[source]\nkind = "serial"\nport = "{os.ttyname(slave)}"\nn_probes = {n_probes}\nrate_hz = {rate}'
        cfg_path = tmp / "live.toml"
        cfg_path.write_text(config_text(tmp, src, port, identity(tmp, plist), plist, rate, block_ms, sim=False))
        stages_out = tmp / "stages.json"
        head = [str(BENCH / "_stages.py"), str(stages_out)] if profile else ["-m", "fluxcal.service.wiring.cli"]
        env = dict(os.environ)
        env.pop("OPENBLAS_NUM_THREADS", None)
        if code is not None:
            env["PYTHONPATH"] = str(code)
        if blas_threads is not None:
            env["OPENBLAS_NUM_THREADS"] = blas_threads
        # (`python -m` looks in the working directory first: the other checkout's, for its service)
        proc = subprocess.Popen([_python(code), *head, "run", "--config", str(cfg_path)], env=env,
                                cwd=None if code is None else str(code), stderr=subprocess.PIPE, text=True)
        try:
            time.sleep(3.0)
            client = BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "bench", streams=["corrected"])
            others = _other_client(port, subscribe, plist)
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
            tasks0, cpu0 = _tasks(proc.pid), process_cpu_s(proc.pid)
            run.wall_s = _feed(master, frames, fl, int(seconds * rate), rate, sent_at)
            run.cpu_s = process_cpu_s(proc.pid) - cpu0
            run.groups = thread_groups(proc.pid, tasks0, _tasks(proc.pid))
            time.sleep(1.0)
            stop.set()
            th.join()
            client.close()
            if others is not None:
                others.close()
        finally:
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=30)
            os.close(master)
            os.close(slave)
        if proc.returncode != 0:
            raise RuntimeError(f"the service failed ({proc.returncode}): {err[-2000:]}")
        if profile:
            run.stages = json.loads(stages_out.read_text())
    run.lat_ms = np.array(lat[len(lat) // 10:]) * 1e3          # skip the first tenth (start-up)
    run.lat_oldest_ms = np.array(lat_oldest[len(lat_oldest) // 10:]) * 1e3
    run.bare_s = bare_seconds(make_samples(seconds + 10, rate, plist, int(seconds * rate)), n_probes)
    return run


def live_floor(rate: float, n_probes: int, seconds: float, block_ms: float = 8.0) -> tuple[float, float]:
    """The per-block work no service with these outputs can skip, in a loop paced as the service's: wake every
    block_ms, read what the port holds (a pty a feeder thread fills at the unit's rate), parse it, scale and
    correct it with its differences and tensor, encode the raw and corrected blocks and the one-probe and series
    messages, put the nine messages on Zenoh (a publisher each, no subscriber, no sender thread) and write two
    messages to a chunked lz4 MCAP file. Returns (this loop's thread CPU per block, us; its share of one core)."""
    import select

    import zenoh
    from mcap.writer import CompressionType, Writer

    from fluxcal.drivers.assemble import scale_samples
    from fluxcal.service.io.bus.keys import encode_series
    from fluxcal.service.io.encoding import encode_corrected, encode_probes, encode_raw
    from fluxcal.service.numerics.outputs import Derived

    plist = probes(n_probes)
    s = make_samples(seconds + 2, rate, plist)
    frames = encode_serial(s.seq_raw, s.t_us_raw, s.counts, s.temp_raw, s.flags)
    fl = len(frames) // len(s.seq_raw)
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    derive = Derived(np.array([p["position_m"] for p in plist], float), n_probes)
    cols = (np.eye(3)[None, None, :, 0], np.eye(3)[None, None, :, 1], np.eye(3)[None, None, :, 2])
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    stop = threading.Event()

    def feed() -> None:
        t0, i, n = time.perf_counter(), 0, int(seconds * rate)
        while i < n and not stop.is_set():
            due = min(n, int((time.perf_counter() - t0) * rate) + 1)
            if due > i:
                os.write(master, frames[i * fl:due * fl])
                i = due
            time.sleep(0.0002)

    with tempfile.TemporaryDirectory() as d, zenoh.open(conf) as session, open(Path(d) / "f.mcap", "wb") as fh:
        pubs = [session.declare_publisher(f"floor/{k}") for k in range(5 + n_probes)]
        w = Writer(fh, chunk_size=1 << 62, compression=CompressionType.LZ4)
        w.start()
        ch = [w.register_channel(f"/floor/{k}", "fluxcal", 0) for k in range(2)]
        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        tail, blocks, cpu0, wall0, last_flush = b"", 0, time.thread_time(), time.perf_counter(), time.monotonic()
        while feeder.is_alive():
            if not select.select([slave], [], [], 0.05)[0]:
                continue
            time.sleep(block_ms / 1000.0)
            buf = tail + os.read(slave, 1 << 16)
            p = parse_serial(buf, n_probes)
            tail = buf[p.consumed:]
            f = p.frames
            seq = f.seq.astype(np.int64)
            block = scale_samples(seq, f.t_us / 1e6, f.counts, f.temp_raw, f.flags, lsb_nT=0.001)
            d0 = block.field_nT - np.zeros((1, n_probes, 3))
            c = d0[..., 0:1] * cols[0]
            c += d0[..., 1:2] * cols[1]
            c += d0[..., 2:3] * cols[2]
            out = derive(block.t_s, block.seq, c, 1)
            raw, cor = encode_raw(block), encode_corrected(out)
            payloads = [raw, cor, encode_series(out.t_s, out.seq, out.diff_nT, 1),
                        encode_series(out.t_s, out.seq, out.tensor_nT_m, 1), b"{}", *encode_probes(out)]
            for pub, payload in zip(pubs, payloads):
                pub.put(payload)
            t_ns = int(block.t_s[0] * 1e9)
            w.add_message(ch[0], log_time=t_ns, data=raw, publish_time=t_ns)
            w.add_message(ch[1], log_time=t_ns, data=cor, publish_time=t_ns)
            if time.monotonic() - last_flush >= 1.0:
                w.flush()
                last_flush = time.monotonic()
            blocks += 1
        cpu, wall = time.thread_time() - cpu0, time.perf_counter() - wall0
        w.finish()
        stop.set()
    os.close(master)
    os.close(slave)
    return cpu / max(blocks, 1) * 1e6, cpu / wall
