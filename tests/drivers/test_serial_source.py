"""SerialSource over a real pseudo-terminal (pyserial opens the slave like hardware; the test writes
ICD bytes on the master): every sample back exactly across the seq and clock wraps, damaged
streams counted, a pulled cable raising DriverError, and reconnecting through a symlink."""

from __future__ import annotations

import os
import socket
import threading
import time

import numpy as np
import pytest
from helpers import read_samples

from fluxcal.drivers import icd
from fluxcal.drivers.block import FLAG_TEMP_INVALID, SampleBlock
from fluxcal.drivers.config import load_section
from fluxcal.drivers.errors import ConfigError, DriverError
from fluxcal.drivers.serial_source import SerialConfig, SerialSource, open_source
from fluxcal.drivers.source import open_source as open_source_by_kind

LSB_NT = 0.001




def assert_block_is(block: SampleBlock, truth, lsb_nT: float = LSB_NT) -> None:
    assert len(block) == len(truth)
    assert np.array_equal(block.seq, truth.seq)
    # t_s is the unit clock unwrapped: back to the exact microsecond
    assert np.array_equal(np.round(block.t_s * 1e6).astype(np.int64), truth.t_us)
    assert np.all(np.diff(block.t_s) > 0)
    assert np.array_equal(np.round(block.field_nT / lsb_nT).astype(np.int64), truth.counts)
    assert np.array_equal(block.field_nT, truth.counts * lsb_nT)
    assert np.array_equal(block.temp_C, truth.temp_raw * 0.01)
    assert np.array_equal(block.flags, truth.flags)


@pytest.mark.parametrize("n", [1, 2, 4])
def test_pty_round_trip_across_wraps(pty_port, icd_truth, n):
    truth = icd_truth(2000, n, seed=n)
    assert truth.seq[-1] > 65535 and truth.t_us[-1] > 2**32     # both counters wrap on the wire
    port = pty_port()
    with SerialSource(port.path, n_probes=n, lsb_nT=LSB_NT) as src:
        port.write(truth.serial_bytes(), chunk=777)               # chunks that split frames
        block = read_samples(src, len(truth))
        assert_block_is(block, truth)
        c = src.counters
        assert (c.frames_accepted, c.crc_failures, c.bytes_skipped, c.seq_gaps) == (len(truth), 0, 0, 0)


