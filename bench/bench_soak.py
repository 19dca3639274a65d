"""Soak benchmark (not a test) of the running service under injected faults ("field hardening").

What is measured. The daemon of `fluxcal run` (fluxcal.service.wiring.daemon.Daemon: source -> pipeline -> MCAP
logger and Zenoh bus, with its reconnects; only tapped, not changed) reads the simulated unit: 4
probes at 1 kHz, tumbling, ICD frames through a pseudo-terminal at full speed (not paced by the
clock), so pyserial, the framer and the reconnect path are the real ones. The unit runs in its own
process (`python -m fluxcal.drivers.sim --transport pty --fast --record F`), as a unit beside the service would, and
the service reads its pty as a serial source; so the service's process holds only the service.
(--sim-in-process runs the unit inside the service instead, as `fluxcal run` on a sim config does:
then its memory counts too, less its fault record, which grows with every fault it injects.) The
unit injects serial garbage, bit flips, lost bytes, dropped frames and two 2-s outages (the pty
closes, disappears and comes back); the service learns its calibration online, records to MCAP
(rotated 4-5 times) and publishes on Zenoh (127.0.0.1, a free port) to a lossless subscriber in
another process. Every 10 simulated seconds the service process's RSS (VmRSS of /proc/self/status),
the CPU time of the service and of the unit (os.times; /proc/<pid>/stat, or the unit's thread in
/proc/self/task) and the number of Python objects are sampled; the table shows them over time.
The summary gives RSS after warm-up (the estimator's ring buffer filled and wrapped, and two gate
checks over it: window_s + 2 check_every_s = 70 s), max and end with the growth in % (the issue asks
for memory flat within 5 % after warm-up) and the least-squares trend; CPU seconds per simulated
second, the service's apart from the unit's; and throughput in probe-samples/s, and CPU per
probe-sample, as ratios against the bare pipeline run over the same blocks in the same process. No
absolute time is asserted. Faster than real time the daemon gathers ~60-120 samples per block
instead of the ~8 of unit.block_ms at real time, so its CPU per simulated second is lower than at
real time (bench_service.py measures that), and its wall throughput is bounded by the gathering
wait per block and the pty's 4-KiB buffer, not by CPU. The warm-up includes the first gate checks
after the ring wraps (they used to copy the whole 60-s ring, ~8.7 MB, which glibc then kept
resident; Pipeline._window now takes only the rows it thins to). A serial port has no end of run:
once the unit has sent its last sample and closed its port, and the service's input has stayed
still for 3 s, the service is stopped; only then is the unit's fault record read. The counts are
checked exactly: samples emitted == delivered intact + lost to the injected damage (the unit's
FaultRecord); delivered == through the pipeline == in the MCAP recording (read back with
fluxcal.service.io.recordings.reader) == received on Zenoh, sample for sample; the source's frame, gap and
skipped-byte counters against the record; and the recording replayed through a fresh pipeline
gives the recorded output bit for bit. Each check prints PASS or FAIL; a FAIL makes the exit status
1. The memory check counts only in runs of at least 3 x the warm-up (not with --quick).
--tracemalloc says where Python/numpy memory grew.

Run by hand:  .venv/bin/python bench/bench_soak.py [--minutes 10] [--quick] [--no-subscriber] [--sim-in-process]
"""

from __future__ import annotations

import argparse
import atexit
import gc
import json
import os
import platform
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from _machine import cpu_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluxcal.drivers.block import SampleBlock  # noqa: E402

N_PROBES, RATE = 4, 1000.0
UNIT = "soak"
TOTAL_NT = 60000.0
# the four-probe cross of configs/sim-cross.toml ([FastRotation]), at 1 kHz and tumbling so it calibrates online
PROBES = [
    {"name": "s1", "position_m": [0.2, 0.0, 0.0], "scale": [1.253, 1.175, 0.859], "nonorth_deg": [3.56, -1.85, 2.27],
     "misalign_deg": [-21.97, 12.88, 13.64], "offset_nT": [357.0, 160.0, -213.0], "noise_nT": 1.0},
    {"name": "s2", "position_m": [0.0, 0.2, 0.0], "scale": [0.951, 1.202, 1.105], "nonorth_deg": [-2.74, 3.11, 1.66],
     "misalign_deg": [12.51, -3.96, 21.42], "offset_nT": [-253.0, 183.0, 97.0], "noise_nT": 1.0},
    {"name": "s3", "position_m": [-0.2, 0.0, 0.0], "scale": [1.110, 0.799, 1.308], "nonorth_deg": [1.86, -2.95, 3.02],
     "misalign_deg": [-11.77, 7.46, -13.03], "offset_nT": [169.0, -364.0, 245.0], "noise_nT": 1.0},
    {"name": "s4", "position_m": [0.0, -0.2, 0.0], "scale": [0.853, 1.235, 1.186], "nonorth_deg": [-3.28, 2.44, -1.88],
     "misalign_deg": [12.17, 13.39, 9.64], "offset_nT": [256.0, 169.0, -166.0], "noise_nT": 1.0},
]
# per frame; about 1,500 garbage insertions, 350 bit flips, 350 lost bytes and 600 dropped frames in 10 minutes
FAULTS = {"garbage_fraction": 0.0025, "garbage_max_bytes": 24, "bitflip_fraction": 0.0006,
          "drop_byte_fraction": 0.0006, "drop_frame_fraction": 0.001, "outage_s": 2.0}


def machine() -> str:
    return f"{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}"


def code_version() -> str:
    """The commit of the tree measured, and whether it had uncommitted changes (others work on it too)."""
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10).stdout.split()
    except (OSError, subprocess.SubprocessError):
        return "unknown (no git)"
    return f"git {head or '?'}" + (f" with uncommitted changes in {', '.join(dirty[1::2])}" if dirty else "")


def free_port() -> int:
    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        return sk.getsockname()[1]


