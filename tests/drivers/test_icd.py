"""The ICD codec against the ICD's own test vectors, the CRC check value, encode/parse round trips,
and the vectorised parser against a straightforward frame-by-frame reference parser."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from fluxcal.drivers import icd

VECTOR = bytes.fromhex("a55a01010100e8030000010000" "00ffffffff80f0fa02c40900c334")


def reference_parse(buf: bytes, n: int) -> list[tuple]:
    """One frame at a time with struct and the byte-wise CRC: resync on the sync word, accept a
    frame only when version, n and CRC match, then continue after it."""
    fl = icd.frame_length(n)
    body = struct.Struct(f"<BBHI{3 * n}i{n}hB")
    out, i = [], 0
    while True:
        i = buf.find(icd.SYNC, i)
        if i < 0 or i + fl > len(buf):
            return out
        frame = buf[i:i + fl]
        (crc,) = struct.unpack_from("<H", frame, fl - 2)
        if frame[2] == icd.VERSION and frame[3] == n and icd.crc16_ccitt_false(frame[2:fl - 2]) == crc:
            out.append(body.unpack_from(frame, 2)[2:])
            i += fl
        else:
            i += 1


def parsed_tuples(p: icd.SerialParse) -> list[tuple]:
    f = p.frames
    return [(int(f.seq[k]), int(f.t_us[k]), *map(int, f.counts[k].ravel()), *map(int, f.temp_raw[k]), int(f.flags[k]))
            for k in range(len(f))]


def test_crc_check_value():
    assert icd.crc16_ccitt_false(b"123456789") == 0x29B1
    cols = np.frombuffer(b"123456789", np.uint8)[:, None]
    assert icd.crc16_rows(cols).tolist() == [0x29B1]


def test_test_vector_encodes_exactly():
    got = icd.encode_serial(np.array([1]), np.array([1000]), np.array([[[1, -1, 50_000_000]]], np.int32),
                            np.array([[2500]], np.int16), np.array([0], np.uint8))
    assert got == VECTOR
    assert len(VECTOR) == icd.frame_length(1) == 27
    assert icd.crc16_ccitt_false(VECTOR[2:25]) == 0x34C3


def test_test_vector_parses_exactly():
    p = icd.parse_serial(VECTOR, 1, final=True)
    assert (p.consumed, p.crc_failures, p.bytes_skipped) == (27, 0, 0)
    f = p.frames
    assert f.seq.tolist() == [1] and f.t_us.tolist() == [1000] and f.flags.tolist() == [0]
    assert f.counts.tolist() == [[[1, -1, 50_000_000]]]
    assert f.temp_raw.tolist() == [[2500]]


@pytest.mark.parametrize("length", [0, 1, 2, 3, 8, 23, 41, 65, 121])
def test_crc_rows_equals_bytewise_crc(length):
    rng = np.random.default_rng(length)
    msgs = rng.integers(0, 256, (50, length), dtype=np.uint8)
    got = icd.crc16_rows(np.ascontiguousarray(msgs.T))
    assert got.dtype == np.uint16
    assert got.tolist() == [icd.crc16_ccitt_false(m.tobytes()) for m in msgs]


@pytest.mark.parametrize("n", range(1, 9))
def test_serial_round_trip_every_probe_count(n):
    rng = np.random.default_rng(n)
    k = 300
    seq = rng.integers(0, 65536, k)
    t_us = rng.integers(0, 2**32, k)
    counts = rng.integers(-2**31, 2**31, (k, n, 3), dtype=np.int64).astype(np.int32)
    temp = rng.integers(-32768, 32768, (k, n)).astype(np.int16)
    flags = rng.integers(0, 8, k).astype(np.uint8)
    buf = icd.encode_serial(seq, t_us, counts, temp, flags)
    assert len(buf) == k * icd.frame_length(n)
    p = icd.parse_serial(buf, n, final=True)
    assert (len(p.frames), p.consumed, p.crc_failures, p.bytes_skipped) == (k, len(buf), 0, 0)
    assert np.array_equal(p.frames.seq, seq) and np.array_equal(p.frames.t_us, t_us)
    assert np.array_equal(p.frames.counts, counts) and np.array_equal(p.frames.temp_raw, temp)
    assert np.array_equal(p.frames.flags, flags)


def test_zero_frames_encode_to_nothing():
    assert icd.encode_serial(np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 2, 3), np.int32),
                             np.empty((0, 2), np.int16), np.empty(0, np.uint8)) == b""


@pytest.mark.parametrize("seed", range(6))
def test_parser_matches_reference_on_damaged_streams(seed):
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(1, 9))
    k = 200
    buf = bytearray(icd.encode_serial(rng.integers(0, 65536, k), rng.integers(0, 2**32, k),
                                      rng.integers(-2**31, 2**31, (k, n, 3), dtype=np.int64).astype(np.int32),
                                      rng.integers(-3000, 3000, (k, n)).astype(np.int16),
                                      rng.integers(0, 8, k).astype(np.uint8)))
    for _ in range(40):
        i = int(rng.integers(0, len(buf)))
        op = rng.integers(0, 4)
        if op == 0:
            buf[i] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:
            del buf[i:i + int(rng.integers(1, 30))]
        elif op == 2:
            buf[i:i] = rng.integers(0, 256, int(rng.integers(1, 60)), dtype=np.uint8).tobytes()
        else:
            buf[i:i] = icd.SYNC + bytes([icd.VERSION, n])      # a false start right before a frame
    data = bytes(buf[int(rng.integers(1, 40)):])                 # and start mid-frame
    p = icd.parse_serial(data, n, final=True)
    ref = reference_parse(data, n)
    assert parsed_tuples(p) == ref
    assert len(ref) > 100
    assert p.bytes_skipped == len(data) - len(ref) * icd.frame_length(n)


@pytest.mark.parametrize("k", [1, 9, 512, 513, 2000])
def test_frame_crc_both_ways_equals_bytewise_crc(k):
    """The parser's CRC of candidate frames: a table look-up per byte for a live port's few frames, a loop over
    words for many (icd._CRC_BY_BYTE_ROWS); both equal the byte-wise CRC of every frame, for every probe count."""
    rng = np.random.default_rng(k)
    for n in (1, 4, 8):
        fl = icd.frame_length(n)
        rows = rng.integers(0, 256, (k, fl), dtype=np.uint8)
        rows[:, 2], rows[:, 3] = icd.VERSION, n
        want = [icd.crc16_ccitt_false(r[2:fl - 2].tobytes()) for r in rows]
        assert icd._crc_frames(rows, n).tolist() == want
        assert icd._crc_by_word(rows, n).tolist() == want


@pytest.mark.parametrize("seed", range(4))
def test_back_to_back_frames_parse_as_the_reference(seed):
    """The live port's usual buffer, intact frames from its first byte and the start of the next (parsed by
    _back_to_back), with sync marks inside payloads; and the same with one byte flipped (the search): both as the
    frame-by-frame reference parser, the partial frame kept for later."""
    rng = np.random.default_rng(200 + seed)
    n = int(rng.integers(1, 9))
    fl = icd.frame_length(n)
    for k in (1, 2, 9, 40, 700):
        counts = rng.integers(-2**31, 2**31, (k, n, 3), dtype=np.int64).astype(np.int32)
        counts.view(np.uint8)[::3, 0, :4] = [0xA5, 0x5A, icd.VERSION, n]         # a false start in every third
        buf = icd.encode_serial(rng.integers(0, 65536, k), rng.integers(0, 2**32, k), counts,
                                rng.integers(-3000, 3000, (k, n)).astype(np.int16), np.zeros(k, np.uint8))
        tail = buf[:int(rng.integers(1, fl))]
        for data in (buf + tail, buf[:-3] + b"\x00\x01\x02", bytes([buf[0] ^ 0x10]) + buf[1:] + tail):
            p = icd.parse_serial(data, n)
            kept = data[p.consumed:]
            assert parsed_tuples(p) == reference_parse(data[:p.consumed], n)
            assert len(kept) < fl and (not kept or kept.startswith(b"\xa5"))
            assert p.bytes_skipped == p.consumed - len(p.frames) * fl
        whole = np.frombuffer(buf + tail, np.uint8)
        assert icd._back_to_back(whole, whole.size, fl, n) is not None          # the intact buffer: the fast way
        assert len(icd.parse_serial(buf + tail, n).frames) == k and icd.parse_serial(buf + tail, n).consumed == len(buf)


def test_parser_keeps_an_incomplete_frame_for_later():
    buf = icd.encode_serial(np.arange(3), np.arange(3), np.ones((3, 2, 3), np.int32), np.ones((3, 2), np.int16),
                            np.zeros(3, np.uint8))
    fl = icd.frame_length(2)
    p = icd.parse_serial(b"\x00\x11" + buf[:2 * fl + 10], 2)
    assert len(p.frames) == 2 and p.consumed == 2 + 2 * fl and p.bytes_skipped == 2
    p = icd.parse_serial(buf[:fl] + b"\xa5", 2)          # a lone first sync byte may start a frame
    assert len(p.frames) == 1 and p.consumed == fl
    p = icd.parse_serial(buf[:fl] + b"\xa5\x5a\x01\x03", 2)   # header says 3 probes: not ours
    assert p.consumed == fl + 4 and p.bytes_skipped == 4


def test_can_round_trip_and_ids():
    rng = np.random.default_rng(7)
    k, n = 50, 3
    seq = rng.integers(0, 65536, k)
    counts = rng.integers(-2**31, 2**31, (k, n, 3), dtype=np.int64).astype(np.int32)
    temp = rng.integers(-3000, 3000, (k, n)).astype(np.int16)
    ids, payloads = icd.encode_can(seq, counts, temp, base_id=0x300)
    assert ids[:9].tolist() == [0x300, 0x301, 0x302, 0x304, 0x305, 0x306, 0x308, 0x309, 0x30A]
    assert payloads.shape == (k * 3 * n, 8)
    probe, axis, value, s, t = icd.decode_can(ids, payloads, n, base_id=0x300)
    assert np.array_equal(probe, np.tile(np.repeat(np.arange(n), 3), k))
    assert np.array_equal(axis, np.tile([0, 1, 2], k * n))
    assert np.array_equal(value.reshape(k, n, 3), counts)
    assert np.array_equal(s.reshape(k, 3 * n), np.repeat(seq[:, None], 3 * n, axis=1))
    assert np.array_equal(t.reshape(k, n, 3)[:, :, 0], temp)
    # ICD payload layout, byte for byte: value int32, seq uint16, temperature int16
    assert payloads[0].tobytes() == struct.pack("<iHh", counts[0, 0, 0], seq[0], temp[0, 0])


def test_can_foreign_and_reserved_ids_are_marked():
    ids = np.array([0x1FF, 0x200, 0x203, 0x207, 0x208, 0x20B])
    probe, axis, *_ = icd.decode_can(ids, np.zeros((6, 8), np.uint8), n_probes=2)
    assert probe.tolist() == [-1, 0, -1, -1, -1, -1]
    assert axis[1] == 0
