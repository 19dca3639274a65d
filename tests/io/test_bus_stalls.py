"""One subscriber that stops taking data (a frozen process) holds back only itself.

Before: the service's BLOCK streams waited for it up to Zenoh's default of 5 s at a time, every other
subscriber (recorders included) stalled with it, the service's outbox overflowed and dropped raw blocks
for everyone, and nothing counted the frozen subscriber's losses. Now Zenoh disconnects a subscriber
that takes nothing for [zenoh] stall_close_ms (500 ms), the sender counts each stall, and the
subscriber, reconnected, counts what it missed by the raw blocks' seq.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_zenoh_security import free_port

from fluxcal.drivers.block import SampleBlock
from fluxcal.service.io.bus import ServiceBus, ZenohConfig

SUBSCRIBER = """
import json, os, sys, time
from fluxcal.service.io.bus import BusClient, ZenohConfig

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.io.bus.sender",)
ep, out = sys.argv[1], sys.argv[2]
worst, samples, end = 0.0, 0, None
with BusClient(ZenohConfig.client(ep), "u1", streams=["raw"]) as c:
    open(out + ".ready", "w").close()
    while end is None or time.monotonic() < end:
        if end is None and os.path.exists(out + ".stop"):
            end = time.monotonic() + 1.0            # what is still on its way
        m = c.recv(timeout=0.1)
        if m is not None:
            worst = max(worst, time.time() - float(m.value.t_s[-1]))   # the publisher puts its wall time in t_s
            samples += m.value.n_samples
    json.dump({"worst_latency_s": worst, "samples": samples, **c.stats}, open(out, "w"))
"""

N = 2000                      # samples per block: ~140 kB, 50 blocks a second fill a frozen reader's buffers fast


def _block(seq0: int) -> SampleBlock:
    return SampleBlock(t_s=np.full(N, time.time()), seq=np.arange(seq0, seq0 + N, dtype=np.int64),
                       field_nT=np.random.default_rng(seq0).normal(size=(N, 2, 3)), temp_C=np.zeros((N, 2)),
                       flags=np.zeros(N, np.uint8))


@pytest.mark.slow
def test_a_frozen_subscriber_holds_back_only_itself_and_counts_its_losses(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    outs = [tmp_path / "healthy.json", tmp_path / "frozen.json"]
    with ServiceBus(ZenohConfig(listen=[ep], stall_close_ms=500.0), "u1") as bus:
        subs = [subprocess.Popen([sys.executable, "-c", SUBSCRIBER, ep, str(o)], cwd=Path.cwd())
                for o in outs]
        try:
            deadline = time.monotonic() + 20
            while not all(Path(str(o) + ".ready").exists() for o in outs):
                assert time.monotonic() < deadline
                time.sleep(0.05)
            time.sleep(0.5)
            seq, t0, frozen, resumed = 0, time.monotonic(), False, False
            while time.monotonic() - t0 < 9.0:
                el = time.monotonic() - t0
                if not frozen and el > 1.0:
                    subs[1].send_signal(signal.SIGSTOP)
                    frozen = True
                if not resumed and el > 6.0:
                    subs[1].send_signal(signal.SIGCONT)
                    resumed = True
                bus.publish_raw(_block(seq))
                seq += N
                time.sleep(0.02)
            assert bus.flush(10.0)
            stats = dict(bus.stats)
            for o in outs:
                Path(str(o) + ".stop").touch()
        finally:
            for p in subs:
                p.send_signal(signal.SIGCONT)
            for p in subs:
                p.wait(40)
    healthy, stopped = (json.loads(o.read_text()) for o in outs)
    assert stats["send_dropped"] == 0 and stats["send_stalls"] >= 1, stats
    # the healthy subscriber: everything, never more than a second late
    assert healthy["samples"] == seq and healthy["missed_raw_samples"] == 0, healthy
    print("worst latency of the healthy subscriber", healthy["worst_latency_s"], "stalls", stats["send_stalls"], stats["send_stalled_ms"])
    assert healthy["worst_latency_s"] < 1.0, healthy
    # the frozen one was disconnected, came back, and knows exactly what it missed
    assert stopped["missed_raw_samples"] > 0 and stopped["raw_gaps"] >= 1, stopped
    assert stopped["samples"] + stopped["missed_raw_samples"] == seq, (stopped, seq)


class _Publisher:
    """What the sender calls: put(payload), recorded in order."""

    def __init__(self, log: list) -> None:
        self.log = log

    def put(self, payload: bytes) -> None:
        self.log.append(payload)


def test_gathered_messages_go_together_in_order_and_the_oldest_beyond_the_bound_are_dropped():
    """The service's loop gathers a turn's messages and releases them at once (one wake-up of the sender per
    block); what nobody releases goes anyway after the sender's half-second wait; a backlog over its bound drops
    the oldest, counted, whether the messages came one by one or together."""
    from fluxcal.service.io.bus.sender import Sender

    sent: list[bytes] = []
    pub = _Publisher(sent)
    stats = {"published_raw": 0, "published_corrected": 0, "send_dropped": 0, "publish_errors": 0}
    s = Sender(stats, backlog_bytes=1000, thread_name="test-send")
    try:
        s.gather = True
        s.put_all([("raw", pub, b"r1"), ("corrected", pub, b"c1")])
        s.put("raw", pub, b"r2")
        s.release()
        assert s.flush(5.0) and sent == [b"r1", b"c1", b"r2"]
        assert stats["published_raw"] == 2 and stats["published_corrected"] == 1
        s.put("raw", pub, b"r3")                         # never released
        deadline = time.monotonic() + 5.0
        while len(sent) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sent[-1] == b"r3"
        s.put_all([("raw", pub, bytes([k]) * 400) for k in range(5)])   # 2,000 bytes against a bound of 1,000
        assert stats["send_dropped"] == 3
        s.release()
        assert s.flush(5.0) and sent[-2:] == [bytes([3]) * 400, bytes([4]) * 400]
    finally:
        s.stop()