def sim_table(seconds: float) -> dict:
    """The [sim] section: the simulated unit, its motion and its faults."""
    outages = [round(seconds * 0.35, 3), round(seconds * 0.7, 3)]
    return {"seed": 7, "rate_hz": RATE, "realtime": False, "lsb_nT": 0.001,
            "field": {"total_nT": TOTAL_NT, "inclination_deg": 57.0, "declination_deg": -5.0},
            "motion": {"kind": "tumble", "rate_deg_s": 20.0, "tumble_period_s": 8.0},
            "temperature": {"start_C": 22.0, "amplitude_C": 3.0, "period_s": 300.0, "reference_C": 20.0},
            "faults": {**FAULTS, "outage_at_s": outages},
            "probes": PROBES}


def toml_text(section: str, table: dict) -> str:
    """A nested dict of numbers, strings and lists as TOML (enough for the [sim] section)."""
    def value(v) -> str:
        return json.dumps(v)            # numbers, strings and flat lists read the same in TOML

    def tables(prefix: str, t: dict) -> list[str]:
        lines = [f"[{prefix}]"] + [f"{k} = {value(v)}" for k, v in t.items()
                                   if not isinstance(v, dict) and not (isinstance(v, list) and v
                                                                        and isinstance(v[0], dict))]
        for k, v in t.items():
            if isinstance(v, dict):
                lines += tables(f"{prefix}.{k}", v)
            elif isinstance(v, list) and v and isinstance(v[0], dict):
                for item in v:
                    lines += [f"[[{prefix}.{k}]]"] + [f"{ik} = {value(iv)}" for ik, iv in item.items()]
        return lines

    return "\n".join(tables(section, table)) + "\n"


def service_config(tmp: Path, seconds: float, port: int, rotate_mb: float, serial_port: str | None = None):
    """The service's configuration: with serial_port, it reads the simulated unit running in another
    process (as beside hardware); without, the unit runs inside the service (source kind "sim")."""
    from fluxcal.service.wiring.config import config_from_dict

    if serial_port is None:
        source = {"kind": "sim", "transport": "pty", "run_s": seconds}
    else:
        source = {"kind": "serial", "port": serial_port, "baudrate": 921600, "n_probes": N_PROBES, "lsb_nT": 0.001,
                  "rate_hz": RATE}
    raw = {
        "unit": {"name": UNIT, "n_probes": N_PROBES, "lsb_nT": 0.001},
        "probes": [{"name": p["name"], "position_m": p["position_m"]} for p in PROBES],
        "source": source,
        "estimator": {"total_nT": TOTAL_NT},
        "calibration": {"file": str(tmp / "state" / "soak-cal.json")},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "mcap": {"dir": str(tmp / "rec"), "rotate_mb": rotate_mb},
    }
    if serial_port is None:
        raw["sim"] = sim_table(seconds)
    return config_from_dict(raw, "<bench_soak>")


# --- what is sampled -----------------------------------------------------------------------------------------

def record_kb(record) -> float:
    """kB the simulator's FaultRecord holds (one growing array per fault kind; it only grows): simulator
    memory that a service beside real hardware does not have, taken out of the service's memory figure."""
    return record.nbytes / 1024


def rss_kb() -> int:
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def stat_cpu_s(stat_path: str | None) -> float | None:
    """CPU seconds (utime + stime) of a thread (/proc/self/task/<tid>/stat) or a process
    (/proc/<pid>/stat); None once it has gone."""
    if stat_path is None:
        return None
    try:
        with open(stat_path, encoding="ascii") as f:
            parts = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


