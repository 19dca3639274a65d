"""CAN: the sample assembler (interleaving, loss, bounded window, time limit, seq wrap, unit
restart) with exact expectations, and CanSource over python-can's virtual bus and over SLCAN on
a pty (python-can's slcan interface opens the pty slave; the test speaks SLCAN on the master)."""

from __future__ import annotations

import os
import select
import time
import uuid

import can
import numpy as np
import pytest
from helpers import read_samples

from fluxcal.drivers.assemble import CanAssembler, CanSamples, can_icd_counters
from fluxcal.drivers.can_source import CanConfig, CanSource, open_source
from fluxcal.drivers.config import load_section
from fluxcal.drivers.errors import ConfigError, DriverError
from fluxcal.drivers.source import open_source as open_source_by_kind

RATE_HZ = 500.0


def feed(asm: CanAssembler, ids: np.ndarray, payloads: np.ndarray, batch_sizes: np.ndarray) -> CanSamples:
    parts, i = [], 0
    for size in batch_sizes:
        parts.append(asm.push(ids[i:i + size], payloads[i:i + size], 0.0, now_s=0.0))
        i += size
        if i >= len(ids):
            break
    parts.append(asm.push(ids[i:], payloads[i:], 0.0, now_s=0.0))
    parts.append(asm.flush())
    return CanSamples.concat(parts, asm.n_probes)


def assert_samples_are(got: CanSamples, truth) -> None:
    assert np.array_equal(got.seq, truth.seq)
    assert np.array_equal(got.counts, truth.counts)
    assert np.array_equal(got.temp_raw, truth.temp_raw)


@pytest.mark.parametrize("seed", range(5))
def test_interleaved_and_lossy_frames_give_exactly_the_complete_samples(icd_truth, seed):
    rng = np.random.default_rng(seed)
    n, window = int(rng.integers(1, 5)), 16
    truth = icd_truth(600, n, seed=seed)              # crosses the seq wrap
    ids, payloads = truth.can_frames()
    per = 3 * n
    sample_of = np.repeat(np.arange(len(truth)), per)
    # neighbouring samples interleave: each frame moves by less than the window
    order = np.argsort(sample_of + rng.uniform(0, window - 1, sample_of.size), kind="stable")
    delivered = rng.random(sample_of.size) > 0.02
    order = order[delivered[order]]
    received = np.bincount(sample_of[delivered], minlength=len(truth))
    counters = can_icd_counters()
    asm = CanAssembler(n, window_samples=window, counters=counters)
    got = feed(asm, ids[order], payloads[order], rng.integers(1, 200, 10_000))
    complete = received == per
    assert_samples_are(got, truth.take(complete))
    assert counters.can_incomplete == np.count_nonzero((received > 0) & (received < per))
    assert counters.frames_accepted == order.size
    assert asm.pending_samples == 0


def test_memory_stays_bounded_when_every_sample_is_incomplete(icd_truth):
    n, window = 2, 8
    truth = icd_truth(3000, n)
    ids, payloads = truth.can_frames()
    keep = np.ones(ids.size, bool)
    keep[5::6] = False                                 # every sample loses its probe-2 z frame
    ids, payloads = ids[keep], payloads[keep]
    counters = can_icd_counters()
    asm = CanAssembler(n, window_samples=window, counters=counters)
    most = 0
    for i in range(0, ids.size, 37):
        assert len(asm.push(ids[i:i + 37], payloads[i:i + 37], 0.0, now_s=0.0)) == 0
        most = max(most, asm.pending_samples)
    assert most <= window + 1
    asm.flush()
    assert counters.can_incomplete == len(truth)


def test_incomplete_sample_expires_after_the_time_limit(icd_truth):
    truth = icd_truth(1, 1)
    ids, payloads = truth.can_frames()
    counters = can_icd_counters()
    asm = CanAssembler(1, window_samples=1000, window_s=0.5, counters=counters)
    assert len(asm.push(ids[:2], payloads[:2], 10.0)) == 0
    assert len(asm.push(ids[:0], payloads[:0], 10.0, now_s=10.4)) == 0 and asm.pending_samples == 1
    asm.push(ids[:0], payloads[:0], 10.0, now_s=10.6)
    assert asm.pending_samples == 0 and counters.can_incomplete == 1
    # its last frame, arriving after the sample was given up, is ignored
    assert len(asm.push(ids[2:], payloads[2:], 10.7)) == 0 and asm.pending_samples == 0


