"""RingBuffer: capacity never exceeded, order across the wrap, views without copying where the
samples are contiguous, counts of appended and overwritten samples."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.ringbuffer import RingBuffer


def block(seq: np.ndarray, n_probes: int = 2, ref: bool = False) -> SampleBlock:
    seq = np.asarray(seq, dtype=np.int64)
    k = seq.size
    field = seq[:, None, None] * 10.0 + np.arange(n_probes)[None, :, None] + np.arange(3)[None, None, :] * 0.1
    return SampleBlock(t_s=seq * 0.002, seq=seq, field_nT=field, temp_C=np.repeat(seq[:, None] * 0.5, n_probes, 1),
                       flags=(seq % 8).astype(np.uint8),
                       extras={"ref_total": seq * 1.5} if ref else {})


def assert_holds(rb: RingBuffer, seq: np.ndarray) -> None:
    v = rb.view()
    expect = block(seq, rb.n_probes)
    assert np.array_equal(v.seq, expect.seq) and np.array_equal(v.t_s, expect.t_s)
    assert np.array_equal(v.field_nT, expect.field_nT) and np.array_equal(v.temp_C, expect.temp_C)
    assert np.array_equal(v.flags, expect.flags)


def test_random_appends_keep_the_newest_samples_in_order():
    rng = np.random.default_rng(0)
    rb = RingBuffer(capacity=100, n_probes=2)
    start = 0
    for _ in range(300):
        k = int(rng.integers(0, 140))                  # sometimes longer than the whole buffer
        rb.append(block(np.arange(start, start + k)))
        start += k
        assert len(rb) == min(100, start) <= rb.capacity
        assert_holds(rb, np.arange(max(0, start - 100), start))
        assert rb.total_appended == start and rb.overwritten == max(0, start - 100)
    assert rb._t_s.shape == (100,) and rb._field_nT.shape == (100, 2, 3)   # never grew


def test_latest_n_across_the_wrap():
    rb = RingBuffer(capacity=10, n_probes=1)
    rb.append(block(np.arange(0, 8), 1))
    rb.append(block(np.arange(8, 14), 1))            # storage now wraps: 10..13 at the front
    assert rb.latest(3).seq.tolist() == [11, 12, 13]
    assert rb.latest(7).seq.tolist() == list(range(7, 14))
    assert rb.latest(50).seq.tolist() == list(range(4, 14))
    assert rb.latest(0).seq.tolist() == []


def test_views_when_contiguous_copy_only_when_wrapping():
    rb = RingBuffer(capacity=10, n_probes=2)
    rb.append(block(np.arange(6)))
    v = rb.view()
    for arr, store in [(v.seq, rb._seq), (v.field_nT, rb._field_nT), (v.temp_C, rb._temp_C), (v.t_s, rb._t_s)]:
        assert np.shares_memory(arr, store)
    rb.append(block(np.arange(6, 12)))               # head at 2: the newest 2 are contiguous, all 10 wrap
    assert np.shares_memory(rb.latest(2).field_nT, rb._field_nT)
    wrapped = rb.view()
    assert not np.shares_memory(wrapped.field_nT, rb._field_nT)
    assert wrapped.seq.tolist() == list(range(2, 12))


def test_extras_are_kept_and_missing_ones_are_nan():
    rb = RingBuffer(capacity=5, n_probes=2)
    rb.append(block(np.arange(3), ref=True))
    rb.append(block(np.arange(3, 5)))                # no ref_total in this block
    v = rb.view()
    assert v.extras["ref_total"][:3].tolist() == [0.0, 1.5, 3.0]
    assert np.all(np.isnan(v.extras["ref_total"][3:]))


def test_wrong_probe_count_is_refused():
    rb = RingBuffer(capacity=5, n_probes=2)
    with pytest.raises(ValueError, match="expected 2 probes, got 3"):
        rb.append(block(np.arange(3), n_probes=3))
    with pytest.raises(ValueError, match="capacity"):
        RingBuffer(capacity=0, n_probes=1)


def test_take_picks_positions_oldest_first_across_the_wrap():
    rb = RingBuffer(10, 2)
    for k in range(3):
        n = 7
        seq = np.arange(k * n, (k + 1) * n)
        rb.append(SampleBlock(t_s=seq / 10.0, seq=seq, field_nT=np.repeat(seq[:, None, None], 2, 1).repeat(3, 2) * 1.0,
                              temp_C=np.zeros((n, 2)), flags=np.zeros(n, np.uint8), extras={"ref_total": seq * 2.0}))
    whole = rb.view()                                   # seq 11..20, stored across the wrap
    idx = np.array([0, 3, 4, 9])
    got = rb.take(idx)
    np.testing.assert_array_equal(got.seq, whole.seq[idx])
    np.testing.assert_array_equal(got.seq, [11, 14, 15, 20])
    np.testing.assert_array_equal(got.field_nT, whole.field_nT[idx])
    np.testing.assert_array_equal(got.extras["ref_total"], [22.0, 28.0, 30.0, 40.0])
    assert rb.take(np.array([], int)).n_samples == 0
    with pytest.raises(IndexError):
        rb.take(np.array([10]))
