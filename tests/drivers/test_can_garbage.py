"""What a CAN adapter or bus gives that is no frame of the unit's never stops the service, and every frame is counted
once, by its kind (issue 38, build 1): the red team's garbled SLCAN lines on a pty through python-can's slcan
interface, and a fuzz of 10,000 random and mutated SLCAN lines, and of 10,000 random python-can frames on a virtual
bus, against a running service, whose counters must sum to what was sent.

Before: one line `t200F0000000000000000` (ValueError), `t2008ZZ...` (non-hexadecimal) or `t20` (IndexError) stopped
`fluxcal run` with a traceback; lines python-can's parser did not know were dropped without a count; frames of 7
bytes and remote frames were counted as CRC failures with the serial line's advice ("check the cable").
"""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path
from typing import Sequence

import can
import numpy as np
import pytest

from fluxcal.drivers import icd
from fluxcal.drivers.can_source import CanSource
from fluxcal.drivers.registry import source_kind
from fluxcal.drivers.slcan import parse_line
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon
from fluxcal.service.wiring.faults import FaultWatch
from fluxcal.service.wiring.sinks import Sink

RATE_HZ = 200.0
#: the counters among which every frame or line received is counted exactly once
KINDS = ("frames_accepted", "foreign_frames", "wrong_length", "remote_frames", "error_frames", "bad_frames")