class SimProcess:
    """The simulated unit in its own process (python -m fluxcal.drivers.sim, as a test rig beside the service
    would be): the service's process then holds only the service. At the end the runner writes its
    whole fault record, which the checks need (read once the run is over)."""

    def __init__(self, tmp: Path, seconds: float) -> None:
        self.conf = tmp / "sim.toml"
        self.conf.write_text(toml_text("sim", {**sim_table(seconds), "duration_s": seconds}), encoding="utf-8")
        self.record_path = tmp / "sim-record.npz"
        root = Path(__file__).resolve().parents[1]
        self.proc = subprocess.Popen([sys.executable, "-m", "fluxcal.drivers.sim", "--config", str(self.conf), "--transport",
                                      "pty", "--fast", "--link-dir", str(tmp), "--record", str(self.record_path)],
                                     cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     preexec_fn=_end_with_parent)
        self.exit_code: int | None = None
        self.cpu_s: float | None = None         # from the kernel's accounting once it has ended
        self.exited = threading.Event()
        self._wait_lock = threading.Lock()      # one waiter reaps it (the end thread, or stop())
        self.stderr = ""
        self.record = None
        self.meta: dict = {}
        ready, _, _ = select.select([self.proc.stdout], [], [], 30.0)
        self.path = self.proc.stdout.readline().strip() if ready else ""
        if not self.path:
            self.stop()
            raise SystemExit(f"the simulated unit did not start: {self.proc.stderr.read().strip()}")
        self.stat_path = f"/proc/{self.proc.pid}/stat"

    def _reaped(self, status: int, ru) -> None:
        self.exit_code = self.proc.returncode = os.waitstatus_to_exitcode(status)
        self.cpu_s = ru.ru_utime + ru.ru_stime
        self.exited.set()

    def wait(self) -> None:
        """Until the run is over (the runner drains the port, closes it and exits)."""
        with self._wait_lock:
            if self.exit_code is None:
                _, status, ru = os.wait4(self.proc.pid, 0)
                self._reaped(status, ru)

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM (the runner then writes its fault record and exits); SIGKILL if it has not ended
        within timeout_s. Safe while another thread waits for it, and twice."""
        if self.exited.is_set():
            return
        try:
            os.kill(self.proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            return
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.exited.wait(0.1):
                return
            if self._wait_lock.acquire(blocking=False):      # nobody else is waiting: reap it here
                try:
                    if self.exit_code is None:
                        pid, status, ru = os.wait4(self.proc.pid, os.WNOHANG)
                        if pid:
                            self._reaped(status, ru)
                finally:
                    self._wait_lock.release()
        if not self.exited.is_set():
            try:
                os.kill(self.proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass

    def load_record(self) -> None:
        """Its fault record, read after the service's last memory sample (reading it costs this
        process ~3 MB, which is the benchmark's, not the service's)."""
        self.stderr = self.proc.stderr.read()
        if self.record_path.exists():
            from fluxcal.drivers.sim import FaultRecord

            self.record, self.meta = FaultRecord.load(str(self.record_path))


def _end_with_parent() -> None:
    """In the simulated unit's process, before it runs: SIGTERM when the benchmark's process ends, however
    it ends (Linux prctl PR_SET_PDEATHSIG), so a killed benchmark leaves no unit waiting for a reader."""
    import ctypes

    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)


class Probe:
    """Taps the daemon's parts: counts what goes through the pipeline, samples memory and CPU."""

    def __init__(self, every_s: float, print_every_s: float, warmup_s: float) -> None:
        self.every_s = every_s
        self.print_every_s = print_every_s
        self.warmup_s = warmup_s
        self.rows: list[dict] = []
        self.n_in = 0                 # samples into pipeline.process
        self.seq_sum = 0
        self.n_corrected = 0
        self.cor_seq_sum = 0
        self.blocks = 0
        self.last_seq = -1
        self.source = None
        self.pipeline = None
        self.logger = None
        self.bus = None
        self.sim_stat: str | None = None   # /proc stat of the simulator's thread, or of its process
        self.sim_process: SimProcess | None = None
        self.sim_cpu = 0.0            # the simulator's CPU seconds, last seen
        self.sim_cpu0 = 0.0
        self.snapshots: list | None = [] if tracemalloc.is_tracing() else None
        self.t0 = self.cpu0 = 0.0
        self._next_row = 0.0
        self.t_first_block: float | None = None
        self.t_last_block = 0.0

    def attach(self, source, pipeline, bus, logger) -> None:
        self.source, self.pipeline, self.bus, self.logger = source, pipeline, bus, logger
        th = getattr(getattr(source, "emitter", None), "_thread", None)
        if getattr(th, "native_id", None) is not None:
            self.sim_stat = f"/proc/self/task/{th.native_id}/stat"
        inner = pipeline.process

        def process(block: SampleBlock):
            self._count_in(block)
            out = inner(block)
            self._count_out(out)
            return out

        pipeline.process = process        # instance attribute: the daemon's loop calls this one

    def start(self) -> None:
        self.t0, self.cpu0 = time.perf_counter(), cpu_s()
        self.sim_cpu0 = 0.0
        self.sim_cpu0 = self._sim_cpu()
        self._row(0.0)
        self._next_row = self.every_s

    def _count_in(self, block: SampleBlock) -> None:
        n = block.n_samples
        if not n:
            return
        now = time.perf_counter()
        if self.t_first_block is None:
            self.t_first_block = now
        self.t_last_block = now
        self.blocks += 1
        self.n_in += n
        self.seq_sum += int(block.seq.sum())
        self.last_seq = int(block.seq[-1])
        sim_s = (self.last_seq + 1) / RATE
        while sim_s >= self._next_row:
            self._row(self._next_row)
            self._next_row += self.every_s

    def _count_out(self, out) -> None:
        if out.corrected is not None:
            self.n_corrected += out.corrected.n_samples
            self.cor_seq_sum += int(out.corrected.seq.sum())

    def finish(self) -> None:
        self._row((self.last_seq + 1) / RATE, final=True)

    def _sim_cpu(self) -> float:
        """The simulator's CPU seconds since start (its last value once it has ended)."""
        sp = self.sim_process
        t = sp.cpu_s if sp is not None and sp.cpu_s is not None else stat_cpu_s(self.sim_stat)
        if t is not None:
            self.sim_cpu = t
        return self.sim_cpu - self.sim_cpu0

    def _row(self, sim_s: float, final: bool = False) -> None:
        # CPU in all: this process's, plus the simulated unit's when it runs in a process of its own
        sim_cpu = self._sim_cpu()
        lost, rec_kb = None, 0.0          # the simulator's record: known along the way only in-process
        rec = getattr(self.source, "record", None)
        if rec is not None:
            lost = int(rec.serial_lost().size)
            rec_kb = record_kb(rec)
        r = {"sim_s": sim_s, "wall_s": time.perf_counter() - self.t0, "rss_kb": rss_kb(), "record_kb": rec_kb,
             "cpu_s": cpu_s() - self.cpu0 + (sim_cpu if self.sim_process is not None else 0.0),
             "sim_cpu_s": sim_cpu,
             "objs": len(gc.get_objects()), "delivered": self.n_in, "lost": lost,
             "files": len(self.logger.files) if self.logger is not None else 0}
        self.rows.append(r)
        if self.snapshots is not None and (final or (len(self.snapshots) == 0 and sim_s >= self.warmup_s)):
            self.snapshots.append(tracemalloc.take_snapshot())
        if final or round(sim_s / self.print_every_s, 6) % 1 == 0:
            self._print_row(r, final)

    HEADER = (f"{'sim s':>7} {'wall s':>7} {'RSS MB':>7} {'vs warm':>8} {'CPU/sim s':>9} {'of which sim':>12} "
              f"{'ksamples/s':>10} {'py objects':>10} {'delivered':>9} {'lost':>6} {'files':>5}")

    def _print_row(self, r: dict, final: bool) -> None:
        prev = next((p for p in reversed(self.rows[:-1]) if p["sim_s"] <= r["sim_s"] - self.print_every_s + 1e-9),
                    self.rows[0] if len(self.rows) > 1 else None)
        warm = self.warm_row()
        vs = "warmup"
        if warm is not None and r["sim_s"] >= self.warmup_s:
            vs = f"{100.0 * (r['rss_kb'] / warm['rss_kb'] - 1):+7.2f}%"
        if prev is not None and r["sim_s"] > prev["sim_s"]:
            dsim = r["sim_s"] - prev["sim_s"]
            cpu = f"{(r['cpu_s'] - prev['cpu_s']) / dsim:9.3f}"
            scpu = f"{(r['sim_cpu_s'] - prev['sim_cpu_s']) / dsim:12.3f}"
            dw = r["wall_s"] - prev["wall_s"]
            rate = f"{(r['delivered'] - prev['delivered']) / dw / 1e3:10.1f}" if dw > 0 else f"{'-':>10}"
        else:
            cpu, scpu, rate = f"{'-':>9}", f"{'-':>12}", f"{'-':>10}"
        print(f"{r['sim_s']:7.1f} {r['wall_s']:7.1f} {r['rss_kb'] / 1024:7.1f} {vs:>8} {cpu} {scpu} {rate} "
              f"{r['objs']:10d} {r['delivered']:9d} {'-' if r['lost'] is None else r['lost']:>6} {r['files']:5d}" + ("  (end)" if final else ""),
              flush=True)

    def warm_row(self) -> dict | None:
        return next((r for r in self.rows if r["sim_s"] >= self.warmup_s), None)


