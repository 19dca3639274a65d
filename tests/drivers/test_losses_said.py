"""Every loss and fault said where people look (issue 27, builds 3 and 4; issue 28's status lines).

    the driver's order of frames    restarts (also after more than 32,768 frames), duplicates, stale frames:
                                    counted exactly against the simulator's record; seq and time never go back
    plausibility                    reserved flag bits, beyond full scale, zero vectors, temperatures out of range:
                                    counted against the digitised truth, flagged, kept out of the estimator
    fit of a recording              time going back is refused, as in a CSV
    FaultWatch                      begin, running count, end and summary of each fault, from counters and a clock
    the dashboard's view            the fault events with their counts, kept across health messages
    status lines                    the error over the interval, with the interval; refusals after usable said so
    a pty unit through `fluxcal run` (slow): each fault scenario gives a console line, a health field and a
                                    dashboard event with the right count, and a summary at stop

Counts are the simulator's truth (its FaultRecord and digitised samples, made again from the seed), never
derived from the wall clock.
"""

from __future__ import annotations

import errno
import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fluxcal.drivers import icd
from fluxcal.drivers.assemble import FrameAssembler, SerialFramer, can_icd_counters, serial_icd_counters
from fluxcal.drivers.block import FLAG_IMPLAUSIBLE, FLAG_TEMP_INVALID, SampleBlock
from fluxcal.drivers.config import load_section
from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.plausibility import Plausibility
from fluxcal.drivers.registry import source_kind
from fluxcal.drivers.serial_source import SerialConfig
from fluxcal.drivers.sim import FaultRecord, Unit, load_sim_config
from fluxcal.drivers.sim.unit import FLAG_RESERVED_SIM
from fluxcal.drivers.source import Counters
from fluxcal.service.io.bus import Message
from fluxcal.service.wiring.dashboard.view import UnitView
from fluxcal.service.wiring.faults import FaultWatch
from fluxcal.service.wiring.status import StatusLog

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.drivers.timeline",)

ROOT = Path(__file__).resolve().parents[2]


def unit(**sim) -> Unit:
    table = {"seed": 5, "rate_hz": 500.0, "duration_s": 4.0,
             "motion": {"kind": "tumble", "rate_deg_s": 60.0, "tumble_period_s": 3.0},
             "probes": [{"position_m": [-0.25, 0, 0], "offset_nT": [210.0, -330.0, 125.0], "noise_nT": 0.5},
                        {"position_m": [0.25, 0, 0], "offset_nT": [-175.0, 260.0, 390.0], "noise_nT": 0.5}]}
    table.update(sim)
    return Unit(load_sim_config(table))


def through_driver(u: Unit, chunk: int = 997) -> tuple[SampleBlock, Counters, FaultRecord, bytes]:
    """The unit's serial bytes (faults and all) through the serial driver's framer and assembler, in chunks
    that split frames anywhere; the record of what the unit did."""
    rec = FaultRecord()
    n = u.n_samples
    wire = b"".join(u.serial_bytes(a, min(a + 100, n), record=rec) for a in range(0, n, 100))
    counters = serial_icd_counters()
    framer, asm = SerialFramer(u.n_probes, counters), FrameAssembler(u.n_probes, u.lsb_nT, counters)
    blocks = [asm.block(framer.feed(wire[i:i + chunk]), rx_time_s=i * 1e-6) for i in range(0, len(wire), chunk)]
    blocks.append(asm.block(framer.finish()))
    return SampleBlock.concat([b for b in blocks if b.n_samples]), counters, rec, wire


def gaps_of(kept: np.ndarray) -> tuple[int, int]:
    steps = np.diff(kept)
    return int(np.count_nonzero(steps > 1)), int((steps[steps > 1] - 1).sum())


def expected_repeats(rec: FaultRecord, n: int, stale_frames: int) -> tuple[np.ndarray, int, int]:
    """(indices of the originals that arrive intact, duplicates a reader can see, stale frames it can see)."""
    keep = np.setdiff1d(np.arange(n), rec.serial_lost())
    dups = np.intersect1d(rec.samples("duplicate"), keep).size         # a copy of a damaged frame is damaged too
    stale = rec.samples("stale")
    # a stale frame (index i - k, intact) steps back when a later original arrived before it: one of i-k+1 .. i;
    # it is a copy of a frame received when its original arrived intact (a duplicate), else stale
    seen_later = np.array([np.any((keep > i - stale_frames) & (keep <= i)) for i in stale], bool)
    copies = np.isin(stale - stale_frames, keep)
    return keep, dups + int(np.count_nonzero(seen_later & copies)), int(np.count_nonzero(seen_later & ~copies))


# --- the driver: restarts, duplicates, stale frames --------------------------------------------------------

