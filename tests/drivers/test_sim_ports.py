"""The simulated unit on the wire: ICD bytes and CAN frames, faults and their record, the pty, CAN and
SLCAN emitters, the in-process source, and the cross-process runner."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial

from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.icd import decode_can, frame_length, parse_serial
from fluxcal.drivers.sim import FaultRecord, Unit, load_sim_config
from fluxcal.drivers.sim.can_ports import CanEmitter, SlcanEmitter, slcan_lines
from fluxcal.drivers.sim.ports import PtyEmitter
from fluxcal.drivers.sim.source import SimSource
from fluxcal.drivers.source import open_source

ROOT = Path(__file__).resolve().parents[2]


def unit(**sim) -> Unit:
    table = {"seed": 3, "rate_hz": 200.0, "duration_s": 2.0, "reference": {"enabled": True},
             "motion": {"kind": "tumble", "rate_deg_s": 30.0},
             "temperature": {"start_C": 21.5, "amplitude_C": 3.0, "period_s": 1.0},
             "probes": [{"position_m": [-0.25, 0, 0], "offset_nT": [200, -300, 100], "noise_nT": 0.7},
                        {"position_m": [0.25, 0, 0], "scale": [1.02, 0.98, 1.0], "noise_nT": 0.7}]}
    table.update(sim)
    return Unit(load_sim_config(table))


def assert_frames_are(frames, s, keep=None) -> None:
    """Parsed frames equal the unit's samples (optionally only rows `keep`)."""
    if keep is not None:
        s_counts, s_temp, s_seq, s_t, s_flags = (s.counts[keep], s.temp_raw[keep], s.seq_raw[keep],
                                                  s.t_us_raw[keep], s.flags[keep])
    else:
        s_counts, s_temp, s_seq, s_t, s_flags = s.counts, s.temp_raw, s.seq_raw, s.t_us_raw, s.flags
    np.testing.assert_array_equal(frames.seq, s_seq)
    np.testing.assert_array_equal(frames.t_us, s_t)
    np.testing.assert_array_equal(frames.counts, s_counts)
    np.testing.assert_array_equal(frames.temp_raw, s_temp)
    np.testing.assert_array_equal(frames.flags, s_flags)


def read_pty(path: str, emitter, *, until_done: bool = True, timeout_s: float = 20.0) -> bytes:
    """Plain os.read on the slave until the emitter is done and the port is quiet."""
    fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    buf = bytearray()
    deadline = time.monotonic() + timeout_s
    try:
        quiet = 0
        while time.monotonic() < deadline:
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                chunk = b""
            if chunk:
                buf += chunk
                quiet = 0
                continue
            if emitter.done.is_set():
                quiet += 1
                if quiet > 5:
                    break
            time.sleep(0.01)
    finally:
        os.close(fd)
    return bytes(buf)


# --- bytes and frames, no ports -----------------------------------------------------------------------------

def test_serial_bytes_parse_into_exactly_the_samples():
    u = unit(seq_start=65500, t_us_start=2**32 - 100_000)
    s = u.digitise(0, u.n_samples)
    data = u.serial_bytes(0, u.n_samples)
    assert len(data) == u.n_samples * frame_length(2)
    p = parse_serial(data, 2, final=True)
    assert p.crc_failures == 0 and p.bytes_skipped == 0
    assert_frames_are(p.frames, s)
    assert s.seq_raw[0] == 65500 and 0 in s.seq_raw.tolist()         # the counters wrapped
    assert s.t_us_raw.min() < 100_000 < s.t_us_raw.max()
    # scaled like a decoder would: nT at lsb 0.001, temperatures at 0.01 degC
    np.testing.assert_allclose(s.counts * 1e-3, s.world.raw_nT, atol=5e-4 + 1e-9)
    np.testing.assert_allclose(s.temp_raw * 0.01, s.world.temp_C, atol=5e-3 + 1e-9)