# --- the Zenoh subscriber (another process) ------------------------------------------------------------------

def subscriber_main(endpoint: str) -> None:
    """Counts raw and corrected samples received until stdin closes and the stream has been quiet 1 s;
    prints them as one JSON line."""
    from fluxcal.service.io.bus import BusClient, ZenohConfig

    client = BusClient(ZenohConfig.client(endpoint), UNIT, streams=["raw", "corrected"], lossless=True)
    counts = {"raw": 0, "raw_seq_sum": 0, "raw_msgs": 0, "corrected": 0, "corrected_seq_sum": 0}
    eof = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), eof.set()), daemon=True).start()
    print("ready", flush=True)
    quiet_since = None
    while True:
        msg = client.recv(timeout=0.2)
        if msg is not None:
            quiet_since = None
            v = msg.value
            if msg.stream == "raw":
                counts["raw"] += v.n_samples
                counts["raw_msgs"] += 1
                counts["raw_seq_sum"] += int(v.seq.sum())
            else:
                counts["corrected"] += v.n_samples
                counts["corrected_seq_sum"] += int(v.seq.sum())
            continue
        if eof.is_set():
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since >= 1.0:
                break
    counts.update({k: v for k, v in client.stats.items()})
    client.close()
    print(json.dumps(counts), flush=True)


class Subscriber:
    def __init__(self, endpoint: str) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__, "--subscribe", endpoint], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        self.result: dict | None = None

    def wait_ready(self, timeout: float = 20.0) -> bool:
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        return bool(ready) and self.proc.stdout.readline().strip() == "ready"

    def finish(self, timeout: float = 60.0) -> dict | None:
        try:
            out, _ = self.proc.communicate(input="", timeout=timeout)      # closes its stdin: the end
            lines = [ln for ln in out.splitlines() if ln.startswith("{")]
            self.result = json.loads(lines[-1]) if lines else None
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return self.result


# --- the soak --------------------------------------------------------------------------------------------------

def make_daemon(cfg, probe: Probe, subscriber_endpoint: str | None, messages: list[str]):
    from fluxcal.service.wiring.daemon import Daemon
    from fluxcal.service.wiring.sinks import BusSink, McapSink

    class SoakDaemon(Daemon):
        """The daemon unchanged, plus taps on its parts (the loop is the daemon's own)."""

        subscriber: Subscriber | None = None
        sub_result: dict | None = None
        bus_stats: dict | None = None
        logger_status: dict | None = None

        def _loop(self, source, pipeline, sinks) -> None:
            # the bus and the recording as the daemon holds them: among its sinks
            bus = next(s.bus for s in sinks.sinks if isinstance(s, BusSink))
            logger = next((s.logger for s in sinks.sinks if isinstance(s, McapSink)), None)
            probe.attach(source, pipeline, bus, logger)
            if subscriber_endpoint is not None:
                # the fast emitter waits in the full pty meanwhile: nothing is lost while we wait
                self.subscriber = Subscriber(subscriber_endpoint)
                self.subscriber.wait_ready()
                deadline = time.monotonic() + 20.0
                while not bus.has_subscribers("raw") and time.monotonic() < deadline:
                    time.sleep(0.05)
                time.sleep(0.3)
            probe.start()
            try:
                super()._loop(source, pipeline, sinks)
            finally:
                probe.finish()
                if self.subscriber is not None:
                    self.sub_result = self.subscriber.finish()
                self.bus_stats = dict(bus.stats)
                if logger is not None:
                    self.logger_status = logger.status()

    def say(msg: str) -> None:
        sim = (probe.last_seq + 1) / RATE
        messages.append(msg)
        print(f"{'':8}service at {sim:.1f} s: {msg if len(msg) <= 110 else msg[:107] + '...'}", flush=True)

    return SoakDaemon(cfg, say=say)


def end_when_delivered(sim: SimProcess, probe: Probe, daemon) -> None:
    """A serial port has no end of run: once the simulated unit has sent its last sample (it drains the
    port, closes it and exits) and the service's count of samples has stayed still for 3 s (bounded
    wait), the service is stopped, as an operator would. The checks then say whether it had them all."""
    sim.wait()
    # everything sent is in the port or already read (the runner drained the port before it closed it):
    # the service has it all once its count stays still (3 s: a slow block or a file rotation is shorter)
    deadline = time.monotonic() + 30.0
    seen, still_since = probe.n_in, time.monotonic()
    while time.monotonic() < deadline and not daemon.stop.is_set():
        time.sleep(0.05)
        if probe.n_in != seen:
            seen, still_since = probe.n_in, time.monotonic()
        elif time.monotonic() - still_since >= 3.0:
            break
    daemon.stop.set()


