"""Block encodings (fluxcal.raw.v1, fluxcal.corrected.v1) and the JSON stream helpers: bit-for-bit round
trips (NaN payloads, signed zeros, extras), the documented layout rebuilt by hand as another language
would, and refusal of everything else with a DataError."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import DataError
from fluxcal.service.io.encoding import (
    CORRECTED_LAYOUT,
    RAW_LAYOUT,
    corrected_payload,
    decode_corrected,
    decode_json,
    decode_raw,
    encode_corrected,
    encode_json,
    encode_probes,
    encode_raw,
    health_record,
    json_ready,
    raw_payload,
)
from fluxcal.service.numerics.outputs import CorrectedBlock

# bit patterns that a float conversion would change: quiet and signalling NaNs with payloads,
# negative NaN, -0.0, infinities, the smallest subnormal
SPECIAL = np.array([0x7FF8000000000123, 0x7FF0000000000001, 0xFFF8DEADBEEF0000, 0x8000000000000000,
                    0x7FF0000000000000, 0xFFF0000000000000, 0x0000000000000001], dtype=np.uint64).view(np.float64)


def bits(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a).view(np.uint8).tobytes()


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal bit for bit, same dtype and shape (NaN payloads included)."""
    return a.dtype == b.dtype and a.shape == b.shape and bits(a) == bits(b)


def raw_block(n: int = 50, p: int = 4, seed: int = 0, extras: tuple[str, ...] = ("ref_total",)) -> SampleBlock:
    rng = np.random.default_rng(seed)
    field = rng.normal(0, 3e4, (n, p, 3))
    temp = rng.normal(25, 3, (n, p))
    if n:
        field.flat[: min(field.size, SPECIAL.size)] = SPECIAL[: min(field.size, SPECIAL.size)]
        temp.flat[: min(temp.size, 2)] = SPECIAL[1:3][: min(temp.size, 2)]
    t = 1234.5 + np.arange(n) * 1e-3
    return SampleBlock(t_s=t, seq=np.arange(n, dtype=np.int64) + 2**40, field_nT=field, temp_C=temp,
                       flags=rng.integers(0, 256, n).astype(np.uint8),
                       extras={name: rng.normal(5e4, 10, n) for name in extras})


def assert_same_raw(got: SampleBlock, want: SampleBlock) -> None:
    for name in ("t_s", "seq", "field_nT", "temp_C", "flags"):
        assert same(getattr(got, name), getattr(want, name)), name
    assert got.extras.keys() == want.extras.keys()
    for k in want.extras:
        assert same(got.extras[k], want.extras[k]), k


def test_raw_round_trip_is_bit_for_bit_with_nan_payloads_and_extras():
    b = raw_block()
    b.extras["ref_total"][:3] = SPECIAL[:3]
    got = decode_raw(encode_raw(b))
    assert_same_raw(got, b)
    assert np.isnan(got.field_nT.flat[0]) and bits(got.field_nT.flat[:1]) == bits(SPECIAL[:1])
    # decoded arrays are ordinary (aligned, writable) arrays the pipeline may work on in place
    assert got.field_nT.flags.writeable and got.field_nT.flags.aligned and got.t_s.flags.c_contiguous


@pytest.mark.parametrize("n,p", [(0, 1), (1, 1), (3, 8), (50, 4)])
def test_raw_round_trip_for_every_shape_and_no_extras(n, p):
    b = raw_block(n, p, extras=())
    assert_same_raw(decode_raw(encode_raw(b)), b)
    b2 = raw_block(n, p, extras=("ref_total", "table_deg", "ünïcode"))
    assert_same_raw(decode_raw(encode_raw(b2)), b2)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(n=st.integers(0, 30), p=st.integers(1, 8), seed=st.integers(0, 2**32 - 1), n_extras=st.integers(0, 3))