def test_serial_faults_record_matches_what_the_parser_drops():
    u = unit(duration_s=10.0, faults={"garbage_fraction": 0.05, "garbage_max_bytes": 60, "bitflip_fraction": 0.02,
                                      "drop_byte_fraction": 0.02, "drop_frame_fraction": 0.02})
    n = u.n_samples
    rec = FaultRecord()
    data = u.serial_bytes(0, n, record=rec)
    p = parse_serial(data, 2, final=True)
    lost = rec.serial_lost()
    keep = np.setdiff1d(np.arange(n), lost)
    assert_frames_are(p.frames, u.digitise(0, n), keep)
    # each kind happened about as often as asked (2000 frames)
    counts = rec.as_dict()
    for kind, frac in (("bitflip", 0.02), ("drop_byte", 0.02), ("drop_frame", 0.02), ("garbage_after", 0.05)):
        assert abs(counts[kind] - frac * n) < 4 * np.sqrt(frac * n), (kind, counts[kind])
    assert counts["garbage_bytes"] > 0
    # corrupted frames (flipped or short) fail their CRC or lose their header; dropped ones are just gone
    assert p.crc_failures > 0.5 * (counts["bitflip"] + counts["drop_byte"])
    # the stream is the same however it is cut into blocks
    cuts = [0, 1, 333, 1500, n]
    pieces = b"".join(u.serial_bytes(a, b) for a, b in zip(cuts, cuts[1:]))
    assert pieces == data


def test_can_frames_and_dropped_frames_record():
    u = unit(duration_s=5.0, faults={"can_drop_fraction": 0.01}, can_base_id=0x300)
    n = u.n_samples
    rec = FaultRecord()
    ids, payloads, sample_of = u.can_frames(0, n, record=rec)
    probe, axis, value, seq, temp = decode_can(ids, payloads, 2, base_id=0x300)
    assert np.all(probe >= 0)
    s = u.digitise(0, n)
    # every frame that arrived carries its sample's value, seq and temperature
    np.testing.assert_array_equal(value, s.counts[sample_of, probe, axis])
    np.testing.assert_array_equal(seq, s.seq_raw[sample_of])
    np.testing.assert_array_equal(temp, s.temp_raw[sample_of, probe])
    dropped = rec.can_dropped()
    assert len(ids) + len(dropped) == n * 6
    assert 0.005 * n * 6 < len(dropped) < 0.02 * n * 6
    # the frames missing are exactly the recorded ones
    got = set(zip(sample_of.tolist(), probe.tolist(), axis.tolist()))
    assert not got & set(map(tuple, dropped.tolist()))
    complete = np.flatnonzero(np.bincount(sample_of, minlength=n) == 6)
    np.testing.assert_array_equal(complete, np.setdiff1d(np.arange(n), rec.can_incomplete()))


def test_slcan_lines_format():
    ids = np.array([0x200, 0x7FF])
    payloads = np.array([[1, 2, 3, 4, 5, 6, 7, 8], [0xAB, 0xCD, 0xEF, 0, 0, 0, 0, 0xFF]], dtype=np.uint8)
    assert slcan_lines(ids, payloads) == b"t20080102030405060708\rt7FF8ABCDEF00000000FF\r"


# --- the pty -------------------------------------------------------------------------------------------------

def test_pty_emitter_delivers_the_world_through_plain_reads():
    u = unit(seq_start=65400)
    with PtyEmitter(u, realtime=False) as em:
        assert os.path.islink(em.path) and os.readlink(em.path).startswith("/dev/pts/")
        data = read_pty(em.path, em)
        em.wait(5)
    p = parse_serial(data, 2, final=True)
    assert p.crc_failures == 0 and p.bytes_skipped == 0
    assert_frames_are(p.frames, u.digitise(0, u.n_samples))
    assert not os.path.lexists(em.path)              # closed: the link is gone


def test_pty_emitter_with_pyserial_faults_and_a_reconnect():
    u = unit(duration_s=3.0, faults={"bitflip_fraction": 0.01, "drop_frame_fraction": 0.01, "garbage_fraction": 0.02,
                                     "outage_at_s": [1.0], "outage_s": 0.3})
    em = PtyEmitter(u, realtime=False).start()
    buf, errors = bytearray(), 0
    port = serial.Serial(em.path, baudrate=921600, timeout=0.05)
    deadline = time.monotonic() + 20
    try:
        while time.monotonic() < deadline:
            try:
                chunk = port.read(max(1, port.in_waiting))
            except serial.SerialException:
                errors += 1
                port.close()
                while time.monotonic() < deadline:           # reopen the same path, as a driver would
                    try:
                        port = serial.Serial(em.path, baudrate=921600, timeout=0.05)
                        break
                    except serial.SerialException:
                        time.sleep(0.02)
                continue
            if chunk:
                buf += chunk
            elif em.done.is_set() and port.in_waiting == 0:
                break
    finally:
        port.close()
        em.close()
    assert errors == 1 and em.reconnects == 1
    rec = em.record
    assert rec.samples("outage").tolist() == list(range(200, 260))
    p = parse_serial(bytes(buf), 2, final=True)
    keep = np.setdiff1d(np.arange(u.n_samples), rec.serial_lost())
    assert_frames_are(p.frames, u.digitise(0, u.n_samples), keep)
    assert len(keep) < u.n_samples - 60