def bare_pipeline(cfg, blocks: list[SampleBlock], runs: int = 2):
    """The pipeline alone (no source, MCAP or Zenoh) over the same blocks, best of `runs`: wall and
    CPU seconds, and its corrected output."""
    from fluxcal.service.wiring.daemon import build_pipeline

    best, best_cpu, outs = float("inf"), float("inf"), []
    for _ in range(runs):
        pipe = build_pipeline(cfg, None)
        outs = []
        c0, t0 = time.process_time(), time.perf_counter()
        for b in blocks:
            r = pipe.process(b)
            if r.corrected is not None:
                outs.append(r.corrected)
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return best, best_cpu, outs


def same_output(a: list, b: list) -> bool:
    """Two lists of CorrectedBlocks hold the same samples, bit for bit (however they are cut)."""
    from fluxcal.service.io.recordings.reader import concat_corrected

    if not a or not b:
        return not a and not b
    x, y = concat_corrected(a), concat_corrected(b)
    return all(np.array_equal(getattr(x, k), getattr(y, k), equal_nan=True) if getattr(x, k) is not None
               else getattr(y, k) is None
               for k in ("seq", "t_s", "corrected_nT", "diff_nT", "tensor_nT_m", "center_nT"))


def print_growth(before, after, top: int = 12) -> None:
    """Where traced memory grew between two tracemalloc snapshots: by line, and the biggest by call stack."""
    skip = [tracemalloc.Filter(False, tracemalloc.__file__), tracemalloc.Filter(False, "<frozen importlib._bootstrap>")]
    before, after = before.filter_traces(skip), after.filter_traces(skip)
    total = sum(st.size_diff for st in after.compare_to(before, "filename"))
    print(f"tracemalloc: traced memory grew {total / 1024:+.0f} kB between warm-up and the end; by line:")
    for st in after.compare_to(before, "lineno")[:top]:
        fr = st.traceback[0]
        print(f"  {st.size_diff / 1024:+9.1f} kB {st.count_diff:+7d} blocks  {fr.filename}:{fr.lineno}")
    for st in after.compare_to(before, "traceback")[:3] if len(after.traces[0].traceback) > 1 else []:
        print(f"  {st.size_diff / 1024:+9.1f} kB {st.count_diff:+7d} blocks, allocated at:")
        for line in st.traceback.format(limit=6, most_recent_first=True):
            if line.strip():
                print(f"    {line.strip()}")


def check(results: list[bool], ok: bool, what: str, counted: bool = True) -> None:
    if counted:
        results.append(bool(ok))
    print(f"{'PASS' if ok else 'FAIL'}  {what}" + ("" if counted else "  (indicative: not counted)"))


def parse_args() -> argparse.Namespace:
    """The command line (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes (default 10)")
    ap.add_argument("--quick", action="store_true", help="one simulated minute (memory check not counted)")
    ap.add_argument("--no-subscriber", action="store_true", help="no Zenoh subscriber process")
    ap.add_argument("--sim-in-process", action="store_true",
                    help="run the simulated unit inside the service's process (source kind \"sim\", as `fluxcal "
                         "run` on a sim config does) instead of in its own process; the memory figure then "
                         "includes the simulator's")
    ap.add_argument("--tracemalloc", type=int, nargs="?", const=1, default=0, metavar="FRAMES",
                    help="diagnosis: trace Python and numpy allocations (FRAMES deep, default 1; several times "
                         "slower) and print where memory grew between warm-up and the end")
    ap.add_argument("--subscribe", help=argparse.SUPPRESS)
    return ap.parse_args()


@dataclass
class Schedule:
    """When the service is sampled and its rows printed, and where its warm-up ends (simulated seconds)."""

    warmup_full: float          # the estimator's ring buffer filled and wrapped, and two gate checks over it
    memory_counted: bool        # the run is at least 3 x warmup_full: the memory check counts
    warmup_s: float
    every_s: float
    print_every_s: float


def schedule(cfg, seconds: float) -> Schedule:
    """The warm-up and the sampling intervals of a run of `seconds` simulated seconds."""
    # warm-up: the estimator's ring buffer has filled, wrapped, and the gate has run twice over it
    est = cfg.estimator
    warmup_full = est.window_s + 2 * est.check_every_s
    memory_counted = seconds >= 3 * warmup_full
    warmup_s = warmup_full if memory_counted else seconds / 3
    every_s = 10.0 if seconds >= 60 else max(1.0, seconds / 6)
    print_every_s = every_s * max(1, round(seconds / every_s / 20))
    warmup_s = every_s * np.ceil(warmup_s / every_s - 1e-9)
    return Schedule(warmup_full, memory_counted, warmup_s, every_s, print_every_s)


def print_plan(seconds: float, rotate_mb: float, sch: Schedule) -> None:
    """The run's set-up in one line: probes, rate, faults, outages, file rotation and warm-up."""
    print(f"soak: {N_PROBES} probes at {RATE:.0f} Hz, {seconds:.0f} simulated s of the daemon through a pty at "
          f"full speed; faults per frame: garbage {FAULTS['garbage_fraction']}, bit flip "
          f"{FAULTS['bitflip_fraction']}, lost byte {FAULTS['drop_byte_fraction']}, dropped frame "
          f"{FAULTS['drop_frame_fraction']}; outages of {FAULTS['outage_s']:.0f} s at "
          f"{', '.join(f'{a:g} s' for a in sim_table(seconds)['faults']['outage_at_s'])}; MCAP rotated every "
          f"{rotate_mb:g} MB; "
          f"warm-up {sch.warmup_s:.0f} s" + ("" if sch.memory_counted else
                                             f" (the run is shorter than 3 x the {sch.warmup_full:g} s warm-up of ring "
                                             f"buffer + 2 gate checks: the memory check is not counted)"))