@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("seq_start", [39_000, 100])
def test_restart_duplicates_and_stale_frames_are_counted_and_time_never_goes_back(seed, seq_start):
    """A restart 1,500 frames in: from seq 40,499 (more than 32,768: it used to read as a wrap and 25,036
    missed samples) or from seq 1,600 (time went back); with bit errors, duplicated and stale frames."""
    u = unit(seed=seed, seq_start=seq_start, t_us_start=3_000_000_000,
             faults={"bitflip_fraction": 0.01, "duplicate_fraction": 0.02, "stale_fraction": 0.01,
                     "stale_frames": 5, "restart_at_s": [3.0]})
    got, c, rec, wire = through_driver(u)
    n, fl = u.n_samples, u.frame_length
    keep, dups, stale = expected_repeats(rec, n, 5)
    assert rec.samples("duplicate").size > 10 and rec.samples("stale").size > 5 and rec.samples("bitflip").size > 10
    want = u.digitise(0, n)
    assert want.seq[1499] == seq_start + 1499 and want.seq[1500] == 0 and want.t_us[1500] == 0

    # exactly the intact originals, once each, in order; the restart neither a gap nor a step back
    np.testing.assert_array_equal(got.field_nT, want.to_block().field_nT[keep])
    assert np.all(np.diff(got.seq) >= 1) and np.all(np.diff(got.t_s) > 0)
    np.testing.assert_array_equal(np.diff(got.seq), np.diff(keep))           # gaps only where frames were lost
    assert c.restarts == 1 and c.duplicates == dups and c.seq_backsteps == stale
    assert (c.seq_gaps, c.samples_missed) == gaps_of(keep)
    # before the restart the unit's own time; after it, its own clock from the restart on
    before = keep < 1500
    np.testing.assert_array_equal(got.t_s[before], want.t_us[keep[before]] / 1e6)
    after = ~before
    np.testing.assert_array_equal(np.diff(np.rint(got.t_s[after] * 1e6).astype(np.int64)), np.diff(want.t_us[keep[after]]))
    # every frame on the wire with a good header is accepted, or failed its CRC
    heads = np.flatnonzero((np.frombuffer(wire, np.uint8)[:-3] == 0xA5) & (np.frombuffer(wire, np.uint8)[1:-2] == 0x5A)
                           & (np.frombuffer(wire, np.uint8)[2:-1] == icd.VERSION)
                           & (np.frombuffer(wire, np.uint8)[3:] == u.n_probes))
    heads = heads[heads + fl <= len(wire)]
    copies = np.intersect1d(rec.samples("duplicate"), keep).size + rec.samples("stale").size   # intact, on the wire
    assert c.frames_accepted == keep.size + copies and "bytes_received" in c.as_dict()   # the port counts those
    assert c.crc_failures == heads.size - c.frames_accepted


def test_a_stale_run_that_goes_on_is_taken_as_a_restart_and_a_long_loss_is_counted_by_the_clock():
    """A unit that jumps back 3,000 frames (not near zero) and goes on from there: the 8th frame following on
    confirms it as a restart, and the 7 held before it are kept with it (they were dropped as stale: samples lost).
    A loss of 70,000 frames (more than the counter's range) is counted right."""
    u = unit(seq_start=10_000, duration_s=1.0)
    s = u.digitise(0, 500)
    frames = icd.RawFrames(seq=s.seq_raw, t_us=s.t_us_raw, counts=s.counts, temp_raw=s.temp_raw, flags=s.flags)
    c = serial_icd_counters()
    asm = FrameAssembler(2, u.lsb_nT, c)
    first = asm.block(icd.RawFrames(*(x[:300] for x in (frames.seq, frames.t_us, frames.counts, frames.temp_raw,
                                                         frames.flags))))
    back = icd.RawFrames(seq=(frames.seq[300:320].astype(np.int64) - 3000).astype(np.uint16),
                         t_us=(frames.t_us[300:320].astype(np.int64) - 3000 * 2000).astype(np.uint32),
                         counts=frames.counts[300:320], temp_raw=frames.temp_raw[300:320], flags=frames.flags[300:320])
    second = asm.block(back)
    assert (c.seq_backsteps, c.restarts, second.n_samples) == (0, 1, 20)
    np.testing.assert_array_equal(second.field_nT, s.counts[300:320] * u.lsb_nT)   # every frame of the run, in order
    assert second.seq[0] == first.seq[-1] + 1 and np.all(np.diff(second.seq) == 1)
    assert second.t_s[0] > first.t_s[-1]
    # 70,000 frames later (140 s at 500 Hz): the counter moved 70,000 mod 65,536 = 4,464
    later = icd.RawFrames(seq=(back.seq[-1:].astype(np.int64) + 70_001).astype(np.uint16),
                          t_us=(back.t_us[-1:].astype(np.int64) + 70_001 * 2000).astype(np.uint32),
                          counts=frames.counts[:1], temp_raw=frames.temp_raw[:1], flags=frames.flags[:1])
    third = asm.block(later)
    assert third.seq[0] - second.seq[-1] == 70_001 and c.samples_missed == 70_000 and c.restarts == 1


@pytest.mark.parametrize("chunk", [997, 61])
def test_a_restart_soon_after_a_restart_loses_no_frame(chunk):
    """A unit restarting 3 s after a restart (600 frames: its counter and clock back by less than a stale frame's
    limit) lost 7 frames, said as stale, none counted missed (a field trial). Through the serial driver, in chunks of
    several frames or of a few (the held frames then come from earlier blocks): every frame the unit sent is
    delivered once, in order, time never goes back, and nothing is counted stale or missed."""
    u = unit(rate_hz=200.0, duration_s=8.0, faults={"restart_at_s": [2.0, 5.0]})
    got, c, rec, _ = through_driver(u, chunk=chunk)
    want = u.digitise(0, u.n_samples)
    assert c.restarts == 2 and c.seq_backsteps == 0 and (c.seq_gaps, c.samples_missed) == (0, 0)
    np.testing.assert_array_equal(got.field_nT, want.to_block().field_nT)        # all 1,600, once each, in order
    assert np.all(np.diff(got.seq) == 1) and np.all(np.diff(got.t_s) > 0)


def test_can_frames_repeated_are_counted_and_a_restart_keeps_time_going(icd_truth):
    from fluxcal.drivers.assemble import CanAssembler, CanSamples

    a, b = icd_truth(50, 2, seq0=40_000), icd_truth(50, 2, seed=1, seq0=0)
    (ia, pa), (ib, pb) = a.can_frames(), b.can_frames()
    c = can_icd_counters()
    asm = CanAssembler(2, window_samples=8, counters=c, rate_hz=500.0)
    parts = [asm.push(ia[:150], pa[:150], 1.0), asm.push(ia[140:], pa[140:], 1.01),      # 10 frames sent twice
             asm.push(ia[:6], pa[:6], 1.02),                                             # a released sample again
             asm.push(ib, pb, 1.05), asm.flush()]
    got = CanSamples.concat(parts, 2)
    assert c.duplicates == 16 and c.restarts == 1 and c.can_incomplete == 0
    assert got.seq.tolist() == list(range(40_000, 40_100))
    assert np.array_equal(got.counts, np.concatenate([a.counts, b.counts]))