def test_raw_round_trip_of_arbitrary_bit_patterns(n, p, seed, n_extras):
    rng = np.random.default_rng(seed)

    def any_f64(*shape: int) -> np.ndarray:          # every 64-bit pattern is a float64, NaNs and all
        return rng.integers(0, 2**64, shape, dtype=np.uint64).view(np.float64)

    b = SampleBlock(t_s=any_f64(n), seq=rng.integers(-2**63, 2**63 - 1, n, dtype=np.int64),
                    field_nT=any_f64(n, p, 3), temp_C=any_f64(n, p), flags=rng.integers(0, 256, n).astype(np.uint8),
                    extras={f"x{k}": any_f64(n) for k in range(n_extras)})
    data = encode_raw(b)
    assert len(data) == 12 + n * (17 + 32 * p) + sum(2 + len(k) + 8 * n for k in b.extras)   # the documented size
    assert_same_raw(decode_raw(data), b)


def test_raw_layout_as_documented_built_by_hand():
    """What a writer in another language would do, value by value with struct, following the table."""
    b = raw_block(n=3, p=2)
    n, p = 3, 2
    hand = b"FXr" + b"0" + struct.pack("<HHI", p, 1, n)
    hand += struct.pack(f"<{n}d", *b.t_s) + struct.pack(f"<{n}q", *b.seq)
    hand += b"".join(struct.pack("<d", v) for v in b.field_nT.reshape(-1))       # (sample, probe, axis)
    hand += b"".join(struct.pack("<d", v) for v in b.temp_C.reshape(-1))
    hand += bytes(b.flags.tolist())
    hand += struct.pack("<H", 9) + b"ref_total" + struct.pack(f"<{n}d", *b.extras["ref_total"])
    assert encode_raw(b) == hand
    assert_same_raw(decode_raw(hand), b)
    assert "12 + 16N          f64[N, P, 3]" in RAW_LAYOUT and "size = 12 + N (17 + 32 P)" in RAW_LAYOUT


def corrected_block(n: int = 40, p: int = 3, *, diff: bool = True, tensor: bool = True, center: bool = True,
                    seed: int = 1) -> CorrectedBlock:
    rng = np.random.default_rng(seed)
    c = rng.normal(0, 5e4, (n, p, 3))
    c.flat[:3] = SPECIAL[:3]
    with np.errstate(invalid="ignore"):                  # the special values make NaNs on purpose
        d, m = c[:, 1:] - c[:, :1], c.mean(axis=1)
    return CorrectedBlock(t_s=np.arange(n) * 0.005, seq=np.arange(n, dtype=np.int64) + 7, corrected_nT=c,
                          diff_nT=d if diff else None, tensor_nT_m=rng.normal(0, 100, (n, 3, 3)) if tensor else None,
                          center_nT=m if center else None, cal_id=-(2**40) + 3)


def assert_same_corrected(got: CorrectedBlock, want: CorrectedBlock) -> None:
    for name in ("t_s", "seq", "corrected_nT", "diff_nT", "tensor_nT_m", "center_nT"):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None), name
        if b is not None:
            assert same(a, b), name
    assert got.cal_id == want.cal_id


@pytest.mark.parametrize("diff,tensor,center", [(d, t, c) for d in (0, 1) for t in (0, 1) for c in (0, 1)])
def test_corrected_round_trip_with_every_combination_of_optional_outputs(diff, tensor, center):
    b = corrected_block(diff=bool(diff), tensor=bool(tensor), center=bool(center))
    data = encode_corrected(b)
    n, p = 40, 3
    assert len(data) == 19 + n * (16 + 24 * p) + diff * 24 * n * (p - 1) + tensor * 72 * n + center * 24 * n
    assert data[4] == diff | tensor << 1 | center << 2                         # the presence bits
    assert_same_corrected(decode_corrected(data), b)


def test_corrected_single_probe_and_empty_block():
    one = CorrectedBlock(np.array([0.5]), np.array([9]), np.full((1, 1, 3), -0.0), None, None, None, 0)
    assert_same_corrected(decode_corrected(encode_corrected(one)), one)
    empty = corrected_block(n=0, p=2)
    assert_same_corrected(decode_corrected(encode_corrected(empty)), empty)