def test_complete_samples_wait_for_an_earlier_incomplete_one(icd_truth):
    truth = icd_truth(3, 1)
    ids, payloads = truth.can_frames()
    asm = CanAssembler(1, window_samples=4)
    order = [0, 1, 3, 4, 5, 6, 7, 8]                    # sample 0 lacks its z frame for now
    assert len(asm.push(ids[order], payloads[order], 0.0)) == 0
    got = asm.push(ids[[2]], payloads[[2]], 0.0)
    assert_samples_are(got, truth)
    # a late duplicate of a released sample changes nothing
    assert len(asm.push(ids[:3], payloads[:3], 0.0)) == 0 and asm.pending_samples == 0


def test_unit_restart_is_followed(icd_truth):
    a = icd_truth(100, 1, seq0=30_000)
    b = icd_truth(100, 1, seed=1, seq0=0)
    ids = np.concatenate([a.can_frames()[0], b.can_frames()[0]])
    payloads = np.concatenate([a.can_frames()[1], b.can_frames()[1]])
    counters = can_icd_counters()
    asm = CanAssembler(1, window_samples=8, counters=counters)
    got = feed(asm, ids, payloads, np.full(100, 50))
    # seq goes on from the last sample's (t_s = seq / rate_hz never goes back), no sample counted missed
    assert got.seq.tolist() == list(range(30_000, 30_200))
    assert np.array_equal(got.counts, np.concatenate([a.counts, b.counts]))
    assert counters.can_incomplete == 0 and counters.restarts == 1


def test_unit_restart_after_more_than_half_the_counter_is_not_taken_for_a_wrap(icd_truth):
    """A restart at seq 40,000 steps 'forward' by 25,536 mod 2^16: with the unit's rate, the receive times say
    it cannot be 25,536 samples (51 s at 500 Hz) in a tenth of a second."""
    a = icd_truth(100, 1, seq0=40_000)
    b = icd_truth(100, 1, seed=1, seq0=0)
    counters = can_icd_counters()
    asm = CanAssembler(1, window_samples=8, counters=counters, rate_hz=RATE_HZ)
    parts = [asm.push(*a.can_frames(), 10.0), asm.push(*b.can_frames(), 10.1), asm.flush()]
    got = CanSamples.concat(parts, 1)
    assert got.seq.tolist() == list(range(40_000, 40_200))
    assert counters.restarts == 1 and counters.can_incomplete == 0
    # the same counters 51 s apart are a wrap with loss, not a restart
    asm = CanAssembler(1, window_samples=8, counters=can_icd_counters(), rate_hz=RATE_HZ)
    got = CanSamples.concat([asm.push(*a.can_frames(), 10.0), asm.push(*b.can_frames(), 61.2), asm.flush()], 1)
    assert got.seq.tolist() == list(range(40_000, 40_100)) + list(range(65_536, 65_636))
    assert asm.counters.restarts == 0


def test_saturated_flag_derived_from_counts(icd_truth):
    truth = icd_truth(3, 2)
    truth.counts[1, 1, 0] = -2147483648
    ids, payloads = truth.can_frames()
    counters = can_icd_counters()
    got = CanAssembler(2, counters=counters).push(ids, payloads, 0.0)
    got_all = CanSamples.concat([got], 2)
    block = got_all.to_block(rate_hz=RATE_HZ, lsb_nT=0.001, counters=counters)
    assert block.flags.tolist() == [0, 1, 0]
    assert np.isnan(block.field_nT[1, 1, 0]) and counters.saturated_axes == 1


# --- CanSource on python-can's virtual bus -------------------------------------------------------

def send(bus: can.BusABC, ids: np.ndarray, payloads: np.ndarray) -> None:
    for i, p in zip(ids.tolist(), payloads):
        bus.send(can.Message(arbitration_id=i, data=p.tobytes(), is_extended_id=False))




@pytest.fixture
def virtual_channel():
    return f"fluxcal-test-{uuid.uuid4().hex}"


@pytest.mark.parametrize("n", [1, 2, 4])
def test_virtual_bus_round_trip_across_the_seq_wrap(icd_truth, virtual_channel, n):
    truth = icd_truth(400, n, seed=n)
    ids, payloads = truth.can_frames(base_id=0x300)
    with can.Bus(interface="virtual", channel=virtual_channel) as tx, \
            CanSource(interface="virtual", channel=virtual_channel, n_probes=n, rate_hz=RATE_HZ,
                      base_id=0x300, lsb_nT=0.002, max_batch=256) as src:
        send(tx, ids, payloads)
        b = read_samples(src, len(truth))
        assert np.array_equal(b.seq, truth.seq)
        assert np.array_equal(b.t_s, truth.seq / RATE_HZ)          # CAN: t from seq and the rate
        assert np.array_equal(b.field_nT, truth.counts * 0.002)
        assert np.array_equal(b.temp_C, truth.temp_raw * 0.01)
        c = src.counters
        assert (c.frames_accepted, c.can_incomplete, c.seq_gaps) == (ids.size, 0, 0)