@pytest.mark.parametrize("window", [8, 32])
def test_a_can_unit_restarting_soon_after_a_restart_loses_nothing(icd_truth, window):
    """A CAN unit restarting 3 s after a restart (600 samples at 200 Hz, back by less than restart_samples): its
    frames were read as 3,588 duplicates and dropped, and everything after was stamped 3 s early (a field trial).
    Now the second restart is one, and every sample is released once, in order, time going on."""
    from fluxcal.drivers.assemble import CanAssembler, CanSamples

    runs = [icd_truth(300, 2, seq0=40_000), icd_truth(600, 2, seed=1, seq0=0), icd_truth(300, 2, seed=2, seq0=0)]
    c = can_icd_counters()
    asm = CanAssembler(2, window_samples=window, counters=c, rate_hz=200.0)
    parts, t = [], 10.0
    for run in runs:
        ids, pay = run.can_frames()
        per = 6                                                # frames of one sample (2 probes x 3 axes)
        for a in range(0, ids.size, 5 * per):                  # 5 samples a batch, 25 ms apart
            parts.append(asm.push(ids[a:a + 5 * per], pay[a:a + 5 * per], t))
            t += 0.025
    parts.append(asm.flush())
    got = CanSamples.concat(parts, 2)
    assert (c.restarts, c.duplicates, c.can_incomplete) == (2, 0, 0)
    assert np.array_equal(got.counts, np.concatenate([r.counts for r in runs]))      # all 1,200, once, in order
    assert np.all(np.diff(got.seq) == 1)                        # nothing counted missed, time never back


@pytest.mark.parametrize("window", [8, 32])
@pytest.mark.parametrize(("restarts", "batch"), [([2.0, 2.4], 5), ([2.0, 2.8], 5), ([1.0, 1.7, 2.3, 6.0], 5),
                                                 ([2.0, 2.05], 1), ([2.0, 2.05], 5), ([2.0, 2.2], 50),
                                                 ([2.0, 2.005], 5), ([1.0, 1.01, 1.03, 2.0], 50)])
def test_the_simulated_units_restarts_on_can_lose_nothing(window, restarts, batch):
    """The simulated unit's own CAN frames, restarting 5 ms to 4 s apart (1 to 800 samples at 200 Hz), received
    frame by frame or in batches of 5 or 50 samples: every sample released once, in order, each restart counted,
    time never stepped. Restarting again before its run passed the last run's counters, the new run's frames were
    once taken as the old run's late frames (31 samples lost); restarting within two windows of its last start,
    as repeats of samples released (0.05 s apart: 10 of 800 lost, counted as duplicates), and within one batch,
    room was kept for old samples that never were (the time stepped 45 ms on)."""
    from fluxcal.drivers.assemble import CanAssembler, CanSamples

    u = unit(rate_hz=200.0, duration_s=8.0, faults={"restart_at_s": restarts})
    c = can_icd_counters()
    asm = CanAssembler(2, window_samples=window, counters=c, rate_hz=200.0)
    parts = []
    for a in range(0, u.n_samples, batch):                 # received as the unit sends them
        ids, payloads, _ = u.can_frames(a, min(a + batch, u.n_samples))
        parts.append(asm.push(ids, payloads, 10.0 + a / 200.0))
    got = CanSamples.concat([*parts, asm.flush()], 2)
    assert (c.restarts, c.duplicates, c.can_incomplete) == (len(restarts), 0, 0)
    np.testing.assert_array_equal(got.counts, u.digitise(0, u.n_samples).counts)
    assert np.all(np.diff(got.seq) == 1)


def test_a_can_frame_sent_again_near_a_wrap_is_a_repeat_and_another_value_there_a_restart(icd_truth):
    """Just after the counter wraps, frames stepping back to counters near zero: sent again bit for bit, each is a
    repeat (dropped, counted); with other values (the unit started again 7 samples after the wrap), a restart, and
    none of the new run is lost."""
    from fluxcal.drivers.assemble import CanAssembler, CanSamples

    a, b = icd_truth(12, 2, seq0=65_531), icd_truth(40, 2, seed=1, seq0=0)      # a: 65,531 ... 65,535, 0 ... 6
    (ia, pa), (ib, pb) = a.can_frames(), b.can_frames()
    per = 6
    c = can_icd_counters()
    asm = CanAssembler(2, window_samples=8, counters=c, rate_hz=200.0)
    parts = [asm.push(ia, pa, 1.0), asm.push(ia[5 * per:8 * per], pa[5 * per:8 * per], 1.01)]   # counters 0-2 again
    assert (c.duplicates, c.restarts) == (3 * per, 0)
    parts += [asm.push(ib[:3 * per], pb[:3 * per], 1.02), asm.push(ib[3 * per:], pb[3 * per:], 1.03), asm.flush()]
    got = CanSamples.concat(parts, 2)
    assert (c.duplicates, c.restarts, c.can_incomplete) == (3 * per, 1, 0)
    assert np.array_equal(got.counts, np.concatenate([a.counts, b.counts]))       # all 52, once, in order
    assert np.all(np.diff(got.seq) == 1)


