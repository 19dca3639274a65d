"""Time base honesty (issue 38, build 7): a clock that jumps while the counter runs on is a clock jump (samples kept,
time repaired from the counter), a counter that jumps while the clock runs on is a counter jump (no sample counted
missed), frames sent again are duplicates by counter and content, and each event is counted once; CAN frames of the
old run that come after a restart stay in the old run.

Before (the red team's trials): +1,000 s on the unit's clock with its counter at +1 was 196,608 samples missed; 100
replayed frames were recorded again as new samples (duplicates 0) after 7 "stale" and a restart; a counter jump near
zero was a restart with thousands of samples missed; on CAN, frames of the last sample before a restart arriving
after it made 3 restarts of 1, 46,002 samples missed and 6 incomplete.
"""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers import icd
from fluxcal.drivers.assemble import (
    CanAssembler,
    CanSamples,
    FrameAssembler,
    SeqGapCounter,
    SerialFramer,
    can_icd_counters,
    serial_icd_counters,
)
from fluxcal.drivers.registry import source_kind
from fluxcal.drivers.source import Counters
from fluxcal.service.wiring.faults import FaultWatch

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.drivers.can_unwrap",)

PERIOD_US = 5000           # 200 Hz
N = 2


def serial_wire(seq: np.ndarray, t_us: np.ndarray, seed: int = 0) -> tuple[bytes, np.ndarray]:
    rng = np.random.default_rng(seed)
    counts = rng.integers(-50_000_000, 50_000_000, (seq.size, N, 3)).astype(np.int32)
    wire = icd.encode_serial(seq & 0xFFFF, t_us & 0xFFFFFFFF, counts, np.full((seq.size, N), 2300, np.int16),
                             np.zeros(seq.size, np.uint8))
    return wire, counts