def test_virtual_bus_loss_foreign_and_malformed_frames(icd_truth, virtual_channel):
    n = 2
    truth = icd_truth(60, n)
    ids, payloads = truth.can_frames()
    drop = 20 * 6 + 4                                   # sample 20 loses one frame
    keep = np.ones(ids.size, bool)
    keep[drop] = False
    keep[30 * 6:33 * 6] = False                         # samples 30..32 never come at all
    with can.Bus(interface="virtual", channel=virtual_channel) as tx, \
            CanSource(interface="virtual", channel=virtual_channel, n_probes=n, rate_hz=RATE_HZ,
                      window_samples=4) as src:
        tx.send(can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False))      # someone else
        tx.send(can.Message(arbitration_id=0x200, data=bytes(8), is_extended_id=True))       # 29-bit id
        tx.send(can.Message(arbitration_id=0x201, data=bytes(4), is_extended_id=False))      # too short
        tx.send(can.Message(arbitration_id=0x202, is_remote_frame=True, dlc=8, is_extended_id=False))
        send(tx, ids[keep], payloads[keep])
        b = read_samples(src, 56)
        expect = np.ones(len(truth), bool)
        expect[[20, 30, 31, 32]] = False
        assert np.array_equal(b.seq, truth.seq[expect])
        assert np.array_equal(b.field_nT, truth.counts[expect] * 0.001)
        c = src.counters
        assert c.can_incomplete == 1 and "crc_failures" not in c.as_dict()   # CAN has no CRC failures: its controller's
        assert (c.wrong_length, c.remote_frames, c.foreign_frames) == (1, 1, 2)   # each kind said as itself
        assert (c.seq_gaps, c.samples_missed) == (2, 4)


def test_incomplete_sample_expires_on_a_silent_bus(icd_truth, virtual_channel):
    truth = icd_truth(2, 1)
    ids, payloads = truth.can_frames()
    with can.Bus(interface="virtual", channel=virtual_channel) as tx, \
            CanSource(interface="virtual", channel=virtual_channel, n_probes=1, rate_hz=RATE_HZ,
                      window_samples=100, window_s=0.05) as src:
        send(tx, ids[:5], payloads[:5])                 # sample 0 complete, sample 1 lacks z
        b = src.read(timeout=0.5)
        assert b.seq.tolist() == [truth.seq[0]]
        assert src.read(timeout=0.2) is None
        assert src.counters.can_incomplete == 1


def test_what_the_assembler_holds_at_the_end_is_released_or_counted(icd_truth, virtual_channel):
    """drain() at the end of reading: the complete samples waiting behind an incomplete one come out, the incomplete
    one is counted; before, the service's stop lost them uncounted (30 samples of a field trial)."""
    truth = icd_truth(6, 2)
    ids, payloads = truth.can_frames()
    keep = np.ones(ids.size, bool)
    keep[2 * 6 + 5] = False                             # sample 2 lacks one frame; 3, 4, 5 wait behind it
    with can.Bus(interface="virtual", channel=virtual_channel) as tx, \
            CanSource(interface="virtual", channel=virtual_channel, n_probes=2, rate_hz=RATE_HZ,
                      window_samples=100, window_s=60.0) as src:
        send(tx, ids[keep][:-6], payloads[keep][:-6])   # sample 5's frames still on the bus at the end
        b = src.read(timeout=0.5)
        assert b.seq.tolist() == truth.seq[:2].tolist()
        assert src.read(timeout=0.05) is None and src.counters.can_incomplete == 0     # held, not yet given up
        send(tx, ids[keep][-6:], payloads[keep][-6:])
        time.sleep(0.05)
        held = src.drain()
        assert held.seq.tolist() == truth.seq[3:].tolist()
        assert np.array_equal(held.field_nT, truth.counts[3:] * 0.001)
        assert src.counters.can_incomplete == 1 and src.drain() is None