# --- plausibility ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("seed", [7, 8])
def test_implausible_values_are_counted_flagged_and_kept_out_of_the_estimator(seed):
    u = unit(seed=seed, duration_s=6.0,
             faults={"reserved_flag_fraction": 0.01, "full_scale_fraction": 0.01, "zero_vector_fraction": 0.01,
                     "temp_rail_fraction": 0.02, "temp_invalid_fraction": 0.2})
    got, c, rec, _ = through_driver(u)
    want = u.digitise(0, u.n_samples)
    assert got.n_samples == u.n_samples
    reserved = (want.flags & FLAG_RESERVED_SIM) != 0
    beyond = (np.abs(want.field_nT) > 1e6) & ~want.saturated
    zero = (want.counts == 0).all(axis=2)
    temp_bad = (want.flags & FLAG_TEMP_INVALID) != 0
    temp_out = ((want.temp_C < -100) | (want.temp_C > 200)) & ~temp_bad[:, None]
    bad = reserved | beyond.any(axis=(1, 2)) | zero.any(axis=1) | temp_out.any(axis=1)
    assert min(reserved.sum(), beyond.sum(), zero.sum(), temp_out.sum()) >= 10
    # the rail temperature where the unit also says "invalid" is not counted twice
    assert np.any(temp_bad & (want.temp_raw[:, 0] == 32767))
    assert (c.reserved_flags, c.beyond_full_scale, c.zero_vectors, c.temp_out_of_range, c.implausible_samples) == (
        reserved.sum(), beyond.sum(), zero.sum(), temp_out.sum(), bad.sum())
    np.testing.assert_array_equal((got.flags & FLAG_IMPLAUSIBLE) != 0, bad)
    np.testing.assert_array_equal(got.field_nT, want.to_block().field_nT)        # recorded as they came

    # the pipeline: an estimator fed only the plausible samples, the flagged ones NaN in the corrected output
    from test_faults import pipeline_for, truth_calibration

    pl = pipeline_for(u, initial=truth_calibration(u), check_every_samples=float("inf"))
    outs = [pl.process(got.slice(a, a + 250)) for a in range(0, got.n_samples, 250)]
    pl.flush_estimator()
    assert pl._estimators[0].n_samples_ == int((~bad).sum())
    corrected = np.concatenate([o.corrected.corrected_nT for o in outs])
    assert np.isnan(corrected[bad]).all() and np.isfinite(corrected[~bad]).all()
    err = corrected[~bad] - u.world.samples(0, u.n_samples).field_platform_nT[~bad]
    assert np.sqrt(np.mean(err ** 2)) < 0.6


def test_plausibility_keys_are_validated_naming_key_value_and_what_is_allowed():
    base = {"kind": "serial", "port": "/dev/null", "n_probes": 2}
    cfg = load_section(SerialConfig, {**base, "full_scale_nT": 100000.0, "temp_min_C": -40.0, "temp_max_C": 85.0},
                       "source")
    assert (cfg.full_scale_nT, cfg.temp_min_C, cfg.temp_max_C) == (100000.0, -40.0, 85.0)
    with pytest.raises(ConfigError, match=r"source.temp_max_C: -50.0 is not allowed \(allowed: above "
                                          r"source.temp_min_C = -40.0\)"):
        load_section(SerialConfig, {**base, "temp_min_C": -40.0, "temp_max_C": -50.0}, "source")
    with pytest.raises(ConfigError, match=r"source.full_scale_nT: 0.5 is below the minimum 1.0"):
        load_section(SerialConfig, {**base, "full_scale_nT": 0.5}, "source")
    with pytest.raises(ConfigError, match=r"source.temp_max_C: 400.0 is above the maximum 327.67"):
        load_section(SerialConfig, {**base, "temp_max_C": 400.0}, "source")
    # a configured full scale flags what the default lets through
    c = serial_icd_counters()
    counts = np.full((3, 1, 3), 150_000_000, np.int32)                          # 150,000 nT
    FrameAssembler(1, 0.001, c, plausibility=Plausibility(full_scale_nT=100_000.0)).block(
        icd.RawFrames(seq=np.arange(3, dtype=np.uint16), t_us=np.arange(3, dtype=np.uint32) * 1000, counts=counts,
                      temp_raw=np.zeros((3, 1), np.int16), flags=np.zeros(3, np.uint8)))
    assert (c.beyond_full_scale, c.implausible_samples) == (9, 3)


def test_fit_refuses_a_recording_whose_time_goes_back(tmp_path, capsys):
    from helpers import write_raw

    from fluxcal.service.wiring.cli import main

    u = unit(duration_s=8.0)
    b = u.digitise(0, u.n_samples).to_block()
    back = SampleBlock(t_s=np.concatenate([b.t_s[:2000], b.t_s[2000:] - 3.0]), seq=b.seq, field_nT=b.field_nT,
                       temp_C=b.temp_C, flags=b.flags)
    write_raw(tmp_path / "rec", [back.slice(a, a + 100) for a in range(0, back.n_samples, 100)])
    rc = main(["fit", str(tmp_path / "rec")])
    err = capsys.readouterr().err
    assert rc != 0 and "Traceback" not in err
    assert re.search(r"sample 2000 \(seq 2000\): time 1\.0 s does not increase \(previous 3\.998 s, seq 1999\); "
                     r"1 such step\(s\)", err), err


# --- FaultWatch, the dashboard's view, the status lines ----------------------------------------------------