def test_realtime_pty_paces_by_the_wall_clock_and_drops_while_nobody_listens():
    u = unit(duration_s=0.6)
    em = PtyEmitter(u, realtime=True, block_s=0.02).start()
    try:
        time.sleep(0.2)                     # nobody listening yet: those samples are thrown away
        t0 = time.monotonic()
        data = read_pty(em.path, em)
        elapsed = time.monotonic() - t0
    finally:
        em.close()
    p = parse_serial(data, 2, final=True)
    lost = em.record.samples("no_reader")
    assert lost.size >= 30 and lost[0] == 0
    keep = np.setdiff1d(np.arange(u.n_samples), lost)
    assert_frames_are(p.frames, u.digitise(0, u.n_samples), keep)
    assert elapsed > 0.25                   # the last samples came at their time, not all at once


# --- CAN ----------------------------------------------------------------------------------------------------

def test_can_emitter_on_a_virtual_bus():
    import can

    u = unit(duration_s=1.0, faults={"can_drop_fraction": 0.02})
    rx = can.Bus(interface="virtual", channel="sim-test-virtual")
    em = CanEmitter(u, channel="sim-test-virtual", realtime=False).start()
    try:
        assert em.wait(10)
        msgs = []
        while (m := rx.recv(0)) is not None:
            msgs.append(m)
    finally:
        em.close()
        rx.shutdown()
    ids, payloads, _ = u.can_frames(0, u.n_samples)            # same faults, same frames, same order
    assert len(msgs) == len(ids) == u.n_samples * 6 - em.record.can_dropped().shape[0]
    assert [m.arbitration_id for m in msgs] == ids.tolist()
    assert b"".join(bytes(m.data) for m in msgs) == payloads.tobytes()
    assert all(not m.is_extended_id and m.dlc == 8 for m in msgs)


def test_slcan_speaker_with_python_can():
    import can

    u = unit(duration_s=0.5)
    em = SlcanEmitter(u, realtime=False).start()
    try:
        bus = can.Bus(interface="slcan", channel=em.path, bitrate=1000000, sleep_after_open=0, timeout=0.01)
        try:
            msgs = []
            deadline = time.monotonic() + 20
            while len(msgs) < u.n_samples * 6 and time.monotonic() < deadline:
                m = bus.recv(0.5)
                if m is not None:
                    msgs.append(m)
            assert bus.get_version(2.0) == (10, 13)
            assert bus.get_serial_number(2.0) == "SIM1"
        finally:
            bus.shutdown()
        deadline = time.monotonic() + 2
        while "C" not in em.commands[-1:] and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        em.close()
    assert em.bitrate_cmd == "S8" and "O" in em.commands and em.commands[-1] == "C"
    ids, payloads, _ = u.can_frames(0, u.n_samples)
    assert [m.arbitration_id for m in msgs] == ids.tolist()
    assert b"".join(bytes(m.data) for m in msgs) == payloads.tobytes()


# --- the in-process source ------------------------------------------------------------------------------------

def test_sim_source_blocks_are_the_units_samples():
    u = unit(duration_s=1.0, faults={"temp_invalid_fraction": 0.1})
    src = open_source("sim", u.config, transport="direct", block_s=0.13)
    blocks = []
    with src:
        while (b := src.read(0)) is not None:
            blocks.append(b)
        assert src.exhausted
    got = type(blocks[0]).concat(blocks)
    expect = u.digitise(0, u.n_samples).to_block()
    np.testing.assert_array_equal(got.field_nT, expect.field_nT)
    np.testing.assert_array_equal(got.temp_C, expect.temp_C)
    np.testing.assert_array_equal(got.seq, expect.seq)
    np.testing.assert_array_equal(got.t_s, expect.t_s)
    np.testing.assert_array_equal(got.extras["ref_total"], expect.extras["ref_total"])
    assert src.counters.frames_accepted == u.n_samples
    assert src.counters.temp_invalid == int(np.isnan(expect.temp_C[:, 0]).sum()) > 0
    assert len(blocks[0]) == 26