def test_corrected_header_as_documented():
    b = corrected_block(n=2, p=2, tensor=False)
    data = encode_corrected(b)
    assert data[:4] == b"FXc0"
    assert struct.unpack_from("<BHIq", data, 4) == (1 | 4, 2, 2, b.cal_id)
    assert struct.unpack_from("<2d", data, 19) == tuple(b.t_s)
    off = 19 + 16 * 2 + 24 * 2 * 2                                               # diff follows corrected
    assert bits(np.frombuffer(data, "<f8", 2 * 1 * 3, off)) == bits(b.diff_nT)
    assert "then, if bit 2:     f64[N, 3, 3]" in CORRECTED_LAYOUT


def test_unknown_revisions_and_foreign_payloads_are_refused():
    raw = encode_raw(raw_block(4, 2))
    with pytest.raises(DataError, match=r"layout revision b'1' is not supported"):
        decode_raw(b"FXr1" + raw[4:])
    with pytest.raises(DataError, match="not a raw block"):
        decode_raw(b"PNG\x00" + raw[4:])
    with pytest.raises(DataError, match="not a raw block"):
        decode_raw(encode_corrected(corrected_block(2, 2)))          # a corrected payload on the raw stream
    cor = encode_corrected(corrected_block(2, 2))
    with pytest.raises(DataError, match=r"layout revision b'7' is not supported"):
        decode_corrected(b"FXc7" + cor[4:])
    with pytest.raises(DataError, match="not a corrected block"):
        decode_corrected(raw)
    with pytest.raises(DataError, match="unknown presence bits"):
        decode_corrected(cor[:4] + bytes([cor[4] | 8]) + cor[5:])


def test_every_truncation_and_trailing_bytes_are_refused():
    raw = encode_raw(raw_block(5, 2, extras=("ref_total", "b")))
    cor = encode_corrected(corrected_block(5, 2))
    for data, decode in ((raw, decode_raw), (cor, decode_corrected)):
        for cut in range(len(data)):
            with pytest.raises(DataError):
                decode(data[:cut])
        with pytest.raises(DataError, match="trailing"):
            decode(data + b"\x00")


def test_duplicate_or_unreadable_extra_names_are_refused():
    b = raw_block(2, 1, extras=("aa", "bb"))
    data = encode_raw(b)
    with pytest.raises(DataError, match="appears twice"):
        decode_raw(data.replace(b"bb", b"aa"))
    with pytest.raises(DataError, match="bad name"):
        decode_raw(data.replace(b"bb", b"\xff\xfe"))


def test_json_messages_are_strict_json_with_nan_as_null():
    rec = {"kind": "calibration", "seq": np.int64(12), "t_s": float("nan"), "rms_nT": np.float32(0.5),
           "offset_nT": np.array([1.0, np.inf, -2.5]), "nested": {"ok": np.bool_(True), 3: (1, 2)}}
    data = encode_json(rec)
    text = data.decode()
    assert "NaN" not in text and "Infinity" not in text
    back = decode_json(data)
    assert back == {"kind": "calibration", "seq": 12, "t_s": None, "rms_nT": 0.5, "offset_nT": [1.0, None, -2.5],
                    "nested": {"ok": True, "3": [1, 2]}}
    assert json.loads(text) == back and json_ready(back) == back
    h = health_record({"frames_accepted": np.int64(10), "crc_failures": 2}, {"dropped": 0})
    assert decode_json(encode_json(h)) == {"counters": {"frames_accepted": 10, "crc_failures": 2},
                                          "recording": {"dropped": 0}}


@pytest.mark.parametrize("ensure_ascii", [False, True])
def test_plain_messages_dump_as_the_walk_over_every_value_does(ensure_ascii):
    """A plain dict of finite numbers, text and lists is dumped as it is, anything else walked (json_ready): the
    bytes are those of the walk either way."""
    plain = {"unit": "grad-é", "seq": 12, "t_s": 0.25, "rms_nT": {"s1.scalar": 0.5, "s2-s1.x": -0.0},
             "flags": [True, None, 3], "x": (1.5, 2)}
    tricky = [plain, {**plain, "t_s": float("nan")}, {**plain, "seq": np.int64(12)}, {"a": np.arange(3.0)},
              {"inf": [float("inf")], "f": np.float64(0.1)}, {"s": "line\u2028sep"}]
    for rec in tricky:
        walked = json.dumps(json_ready(rec), allow_nan=False, separators=(",", ":"),
                            ensure_ascii=ensure_ascii).encode()
        assert encode_json(rec, ensure_ascii=ensure_ascii) == walked