class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_fault_watch_says_begin_running_count_end_and_summary_from_the_counters():
    clock, said = Clock(), []
    fw = FaultWatch(said.append, words=source_kind("serial").words(), silence_s=5.0, every_s=10.0, clock=clock,
                    wall=lambda: 1.7e9)
    c = dict(frames_accepted=0, crc_failures=0, bytes_received=0, bytes_skipped=0, samples_missed=0, seq_gaps=0,
             duplicates=0, restarts=0, implausible_samples=0, zero_vectors=0)
    health = []

    def step(s: float, recording=None, **grow) -> None:
        clock.t += s
        for k, v in grow.items():
            c[k] += v
        health.append(fw.tick(c, recording))

    step(1, frames_accepted=8, crc_failures=192, bytes_received=8000)    # 96 % of the frames fail
    assert said[-1].startswith("CRC failures: 192 frame(s) failed their CRC in the last 1.0 s (96% of the frames); "
                               "192 so far"), said
    for _ in range(10):
        step(1, frames_accepted=8, crc_failures=192, bytes_received=8000)
    assert said[-1].startswith("CRC failures go on: 1,920 frame(s) failed their CRC in the last 10 s (96% of the "
                               "frames); 2,112 since they began 11 s ago, 2,112 so far"), said
    for _ in range(3):
        step(1, frames_accepted=200, bytes_received=8200)
    assert said[-1].startswith("CRC failures stopped: 2,112 frame(s) failed their CRC over 11 s, none for 3.0 s"), said

    # bytes without a frame (a wrong baud rate): said after 2 s, its end when frames decode again
    n = len(said)
    for _ in range(3):
        step(1, bytes_received=9000, bytes_skipped=9000)
    assert said[n:] == ["no frame decodes: bytes arrive but no frame decodes (baud rate? probe count?): 18,000 bytes "
                        "in 2.0 s, 0 frames; check source.baudrate and unit.n_probes against the unit (health: "
                        "counters.bytes_skipped)"]
    step(1, frames_accepted=200, bytes_received=8200)
    assert said[-1] == "no frame decodes ended: frames decode again after 4.0 s; 27,000 bytes in between decoded into " \
                       "no frame"

    # silence: said once it lasts silence_s, its end when data come again
    n = len(said)
    for _ in range(7):
        step(1)
    assert said[n:] == ["silence: no data from the unit for 5.0 s (unit.silence_s = 5): is it powered, connected and "
                        "sending? (1 silence(s) so far; health: faults.active)"]
    assert health[-1]["active"] == ["silence"] and health[-1]["totals"]["silence"] == 1
    step(1, frames_accepted=200, bytes_received=8200, samples_missed=1400, seq_gaps=1)
    assert said[-2] == "silence ended: data from the unit again after about 8.0 s"
    assert said[-1].startswith("samples missed: 1,400 sample(s) missed in gaps of the unit's counter in the last 1.0 s "
                               "(1 gap(s)); 1,400 so far")

    # one-shot: a restart, each time; duplicates with their count
    step(1, frames_accepted=200, bytes_received=8200, restarts=1, duplicates=3)
    assert any(s.startswith("unit restart: 1 restart(s) of the unit") for s in said[-2:])
    assert any(s.startswith("duplicate frames: 3 frame(s) repeating one received before") for s in said[-2:])

    # recording trouble: the running count, its end, the total
    n = len(said)
    live = dict(frames_accepted=200, bytes_received=8200)            # the unit goes on meanwhile
    rec = {"errors": 0, "dropped": 0, "messages_written": 500, "pending": 0, "current": "a.mcap", "last_error": ""}
    step(1, rec, **live)
    rec = {**rec, "errors": 1, "dropped": 3, "pending": 40, "current": None,
           "last_error": "OSError: [Errno 28] No space left on device"}
    step(1, rec, **live)
    for k in range(12):
        rec = {**rec, "errors": 2 + k // 5, "dropped": rec["dropped"] + 214}
        step(1, rec, **live)
    rec = {**rec, "messages_written": 600, "current": "b.mcap"}
    step(1, rec, **live)
    rec_lines = [s for s in said[n:] if "recording" in s]
    assert rec_lines == [
        "recording trouble: OSError: [Errno 28] No space left on device; 3 message(s) dropped so far, 40 waiting to "
        "be written; retrying (health: recording)",
        "recording still failing: OSError: [Errno 28] No space left on device; 2,143 message(s) dropped since it "
        "began 10 s ago (2,140 in the last 10 s), 40 waiting; 2,143 in all",
        "recording resumed after 13 s into b.mcap: 2,571 message(s) dropped meanwhile, 2,571 in all"]
    h = health[-1]
    assert h["totals"]["recording_dropped"] == 2571 and "recording" not in h["active"]
    assert [e["count"] for e in h["events"] if e["kind"] == "recording"] == [3, 2143, 2571]

    # the summary at stop: every kind with its total
    lines = fw.summary(c, rec)
    assert lines[0] == "summary at stop: 4,288 frame(s) with a good CRC; 7 kind(s) of loss or fault:"
    assert "summary: CRC failures: 2,112 frame(s) failed their CRC (33% of the frames)" in lines
    assert "summary: samples missed: 1,400 sample(s) missed in gaps of the unit's counter (1 gap(s))" in lines
    assert "summary: recording: 2,571 message(s) dropped, 4 write error(s) in 1 stretch(es) of trouble" in lines
    assert "summary: silence: the unit was silent 1 time(s) for 5 s or more" in lines
    assert "summary: no frame decodes: 1 stretch(es) of bytes that decoded into no frame (27,000 bytes)" in lines
    quiet = FaultWatch(said.append, words=source_kind("serial").words(), clock=Clock())
    assert quiet.summary({"frames_accepted": 12345}) == ["summary at stop: 12,345 frame(s) with a good CRC; no loss and no "
                                                         "fault seen"]

    # the dashboard's view: every event once, in order, with its count, however the health messages overlap
    view = UnitView("u1")
    for i, hh in enumerate(health):
        view.update(Message("health", "fluxcal/u1/health", {"counters": dict(c), "faults": hh}))
        if i % 3 == 0:                                                   # a message seen twice changes nothing
            view.update(Message("health", "fluxcal/u1/health", {"counters": dict(c), "faults": hh}))
    events = view.view({})["faults"]["events"]
    assert [e["n"] for e in events] == list(range(1, fw.n_events + 1))
    assert [e["text"] for e in events] == said[:fw.n_events]
    assert view.view({})["faults"]["totals"]["recording_dropped"] == 2571


def test_the_dashboard_keeps_fault_events_of_a_service_that_started_again():
    view = UnitView("u1")
    ev = [{"n": k, "kind": "crc", "phase": "begin", "count": 10 * k, "text": f"t{k}", "time_unix_s": 1.0}
          for k in range(1, 4)]
    view.update(Message("health", "k", {"faults": {"n_events": 3, "events": ev, "active": ["crc"], "totals": {}}}))
    view.update(Message("health", "k", {"faults": {"n_events": 1, "events": ev[:1], "active": [], "totals": {}}}))
    assert [e["text"] for e in view.view({})["faults"]["events"]] == ["t1", "t2", "t3", "t1"]


def test_status_line_gives_the_error_over_its_interval_with_the_interval():
    said: list[str] = []
    log = StatusLog(said.append, 0.0)
    log.block(200, {"s1.scalar": 0.37, "s2-s1.x": float("nan")})
    log.block(200, {"s1.scalar": 1.31})
    log.block(100, {"s1.scalar": 0.5})
    log.tick({"usable": True, "cal_id": 2})
    rms = np.sqrt((200 * 0.37 ** 2 + 200 * 1.31 ** 2 + 100 * 0.5 ** 2) / 500)
    assert re.search(rf"; error rms nT over the last \d s \(500 samples\): s1\.scalar {rms:.3g}$", said[-1]), said
    log.tick({"usable": True, "cal_id": 2})
    assert "error rms" not in said[-1]                     # nothing in this interval: nothing said for it


def test_quality_gate_refusals_after_usable_are_said_as_such_once_per_set_of_reasons():
    said: list[str] = []
    log = StatusLog(said.append, 3600.0)
    log.gate(False, ["s1: coverage 12 % of the direction bins (needs 30 %)"])
    assert said[-1] == "quality gate: not yet: s1: coverage 12 % of the direction bins (needs 30 %)"
    log.gate(True, [])
    log.tick({"usable": True, "cal_id": 4})
    cov = ["s1: coverage 22 % of the direction bins (needs 30 %)"]
    rms = ["s2: scalar residual 31 nT RMS (allowed 20)"]
    for reasons in (cov, rms, cov, rms, [x.replace("22", "25") for x in cov]):
        log.gate(False, reasons)
    assert said[-3:] == ["quality gate: candidate usable",
                         "quality gate: the latest candidate was refused; the calibration 4 in use stays: " + cov[0],
                         "quality gate: the latest candidate was refused; the calibration 4 in use stays: " + rms[0]]
    log.tick({"usable": True, "cal_id": 5})                # another calibration in use: its refusals are news
    log.gate(False, cov)
    assert said[-1] == "quality gate: the latest candidate was refused; the calibration 5 in use stays: " + cov[0]


# --- a pty unit through `fluxcal run` ----------------------------------------------------------------------

def run_service(tmp_path: Path, sim: dict, *, realtime: bool, run_s: float, unit_keys: str = "",
                timeout_s: float = 90.0) -> tuple[list[str], Path, Unit]:
    """`fluxcal run` (the Daemon, in a thread) on configs/sim-gradiometer.toml with the simulated unit behind a pty
    and the given [sim] keys; once it stopped by itself, what it said, the recording directory and the unit it ran
    (made again from the same configuration: the truth)."""
    from test_recording import service_config

    from fluxcal.service.wiring.config import load_config
    from fluxcal.service.wiring.daemon import Daemon

    text = open(service_config(tmp_path, run_s=run_s, realtime=realtime)).read()
    faults = sim.pop("faults", {})
    for k, v in sim.items():                               # [sim] keys: the example's value replaced, or added
        line = f"{k} = {json.dumps(v)}"
        text, n = re.subn(rf"^{k} = .*$", line, text, count=1, flags=re.M)
        if not n:
            text = text.replace("[sim]\n", f"[sim]\n{line}\n", 1)
    text = text.replace("[sim.faults]", "[sim.faults]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in faults.items()), 1)
    text = text.replace("[unit]\n", "[unit]\n" + unit_keys, 1)
    (tmp_path / "c.toml").write_text(text)
    cfg = load_config(tmp_path / "c.toml")
    assert cfg.source.transport == "pty"
    said: list[str] = []
    daemon = Daemon(cfg, say=said.append)
    error: list[BaseException] = []

    def run() -> None:
        try:
            daemon.run()
        except BaseException as e:                        # reported below
            error.append(e)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        daemon.stop.set()
        thread.join(10)
        pytest.fail(f"the service did not stop by itself within {timeout_s} s: {said[-5:]}")
    assert not error, error
    assert "source exhausted" in said and said[-1] == "stopped", said[-5:]
    import dataclasses

    return said, tmp_path / "rec", Unit(dataclasses.replace(cfg.sim, duration_s=cfg.source.run_s))


def recorded(rec_dir: Path) -> tuple[SampleBlock, list[dict], dict[str, list[int]]]:
    """The recording's raw samples, its health messages and each channel's log times."""
    from fluxcal.drivers.mcap_source import iter_records
    from fluxcal.service.io.recordings.reader import read_recording

    rec = read_recording(rec_dir)
    times: dict[str, list[int]] = {}
    for r in iter_records(rec_dir):
        times.setdefault(r.topic, []).append(r.log_time_ns)
    return rec.raw, rec.health, times


def dashboard_of(health: list[dict]) -> dict:
    view = UnitView("grad1")
    for h in health:
        view.update(Message("health", "fluxcal/grad1/health", h))
    return view.view({})["faults"]


def said_for(said: list[str], label: str) -> list[str]:
    return [s for s in said if s.startswith(label)]


@pytest.mark.slow
def test_a_pty_unit_with_bit_errors_repeats_a_restart_and_absurd_values_is_said_everywhere(tmp_path):
    sim = {"seed": 31, "seq_start": 39_000, "t_us_start": 3_000_000_000,
           "faults": {"bitflip_fraction": 0.01, "duplicate_fraction": 0.01, "stale_fraction": 0.005,
                      "stale_frames": 5, "restart_at_s": [8.0], "reserved_flag_fraction": 0.002,
                      "full_scale_fraction": 0.002, "zero_vector_fraction": 0.002, "temp_rail_fraction": 0.002}}
    said, rec_dir, u = run_service(tmp_path, dict(sim, faults=dict(sim["faults"])), realtime=False, run_s=12.0)

    # the truth: the same unit, its wire bytes made again from the seed
    n = u.n_samples
    rec = FaultRecord()
    wire = np.frombuffer(u.serial_bytes(0, n, record=rec), np.uint8)
    keep, dups, stale = expected_repeats(rec, n, 5)
    heads = np.flatnonzero((wire[:-3] == 0xA5) & (wire[1:-2] == 0x5A) & (wire[2:-1] == icd.VERSION)
                           & (wire[3:] == u.n_probes))
    # frames with a good CRC on the wire: the intact originals, their intact copies and the stale frames
    frames = keep.size + np.intersect1d(rec.samples("duplicate"), keep).size + rec.samples("stale").size
    want = u.digitise(0, n)
    restart = int(u.restarts()[0])
    assert want.seq[restart - 1] > 32_768 and want.seq[restart] == 0
    kept = want.flags[keep]
    bad = (((kept & FLAG_RESERVED_SIM) != 0) | ((np.abs(want.field_nT[keep]) > 1e6) & ~want.saturated[keep]).any(axis=(1, 2))
           | (want.counts[keep] == 0).all(axis=2).any(axis=1) | (want.temp_raw[keep] == 32767).any(axis=1))
    truth = {"crc_failures": int(heads[heads + u.frame_length <= wire.size].size) - frames, "duplicates": dups, "seq_backsteps": stale, "restarts": 1, "samples_missed": gaps_of(keep)[1],
             "implausible_samples": int(bad.sum())}
    assert min(v for k, v in truth.items() if k != "seq_backsteps") >= 1     # stale copies of intact frames are

    raw, health, times = recorded(rec_dir)
    final = health[-1]
    c = final["counters"]
    # every frame accounted for: the intact originals, their intact copies, the stale frames; every other
    # complete frame header on the wire is one CRC failure
    assert c["frames_accepted"] == frames and c["bytes_received"] == wire.size
    for key in ("crc_failures", "duplicates", "seq_backsteps", "restarts", "samples_missed", "implausible_samples"):
        assert c[key] == truth[key], (key, c[key], truth[key])

    # the recording: every sample kept once, time and seq never back, log times never back; flagged samples
    np.testing.assert_array_equal(raw.field_nT, want.to_block().field_nT[keep])
    assert np.all(np.diff(raw.t_s) > 0) and np.all(np.diff(raw.seq) >= 1)
    assert all(np.all(np.diff(t) >= 0) for t in times.values())
    assert int(np.count_nonzero(raw.flags & FLAG_IMPLAUSIBLE)) == truth["implausible_samples"]

    # the console: a line as each began, the summary at stop with the totals
    for label, key in (("CRC failures: ", "crc_failures"), ("duplicate frames: ", "duplicates"),
                       ("frames stepping back: ", "seq_backsteps"), ("unit restart: ", "restarts"),
                       ("implausible values: ", "implausible_samples"), ("samples missed: ", "samples_missed")):
        assert bool(said_for(said, label)) == bool(truth[key]), (label, said)
    summary = final["faults"]["summary"]
    assert summary == [s for s in said if s.startswith("summary")]
    assert f"summary: CRC failures: {c['crc_failures']:,} frame(s) failed their CRC" in "\n".join(summary)
    assert f"summary: duplicate frames: {truth['duplicates']:,} frame(s) repeating one received before" \
        in "\n".join(summary)
    assert (f"summary: frames stepping back: {truth['seq_backsteps']:,} frame(s)" in "\n".join(summary)) \
        == bool(truth["seq_backsteps"])
    assert "summary: unit restart: 1 restart(s) of the unit" in "\n".join(summary)
    assert f"summary: implausible values: {truth['implausible_samples']:,} sample(s)" in "\n".join(summary)
    assert (f"summary: samples missed: {truth['samples_missed']:,} sample(s) missed in gaps of the unit's counter "
            f"({gaps_of(keep)[0]:,} gap(s))") in summary
    # the health field and the dashboard
    totals = final["faults"]["totals"]
    assert (totals["duplicates"], totals["backsteps"], totals["restarts"], totals["implausible"], totals["gaps"]) == (
        truth["duplicates"], truth["seq_backsteps"], 1, truth["implausible_samples"], truth["samples_missed"])
    dash = dashboard_of(health)
    assert dash["summary"] == summary and dash["totals"] == totals
    kinds = {e["kind"] for e in dash["events"]}
    assert {"crc", "duplicates", "restarts", "implausible", "gaps"} <= kinds
    assert ("backsteps" in kinds) == bool(truth["seq_backsteps"])
    assert [e["count"] for e in dash["events"] if e["kind"] == "restarts"] == [1]
    for kind, key in (("duplicates", "duplicates"), ("backsteps", "seq_backsteps"), ("gaps", "samples_missed")):
        counts = [e["count"] for e in dash["events"] if e["kind"] == kind]
        assert counts == sorted(counts) and (counts[-1] if counts else 0) <= truth[key]

    # fit takes the recording (time increases), without the flagged samples
    from fluxcal.service.io.recordings.load import load_data

    data = load_data(rec_dir)
    assert np.isnan(data.block.field_nT[(data.block.flags & FLAG_IMPLAUSIBLE) != 0]).all()


@pytest.mark.slow
def test_a_pty_unit_read_at_a_wrong_baud_rate_then_silent_is_said_with_its_ends(tmp_path):
    sim = {"seed": 32, "faults": {"wrong_baud_at_s": [2.0], "wrong_baud_s": 4.0, "silence_at_s": [7.5],
                                  "silence_s": 3.5}}
    said, rec_dir, u = run_service(tmp_path, dict(sim, faults=dict(sim["faults"])), realtime=True, run_s=12.0,
                                   unit_keys="silence_s = 1.5\n")
    n, fl = u.n_samples, u.frame_length
    (a, b), = u.wrong_baud()
    (s0, s1), = u.silences()
    raw, health, _ = recorded(rec_dir)
    c = health[-1]["counters"]
    # what the service did not read at all (before it opened the port) does not count; the rest exactly
    first = int(raw.seq[0])
    assert first < a
    keep = np.setdiff1d(np.arange(first, n), np.r_[a:b, s0:s1])
    np.testing.assert_array_equal(raw.seq, keep)
    assert c["bytes_skipped"] == (b - a) * fl and c["crc_failures"] <= 2
    assert (c["seq_gaps"], c["samples_missed"]) == (2, (b - a) + (s1 - s0))

    nd = said_for(said, "no frame decodes: bytes arrive but no frame decodes (baud rate? probe count?)")
    assert len(nd) == 1 and len(said_for(said, "no frame decodes ended: frames decode again after")) == 1
    assert len(said_for(said, "silence: no data from the unit for")) == 1
    assert len(said_for(said, "silence ended: data from the unit again after about")) == 1
    summary = health[-1]["faults"]["summary"]
    assert "summary: silence: the unit was silent 1 time(s) for 1.5 s or more" in summary
    assert any(s.startswith("summary: no frame decodes: 1 stretch(es) of bytes") for s in summary)
    assert (f"summary: samples missed: {(b - a) + (s1 - s0):,} sample(s) missed in gaps of the unit's counter "
            f"(2 gap(s))") in summary
    totals = health[-1]["faults"]["totals"]
    assert (totals["silence"], totals["no_decode"]) == (1, 1) and 0 < totals["no_decode_bytes"] <= (b - a) * fl
    dash = dashboard_of(health)
    phases = [(e["kind"], e["phase"], e["count"]) for e in dash["events"] if e["kind"] in ("silence", "no_decode")]
    assert [p[:2] for p in phases] == [("no_decode", "begin"), ("no_decode", "end"), ("silence", "begin"),
                                       ("silence", "end")]
    assert phases[2][2] == phases[3][2] == 1 and phases[0][2] <= (b - a) * fl


@pytest.mark.slow
def test_a_full_disk_is_said_as_it_begins_with_its_running_count_when_it_ends_and_at_stop(tmp_path, monkeypatch):
    import fluxcal.service.io.recordings.writer as sink

    monkeypatch.setattr(sink, "_RETRY_S", 0.5)
    real_open = sink._default_opener
    state = {"full": False}

    class FillingDisk:
        def __init__(self, path, mode):
            if state["full"]:
                raise OSError(errno.ENOSPC, "No space left on device")
            self.f = real_open(path, mode)

        def write(self, b):
            if state["full"]:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(b)

        def __getattr__(self, name):
            return getattr(self.f, name)

    monkeypatch.setattr(sink, "_default_opener", FillingDisk)

    def disk() -> None:
        time.sleep(2.5)
        state["full"] = True
        time.sleep(4.0)
        state["full"] = False

    threading.Thread(target=disk, daemon=True).start()
    said, rec_dir, _ = run_service(tmp_path, {"seed": 33}, realtime=True, run_s=10.0)
    from fluxcal.drivers.mcap_source import iter_records

    health = [json.loads(r.data) for r in iter_records(rec_dir) if r.topic.endswith("/health")]
    final = health[-1]
    dropped = final["recording"]["dropped"]
    assert dropped > 20                                   # of 4 s of raw, corrected and 10 Hz messages
    assert len(said_for(said, "recording trouble: OSError: [Errno 28] No space left on device")) == 1
    resumed = said_for(said, "recording resumed after")
    assert len(resumed) == 1 and f": {dropped:,} message(s) dropped meanwhile, {dropped:,} in all" in resumed[0]
    assert f"summary: recording: {dropped:,} message(s) dropped" in "\n".join(final["faults"]["summary"])
    assert final["faults"]["totals"]["recording_dropped"] == dropped and final["faults"]["active"] == []
    dash = dashboard_of(health)
    rec_events = [e for e in dash["events"] if e["kind"] == "recording"]
    # messages written while the disk was full never reach the file: the dashboard sees the end and the summary
    assert rec_events and rec_events[-1]["phase"] == "end" and rec_events[-1]["count"] == dropped
    assert f"summary: recording: {dropped:,} message(s) dropped" in "\n".join(dash["summary"])


def test_an_input_lost_is_the_fault_going_on_until_it_is_back():
    """The adapter gone while the service reconnects: "input lost" is an active fault, first among them, with the
    reader's reason, in the health events (said on the console once, by the reader) until the input is back. A field
    trial's watch said only the faults counted before the loss ("CAN samples incomplete") while the adapter was gone."""
    from fluxcal.service.wiring.commands.client import active_faults

    clock, said = Clock(), []
    fw = FaultWatch(said.append, words=source_kind("can").words(), silence_s=5.0, clock=clock, wall=lambda: 1.7e9)
    c = {"frames_accepted": 0, "can_incomplete": 0, "read_errors": 0}
    clock.t += 1.0
    fw.tick({**c, "frames_accepted": 600, "can_incomplete": 4})
    why = "CAN bus slcan:/dev/x: receive failed (device gone): the adapter was probably disconnected"
    clock.t += 1.0
    health = fw.tick({**c, "frames_accepted": 600, "can_incomplete": 4, "read_errors": 1}, input_lost=why)
    assert health["active"] == ["input_lost", "can_incomplete"]
    assert active_faults({"faults": health}).startswith(f"input lost: {why}; reconnecting; ")
    assert not any("input lost" in s for s in said)                     # the reader said it as it happened
    for _ in range(8):                # down for 8 s: no silence said beside it (is the unit powered? the port is gone)
        clock.t += 1.0
        health = fw.tick({**c, "frames_accepted": 600, "can_incomplete": 4, "read_errors": 1}, input_lost=why)
    assert health["active"] == ["input_lost"] and not any(e["kind"] == "silence" for e in health["events"])
    clock.t += 1.0
    health = fw.tick({**c, "frames_accepted": 660, "can_incomplete": 4, "read_errors": 1})
    assert health["active"] == []
    assert [e["text"] for e in health["events"] if e["kind"] == "input_lost"] == [
        f"input lost: {why}; reconnecting", "input back after about 9.0 s"]