@dataclass
class SoakRun:
    """What a soak leaves for its summary and its checks."""

    cfg: Any
    seconds: float
    schedule: Schedule
    probe: Probe
    daemon: Any
    messages: list[str]
    endpoint: str | None            # the Zenoh subscriber's, or None without one
    sim_proc: SimProcess | None     # None: the unit ran in the service's process
    rc: int                         # the daemon's exit status
    t_run: float                    # wall seconds of the daemon's run
    counters: dict                  # the source's
    record: Any                     # the simulated unit's FaultRecord
    framer: Any                     # the source's framer (its pending bytes)
    emitted: int
    reconnects: int
    sim_ok: bool                    # the unit's process ended well (always, in process)
    rec: Any                        # the recording read back
    rec_seq: np.ndarray             # the seq of every recorded raw sample
    rec_mb: float
    t_bare: float                   # the bare pipeline over the recorded blocks: wall and CPU seconds
    cpu_bare: float
    bare_out: list


def run_watched(daemon, sim_proc: SimProcess | None, seconds: float) -> tuple[int, float]:
    """The daemon's run, stopped by a watchdog after twice real time (a stuck soak, whose checks then fail):
    its exit status and wall seconds. The simulated unit is stopped after it, if it has not ended."""
    limit_s = 2 * seconds + 120
    watchdog = threading.Timer(limit_s, lambda: (print(f"watchdog: stopping the daemon after {limit_s:.0f} s",
                                                       flush=True), daemon.stop.set()))
    watchdog.daemon = True
    print(Probe.HEADER, flush=True)
    t_run = time.perf_counter()
    watchdog.start()
    try:
        rc = daemon.run()
    finally:
        watchdog.cancel()
        if sim_proc is not None:
            sim_proc.stop()           # it has ended by itself, unless the run was cut short
    return rc, time.perf_counter() - t_run


def unit_outcome(probe: Probe, sim_proc: SimProcess | None) -> tuple[Any, Any, int, int, bool]:
    """The simulated unit's side once the run is over: its fault record, the source's framer, the samples it
    emitted, its reconnects and whether its process ended well."""
    source = probe.source
    if sim_proc is None:
        return (source.record, source.inner._decoder.framer, int(source.emitter.next_index), source.emitter.reconnects,
                True)
    if sim_proc.exit_code is None:
        sim_proc.wait()
    sim_proc.load_record()
    if sim_proc.record is None:
        raise SystemExit(f"the simulated unit left no fault record (exit {sim_proc.exit_code}): "
                         f"{sim_proc.stderr.strip()}")
    return (sim_proc.record, source._decoder.framer, sim_proc.meta["next_index"], sim_proc.meta["reconnects"],
            sim_proc.exit_code == 0)


def soak(tmp: Path, seconds: float, args: argparse.Namespace) -> SoakRun:
    """One soak in `tmp`: the simulated unit (in its own process unless --sim-in-process) read by the daemon,
    tapped by a Probe; then the recording read back and the bare pipeline run over its raw blocks."""
    tempfile.tempdir = str(tmp)           # the emitter's pty symlink directory goes in here too
    port = free_port()
    rotate_mb = max(4.0, round(seconds * 0.08))           # 4-5 files per run (about 0.35 MB per sim s)
    sim_proc = None if args.sim_in_process else SimProcess(tmp, seconds)
    if sim_proc is not None:
        atexit.register(sim_proc.stop)          # whatever stops this run stops the simulated unit too
    cfg = service_config(tmp, seconds, port, rotate_mb, None if sim_proc is None else sim_proc.path)
    sch = schedule(cfg, seconds)
    print_plan(seconds, rotate_mb, sch)
    probe = Probe(sch.every_s, sch.print_every_s, sch.warmup_s)
    messages: list[str] = []
    endpoint = None if args.no_subscriber else f"tcp/127.0.0.1:{port}"
    daemon = make_daemon(cfg, probe, endpoint, messages)
    if sim_proc is not None:
        print(f"the simulated unit runs in its own process (pid {sim_proc.proc.pid}) on {sim_proc.path}")
        probe.sim_stat, probe.sim_process = sim_proc.stat_path, sim_proc
        threading.Thread(target=end_when_delivered, args=(sim_proc, probe, daemon), daemon=True).start()
    rc, t_run = run_watched(daemon, sim_proc, seconds)
    tempfile.tempdir = None
    counters = {**probe.source.counters.as_dict(), **daemon._link.counts()}   # the source's, the input's losses
    record, framer, emitted, reconnects, sim_ok = unit_outcome(probe, sim_proc)

    # --- read the recording back; the bare pipeline over the same blocks ----------------------------
    from fluxcal.service.io.recordings.reader import read_recording

    rec = read_recording(tmp / "rec")
    t_bare, cpu_bare, bare_out = bare_pipeline(cfg, rec.raw_blocks)
    return SoakRun(cfg=cfg, seconds=seconds, schedule=sch, probe=probe, daemon=daemon, messages=messages,
                   endpoint=endpoint, sim_proc=sim_proc, rc=rc, t_run=t_run, counters=counters, record=record,
                   framer=framer, emitted=emitted, reconnects=reconnects, sim_ok=sim_ok, rec=rec,
                   rec_seq=np.concatenate([b.seq for b in rec.raw_blocks]),
                   rec_mb=sum(os.path.getsize(f) for f in rec.files) / 1e6,
                   t_bare=t_bare, cpu_bare=cpu_bare, bare_out=bare_out)


@dataclass
class Memory:
    """The service's memory over the rows after warm-up: RSS less the simulator's own fault record, which grows
    with every fault it injects (the simulated unit shares the process in process; beside real hardware it
    does not exist)."""

    warm: dict                  # the row at the end of the warm-up, the row of the largest, the last row
    rmax: dict
    end: dict
    svc: dict[int, float]       # the service's kB per row, by id(row)
    growth_end: float           # % of the warm row's, at the end and at most
    growth_max: float
    raw_end: float              # VmRSS itself at the end, % of the warm row's
    slope: float                # least-squares trend, kB per simulated minute