def test_one_probe_messages_are_each_probe_alone_and_outputs_share_one_encoding():
    """encode_probes: the P messages of the bus's corrected/<probe> streams, each what encode_corrected gives that
    probe alone; raw_payload and corrected_payload encode a block once for every output that sends it."""
    import gc

    rng = np.random.default_rng(3)
    for n, p in ((9, 4), (1, 1), (0, 2), (40, 8)):
        c = rng.normal(0, 3e4, (n, p, 3))
        c.flat[: min(c.size, SPECIAL.size)] = SPECIAL[: min(c.size, SPECIAL.size)]
        block = CorrectedBlock(t_s=1234.5 + np.arange(n) * 1e-3, seq=np.arange(n, dtype=np.int64) + 2**40,
                               corrected_nT=c, diff_nT=None, tensor_nT_m=None, center_nT=None, cal_id=7)
        alone = [encode_corrected(CorrectedBlock(t_s=block.t_s, seq=block.seq, corrected_nT=c[:, k:k + 1],
                                                 diff_nT=None, tensor_nT_m=None, center_nT=None, cal_id=7))
                 for k in range(p)]
        assert encode_probes(block) == alone
        first = corrected_payload(block)
        assert first == encode_corrected(block) and corrected_payload(block) is first     # one encoding, shared
    raw = raw_block()
    assert raw_payload(raw) is raw_payload(raw) and raw_payload(raw) == encode_raw(raw)
    del raw
    gc.collect()
    assert raw_payload._last is None                      # the block gone, its bytes are not kept


@pytest.mark.parametrize("bad", [b"{not json", b"[1, 2]", b"\xff\xfe", b"3"])
def test_malformed_json_messages_are_data_errors(bad):
    with pytest.raises(DataError, match="JSON message"):
        decode_json(bad)


def test_runs_of_messages_decode_as_each_message_does_bit_for_bit():
    # runs broken by a change of samples per message, of probes, of extras, and by extras of the same
    # length under other names (the bytes of the header and the sizes agree there: the names must not)
    from fluxcal.drivers.encoding import decode_raw_runs

    blocks = ([raw_block(20, 4, seed=k) for k in range(5)] + [raw_block(7, 4, seed=9)]
              + [raw_block(20, 4, seed=10 + k, extras=()) for k in range(3)]
              + [raw_block(20, 4, seed=20 + k, extras=("ref_total",)) for k in range(2)]
              + [raw_block(20, 4, seed=30 + k, extras=("abc_xyz_1",)) for k in range(2)]
              + [raw_block(20, 2, seed=40 + k) for k in range(3)] + [raw_block(0, 2, seed=50)])
    blocks[2].field_nT[:] = SPECIAL[0]                        # NaN payloads inside a run survive
    payloads = [encode_raw(b) for b in blocks]
    runs = decode_raw_runs(payloads)
    assert [len(sizes) for _, sizes in runs] == [5, 1, 3, 2, 2, 3, 1]
    got = [run.slice(a, a + n) for run, sizes in runs
           for a, n in zip(np.concatenate([[0], np.cumsum(sizes)[:-1]]), sizes)]
    assert len(got) == len(blocks)
    for g, want in zip(got, blocks):
        assert_same_raw(g, want)
    whole = runs[0][0]
    assert whole.field_nT.flags.writeable and whole.field_nT.flags.aligned and whole.field_nT.flags.c_contiguous
    # a damaged message fails as decode_raw fails on it
    with pytest.raises(DataError, match="trailing"):
        decode_raw_runs(payloads[:2] + [payloads[2] + b"\0"])