def test_can_config_and_factories(virtual_channel):
    table = {"kind": "can", "interface": "virtual", "channel": virtual_channel, "n_probes": 2, "rate_hz": 250.0}
    cfg = load_section(CanConfig, table, "source")
    assert (cfg.bitrate, cfg.base_id, cfg.window_samples) == (1_000_000, 0x200, 32)
    with open_source_by_kind("can", cfg) as src:
        assert isinstance(src, CanSource) and src.rate_hz == 250.0
    with open_source(interface="virtual", channel=virtual_channel, n_probes=1, rate_hz=10.0) as src:
        assert src.n_probes == 1
    with pytest.raises(ConfigError, match="source.rate_hz: required key is missing"):
        load_section(CanConfig, {k: v for k, v in table.items() if k != "rate_hz"}, "source")
    with pytest.raises(ConfigError, match="source.base_id: 0x7f0 is not allowed for 8 probes"):
        load_section(CanConfig, {**table, "n_probes": 8, "base_id": 0x7F0}, "source")
    with pytest.raises(DriverError, match="cannot open"):
        CanSource(interface="no-such-interface", channel="x", n_probes=1, rate_hz=1.0)


# --- SLCAN over a pty: the cross-process path of a USB-CAN adapter ------------------------------

def slcan_bytes(ids: np.ndarray, payloads: np.ndarray) -> bytes:
    return b"".join(b"t%03X8%s\r" % (i, p.tobytes().hex().upper().encode()) for i, p in zip(ids.tolist(), payloads))


def test_slcan_over_a_pty(icd_truth, pty_port):
    n = 2
    truth = icd_truth(80, n, seed=9)
    ids, payloads = truth.can_frames()
    port = pty_port()
    src = CanSource(interface="slcan", channel=port.path, n_probes=n, rate_hz=RATE_HZ,
                    bus_kwargs={"sleep_after_open": 0})
    try:
        setup, deadline = b"", time.monotonic() + 5.0        # the adapter is told 1 Mbit/s, then opened
        while not setup.endswith(b"O\r") and time.monotonic() < deadline:    # in several writes: read them all
            if select.select([port.master], [], [], 0.1)[0]:
                setup += os.read(port.master, 100)
        assert b"S8\r" in setup and setup.endswith(b"O\r"), setup
        port.write(slcan_bytes(ids, payloads), chunk=512)
        b = read_samples(src, len(truth))
        assert np.array_equal(b.seq, truth.seq) and np.array_equal(b.field_nT, truth.counts * 0.001)
        assert np.array_equal(b.temp_C, truth.temp_raw * 0.01)
        port.close_master()                                 # the adapter is unplugged
        with pytest.raises(DriverError, match="receive failed"):
            for _ in range(20):
                src.read(timeout=0.1)
        with pytest.raises(DriverError, match="cannot open"):
            src.reopen()
    finally:
        src.close()


def test_rate_estimate_from_log_timestamps():
    from fluxcal.drivers.can_source import estimate_rate_hz

    rng = np.random.default_rng(0)
    seq = np.arange(1000, 3000)
    for rate, jitter_s in [(487.3, 1e-6), (500.0, 2e-4), (1000.0, 0.0)]:
        rx = 50.0 + seq / rate + rng.uniform(0, jitter_s, seq.size)
        s = CanSamples(seq=seq, counts=np.zeros((seq.size, 1, 3), np.int32),
                       temp_raw=np.zeros((seq.size, 1), np.int16), rx_time_s=rx)
        assert estimate_rate_hz(s) == rate
    one = CanSamples(seq=seq[:1], counts=np.zeros((1, 1, 3), np.int32), temp_raw=np.zeros((1, 1), np.int16),
                     rx_time_s=np.zeros(1))
    assert estimate_rate_hz(one) is None


class _NoFinish:
    """A CAN protocol's decoder written before finish() was part of the interface."""

    def __init__(self, n_probes, **kwargs) -> None:
        pass

    def decode(self, messages, now_s):
        return None


def test_a_can_protocol_without_finish_is_refused_as_the_source_opens(virtual_channel):
    """drain() at the stop asks the decoder finish(): a protocol without one raised AttributeError at every stop (a
    review), past the service's loop. It is refused as the source opens, with the method named."""
    from fluxcal.drivers.declare import Protocol
    from fluxcal.drivers.registry import forget_protocol, register_protocol

    register_protocol("can", Protocol("old-style", "a decoder without finish()", decoder=_NoFinish, kind="can"))
    try:
        with pytest.raises(ConfigError, match=r"'old-style': its decoder has no finish\(\)"):
            CanSource(interface="virtual", channel=virtual_channel, n_probes=1, rate_hz=RATE_HZ, protocol="old-style")
    finally:
        forget_protocol("can", "old-style")
