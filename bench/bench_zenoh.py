"""Benchmark: fluxcal's Zenoh bus across two processes on loopback, against plain Zenoh in the same run.

Latency: a block message from `ServiceBus.publish_*` (encoding included) in this process to
`BusClient.recv()` returning it decoded in a second process, at a 1 kHz sample rate: 20-sample
blocks at 50 Hz and single samples at 1 kHz, 4 probes, with Zenoh's batching and with `express`.
Throughput: blocks published as fast as the BLOCK stream allows, in probe-samples per second.
Baseline: the same payload sizes put and received with plain zenoh (no encode/decode, no reader
thread), in the same session; ratios are bus/baseline. Both processes read CLOCK_MONOTONIC, which
is system-wide on Linux. Run by hand:

    .venv/bin/python bench/bench_zenoh.py [--seconds 6] [--messages 20000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh  # noqa: E402

from fluxcal.drivers.block import SampleBlock  # noqa: E402
from fluxcal.service.io.bus import (  # noqa: E402
    BusClient,
    ServiceBus,
    ZenohConfig,
    open_session,
)
from fluxcal.service.io.encoding import encode_corrected, encode_raw  # noqa: E402
from fluxcal.service.numerics.outputs import CorrectedBlock  # noqa: E402

N_PROBES = 4
UNIT = "bench"
PLAIN_KEY = "bench/plain"


def _zenoh_version() -> str:
    from importlib.metadata import version

    return version("eclipse-zenoh")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- the receiving process -----------------------------------------------------------------------

def child(args: argparse.Namespace) -> None:
    """Receive `count` messages; print latencies (s) and the time of the first and last arrival as JSON."""
    lat, n_samples, first, last = [], 0, None, None
    if args.kind == "bus":
        client = BusClient(ZenohConfig.client(args.endpoint), UNIT, streams=[args.stream], lossless=True)
        try:
            print("ready", flush=True)
            while len(lat) < args.count:
                m = client.recv(timeout=10.0)
                if m is None:
                    break
                now = time.monotonic()
                lat.append(now - float(m.value.t_s[0]))          # the sender wrote its clock into t_s
                n_samples += m.value.n_samples * m.value.n_probes
                first = first if first is not None else now
                last = now
        finally:
            client.close()
    else:
        session = open_session(ZenohConfig.client(args.endpoint))
        try:
            sub = session.declare_subscriber(PLAIN_KEY, zenoh.handlers.FifoChannel(4096))
            print("ready", flush=True)
            while len(lat) < args.count:
                s = sub.recv()
                now = time.monotonic()
                data = s.payload.to_bytes()
                (t_sent,) = struct.unpack_from("<d", data, 0)
                lat.append(now - t_sent)
                n_samples += args.samples_per_msg
                first = first if first is not None else now
                last = now
            sub.undeclare()
        finally:
            session.close()
    print(json.dumps({"lat": lat, "probe_samples": n_samples, "first": first, "last": last}), flush=True)


def start_child(endpoint: str, kind: str, stream: str, count: int, samples_per_msg: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, __file__, "--child", "--endpoint", endpoint, "--kind", kind,
                             "--stream", stream, "--count", str(count), "--samples-per-msg", str(samples_per_msg)],
                            stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if line.strip() != "ready":
        proc.kill()
        raise RuntimeError(f"receiver did not start: {line!r}")
    return proc


def finish_child(proc: subprocess.Popen) -> dict:
    out, _ = proc.communicate(timeout=60)
    return json.loads(out.strip().splitlines()[-1])


# --- the sending side -----------------------------------------------------------------------------

def make_raw(n: int, rng: np.random.Generator) -> SampleBlock:
    return SampleBlock(t_s=np.zeros(n), seq=np.arange(n, dtype=np.int64),
                       field_nT=rng.normal(0, 30000, (n, N_PROBES, 3)), temp_C=rng.normal(22, 1, (n, N_PROBES)),
                       flags=np.zeros(n, np.uint8), extras={"ref_total": rng.normal(52500, 1, n)})


def make_corrected(n: int, rng: np.random.Generator) -> CorrectedBlock:
    c = rng.normal(0, 30000, (n, N_PROBES, 3))
    return CorrectedBlock(t_s=np.zeros(n), seq=np.arange(n, dtype=np.int64), corrected_nT=c,
                          diff_nT=c[:, 1:] - c[:, :1], tensor_nT_m=rng.normal(0, 10, (n, 3, 3)),
                          center_nT=c.mean(axis=1), cal_id=1)


def wait_matching(pub_ok, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not pub_ok():
        if time.monotonic() > deadline:
            raise RuntimeError("the receiver never subscribed")
        time.sleep(0.01)


def paced(count: int, rate_hz: float | None):
    """Yield count times, at rate_hz (None: as fast as possible)."""
    t0 = time.monotonic()
    for i in range(count):
        if rate_hz is not None:
            wait = t0 + i / rate_hz - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        yield i


def run_bus(endpoint: str, express: bool, stream: str, n: int, count: int, rate_hz: float | None) -> dict:
    rng = np.random.default_rng(0)
    bus = ServiceBus(ZenohConfig(listen=[endpoint], express=express), UNIT, per_probe=True,
                     probe_names=[f"s{k + 1}" for k in range(N_PROBES)])
    try:
        proc = start_child(endpoint, "bus", stream, count, n * N_PROBES)
        wait_matching(lambda: bus.has_subscribers(stream))
        blocks = [make_raw(n, rng) if stream == "raw" else make_corrected(n, rng) for _ in range(16)]
        publish = bus.publish_raw if stream == "raw" else bus.publish_corrected
        t_first = time.monotonic()
        for i in paced(count, rate_hz):
            b = blocks[i % 16]
            b.t_s[:] = time.monotonic()                # the send time rides in the block (arrays are writable)
            publish(b)
        res = finish_child(proc)
    finally:
        bus.close()
    res["t_first_send"] = t_first
    return res


def run_plain(endpoint: str, express: bool, payload_bytes: int, samples_per_msg: int, count: int,
              rate_hz: float | None) -> dict:
    cfg = ZenohConfig(listen=[endpoint])
    session = open_session(cfg)
    try:
        pub = session.declare_publisher(PLAIN_KEY, congestion_control=zenoh.CongestionControl.BLOCK,
                                        priority=zenoh.Priority.DATA, express=express)
        proc = start_child(endpoint, "plain", PLAIN_KEY, count, samples_per_msg)
        wait_matching(lambda: pub.matching_status.matching)
        buf = bytearray(os.urandom(payload_bytes))
        t_first = time.monotonic()
        for _ in paced(count, rate_hz):
            struct.pack_into("<d", buf, 0, time.monotonic())
            pub.put(bytes(buf))
        res = finish_child(proc)
        pub.undeclare()
    finally:
        session.close()
    res["t_first_send"] = t_first
    return res


def summary(res: dict, count: int) -> tuple[float, float, float, int]:
    lat = np.asarray(res["lat"]) * 1e3
    received = len(lat)
    if not received:
        return float("nan"), float("nan"), float("nan"), 0
    rate = res["probe_samples"] / (res["last"] - res["t_first_send"])
    return float(np.percentile(lat, 50)), float(np.percentile(lat, 99)), rate, received


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="length of each paced latency run")
    ap.add_argument("--messages", type=int, default=20000, help="messages in each throughput run")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--endpoint", help=argparse.SUPPRESS)
    ap.add_argument("--kind", help=argparse.SUPPRESS)
    ap.add_argument("--stream", help=argparse.SUPPRESS)
    ap.add_argument("--count", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--samples-per-msg", dest="samples_per_msg", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)

    print(f"machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, Python {platform.python_version()}, numpy {np.__version__}, "
          f"eclipse-zenoh {_zenoh_version()}")
    print(f"two processes on loopback (tcp/127.0.0.1), {N_PROBES} probes, BLOCK congestion control, "
          f"latency = publish (encode included) -> recv() returns decoded in the other process\n")
    rng = np.random.default_rng(0)
    paced_cases = [
        ("raw 20-sample blocks @ 50 Hz", "raw", 20, 50.0, int(50 * args.seconds)),
        ("raw 1-sample blocks @ 1 kHz", "raw", 1, 1000.0, int(1000 * args.seconds)),
        ("corrected (+diff, tensor, 4 per-probe) 20 @ 50 Hz", "corrected", 20, 50.0, int(50 * args.seconds)),
    ]
    flat_cases = [
        ("raw 20-sample blocks", "raw", 20, None, args.messages),
        ("raw 200-sample blocks", "raw", 200, None, max(args.messages // 10, 100)),
    ]
    for title, cases, paced_run in (("latency, paced at a 1 kHz sample rate", paced_cases, True),
                                    ("throughput, published as fast as BLOCK allows", flat_cases, False)):
        print(f"[{title}]")
        if paced_run:
            header = f"{'case':<58}{'msgs':>7}{'p50 ms':>9}{'p99 ms':>9}{'p50/plain':>11}"
        else:
            header = f"{'case':<58}{'msgs':>7}{'probe-samples/s':>17}{'bus/plain':>11}"
        print(header)
        print("-" * len(header))
        for express in (False, True):
            for label, stream, n, rate, count in cases:
                size = len(encode_raw(make_raw(n, rng)) if stream == "raw" else encode_corrected(make_corrected(n, rng)))
                plain = summary(run_plain(f"tcp/127.0.0.1:{free_port()}", express, size, n * N_PROBES, count, rate),
                                count)
                bus = summary(run_bus(f"tcp/127.0.0.1:{free_port()}", express, stream, n, count, rate), count)
                name = f"{label}{', express' if express else ''}"
                pname = f"  plain zenoh, {size} B payloads"
                if paced_run:
                    print(f"{pname:<58}{plain[3]:>7}{plain[0]:9.3f}{plain[1]:9.3f}")
                    print(f"{name:<58}{bus[3]:>7}{bus[0]:9.3f}{bus[1]:9.3f}{bus[0] / plain[0]:10.2f}x")
                else:
                    print(f"{pname:<58}{plain[3]:>7}{plain[2]:17,.0f}")
                    print(f"{name:<58}{bus[3]:>7}{bus[2]:17,.0f}{bus[2] / plain[2]:10.2f}x")
                if bus[3] != count or plain[3] != count:
                    print(f"  !! lost messages: bus {count - bus[3]}, plain {count - plain[3]}")
        print()

if __name__ == "__main__":
    main()