def good_lines(n_samples: int, seed: int = 1) -> list[str]:
    """The SLCAN lines of n_samples ICD samples of a 2-probe unit at base 0x200."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(-60_000_000, 60_000_000, (n_samples, 2, 3)).astype(np.int32)
    ids, payloads = icd.encode_can(np.arange(n_samples) & 0xFFFF, counts, np.full((n_samples, 2), 2100, np.int16))
    return [f"t{i:03X}8{p.tobytes().hex().upper()}\r" for i, p in zip(ids.tolist(), payloads)]


def test_the_red_teams_lines_are_counted_by_kind_never_raised():
    for line in ("t200F0000000000000000\r", "t2008ZZZZZZZZZZZZZZZZ\r", "t20\r", "t\r", "x\r", "t8008" + "00" * 8 + "\r",
                 "T1FFFFFFF9" + "00" * 8 + "\r", "t2008" + "00" * 7 + "\r", "t2008" + "00" * 9 + "\r", "\x1b[2J\r"):
        assert parse_line(line) is None, line
    seven = parse_line("t2007" + "11" * 7 + "\r")
    assert (seven.dlc, len(seven.data), seven.is_remote_frame) == (7, 7, False)
    remote = parse_line("r2008\r")
    assert remote.is_remote_frame and remote.arbitration_id == 0x200
    stamped = parse_line("t2018" + "AB" * 8 + "1F2E\r")                # a time stamp after the data (Z1)
    assert stamped.data == bytes([0xAB] * 8) and stamped.arbitration_id == 0x201
    assert parse_line("D1234567FF" + "00" * 64 + "\r").is_fd


def test_slcan_on_a_pty_counts_garbled_lines_and_keeps_the_samples(pty_port):
    """The adapter on a pty, read by CanSource through python-can's slcan interface (fluxcal.drivers.slcan): the samples
    between the garbage arrive whole, and each line is counted once as what it is."""
    port = pty_port()
    src = CanSource(interface="slcan", channel=port.path, n_probes=2, rate_hz=RATE_HZ,
                    bus_kwargs={"sleep_after_open": 0})
    try:
        lines = good_lines(40)
        bad = ["t200F0000000000000000\r", "t2008ZZZZZZZZZZZZZZZZ\r", "t20\r", "\x07", "Q" * 500 + "\r"]
        seven, remote = "t2017" + "00" * 7 + "\r", "r2008\r"
        wire = lines[:60] + bad + [seven, remote] + lines[60:]
        port.write("".join(wire).encode("latin-1"), chunk=97)
        got = []
        deadline = time.monotonic() + 10
        while sum(len(b) for b in got) < 40 and time.monotonic() < deadline:
            b = src.read(timeout=0.2)
            if b is not None:
                got.append(b)
        seqs = np.concatenate([b.seq for b in got])
        assert seqs.tolist() == list(range(40))
        c = src.counters
        assert (c.bad_frames, c.wrong_length, c.remote_frames) == (len(bad), 1, 1)
        assert "crc_failures" not in c.as_dict()                 # CAN has none: its controller drops those
        assert c.frames_accepted == len(lines)
    finally:
        src.close()


@pytest.mark.parametrize("stamps", [False, True])
def test_slcan_lines_of_the_other_form_than_the_adapters_are_garbled_not_data(pty_port, stamps):
    """An adapter sends time stamps or not. Four characters doubled in a stamp-less line read as the data and a time
    stamp: 117 samples of a field trial got a probe temperature of 20.0-59.5 degC where 22.0 was sent, with every
    counter at zero. After the first frames the bus holds to the adapter's form: a line of the other is garbled,
    counted, and no sample takes its value."""
    port = pty_port()
    src = CanSource(interface="slcan", channel=port.path, n_probes=2, rate_hz=RATE_HZ,
                    bus_kwargs={"sleep_after_open": 0})
    try:
        lines = [ln[:-1] + ("0A0B\r" if stamps else "\r") for ln in good_lines(40)]
        doubled = {}
        for k in range(30, 70, 7):            # frames past the first 16: four characters of the data doubled
            body = lines[k][:-1]
            doubled[k] = body[:9] + body[9:13] * 2 + body[13:] + "\r"
        wire = [doubled.get(k, ln) for k, ln in enumerate(lines)]
        port.write("".join(wire).encode("latin-1"), chunk=97)
        got = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and src.counters.frames_accepted + src.counters.bad_frames < len(wire):
            b = src.read(timeout=0.2)
            if b is not None:
                got.append(b)
        c = src.counters
        assert (c.bad_frames, c.frames_accepted) == (len(doubled), len(lines) - len(doubled))
        if got:
            temps = np.concatenate([b.temp_C for b in got])
            ok = temps[np.isfinite(temps)]
            assert np.all(ok == ok.flat[0])                      # none took a garbled value
    finally:
        src.close()


def test_can_faults_are_said_in_the_buss_own_words():
    said: list[str] = []
    clock = [0.0]
    watch = FaultWatch(said.append, words=source_kind("can").words(), clock=lambda: clock[0], wall=lambda: 0.0)
    base = dict.fromkeys(("frames_accepted", "bad_frames", "wrong_length", "remote_frames"), 0)
    watch.tick(base)
    clock[0] = 1.0
    watch.tick({**base, "frames_accepted": 600, "bad_frames": 3, "wrong_length": 2, "remote_frames": 1})
    text = "\n".join(said)
    assert "bad CAN frames: 3 line(s) or frame(s) from the CAN adapter that are no frame" in text
    assert "CAN frames of a wrong length: 2 frame(s)" in text and "CAN remote frames: 1 remote frame(s)" in text
    assert "CRC" not in text and "check the cable" not in text
    summary = watch.summary({**base, "frames_accepted": 600, "bad_frames": 3, "wrong_length": 2, "remote_frames": 1})
    assert len([line for line in summary if line.startswith("summary: ")]) == 3


# --- the fuzz, against a running service -----------------------------------------------------------------------

class LastHealth(Sink):
    """Keeps the counters of the last health message (the one at stop is the last)."""

    name = "test-health"

    def __init__(self) -> None:
        self.counters: dict = {}

    def on_health(self, counters, faults) -> None:
        self.counters = dict(counters)


class Samples(Sink):
    """Keeps the seqs of the raw samples the service took."""

    name = "test-samples"

    def __init__(self) -> None:
        self.seq: list[int] = []

    def on_raw(self, block) -> None:
        self.seq += block.seq.tolist()


def can_service(tmp_path: Path, interface: str, channel: str, *, sinks: Sequence[Sink] = (),
                window_s: float = 0.5) -> tuple[Daemon, LastHealth, threading.Thread, list]:
    text = (Path("configs/can-example.toml").read_text()
            .replace("[source]\n", f"[source]\nwindow_s = {window_s}\n")
            .replace('interface = "socketcan"', f'interface = "{interface}"')
            .replace('channel = "can0"', f'channel = "{channel}"')
            .replace('listen = ["tcp/127.0.0.1:7447"]', 'listen = ["tcp/127.0.0.1:0"]')
            .replace('file = "../state/grad1-can-cal.json"', f'file = "{tmp_path / "cal.json"}"')
            .replace('[mcap]', '[mcap]\nenabled = false'))
    (tmp_path / "can.toml").write_text(text)
    health = LastHealth()
    said: list[str] = []
    daemon = Daemon(load_config(tmp_path / "can.toml"), say=said.append, sinks=[health, *sinks])
    result: list = []

    def run() -> None:
        try:
            result.append(daemon.run())
        except BaseException as e:  # noqa: BLE001 - the test asserts there was none
            result.append(e)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 15
    while not any(m.startswith("publishing on zenoh") for m in said):
        assert time.monotonic() < deadline and thread.is_alive(), (said, result)
        time.sleep(0.05)
    return daemon, health, thread, result


def fuzz_lines(rng: np.random.Generator, n: int) -> list[str]:
    """n SLCAN lines: random characters, mutated good lines (a character changed, cut, doubled, inserted), good
    lines, remote and short frames, the adapter's error bell; each ends in \\r (the adapter's terminator) but the
    bells, none is the bare OK "\\r"."""
    alphabet = list("tTrRdDbB0123456789ABCDEFabcdefXZ\x1b\n ")
    good = good_lines(n, seed=int(rng.integers(1 << 30)))
    out = []
    for i in range(n):
        pick = rng.integers(6)
        line = good[i][:-1]
        if pick == 0:
            line = "".join(rng.choice(alphabet, int(rng.integers(1, 40))))
        elif pick == 1:
            k = int(rng.integers(len(line)))
            line = line[:k] + str(rng.choice(alphabet)) + line[k + 1:]
        elif pick == 2:
            line = line[:int(rng.integers(len(line)))] or "t"
        elif pick == 3:
            k = int(rng.integers(len(line)))
            line = line[:k] + line[k:k + int(rng.integers(1, 6))] * 2 + line[k:]
        elif pick == 4:
            line = f"r{int(rng.integers(0x1F0, 0x210)):03X}{int(rng.integers(9))}" if rng.random() < 0.5 else \
                f"t{int(rng.integers(0x1F0, 0x210)):03X}5" + "00" * 5
        # the adapter's error bell ends a line of its own (no \r after it)
        out.append("\x07" if pick == 5 and i % 50 == 0 else (line or "Z") + "\r")
    return out


def expected_good(lines: Sequence[str]) -> int:
    """The lines the adapter's bus takes as frames: those that parse, after its first STAMP_LOCK_FRAMES frames only
    those of the form most of them had (time stamps or none): the fuzz mixes both forms, an adapter sends one."""
    from fluxcal.drivers.slcan import STAMP_LOCK_FRAMES, stamped_line

    forms, good = [0, 0], 0
    for x in lines:
        msg = parse_line(x) if x.endswith("\r") else None
        if msg is None:
            continue
        form = int(stamped_line(x, msg))
        if sum(forms) < STAMP_LOCK_FRAMES:
            forms[form] += 1
        elif forms[form] < forms[1 - form]:
            continue
        good += 1
    return good


@pytest.mark.slow
def test_a_fuzz_of_slcan_lines_against_a_running_service_is_counted_line_for_line(tmp_path, pty_port):
    port = pty_port()
    daemon, health, thread, result = can_service(tmp_path, "slcan", port.path)
    try:
        lines = fuzz_lines(np.random.default_rng(38), 10_000)
        port.write("".join(lines).encode("latin-1"), chunk=1024).join(30)
        deadline = time.monotonic() + 30
        while sum(health.counters.get(k, 0) for k in KINDS) < len(lines):
            assert time.monotonic() < deadline and thread.is_alive(), (health.counters, result)
            time.sleep(0.2)
        assert thread.is_alive()
    finally:
        daemon.stop.set()
        thread.join(20)
    assert result == [0], result
    c = health.counters
    assert sum(c[k] for k in KINDS) == len(lines), {k: c[k] for k in KINDS}
    assert c["bad_frames"] == len(lines) - expected_good(lines)
    assert c["bad_frames"] > 2000 and c["frames_accepted"] > 2000 and c["remote_frames"] > 100


@pytest.mark.slow
def test_a_fuzz_of_can_frames_against_a_running_service_is_counted_frame_for_frame(tmp_path):
    channel = f"fuzz-{uuid.uuid4().hex}"
    rng = np.random.default_rng(43)
    with can.Bus(interface="virtual", channel=channel) as tx:
        daemon, health, thread, result = can_service(tmp_path, "virtual", channel)
        try:
            sent = 0
            good = good_lines(3000, seed=4)
            for i in range(10_000):
                kind = rng.integers(6)
                ident = int(rng.integers(0x1F0, 0x212))
                if kind == 0:
                    msg = can.Message(arbitration_id=ident, data=rng.bytes(int(rng.integers(0, 9))),
                                      is_extended_id=False)
                elif kind == 1:
                    msg = can.Message(arbitration_id=ident, is_remote_frame=True, dlc=int(rng.integers(9)),
                                      is_extended_id=False)
                elif kind == 2:
                    msg = can.Message(arbitration_id=int(rng.integers(1 << 29)), data=rng.bytes(8), is_extended_id=True)
                elif kind == 3:
                    msg = can.Message(is_error_frame=True, arbitration_id=0x20000080, is_extended_id=True)
                elif kind == 4:
                    msg = can.Message(arbitration_id=ident, data=rng.bytes(12), is_fd=True, is_extended_id=False)
                else:
                    msg = parse_line(good[i % len(good)])
                tx.send(msg)
                sent += 1
            deadline = time.monotonic() + 30
            while sum(health.counters.get(k, 0) for k in KINDS) < sent:
                assert time.monotonic() < deadline and thread.is_alive(), (health.counters, result)
                time.sleep(0.2)
        finally:
            daemon.stop.set()
            thread.join(20)
    assert result == [0], result
    c = health.counters
    assert sum(c[k] for k in KINDS) == sent, {k: c[k] for k in KINDS}
    assert min(c[k] for k in KINDS if k != "bad_frames") > 100 and "crc_failures" not in c



def test_a_stopping_service_releases_the_samples_its_can_assembler_holds(tmp_path):
    """At the service's stop, the complete samples waiting behind an incomplete one are taken (recorded, published,
    processed) and the incomplete one counted: none lost uncounted (a field trial lost 30 of 3,386 at a stop that
    followed an adapter gone away)."""
    channel = f"held-{uuid.uuid4().hex}"
    good = [parse_line(line) for line in good_lines(40, seed=5)]
    del good[20 * 6 + 3]                                  # sample 20 lacks a frame: 21-39 wait behind it
    taken = Samples()
    with can.Bus(interface="virtual", channel=channel) as tx:
        daemon, health, thread, result = can_service(tmp_path, "virtual", channel, sinks=[taken], window_s=60.0)
        try:
            for msg in good:
                tx.send(msg)
            deadline = time.monotonic() + 15
            while health.counters.get("frames_accepted", 0) < len(good) or len(taken.seq) < 20:
                assert time.monotonic() < deadline and thread.is_alive(), (health.counters, result)
                time.sleep(0.1)
            assert len(taken.seq) == 20 and health.counters.get("can_incomplete", 0) == 0    # the rest held
        finally:
            daemon.stop.set()
            thread.join(20)
    assert result == [0], result
    assert taken.seq == [s for s in range(40) if s != 20]
    assert health.counters["can_incomplete"] == 1