def test_sim_source_realtime_waits_for_samples():
    src = SimSource(unit(duration_s=10.0).config, realtime=True)
    try:
        time.sleep(0.1)
        first = src.read(0.5)
        assert first is not None and 10 <= len(first) <= 200     # what accumulated since it opened
        nxt = src.read(0.5)
        assert nxt is not None and len(nxt) >= 1
        assert nxt.seq[0] == first.seq[-1] + 1
    finally:
        src.close()


def test_sim_source_checks_the_unit_section():
    class UnitCfg:
        n_probes, lsb_nT = 3, 0.001

    with pytest.raises(ConfigError, match=r"sim.probes: 2 simulated probes but unit.n_probes = 3"):
        open_source("sim", unit().config, unit=UnitCfg())
    UnitCfg.n_probes, UnitCfg.lsb_nT = 2, 0.01
    with pytest.raises(ConfigError, match=r"sim.lsb_nT"):
        open_source("sim", unit().config, unit=UnitCfg())
    with pytest.raises(ConfigError, match=r"source.transport: 'usb'"):
        open_source("sim", unit().config, transport="usb")


@pytest.mark.slow
def test_runner_serves_another_process(tmp_path):
    cfg = tmp_path / "sim.toml"
    cfg.write_text('[sim]\nseed = 5\nrate_hz = 100.0\nduration_s = 1.0\n'
                   '[[sim.probes]]\nposition_m = [0.0, 0.0, 0.0]\nnoise_nT = 0.5\n')
    proc = subprocess.Popen([sys.executable, "-m", "fluxcal.drivers.sim", "--config", str(cfg), "--transport", "pty", "--fast",
                             "--truth", str(tmp_path / "truth.json"), "--record", str(tmp_path / "record.npz")], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        path = proc.stdout.readline().strip()
        assert path.endswith("serial")
        port = serial.Serial(path, timeout=0.1)
        buf = bytearray()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                chunk = port.read(max(1, port.in_waiting))
            except serial.SerialException:
                break                        # the runner closed the port at the end of the run
            buf += chunk
        port.close()
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    p = parse_serial(bytes(buf), 1, final=True)
    u = Unit(load_sim_config({"seed": 5, "rate_hz": 100.0, "duration_s": 1.0,
                              "probes": [{"position_m": [0.0, 0.0, 0.0], "noise_nT": 0.5}]}))
    assert_frames_are(p.frames, u.digitise(0, 100))
    assert "sent samples 0..100" in proc.stderr.read()
    assert (tmp_path / "truth.json").exists()
    rec, meta = FaultRecord.load(str(tmp_path / "record.npz"))
    assert meta == {"start_index": 0, "next_index": 100, "reconnects": 0, "n_probes": 1}
    assert rec.serial_lost().size == 0 and rec.garbage_bytes == 0


def test_fault_record_round_trips_through_a_file(tmp_path):
    """What a simulator in another process did reaches its reader whole: every index of every kind."""
    rec = FaultRecord()
    rec.add("bitflip", np.array([7, 3]))
    rec.add("bitflip", np.array([11]))
    rec.add_range("outage", 100, 150)
    rec.add("can_dropped", np.array([[5, 0, 2], [9, 1, 0]]).ravel())
    rec.add_garbage_bytes(37)
    path = str(tmp_path / "r.npz")
    rec.save(path, next_index=400)
    back, meta = FaultRecord.load(path)
    assert meta == {"next_index": 400}
    assert back.garbage_bytes == 37
    assert back.samples("bitflip").tolist() == [3, 7, 11]
    assert np.array_equal(back.samples("outage"), np.arange(100, 150))
    assert back.can_dropped().tolist() == [[5, 0, 2], [9, 1, 0]]
    assert back.as_dict() == rec.as_dict()


def test_fault_record_holds_indices_not_an_array_per_batch():
    """A long run adds a few indices per block, thousands of times: the record keeps them in one growing
    array per kind (~8 bytes an index, not a numpy array each), and a range that continues the last one
    (no_reader block after block while nobody listens) stays one [start, stop) pair."""
    u = unit(duration_s=60.0, faults={"garbage_fraction": 0.02, "bitflip_fraction": 0.01, "drop_byte_fraction": 0.01,
                                      "drop_frame_fraction": 0.01, "can_drop_fraction": 0.002})
    rec, block = FaultRecord(), 4
    for a in range(0, u.n_samples, block):                     # 3000 blocks, as an emitter sends them
        u.serial_bytes(a, a + block, record=rec)
        u.can_frames(a, a + block, record=rec)
    for a in range(20000, 40000, block):                       # 5000 blocks nobody read: one range
        rec.add_range("no_reader", a, a + block)
    rec.add_range("outage", 50000, 52000)
    counts = rec.as_dict()
    points = (sum(counts[k] for k in ("drop_frame", "bitflip", "drop_byte", "garbage_after"))
              + 3 * counts["can_dropped_frames"])
    assert points > 1000                                       # (duplicates within a kind cannot occur here)
    assert len(rec._kinds) == 7
    assert all(i.ranges.n == 0 for k, i in rec._kinds.items() if k not in ("no_reader", "outage"))
    assert rec._kinds["no_reader"].ranges.n == 2 and rec._kinds["outage"].ranges.n == 2
    assert rec._kinds["no_reader"].points.n == 0 and rec._kinds["outage"].points.n == 0
    # 8 bytes an index, at most twice that in spare capacity, plus the small initial arrays
    assert rec.nbytes <= 2 * 8 * points + 2 * 8 * 64 * len(rec._kinds)
    # what it reports is unchanged: every index, the ranges spelled out
    assert np.array_equal(rec.samples("no_reader"), np.arange(20000, 40000))
    assert np.array_equal(rec.samples("outage"), np.arange(50000, 52000))
    lost = np.concatenate([rec.samples(k) for k in ("drop_frame", "bitflip", "drop_byte")]
                          + [np.arange(20000, 40000), np.arange(50000, 52000)])
    assert np.array_equal(rec.serial_lost(), np.unique(lost))
    assert counts["no_reader"] == 20000 and counts["outage"] == 2000


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["pty", "can-virtual", "slcan"])
def test_transports_through_the_real_drivers(transport):
    """The sim source over the wire: the serial/CAN driver yields exactly the world's samples, less those
    the fault record says were corrupted or dropped on purpose."""
    from fluxcal.drivers.block import SampleBlock

    u = unit(duration_s=1.0, seq_start=65400,
             faults={"bitflip_fraction": 0.02, "garbage_fraction": 0.02, "can_drop_fraction": 0.01})
    src = open_source("sim", u.config, transport=transport)
    blocks = []
    deadline = time.monotonic() + 20
    try:
        # exhausted: the run is over and the driver stayed quiet for a second (the CAN assembler may
        # hold samples behind an incomplete one for its window_s = 0.5 s)
        while not src.exhausted and time.monotonic() < deadline:
            b = src.read(0.1)
            if b is not None and len(b):
                blocks.append(b)
        assert src.exhausted
        rec = src.record
        counters = src.counters.as_dict()
    finally:
        src.close()
    got = SampleBlock.concat(blocks)
    lost = rec.serial_lost() if transport == "pty" else rec.can_incomplete()
    assert lost.size > 0
    keep = np.setdiff1d(np.arange(u.n_samples), lost)
    expect = u.digitise(0, u.n_samples).to_block()
    np.testing.assert_array_equal(got.seq, expect.seq[keep])
    np.testing.assert_array_equal(got.field_nT, expect.field_nT[keep])
    np.testing.assert_array_equal(got.temp_C, expect.temp_C[keep])
    if transport == "pty":
        np.testing.assert_array_equal(got.t_s, expect.t_s[keep])          # the unit clock
        assert counters["crc_failures"] >= 1
    else:
        np.testing.assert_allclose(got.t_s, got.seq / u.rate_hz)           # CAN carries no clock
        assert counters["can_incomplete"] == lost.size
    assert "ref_total" not in got.extras                                   # not on the wire