def through(wire: bytes, chunk_frames: int = 333, paced: bool = False):
    """The wire through the serial framer and assembler in chunks; (seq, t_s, field counts, counters). paced: each
    chunk read by the host when its last frame was sent, at the unit's rate (else all at once)."""
    c = serial_icd_counters()
    framer, asm = SerialFramer(N, c), FrameAssembler(N, 0.001, c)
    fl = icd.frame_length(N)
    step = chunk_frames * fl
    blocks = [asm.block(framer.feed(wire[i:i + step]),
                        rx_time_s=(i + step) // fl * PERIOD_US * 1e-6 if paced else i * 1e-7)
              for i in range(0, len(wire), step)]
    blocks = [b for b in blocks if b.n_samples]
    return (np.concatenate([b.seq for b in blocks]), np.concatenate([b.t_s for b in blocks]),
            np.concatenate([b.field_nT for b in blocks]), c)


def nonzero(c: Counters) -> dict[str, int]:
    return {k: v for k, v in c.as_dict().items() if v and k not in ("frames_accepted", "bytes_received")}


@pytest.mark.parametrize("seq0, t0_us", [(20_000, 200_000_000), (1_000, 10_000_000), (0, 4_290_000_000)])
def test_a_clock_jump_with_the_counter_running_on_is_a_clock_jump_not_missed_samples(seq0, t0_us):
    """+1,000 s on the clock at frame 1,500, the counter at +1 (near zero too, and across the clock's wrap)."""
    i = np.arange(3000)
    t = t0_us + i * PERIOD_US
    t[1500:] += 1_000_000_000
    wire, counts = serial_wire(seq0 + i, t)
    seq, t_s, field, c = through(wire)
    assert nonzero(c) == {"clock_jumps": 1}
    np.testing.assert_array_equal(seq, seq0 + i)                                  # every sample kept, none missed
    np.testing.assert_array_equal(field, counts * 0.001)
    np.testing.assert_allclose(np.diff(t_s), PERIOD_US * 1e-6, rtol=0, atol=1e-9)  # time repaired from the counter


def test_a_clock_that_jumps_back_or_glitches_for_a_few_frames_is_one_clock_jump():
    i = np.arange(2000)
    for glitch in (slice(900, None), slice(900, 903), slice(900, 901)):
        for size in (-100_000_000, 5_000_000_000, -3 * PERIOD_US):
            t = 300_000_000 + i * PERIOD_US
            t[glitch] += size
            seq, t_s, _, c = through(serial_wire(40_000 + i, t)[0])
            assert nonzero(c) == {"clock_jumps": 1}, (glitch, size, nonzero(c))
            assert seq.size == i.size and np.all(np.diff(t_s) > 0)


@pytest.mark.parametrize("jump", [1000, -1000, 20_000])
def test_a_counter_jump_with_the_clock_running_on_counts_no_missed_sample(jump):
    i = np.arange(3000)
    for seq0 in (30_000, 1_000):                   # far from zero, and near it (where it was read as a restart)
        s = seq0 + i
        s[1500:] += jump
        seq, t_s, _, c = through(serial_wire(s, 100_000_000 + i * PERIOD_US)[0])
        assert nonzero(c) == {"counter_jumps": 1}, (seq0, nonzero(c))
        assert np.all(np.diff(seq) == 1) and seq.size == i.size
    s = 30_000 + i
    s[1500] += jump                                # one glitched frame: one jump, not two
    _, _, _, c = through(serial_wire(s, 100_000_000 + i * PERIOD_US)[0])
    assert nonzero(c) == {"counter_jumps": 1}


def test_replayed_frames_are_duplicates_by_counter_and_content():
    i = np.arange(3000)
    fl = icd.frame_length(N)
    wire, counts = serial_wire(50_000 + i, 100_000_000 + i * PERIOD_US)
    replayed = wire[:1500 * fl] + wire[1400 * fl:1500 * fl] + wire[1500 * fl:]       # 100 frames sent again
    seq, _, field, c = through(replayed)
    assert nonzero(c) == {"duplicates": 100}
    np.testing.assert_array_equal(field, counts * 0.001)
    # a frame stepping back that equals none received (another content) is stale, not a duplicate
    other, _ = serial_wire(50_000 + i[1400:1403], 100_000_000 + i[1400:1403] * PERIOD_US, seed=9)
    _, _, _, c = through(wire[:1500 * fl] + other + wire[1500 * fl:])
    assert nonzero(c) == {"seq_backsteps": 3}


@pytest.mark.parametrize("chunk", [2, 333])
def test_in_a_units_first_minute_a_clock_freeze_or_a_jump_back_is_no_restart_and_misses_nothing(chunk):
    """In a unit's first minute its counter and clock are 'near zero', where a frame whose clock did not follow its
    counter read as a restart: a clock frozen 2 s was a restart with 2,400 samples missed, and counter and clock
    both back 1,000 frames one with 999 missed, every frame having come, without a pause (a field trial). A unit
    restarted cannot have counted more frames than the host's time since it was last heard holds."""
    i = np.arange(3000)
    t = 500_000 + i * PERIOD_US
    t[1500:1900] = t[1499]                                   # the clock frozen for 400 frames (2 s), then on
    seq, t_s, _, c = through(serial_wire(100 + i, t)[0], chunk, paced=True)
    assert nonzero(c) == {"clock_jumps": 2}, nonzero(c)          # frozen, then on again: not 401
    assert np.all(np.diff(seq) == 1) and seq.size == i.size and np.all(np.diff(t_s) > 0)
    s, t = 100 + i, 500_000 + i * PERIOD_US
    s[1500:] -= 1000
    t[1500:] -= 1000 * PERIOD_US                             # both back 1,000 frames together, and on from there
    seq, t_s, _, c = through(serial_wire(s, t)[0], chunk, paced=True)
    assert np.all(np.diff(seq) == 1) and seq.size == i.size and np.all(np.diff(t_s) > 0), nonzero(c)
    assert "samples_missed" not in nonzero(c)


def test_a_counter_that_runs_on_further_than_the_host_time_allows_misses_nothing():
    """Counter +1,000 and clock +3 s at once, read at the unit's pace: a clock jump with the counter run on by 1,000
    counted 1,000 samples missed, where the host had read the frames without a pause (review); the host's time now
    says they never existed."""
    i = np.arange(3000)
    s, t = 100 + i, 500_000 + i * PERIOD_US
    s[1500:] += 1000
    t[1500:] += 3_000_000
    seq, t_s, _, c = through(serial_wire(s, t)[0], 2, paced=True)
    assert "samples_missed" not in nonzero(c) and np.all(np.diff(seq) == 1) and seq.size == i.size, nonzero(c)
    assert np.all(np.diff(t_s) > 0)


def test_another_units_frames_read_as_a_restart_cost_no_sample_and_no_time():
    """Twenty valid frames of another unit just started (counter and clock near zero) among a unit's, read at its
    pace: a restart, then the unit's own frames 'forward' by 5,579, counted missed, and every later sample 27.9 s late
    (a field trial). Forward by more than the host's time holds, they are the line the unit left: taken back to."""
    i = np.arange(8000)
    s, t = 4000 + i, 20_000_000 + i * PERIOD_US
    wire, _ = serial_wire(s, t)
    fl = icd.frame_length(N)
    other, _ = serial_wire(np.arange(20), np.arange(20) * PERIOD_US, seed=7)
    seq, t_s, _, c = through(wire[:5000 * fl] + other + wire[5000 * fl:], 2, paced=True)
    assert "samples_missed" not in nonzero(c) and np.all(np.diff(seq) == 1), nonzero(c)
    assert seq.size == i.size + 20 and np.all(np.diff(t_s) > 0)
    assert t_s[-1] - t_s[0] < (i.size + 20) * PERIOD_US * 1e-6 + 1.0             # not 27.9 s late


def test_a_restart_whose_first_frames_were_lost_counts_them_missed_when_read_unpaced():
    """The host's clock says nothing of a unit read faster than it ran (a pty fed unpaced, a capture): a restart whose
    first 300 frames were lost counts them missed there, as before the host-time test (review)."""
    i = np.arange(3000)
    s, t = 100 + i, 500_000 + i * PERIOD_US
    s[1500:], t[1500:] = i[:1500] + 300, (i[:1500] + 300) * PERIOD_US
    seq, _, _, c = through(serial_wire(s, t)[0])
    assert c.restarts == 1 and seq[-1] - seq[0] + 1 - seq.size == 300, nonzero(c)


def test_a_restart_is_one_restart():
    i = np.arange(3000)
    s, t = 12_600 + i, 700_000_000 + i * PERIOD_US
    s[1500:], t[1500:] = i[:1500], i[:1500] * PERIOD_US
    seq, t_s, _, c = through(serial_wire(s, t)[0])
    assert nonzero(c) == {"restarts": 1} and seq.size == i.size and np.all(np.diff(t_s) > 0)


def can_frames(seq: np.ndarray, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    counts = rng.integers(-50_000_000, 50_000_000, (seq.size, N, 3)).astype(np.int32)
    ids, payloads = icd.encode_can(seq & 0xFFFF, counts, np.full((seq.size, N), 2300, np.int16))
    return ids, payloads, counts


@pytest.mark.parametrize("batch", [60, 600, 6000])
@pytest.mark.parametrize("swap", [1, 3, 5])
def test_can_frames_of_the_old_run_after_a_restart_stay_in_it(batch, swap):
    """The unit restarts at sample 3,000 (counter 23,000 -> 0); frames of neighbouring samples trade places on the
    bus, so frames of the last old samples come after the new run's first: one restart, every sample whole."""
    i = np.arange(6000)
    s = 20_000 + i
    s[3000:] = i[:3000]
    ids, payloads, counts = can_frames(s)
    order = np.arange(ids.size)
    for a in range(0, ids.size - swap, 7):
        order[[a, a + swap]] = order[[a + swap, a]]
    ids, payloads = ids[order], payloads[order]
    c = can_icd_counters()
    asm, gaps = CanAssembler(N, counters=c, rate_hz=200.0), SeqGapCounter()
    parts = []
    for j, a in enumerate(range(0, ids.size, batch)):
        now = j * batch / (6 * 200.0)
        parts.append(asm.push(ids[a:a + batch], payloads[a:a + batch], now, now_s=now))
        gaps.update(parts[-1].seq, c)
    parts.append(asm.flush())
    got = CanSamples.concat(parts, N)
    assert nonzero(c) == {"restarts": 1}
    np.testing.assert_array_equal(got.counts, counts)
    assert np.all(np.diff(got.seq) == 1)


def test_clock_and_counter_jumps_are_said_as_what_they_are():
    said: list[str] = []
    clock = [0.0]
    watch = FaultWatch(said.append, words=source_kind("serial").words(), clock=lambda: clock[0], wall=lambda: 0.0)
    base = {"frames_accepted": 0, "samples_missed": 0, "restarts": 0, "clock_jumps": 0, "counter_jumps": 0}
    watch.tick(base)
    clock[0] = 1.0
    watch.tick({**base, "frames_accepted": 200, "clock_jumps": 1, "counter_jumps": 1})
    text = "\n".join(said)
    assert "unit clock jump: 1 jump(s) of the unit's clock while its counter ran on" in text
    assert "unit counter jump: 1 jump(s) of the unit's counter while its clock ran on" in text
    assert "missed" not in text.replace("counted missed", "") and "restart" not in text


def test_what_a_can_slot_holds_tells_a_repeat_from_another_value():
    """can_settled: the newest `keep` settled samples kept; a frame on a filled slot with another value or
    temperature differs, the same frame or an empty slot does not; in a batch, against the slot's first frame."""
    from fluxcal.drivers.can_settled import SettledFrames, earlier_in_batch_differs, slot_differs

    s = SettledFrames(1, keep=3)
    value = np.arange(5 * 3, dtype=np.int32).reshape(5, 1, 3)
    have = np.ones((5, 1, 3), bool)
    have[4, 0, 2] = False                                          # sample 14's z never came
    s.add(np.arange(10, 15), value, np.full((5, 1, 3), 7, np.int16), have)
    s.add(np.arange(15, 16), value[:1] + 100, np.full((1, 1, 3), 7, np.int16), np.ones((1, 1, 3), bool))
    held = s.held()
    assert held[0].tolist() == [12, 13, 14, 15]                   # 10, 11 more than `keep` behind the newest (15)
    u = np.array([10, 12, 12, 12, 14, 20])
    probe, axis = np.zeros(6, int), np.array([0, 0, 1, 2, 2, 0])
    val = np.array([0, 6, 99, 8, 99, 1], np.int32)                 # 12: x the same, y another value, z the same
    temp = np.array([7, 7, 7, 9, 7, 7], np.int16)                  # ... but z another temperature
    got = slot_differs(u, probe, axis, val, temp, *held)
    assert got.tolist() == [False, False, True, True, False, False]   # 10 not held, 14's z empty, 20 not yet
    u2 = np.array([5, 5, 5, 6])
    d = earlier_in_batch_differs(u2, np.zeros(4, int), np.zeros(4, int), np.array([1, 1, 2, 3]), np.zeros(4, int),
                                 np.arange(4), 1)
    assert d.tolist() == [False, False, True, False]