def test_damaged_stream_gives_the_intact_samples_and_counts_the_rest(pty_port, icd_truth):
    n = 2
    truth = icd_truth(300, n, seed=11)
    fl = icd.frame_length(n)
    frames = [truth.take(slice(i, i + 1)).serial_bytes() for i in range(len(truth))]
    lost = {50, 51, 52}                 # never sent: one gap of 3
    corrupt = {100, 200}                # one payload bit flipped: CRC failures and gaps of 1
    noise = b"\x00\xa5\x13\xa5\x5a\x07" * 5
    stream = bytearray(frames[0][fl // 2:])          # the capture starts mid-frame
    for i in range(1, len(frames)):
        f = bytearray(frames[i])
        if i in lost:
            continue
        if i in corrupt:
            f[20] ^= 0x10
        if i == 150:
            stream += noise
        stream += f
    port = pty_port()
    with SerialSource(port.path, n_probes=n) as src:
        port.write(bytes(stream), chunk=100)
        keep = np.array([i not in lost | corrupt and i > 0 for i in range(len(truth))])
        block = read_samples(src, int(keep.sum()))
        assert_block_is(block, truth.take(keep))
        c = src.counters
        assert c.frames_accepted == keep.sum()
        assert c.crc_failures == 2
        assert (c.seq_gaps, c.samples_missed) == (3, 5)
        assert c.bytes_skipped == (fl - fl // 2) + len(noise) + 2 * fl


def test_saturated_axes_and_invalid_temperature_become_nan(pty_port, icd_truth):
    truth = icd_truth(20, 2, seed=5)
    truth.counts[3, 1, 2] = 2147483647
    truth.counts[7, 0, 0] = -2147483648
    truth.flags[9] = FLAG_TEMP_INVALID
    port = pty_port()
    with SerialSource(port.path, n_probes=2) as src:
        port.write(truth.serial_bytes())
        b = read_samples(src, 20)
    assert np.isnan(b.field_nT[3, 1, 2]) and np.isnan(b.field_nT[7, 0, 0])
    assert np.count_nonzero(np.isnan(b.field_nT)) == 2
    assert np.all(np.isnan(b.temp_C[9])) and np.count_nonzero(np.isnan(b.temp_C)) == 2
    assert src.counters.saturated_axes == 2 and src.counters.temp_invalid == 1
    assert b.flags[9] == FLAG_TEMP_INVALID


def test_read_returns_none_when_nothing_comes(pty_port):
    port = pty_port()
    with SerialSource(port.path, n_probes=1, read_timeout_s=0.01) as src:
        t0 = time.monotonic()
        assert src.read(timeout=0.1) is None
        assert 0.09 <= time.monotonic() - t0 < 0.5
        assert src.read(timeout=0) is None
        os.write(port.master, b"\xa5\x5a\x01")       # part of a frame is not a block
        assert src.read(timeout=0.05) is None


def test_pulled_cable_raises_driver_error_and_reopen_says_it_cannot(pty_port, icd_truth):
    truth = icd_truth(10, 1)
    port = pty_port()
    src = SerialSource(port.path, n_probes=1)
    port.write(truth.serial_bytes())
    assert len(read_samples(src, 10)) == 10
    port.close_master()
    with pytest.raises(DriverError, match="read failed"):
        src.read(timeout=0.5)
    with pytest.raises(DriverError, match="not open"):
        src.read(timeout=0.1)
    with pytest.raises(DriverError, match="cannot open"):
        src.reopen()
    src.close()
    src.close()                                  # twice is fine
    with pytest.raises(DriverError, match="after close"):
        src.read()


def test_reopen_follows_the_port_when_it_comes_back(pty_port, icd_truth, tmp_path):
    """Like a USB adapter re-plugged behind a udev symlink: the same path, a new device."""
    n = 2
    truth = icd_truth(100, n, seed=3)
    fl = icd.frame_length(n)
    first, second = pty_port(), pty_port()
    link = tmp_path / "ttyFLUX"
    link.symlink_to(first.path)
    src = SerialSource(str(link), n_probes=n)
    data = truth.serial_bytes()
    first.write(data[:40 * fl + 7])              # 40 frames and the start of one more
    assert_block_is(read_samples(src, 40), truth.take(slice(0, 40)))
    first.close_master()
    with pytest.raises(DriverError):
        src.read(timeout=0.5)
    link.unlink()
    link.symlink_to(second.path)
    src.reopen()
    second.write(data[60 * fl:])                 # samples 40..59 were lost while unplugged
    assert_block_is(read_samples(src, 40), truth.take(slice(60, 100)))
    c = src.counters
    assert (c.seq_gaps, c.samples_missed) == (1, 20)
    assert c.bytes_skipped == 7                   # the partial frame from before the cable was pulled
    src.close()


def test_any_pyserial_url_works():
    truth_counts = np.arange(12, dtype=np.int32).reshape(2, 2, 3)
    data = icd.encode_serial(np.array([5, 6]), np.array([10, 20]), truth_counts, np.zeros((2, 2), np.int16),
                             np.zeros(2, np.uint8))
    with SerialSource("loop://", n_probes=2) as src:
        src._ser.write(data)                      # loop:// echoes what is written to it
        b = src.read(timeout=1.0)
    assert b.seq.tolist() == [5, 6] and np.array_equal(b.field_nT, truth_counts * LSB_NT)


def test_missing_port_is_a_driver_error():
    with pytest.raises(DriverError, match="cannot open"):
        SerialSource("/dev/does-not-exist-fluxcal", n_probes=2)


def test_config_and_factories(pty_port):
    port = pty_port()
    cfg = load_section(SerialConfig, {"kind": "serial", "port": port.path, "n_probes": 3, "lsb_nT": 0.002},
                       "source")
    assert (cfg.baudrate, cfg.read_timeout_s) == (921600, 0.02)
    with open_source_by_kind("serial", cfg) as src:
        assert isinstance(src, SerialSource) and src.n_probes == 3 and src.lsb_nT == 0.002
    with open_source(port=port.path, n_probes=1, baudrate=115200, lsb_nT=0.01) as src:
        assert (src.n_probes, src.baudrate, src.lsb_nT) == (1, 115200, 0.01)
    with pytest.raises(ConfigError, match="source.baud: unknown key"):
        load_section(SerialConfig, {"port": "x", "n_probes": 1, "baud": 9600}, "source")
    with pytest.raises(ConfigError, match="source.n_probes: 9 is above the maximum 8"):
        load_section(SerialConfig, {"port": "x", "n_probes": 9}, "source")
    with pytest.raises(ConfigError, match="n_probes: 0 is not allowed"):
        SerialSource(port.path, n_probes=0)


def test_socket_url_reads_in_bulk(icd_truth):
    """socket:// (a serial device server) reports in_waiting only as 0/1: the source must still
    take what has arrived at once, not two bytes per read."""
    truth = icd_truth(2000, 4, seed=8)
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve() -> None:
        conn, _ = server.accept()
        with conn:
            conn.recv(1)                          # the client is ready: pyserial drops bytes sent during open
            conn.sendall(truth.serial_bytes())
            time.sleep(0.5)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        with SerialSource(f"socket://127.0.0.1:{port}", n_probes=4) as src:
            src._ser.write(b"!")
            blocks, got = [], 0
            deadline = time.monotonic() + 5
            while got < len(truth) and time.monotonic() < deadline:
                b = src.read(timeout=0.2)
                if b is not None:
                    blocks.append(b)
                    got += len(b)
            assert_block_is(SampleBlock.concat(blocks), truth)
            assert len(blocks) < 200
    finally:
        t.join(2)
        server.close()