def memory(probe: Probe) -> Memory:
    """The service's memory figures from the probe's rows."""
    rows = probe.rows
    warm = probe.warm_row() or rows[0]
    after = [r for r in rows if r["sim_s"] >= warm["sim_s"]]
    end = rows[-1]
    svc = {id(r): r["rss_kb"] - r["record_kb"] for r in rows}
    rmax = max(after, key=lambda r: svc[id(r)])
    xs = np.array([r["sim_s"] for r in after])
    ys = np.array([svc[id(r)] for r in after], float)
    slope = float(np.polyfit(xs, ys, 1)[0]) * 60.0 if xs.size >= 3 and np.ptp(xs) > 0 else float("nan")
    return Memory(warm=warm, rmax=rmax, end=end, svc=svc,
                  growth_end=100.0 * (svc[id(end)] / svc[id(warm)] - 1),
                  growth_max=100.0 * (svc[id(rmax)] / svc[id(warm)] - 1),
                  raw_end=100.0 * (end["rss_kb"] / warm["rss_kb"] - 1), slope=slope)


def print_summary(run: SoakRun, mem: Memory) -> None:
    """The run in figures: memory, CPU, throughput against the bare pipeline, the recording, the counters, the
    fault record, the bus; and where traced memory grew (--tracemalloc)."""
    probe, daemon, sim_proc, cfg, rec = run.probe, run.daemon, run.sim_proc, run.cfg, run.rec
    rows, warm, rmax, end, svc = probe.rows, mem.warm, mem.rmax, mem.end, mem.svc
    blocks = rec.raw_blocks
    sim_total, cpu_total, sim_cpu = end["sim_s"], end["cpu_s"], end["sim_cpu_s"]
    service_cpu = cpu_total - sim_cpu
    wall_data = probe.t_last_block - probe.t_first_block
    ps = probe.n_in * N_PROBES                                  # probe-samples delivered
    thr, thr_bare = ps / wall_data, ps / run.t_bare
    print(f"\ndaemon exit {run.rc} after {run.t_run:.1f} s wall for {sim_total:.0f} simulated s "
          f"({sim_total / run.t_run:.1f}x real time), {len(run.messages)} service messages; load average at end: "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    what = ("VmRSS of the service's process (the simulated unit runs in another)" if sim_proc is not None
            else "VmRSS less the simulator's fault record")
    print(f"memory ({what}): {rows[0]['rss_kb'] / 1024:.1f} MB before the first "
          f"sample; after warm-up ({warm['sim_s']:.0f} s) {svc[id(warm)] / 1024:.1f} MB, max "
          f"{svc[id(rmax)] / 1024:.1f} MB (at {rmax['sim_s']:.0f} s), end {svc[id(end)] / 1024:.1f} MB: growth "
          f"{mem.growth_end:+.2f} % at the end, {mem.growth_max:+.2f} % at most; least-squares trend after warm-up "
          f"{mem.slope:+.0f} kB per simulated minute; Python objects {warm['objs']} -> {end['objs']}"
          + ("" if sim_proc is not None else f"; VmRSS itself {mem.raw_end:+.2f} % at the end, the record "
                                             f"{end['record_kb']:.0f} kB"))
    print(f"CPU: {cpu_total / sim_total:.3f} s per simulated s in all ({cpu_total:.1f} s), of which the simulated "
          f"unit {sim_cpu / sim_total:.3f} ({'its emitter thread' if sim_proc is None else 'its own process'}) "
          f"and the service (its thread, zenoh, MCAP) "
          f"{service_cpu / sim_total:.3f}; at {sim_total / run.t_run:.1f}x real time the daemon gathers about "
          f"{probe.n_in / max(probe.blocks, 1):.0f} samples per block (about {cfg.unit.block_ms * RATE / 1000:g} at "
          f"real time: block_ms {cfg.unit.block_ms:g})")
    print(f"throughput: {thr:,.0f} probe-samples/s through the daemon (wall, first to last block, outages and the "
          f"{cfg.unit.block_ms:g} ms gathering wait per block included); bare pipeline over the same {len(blocks)} "
          f"blocks {thr_bare:,.0f} probe-samples/s (best of 2): ratio {thr / thr_bare:.3f}")
    print(f"CPU per probe-sample: service {1e6 * service_cpu / ps:.2f} us, bare pipeline "
          f"{1e6 * run.cpu_bare / ps:.2f} us: ratio bare / service {run.cpu_bare / service_cpu:.3f}")
    logger = {k: (daemon.logger_status or {}).get(k) for k in ('messages', 'messages_written', 'dropped', 'errors')}
    print(f"recording: {len(rec.files)} files, {run.rec_mb:.1f} MB, {len(blocks)} raw messages, "
          f"{len(rec.corrected_blocks)} corrected, {len(rec.calibration)} calibration events, {len(rec.health)} "
          f"health; truncated {len(rec.truncated)}, warnings {len(rec.warnings)}; logger: {json.dumps(logger)}")
    print(f"source counters: {json.dumps(run.counters)}")
    rec_kb = record_kb(run.record)
    print(f"fault record: {json.dumps(run.record.as_dict())}; emitter reconnects {run.reconnects}; the record "
          f"itself holds {rec_kb:.0f} kB" + (" of the process's memory (it grows with every fault: simulator only)"
                                if sim_proc is None else " in the simulator's process"))
    if daemon.bus_stats:
        bs = daemon.bus_stats
        print(f"bus: published raw {bs.get('published_raw')}, corrected {bs.get('published_corrected')}, "
              f"publish errors {bs.get('publish_errors')}" + (f"; subscriber: decode errors "
                                                             f"{daemon.sub_result.get('decode_errors')}, dropped "
                                                             f"{daemon.sub_result.get('dropped')}"
                                                             if daemon.sub_result else ""))

    if probe.snapshots is not None and len(probe.snapshots) == 2:
        print_growth(*probe.snapshots)


def check_counts(run: SoakRun, mem: Memory, results: list[bool]) -> None:
    """The exact counts (emitted == delivered + lost; delivered == through the pipeline == recorded == received
    on Zenoh; the source's counters against the fault record), the recorded output reproduced, the memory flat:
    each printed PASS or FAIL and appended to `results` (the memory check only in a long enough run)."""
    probe, record, emitted, counters = run.probe, run.record, run.emitted, run.counters
    rec_seq = run.rec_seq
    n_rec = int(rec_seq.size)
    n_rec_cor = sum(b.n_samples for b in run.rec.corrected_blocks)
    n_run = int(round(RATE * run.seconds))
    lost = record.serial_lost()
    expected = np.setdiff1d(np.arange(emitted, dtype=np.int64), lost)
    sub = run.daemon.sub_result
    print()
    print(f"samples emitted by the simulator     {emitted}")
    print(f"lost to injected damage (record)     {lost.size}  ("
          + ", ".join(f"{k} {record.samples(k).size}" for k in record.SERIAL_LOSSES) + ")")
    print(f"delivered intact (through pipeline)  {probe.n_in}")
    print(f"in the MCAP recording                {n_rec}")
    if run.endpoint is not None:
        print(f"received on Zenoh (raw)              {sub['raw'] if sub else 'no result'}")
    print(f"corrected samples                    pipeline {probe.n_corrected}, recording {n_rec_cor}"
          + (f", Zenoh {sub['corrected']}" if sub else ""))
    check(results, run.rc == 0 and run.sim_ok and emitted == n_run,
          f"the run completed: {emitted} samples emitted of {n_run}, the service stopped "
          + ("by itself at the end of the simulated run" if run.sim_proc is None
             else "once the unit had closed its port and the input had stayed still 3 s"))
    check(results, emitted == probe.n_in + lost.size,
          f"emitted {emitted} == delivered {probe.n_in} + lost {lost.size} ({probe.n_in + lost.size})")
    check(results, probe.n_in == n_rec, f"delivered through the pipeline {probe.n_in} == in the recording {n_rec}")
    check(results, np.array_equal(rec_seq, expected) and probe.seq_sum == int(rec_seq.sum()),
          f"the recorded samples are exactly the undamaged ones, in order, and the pipeline saw the same (missing "
          f"{np.setdiff1d(expected, rec_seq).size}, unexpected {np.setdiff1d(rec_seq, expected).size}, duplicates "
          f"{rec_seq.size - np.unique(rec_seq).size})")
    check(results, counters["frames_accepted"] == probe.n_in,
          f"source frames_accepted {counters['frames_accepted']} == delivered {probe.n_in}")
    inner_lost = int(((lost > rec_seq[0]) & (lost < rec_seq[-1])).sum())
    check(results, counters["samples_missed"] == inner_lost,
          f"source samples_missed (seq gaps) {counters['samples_missed']} == lost between the first and last "
          f"delivered sample {inner_lost}")
    check_skipped_bytes(run, results)
    check(results, probe.n_corrected == n_rec_cor,
          f"corrected samples: pipeline {probe.n_corrected} == recording {n_rec_cor}")
    if run.endpoint is not None:
        ok = sub is not None and sub["raw"] == probe.n_in and sub["raw_seq_sum"] == probe.seq_sum
        check(results, ok, f"received on Zenoh (raw) {sub['raw'] if sub else '-'} == delivered {probe.n_in}, same "
                           f"seq checksum")
        ok = sub is not None and sub["corrected"] == probe.n_corrected and sub["corrected_seq_sum"] == probe.cor_seq_sum
        check(results, ok, f"received on Zenoh (corrected) {sub['corrected'] if sub else '-'} == pipeline "
                           f"{probe.n_corrected}, same seq checksum")
    check(results, run.daemon._process.errors == 0, f"blocks whose processing failed: {run.daemon._process.errors}")
    check(results, same_output(run.bare_out, run.rec.corrected_blocks),
          "the bare pipeline over the recorded raw blocks reproduces the recorded corrected output bit for bit")
    check(results, mem.growth_end <= 5.0 and mem.growth_max <= 5.0,
          f"memory flat within 5 % after warm-up (end {mem.growth_end:+.2f} %, max {mem.growth_max:+.2f} %)",
          counted=run.schedule.memory_counted)


def check_skipped_bytes(run: SoakRun, results: list[bool]) -> None:
    """The bytes the source skipped (and its framer holds) against the injected garbage and damaged frames."""
    record, counters, framer = run.record, run.counters, run.framer
    fl = 13 + 14 * N_PROBES
    # a frame can have a bit flipped and a byte lost both (the unit draws them independently): on the
    # wire it is then fl - 1 bytes, once
    lost_byte = np.unique(record.samples("drop_byte"))
    only_flipped = np.setdiff1d(record.samples("bitflip"), lost_byte)
    damaged = only_flipped.size * fl + lost_byte.size * (fl - 1)
    skipped = counters["bytes_skipped"] + framer.pending_bytes
    check(results, skipped == record.garbage_bytes + damaged,
          f"bytes skipped {counters['bytes_skipped']} + left pending {framer.pending_bytes} == garbage "
          f"{record.garbage_bytes} + damaged frames {damaged}")


def main() -> int:
    args = parse_args()
    if args.subscribe:
        subscriber_main(args.subscribe)
        return 0
    if args.tracemalloc:
        tracemalloc.start(args.tracemalloc)
    seconds = 60.0 * (1.0 if args.quick else args.minutes)
    print("machine:", machine())
    print(f"code: {code_version()}")
    print(f"load average at start: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    results: list[bool] = []
    with tempfile.TemporaryDirectory(prefix="fluxcal-soak-") as d:
        run = soak(Path(d), seconds, args)
    mem = memory(run.probe)
    print_summary(run, mem)
    check_counts(run, mem, results)
    n_fail = results.count(False)
    print(f"{'PASS' if not n_fail else 'FAIL'}: {len(results) - n_fail} of {len(results)} counted checks passed")
    return 1 if n_fail else 0


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    sys.exit(main())
