"""Field hardening: every fault the simulated unit can inject, checked against the simulator's own
record of what it corrupted, dropped or flagged (drivers/sim/unit.py FaultRecord), never against
hard-coded results.

    serial garbage at 1 %, 10 % and 50 % of the bytes    exactly the intact samples, counters add up
    5 % of CAN frames lost on python-can's virtual bus   exactly the complete samples, pipeline goes on
    seq and unit clock wraps on the serial path          unwrapped, monotonic, exact, with gaps at the wrap
    saturated axes through the service pipeline          the estimator is not corrupted, outputs are NaN
    temperature-invalid samples                          no bad temperature reaches the temperature effect
    a Zenoh client or router going away and coming back  the service keeps publishing, clients hear again
    damaged MCAP files (hypothesis)                      what is intact, the loss said, or RecordingError

Everything networked binds 127.0.0.1 on free ports; every emitter, source and session is closed.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fluxcal.drivers import icd
from fluxcal.drivers.assemble import FrameAssembler, SerialFramer, serial_icd_counters
from fluxcal.drivers.block import FLAG_SATURATED, FLAG_TEMP_INVALID, SampleBlock
from fluxcal.drivers.can_source import CanSource
from fluxcal.drivers.config import load_section
from fluxcal.drivers.errors import FluxcalError, RecordingError
from fluxcal.drivers.serial_source import SerialSource
from fluxcal.drivers.sim import FaultRecord, Unit, load_sim_config
from fluxcal.drivers.sim.can_ports import CanEmitter
from fluxcal.drivers.sim.ports import PtyEmitter
from fluxcal.drivers.source import Counters
from fluxcal.service.io.bus import BusClient, ServiceBus, ZenohConfig, open_session
from fluxcal.service.io.encoding import encode_raw
from fluxcal.service.io.recordings.reader import read_recording, repair_recording
from fluxcal.service.io.recordings.writer import McapLogger
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.wiring.pipeline import Pipeline


def sim_unit(**sim) -> Unit:
    """A two-probe gradiometer on a tumbling platform, with known errors and noise."""
    table = {"seed": 11, "rate_hz": 500.0, "duration_s": 4.0, "reference": {"enabled": True, "noise_nT": 0.02},
             "motion": {"kind": "tumble", "rate_deg_s": 60.0, "tumble_period_s": 3.0},
             "temperature": {"start_C": 21.0, "amplitude_C": 3.0, "period_s": 2.0},
             "probes": [{"position_m": [-0.25, 0, 0], "offset_nT": [210.0, -330.0, 125.0],
                         "scale": [1.02, 0.985, 1.01], "nonorth_deg": [0.8, -1.2, 1.5], "noise_nT": 0.5},
                        {"position_m": [0.25, 0, 0], "offset_nT": [-175.0, 260.0, 390.0],
                         "scale": [0.975, 1.03, 0.99], "misalign_deg": [-2.0, 1.5, -1.0], "noise_nT": 0.5}]}
    table.update(sim)
    u = Unit(load_sim_config(table))
    u.config_table = table                                # what it was made from, to vary one thing
    return u


def read_all(src, emitter, timeout_s: float = 20.0) -> list[SampleBlock]:
    """Read a source fed by an emitter until the emitter has finished (it drains the port before it
    says so) and the source has nothing more."""
    blocks: list[SampleBlock] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        b = src.read(timeout=0.05)
        if b is not None and len(b):
            blocks.append(b)
        elif emitter.done.is_set():
            break
    assert emitter.wait(0), "the emitter did not finish in time"
    return blocks


def gaps_of(kept: np.ndarray) -> tuple[int, int]:
    """(number of gaps, samples missed inside them) in a sorted array of the indices received."""
    steps = np.diff(kept)
    return int(np.count_nonzero(steps > 1)), int((steps[steps > 1] - 1).sum())


# --- 1. serial garbage -----------------------------------------------------------------------------

# target fraction of the bytes on the wire that are garbage -> (per-frame probability, max length).
# A frame of 2 probes is 41 bytes and a run of garbage is 1..gmax bytes, gmax/2 + 1/2 on average, so
# garbage per frame is p (gmax + 1) / 2 and the fraction g / (41 + g):
#   1 %: 0.05 x 8.5 = 0.425 B/frame -> 1.03 %;  10 %: 0.5 x 9 = 4.5 -> 9.9 %;  50 %: 1.0 x 41 = 41 -> 50 %
GARBAGE = {0.01: (0.05, 16), 0.10: (0.5, 17), 0.50: (1.0, 81)}


@pytest.mark.parametrize("target", sorted(GARBAGE))
def test_serial_garbage_yields_exactly_the_intact_samples_and_counts_the_rest(target):
    p, gmax = GARBAGE[target]
    # garbage between frames, plus a few frames damaged in place so that "intact" is not "all"
    u = sim_unit(faults={"garbage_fraction": p, "garbage_max_bytes": gmax, "bitflip_fraction": 0.01,
                         "drop_byte_fraction": 0.01, "drop_frame_fraction": 0.005})
    n, fl = u.n_samples, u.frame_length
    em = PtyEmitter(u, realtime=False)
    em.start()
    try:
        with SerialSource(em.path, n_probes=2, lsb_nT=u.lsb_nT, read_timeout_s=0.01) as src:
            blocks = read_all(src, em)
            counters = src.counters
            pending = src._decoder.framer.pending_bytes   # a partial frame's worth of bytes kept back
            fed = src._decoder.framer.bytes_fed           # everything pyserial handed over
    finally:
        em.close()
    rec = em.record
    assert rec.samples("no_reader").size == 0 and rec.samples("outage").size == 0

    # the bytes the unit put on the wire, from the record alone
    dropped = rec.samples("drop_frame")
    lost_byte = rec.samples("drop_byte")
    damaged = np.setdiff1d(np.union1d(rec.samples("bitflip"), lost_byte), dropped)
    sent_bytes = (n - dropped.size) * fl - lost_byte.size + rec.garbage_bytes
    achieved = rec.garbage_bytes / sent_bytes
    assert fed == sent_bytes
    assert abs(achieved - target) < 0.15 * target, (target, achieved)

    # exactly the samples sent intact, bit for bit, in order
    keep = np.setdiff1d(np.arange(n), rec.serial_lost())
    assert keep.size == n - np.union1d(dropped, damaged).size
    got = SampleBlock.concat(blocks)
    want = u.digitise(0, n).to_block()
    np.testing.assert_array_equal(got.seq, want.seq[keep])
    np.testing.assert_array_equal(got.t_s, want.t_s[keep])
    np.testing.assert_array_equal(got.field_nT, want.field_nT[keep])
    np.testing.assert_array_equal(got.temp_C, want.temp_C[keep])
    np.testing.assert_array_equal(got.flags, want.flags[keep])

    # the counters account for every byte and every missing sample
    assert counters.frames_accepted == keep.size
    damaged_bytes = damaged.size * fl - np.intersect1d(damaged, lost_byte).size
    assert counters.bytes_skipped + pending == rec.garbage_bytes + damaged_bytes
    assert counters.frames_accepted * fl + counters.bytes_skipped + pending == sent_bytes
    assert pending < fl
    # every complete frame header (sync, version, n) on the wire that gave no frame is one CRC failure:
    # the damaged frames whose first 4 bytes survived (the bytes are the unit's, made again from the seed)
    wire = np.frombuffer(u.serial_bytes(0, n), np.uint8)
    assert wire.size == sent_bytes
    heads = np.flatnonzero((wire[:-3] == 0xA5) & (wire[1:-2] == 0x5A) & (wire[2:-1] == icd.VERSION)
                           & (wire[3:] == u.n_probes))
    heads = heads[heads + fl <= wire.size]
    assert counters.crc_failures == heads.size - keep.size
    assert 0.5 * damaged.size < counters.crc_failures <= damaged.size
    print(f"garbage {achieved:.4f} of {sent_bytes} bytes; samples {keep.size}/{n}; {counters}")
    assert (counters.seq_gaps, counters.samples_missed) == gaps_of(keep)
    assert counters.bytes_received == fed                 # every byte the port read, counted by the port


# --- 2. CAN frames lost ----------------------------------------------------------------------------

def truth_calibration(u: Unit) -> ArrayCalibration:
    """The world's own calibration: corrected = truth_matrix (raw - offset) is the field in the platform frame."""
    pr = u.world.probes
    return ArrayCalibration("truth", None, [ProbeCalibration(name, pr.offset_nT[k], pr.truth_matrix[k])
                                            for k, name in enumerate(pr.names)])


def pipeline_for(u: Unit, **kw) -> Pipeline:
    opts = dict(n_probes=u.n_probes, probe_names=list(u.world.probes.names), positions_m=None,
                total_nT=u.config.field.total_nT, min_samples=500, check_every_samples=400, window_samples=4000,
                chunk_samples=100)
    opts.update(kw)
    return Pipeline(**opts)


def read_until_quiet(src, emitter, quiet_s: float, timeout_s: float = 20.0) -> list[SampleBlock]:
    """Read until the emitter has finished and the source stayed quiet for quiet_s (the CAN assembler
    holds complete samples behind an incomplete one until it gives that one up)."""
    blocks: list[SampleBlock] = []
    deadline = time.monotonic() + timeout_s
    quiet_since: float | None = None
    while time.monotonic() < deadline:
        b = src.read(timeout=0.02)
        if b is not None and len(b):
            blocks.append(b)
            quiet_since = None
        elif emitter.done.is_set():
            quiet_since = quiet_since or time.monotonic()
            if time.monotonic() - quiet_since >= quiet_s:
                break
    assert emitter.wait(0), "the emitter did not finish in time"
    return blocks


def test_can_frames_lost_give_exactly_the_complete_samples_and_the_pipeline_goes_on():
    u = sim_unit(duration_s=3.0, seq_start=65000, faults={"can_drop_fraction": 0.05})
    n, per = u.n_samples, 3 * u.n_probes
    channel = f"fluxcal-faults-{uuid.uuid4().hex}"
    em = CanEmitter(u, channel=channel, realtime=False)
    pl = pipeline_for(u, initial=truth_calibration(u))
    outputs: list = []
    with CanSource(interface="virtual", channel=channel, n_probes=u.n_probes, rate_hz=u.rate_hz,
                   lsb_nT=u.lsb_nT, window_samples=32, window_s=0.1) as src:
        em.start()
        try:
            blocks = read_until_quiet(src, em, quiet_s=0.3)
        finally:
            em.close()
        counters = src.counters
        for b in blocks:                                  # the service's loop: every block, in order
            outputs.append(pl.process(b))
    rec = em.record

    # the record: which frames never went out; a sample is complete when all its 3n frames did
    dropped = rec.can_dropped()
    assert abs(dropped.shape[0] - 0.05 * n * per) < 4 * np.sqrt(0.05 * n * per)
    arrived = per - np.bincount(dropped[:, 0], minlength=n)
    complete = np.flatnonzero(arrived == per)
    np.testing.assert_array_equal(complete, np.setdiff1d(np.arange(n), rec.can_incomplete()))
    assert 0.2 * n < n - complete.size < 0.35 * n              # 1 - 0.95^6 = 26.5 % of the samples

    got = SampleBlock.concat(blocks)
    want = u.digitise(0, n).to_block()
    np.testing.assert_array_equal(got.seq, want.seq[complete])          # across the seq wrap at 536
    assert got.seq[-1] > 65536
    np.testing.assert_array_equal(got.field_nT, want.field_nT[complete])
    np.testing.assert_array_equal(got.temp_C, want.temp_C[complete])
    np.testing.assert_array_equal(got.t_s, want.seq[complete] / u.rate_hz)   # CAN: t from seq and rate

    # counters: frames that arrived, samples given up (some but not all frames came), gaps in seq
    assert counters.frames_accepted == n * per - dropped.shape[0]
    assert counters.can_incomplete == int(np.count_nonzero((arrived > 0) & (arrived < per)))
    assert (counters.seq_gaps, counters.samples_missed) == gaps_of(complete)

    # the pipeline went on through every gap: one corrected sample per delivered sample, equal to the
    # world's field (truth calibration) within the probes' noise, and the estimator saw each of them once
    cor = [o.corrected for o in outputs if o.corrected is not None]
    seq = np.concatenate([c.seq for c in cor])
    np.testing.assert_array_equal(seq, got.seq)
    corrected = np.concatenate([c.corrected_nT for c in cor])
    err = corrected - u.world.samples(0, n).field_platform_nT[complete]
    assert np.sqrt(np.mean(err ** 2)) < 0.6 and np.abs(err).max() < 3.5, np.sqrt(np.mean(err ** 2))
    pl.flush_estimator()
    assert pl._estimators[0].n_samples_ == complete.size
    assert all(np.isfinite(v) for o in outputs for v in o.error.values())
    print(f"CAN frames dropped {dropped.shape[0]}/{n * per}, samples complete {complete.size}/{n}, "
          f"rms error {np.sqrt(np.mean(err ** 2)):.3f} nT; {counters}")


# --- 3. seq and unit clock wraps on the serial path --------------------------------------------------
# (CAN: tests/drivers/test_can_source.py crosses the seq wrap with loss and interleaving; serial: test_serial_source
# crosses both wraps with clean frames. Here: the simulated unit, random damage, and whole runs of frames
# lost exactly across each wrap, over a pty and with block boundaries exactly at the wraps.)

def test_serial_seq_and_clock_wraps_with_frames_lost_across_them_stay_monotonic(pty_port):
    seq_wrap, clock_wrap = 300, 600                    # sample indices where seq and t_us pass 0
    u = sim_unit(duration_s=1.0, rate_hz=1000.0, seq_start=65536 - seq_wrap, t_us_start=2**32 - clock_wrap * 1000,
                 faults={"drop_frame_fraction": 0.03, "bitflip_fraction": 0.02, "garbage_fraction": 0.05})
    n = u.n_samples
    skipped = [(seq_wrap - 3, seq_wrap + 4), (clock_wrap - 2, clock_wrap + 3)]    # never sent
    edges = [0] + [x for r in skipped for x in r] + [n]
    rec = FaultRecord()
    segments = [u.serial_bytes(a, b, record=rec) for a, b in zip(edges[::2], edges[1::2])]
    lost = np.union1d(rec.serial_lost(), np.concatenate([np.arange(a, b) for a, b in skipped]))
    keep = np.setdiff1d(np.arange(n), lost)
    want = u.digitise(0, n)
    assert want.seq_raw[seq_wrap] == 0 and want.t_us_raw[clock_wrap] == 0 and want.t_us_raw[clock_wrap - 1] > 2**31

    def check(got: SampleBlock, counters: Counters) -> None:
        np.testing.assert_array_equal(got.seq, want.seq[keep])                 # unwrapped: 65536 + ...
        np.testing.assert_array_equal(got.t_s, want.t_us[keep] / 1e6)          # exact microseconds, unwrapped
        assert np.all(np.diff(got.seq) >= 1) and np.all(np.diff(got.t_s) > 0)
        np.testing.assert_array_equal(np.diff(got.seq), np.diff(keep))        # gaps as long as the loss
        assert got.seq[-1] > 65536 and got.t_s[-1] > 2**32 / 1e6
        np.testing.assert_array_equal(got.field_nT, want.to_block().field_nT[keep])
        assert counters.frames_accepted == keep.size
        assert (counters.seq_gaps, counters.samples_missed) == gaps_of(keep)

    # the framer fed segment by segment: block boundaries fall exactly on the wraps
    counters = serial_icd_counters()
    framer, assembler = SerialFramer(2, counters), FrameAssembler(2, u.lsb_nT, counters)
    blocks = [assembler.block(framer.feed(seg)) for seg in segments] + [assembler.block(framer.finish())]
    check(SampleBlock.concat(blocks), counters)

    # the serial source on a pty, the bytes written in chunks that split frames anywhere
    port = pty_port()
    with SerialSource(port.path, n_probes=2, lsb_nT=u.lsb_nT) as src:
        port.write(b"".join(segments), chunk=997)
        got, deadline = [], time.monotonic() + 10
        while sum(map(len, got)) < keep.size and time.monotonic() < deadline:
            b = src.read(timeout=0.2)
            if b is not None:
                got.append(b)
        check(SampleBlock.concat(got), src.counters)

    # the pipeline's outputs carry the unwrapped time, monotonic across both wraps
    pl = pipeline_for(u, initial=truth_calibration(u))
    outs = [pl.process(b) for b in got]
    t = np.concatenate([o.corrected.t_s for o in outs])
    np.testing.assert_array_equal(t, want.t_us[keep] / 1e6)
    print(f"wraps: {keep.size}/{n} samples kept, seq {got[0].seq[0]}..{got[-1].seq[-1]}, "
          f"t {got[0].t_s[0]:.6f}..{got[-1].t_s[-1]:.6f} s")


# --- 4. saturated axes through the service pipeline ---------------------------------------------------

def serial_blocks(u: Unit, counts: np.ndarray, temp_raw: np.ndarray, flags: np.ndarray, sizes) -> tuple[list, Counters]:
    """The unit's samples (with counts, temperatures and flags as given) as ICD frames through the
    serial driver's framer and assembler, cut into blocks of the given sizes (cycled)."""
    n = counts.shape[0]
    seq = (u.config.seq_start + np.arange(n)) & 0xFFFF
    t_us = (u.config.t_us_start + np.rint(np.arange(n) * (1e6 / u.rate_hz)).astype(np.int64)) & 0xFFFFFFFF
    data = icd.encode_serial(seq, t_us, counts, temp_raw, flags)
    counters = serial_icd_counters()
    framer, assembler = SerialFramer(u.n_probes, counters), FrameAssembler(u.n_probes, u.lsb_nT, counters)
    blocks, i, k, fl = [], 0, 0, u.frame_length
    while i < n:
        m = sizes[k % len(sizes)]
        frames = framer.feed(data[i * fl:(i + m) * fl])
        blocks.append(assembler.block(frames))
        i, k = i + m, k + 1
    return blocks, counters


def run_pipeline(pl: Pipeline, blocks: list[SampleBlock], add_effect: tuple[str, int] | None = None) -> list:
    """Process the blocks in order; add an effect (name, i) between samples i - 1 and i of the stream
    (splitting the block there, as a replay applying the recorded command does)."""
    outs, i = [], 0
    for b in blocks:
        parts = [b]
        if add_effect is not None and i < add_effect[1] < i + len(b):
            parts = [b.slice(0, add_effect[1] - i), b.slice(add_effect[1] - i, len(b))]
        for part in parts:
            if add_effect is not None and i >= add_effect[1] and add_effect[0] not in pl.effects:
                pl.command("add-effect", add_effect[0], seq=int(part.seq[0]), t_s=float(part.t_s[0]))
            outs.append(pl.process(part))
            i += len(part)
    return outs


def corrected_of(outs: list) -> "tuple[np.ndarray, np.ndarray, np.ndarray | None]":
    cor = [o.corrected for o in outs if o.corrected is not None]
    return (np.concatenate([c.seq for c in cor]), np.concatenate([c.corrected_nT for c in cor]),
            np.concatenate([c.diff_nT for c in cor]) if cor[0].diff_nT is not None else None)


# a block in which a probe is saturated throughout has no error figure for it: NaN (null on the bus)
def test_saturated_axes_do_not_corrupt_the_estimator_and_come_out_as_nan():
    # |B| = 50,000 nT and a probe range of 47,000 nT: near an axis the unit saturates (bit0, rails)
    # the probes also drift a little with temperature (±0.45 nT over the 3 degC swings, below what would
    # bias the linear estimate checked here): the live effect added later has something to correct, as it
    # must (add-effect refuses an effect the data do not show)
    probes = [dict(p, temp_offset_nT_per_C=c) for p, c in zip(sim_unit().config_table["probes"],
                                                              ([0.15, -0.12, 0.09], [-0.1, 0.14, 0.08]))]
    u = sim_unit(duration_s=30.0, rate_hz=200.0, range_nT=47000.0, field={"total_nT": 50000.0}, probes=probes,
                 temperature={"start_C": 21.0, "amplitude_C": 3.0, "period_s": 2.0, "reference_C": 21.0})
    n = u.n_samples
    s = u.digitise(0, n)
    counts, flags = s.counts.copy(), s.flags.copy()
    stretch = slice(2000, 2400)                       # and 2 s with a magnet next to s2: every axis on the rail
    counts[stretch, 1, :] = icd.SATURATED_COUNTS[0]
    flags[stretch] |= FLAG_SATURATED
    sat_axis = (counts == icd.SATURATED_COUNTS[0]) | (counts == icd.SATURATED_COUNTS[1])
    sat = sat_axis.any(axis=2)                                         # (N, P) probe has a saturated axis
    assert 0.1 < sat[:, 0].mean() < 0.4 and 0.1 < sat[:, 1].mean() < 0.4
    blocks, counters = serial_blocks(u, counts, s.temp_raw, flags, sizes=(37, 5, 120))

    # the driver: NaN exactly on the saturated axes, flags as sent, counted
    got = SampleBlock.concat(blocks)
    np.testing.assert_array_equal(np.isnan(got.field_nT), sat_axis)
    np.testing.assert_array_equal(got.flags & FLAG_SATURATED != 0, sat.any(axis=1))
    assert counters.saturated_axes == int(sat_axis.sum())

    pl = pipeline_for(u, min_samples=2000, window_samples=6000)
    outs = run_pipeline(pl, blocks[:len(blocks) * 2 // 3])
    # the estimator took exactly the unsaturated samples of each probe, and its calibration is the truth
    pl.flush_estimator()
    np.testing.assert_array_equal([e.n_samples_ for e in pl._estimators], (~sat[:pl.next_seq]).sum(axis=0))
    assert pl.calibration is not None and pl.calibration.method == "rls"
    truth = truth_calibration(u)
    d_offs = [np.round(p.offset_nT - t.offset_nT, 3).tolist() for p, t in zip(pl.calibration.probes, truth.probes)]
    for est, got_p, want in zip(pl._estimators, pl.calibration.probes, truth.probes):
        d_off = got_p.offset_nT - want.offset_nT
        assert np.all(np.abs(d_off) < 4 * est.offset_se_ + 0.02), (d_off, est.offset_se_)
        # the shape of the ellipsoid (M^T M, whatever rotation the alignment chose) to 1e-5
        np.testing.assert_allclose(got_p.matrix.T @ got_p.matrix, want.matrix.T @ want.matrix, atol=1e-5)

    # outputs: a probe with a saturated axis comes out NaN (all three axes: the matrix mixes them), the
    # other probe's output stays finite and right; differences are NaN where either probe saturated
    outs += run_pipeline(pl, blocks[len(blocks) * 2 // 3:], add_effect=("temperature", 0))
    assert pl.effects == ["temperature"]
    seq, corrected, diff = corrected_of(outs)
    rows = seq - u.config.seq_start
    np.testing.assert_array_equal(np.isnan(corrected).any(axis=2), sat[rows])
    np.testing.assert_array_equal(np.isnan(corrected).all(axis=2), sat[rows])
    np.testing.assert_array_equal(np.isnan(diff[:, 0]).any(axis=1), sat[rows].any(axis=1))
    b_true = np.linalg.norm(s.world.field_platform_nT[rows], axis=2)
    ok = ~sat[rows]
    scalar_err = np.linalg.norm(corrected, axis=2)[ok] - b_true[ok]
    assert np.sqrt(np.mean(scalar_err ** 2)) < 0.7, np.sqrt(np.mean(scalar_err ** 2))
    after = rows >= pl.next_seq - n // 3
    assert np.isnan(corrected[after]).any() and np.isfinite(corrected[after][~sat[rows][after]]).all()
    # the per-block error figures: NaN exactly for a probe (and its differences) saturated all block long
    for o in outs:
        if o.corrected is None:
            continue
        whole = sat[o.corrected.seq - u.config.seq_start].all(axis=0)
        for k, name in enumerate(("s1", "s2")):
            assert np.isnan(o.error[f"{name}.scalar"]) == whole[k]
        assert all(np.isnan(o.error[f"s2-s1.{ax}"]) == whole.any() for ax in "xyz")
    assert any(np.isnan(o.error.get("s2.scalar", 0.0)) for o in outs)           # the magnet stretch
    print(f"saturated samples s1 {sat[:, 0].mean():.3f} s2 {sat[:, 1].mean():.3f}, axes {counters.saturated_axes}; "
          f"offset errors {d_offs} nT; "
          f"scalar rms {np.sqrt(np.mean(scalar_err ** 2)):.3f} nT")


# --- 5. temperature-invalid samples ---------------------------------------------------------------------

TEMP_COEFF = ([3.0, -2.0, 1.5], [-1.0, 2.0, 0.5])        # nT/degC per axis, probes s1 and s2


def test_invalid_temperatures_never_reach_the_temperature_effect():
    u = sim_unit(duration_s=40.0, rate_hz=200.0, faults={"temp_invalid_fraction": 0.1},
                 temperature={"start_C": 20.0, "amplitude_C": 6.0, "period_s": 10.0, "reference_C": 20.0},
                 probes=[{"position_m": [-0.25, 0, 0], "offset_nT": [150.0, -80.0, 40.0], "noise_nT": 0.5,
                          "temp_offset_nT_per_C": TEMP_COEFF[0]},
                         {"position_m": [0.25, 0, 0], "offset_nT": [-120.0, 60.0, 210.0], "scale": [1.01, 0.99, 1.0],
                          "noise_nT": 0.5, "temp_offset_nT_per_C": TEMP_COEFF[1]}])
    n = u.n_samples
    s = u.digitise(0, n)
    invalid = (s.flags & FLAG_TEMP_INVALID) != 0
    assert abs(invalid.mean() - 0.1) < 0.02
    # what a broken sensor reads while the unit flags it: 327.67 degC. Were it used, the temperature
    # effect would move those samples by some 300 degC x 3 nT/degC = 900 nT
    temp_raw = s.temp_raw.copy()
    temp_raw[invalid] = 32767
    # the live service's blocks are short (a few samples at 200 Hz): single samples among them
    blocks, counters = serial_blocks(u, s.counts, temp_raw, s.flags, sizes=(1, 7, 3, 1, 50, 2))

    got = SampleBlock.concat(blocks)
    np.testing.assert_array_equal(np.isnan(got.temp_C), np.repeat(invalid[:, None], 2, axis=1))
    np.testing.assert_array_equal(got.temp_C[~invalid], s.temp_raw[~invalid] * 0.01)
    assert counters.temp_invalid == int(invalid.sum())

    add_at = 4000
    pl = pipeline_for(u, initial=truth_calibration(u), window_samples=4000)
    outs = run_pipeline(pl, blocks, add_effect=("temperature", add_at))
    assert pl.effects == ["temperature"]
    # the coefficients fitted over the ring buffer (10 % of its temperatures invalid) are the truth
    fitted = {p.name: (p.value, p.stderr) for p in pl.effect_fit.parameters if p.name.endswith("nT/degC")}
    for k, name in enumerate(("s1", "s2")):
        for a, ax in enumerate("xyz"):
            value, se = fitted[f"{name}.{ax} nT/degC"]
            assert abs(value - TEMP_COEFF[k][a]) < max(5 * se, 0.05), (name, ax, value, se)

    # every sample after the effect came in is corrected, the flagged ones as well as the others,
    # and to the noise: |corrected| against the true field at each probe
    seq, corrected, _ = corrected_of(outs)
    rows = seq - u.config.seq_start
    late = rows >= add_at + 200
    assert np.isfinite(corrected[late]).all()
    err = np.linalg.norm(corrected, axis=2) - np.linalg.norm(s.world.field_platform_nT[rows], axis=2)
    rms_flagged = float(np.sqrt(np.mean(err[late & invalid[rows]] ** 2)))
    rms_valid = float(np.sqrt(np.mean(err[late & ~invalid[rows]] ** 2)))
    rms_before = float(np.sqrt(np.mean(err[(rows > 1000) & (rows < add_at)] ** 2)))
    assert rms_valid < 0.7 and rms_flagged < 0.7 and np.abs(err[late]).max() < 4.0, (rms_valid, rms_flagged)
    assert rms_before > 3 * rms_valid                  # the effect was there to be corrected

    # and the same samples cut into other blocks give the same output, bit for bit (replay = live)
    again, _ = serial_blocks(u, s.counts, temp_raw, s.flags, sizes=(400,))
    pl2 = pipeline_for(u, initial=truth_calibration(u), window_samples=4000)
    seq2, corrected2, _ = corrected_of(run_pipeline(pl2, again, add_effect=("temperature", add_at)))
    np.testing.assert_array_equal(seq2, seq)
    np.testing.assert_array_equal(corrected2, corrected)
    print(f"temperature invalid {int(invalid.sum())}/{n}; rms before {rms_before:.3f}, after: valid {rms_valid:.3f}, "
          f"flagged {rms_flagged:.3f} nT; fitted {({k: round(v[0], 3) for k, v in fitted.items()})}")


def test_an_effect_the_data_do_not_show_is_not_added_live():
    # adding drift to data without drift would fit noise and then extrapolate it block after block: the
    # service refuses it and keeps correcting as before; an effect that is there is added
    u = sim_unit(duration_s=30.0, rate_hz=200.0,
                 temperature={"start_C": 20.0, "amplitude_C": 6.0, "period_s": 10.0, "reference_C": 20.0})
    b = u.digitise(0, u.n_samples).to_block()
    for effect in ("drift", "nonlinearity", "temperature"):
        pl = pipeline_for(u, initial=truth_calibration(u))
        pl.process(b.slice(0, 4000))
        cal_id = pl.cal_id
        with pytest.raises(FluxcalError, match=f"do not show {effect}: none of its 12 parameters is 3 standard errors"):
            pl.command("add-effect", effect, seq=int(b.seq[4000]), t_s=float(b.t_s[4000]))
        assert pl.effects == [] and pl.cal_id == cal_id
        assert pl.process(b.slice(4000, 4100)).corrected.n_samples == 100
    probes = [dict(p, temp_offset_nT_per_C=c) for p, c in zip(u.config_table["probes"], TEMP_COEFF)]
    v = sim_unit(duration_s=30.0, rate_hz=200.0, probes=probes,
                 temperature={"start_C": 20.0, "amplitude_C": 6.0, "period_s": 10.0, "reference_C": 20.0})
    c = v.digitise(0, v.n_samples).to_block()
    pl = pipeline_for(v, initial=truth_calibration(v))
    pl.process(c.slice(0, 4000))
    pl.command("add-effect", "temperature", seq=int(c.seq[4000]), t_s=float(c.t_s[4000]))
    assert pl.effects == ["temperature"]


def test_missing_reference_readings_do_not_stop_effect_correction():
    # ref_total (a scalar magnetometer beside the array) drops out now and then: NaN in its column. It
    # enters the fit's comparison, never the corrected vector, so once an effect is live the output must
    # be exactly what it is with the readings present
    u = sim_unit(duration_s=20.0, rate_hz=200.0, reference={"enabled": True},
                 temperature={"start_C": 20.0, "amplitude_C": 6.0, "period_s": 10.0, "reference_C": 20.0},
                 probes=[{"offset_nT": [150.0, -80.0, 40.0], "noise_nT": 0.5, "temp_offset_nT_per_C": TEMP_COEFF[0]},
                         {"offset_nT": [-120.0, 60.0, 210.0], "noise_nT": 0.5,
                          "temp_offset_nT_per_C": TEMP_COEFF[1]}])
    whole = u.digitise(0, u.n_samples).to_block()
    assert "ref_total" in whole.extras
    sizes = np.r_[1, 7, 3, 50, 2, 1, 20]
    cuts = np.cumsum(np.resize(sizes, u.n_samples // 4))
    cuts = cuts[cuts < u.n_samples]
    pieces = [whole.slice(a, b) for a, b in zip(np.r_[0, cuts], np.r_[cuts, u.n_samples])]
    add_at = 2000
    holed = []
    for b in pieces:
        ref = b.extras["ref_total"].copy()
        late = b.seq - u.config.seq_start >= add_at + 100
        ref[late & (np.arange(b.n_samples) % 3 == 0)] = np.nan       # a third of the readings, whole blocks too
        if b.n_samples == 1 and late.all():
            ref[:] = np.nan
        holed.append(SampleBlock(b.t_s, b.seq, b.field_nT, b.temp_C, b.flags, {**b.extras, "ref_total": ref}))
    assert sum(np.isnan(b.extras["ref_total"]).sum() for b in holed) > 500
    want = corrected_of(run_pipeline(pipeline_for(u, initial=truth_calibration(u)), pieces,
                                     add_effect=("temperature", add_at)))
    got = corrected_of(run_pipeline(pipeline_for(u, initial=truth_calibration(u)), holed,
                                    add_effect=("temperature", add_at)))
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert np.isfinite(got[1]).all()


# --- 6. Zenoh: a client and a router that go away and come back ----------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(cond, timeout: float = 10.0, what: str = "condition") -> float:
    """Wait for cond(); the seconds it took."""
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)
    return time.monotonic() - t0


class ServiceLoop:
    """The daemon's publishing side, in a thread: the simulated unit's samples as raw blocks of 5, one
    every 2 ms, commands and state queries served between blocks. Stops by itself after `max_s`."""

    BLOCK = 5

    def __init__(self, bus: ServiceBus, u: Unit, max_s: float = 30.0) -> None:
        self.bus, self.max_s = bus, max_s
        self.truth = u.digitise(0, u.n_samples).to_block()
        self.sent = 0                                     # blocks published
        self.slowest_s = 0.0                              # longest single publish
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="fluxcal-test-service")
        self.thread.start()

    #: after the unit's last sample, start over with seq and time carried on (a long run from a short simulation)
    REPEAT = False

    def block(self, i: int) -> SampleBlock:
        per = self.truth.n_samples // self.BLOCK
        if not self.REPEAT or i < per:
            return self.truth.slice(i * self.BLOCK, (i + 1) * self.BLOCK)
        turn, j = divmod(i, per)
        b = self.truth.slice(j * self.BLOCK, (j + 1) * self.BLOCK)
        span = per * self.BLOCK
        return SampleBlock(t_s=b.t_s + turn * span * float(self.truth.t_s[1] - self.truth.t_s[0]),
                           seq=b.seq + turn * span, field_nT=b.field_nT, temp_C=b.temp_C, flags=b.flags,
                           extras=b.extras)

    def _run(self) -> None:
        t_end = time.monotonic() + self.max_s
        try:
            while not self._stop.is_set() and time.monotonic() < t_end \
                    and (self.REPEAT or (self.sent + 1) * self.BLOCK <= self.truth.n_samples):
                for cmd in self.bus.pending_commands():
                    cmd.reply({"ok": True})
                t0 = time.monotonic()
                self.bus.publish_raw(self.block(self.sent))
                self.slowest_s = max(self.slowest_s, time.monotonic() - t0)
                self.sent += 1
                self._stop.wait(0.002)
        except BaseException as e:                       # reported by stop()
            self.error = e

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5.0)
        assert not self.thread.is_alive()
        if self.error is not None:
            raise self.error


def received_blocks(client: BusClient, k: int, loop: ServiceLoop, timeout: float = 10.0) -> list[int]:
    """Receive k raw blocks; each must be one the service sent, bit for bit; their block indices."""
    got: list[int] = []
    deadline = time.monotonic() + timeout
    while len(got) < k and time.monotonic() < deadline:
        m = client.recv(timeout=0.2)
        if m is None:
            continue
        b = m.value
        i = int(b.seq[0] - loop.truth.seq[0]) // loop.BLOCK
        want = loop.block(i)
        for name in ("t_s", "seq", "field_nT", "temp_C", "flags"):
            np.testing.assert_array_equal(getattr(b, name), getattr(want, name), err_msg=name)
        got.append(i)
    assert len(got) == k, f"received {len(got)} of {k} blocks"
    return got


def test_zenoh_client_that_goes_away_and_comes_back_hears_the_service_again():
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = ZenohConfig(mode="peer", listen=[ep])
    cfg.validate("zenoh")
    u = sim_unit(duration_s=30.0)
    with ExitStack() as stack:
        bus = stack.enter_context(ServiceBus(cfg, "grad1", per_probe=False))
        loop = ServiceLoop(bus, u)
        stack.callback(loop.stop)
        first = BusClient(ZenohConfig.client(ep), "grad1", streams=["raw"])
        try:
            wait_until(lambda: bus.has_subscribers("raw"), what="the first client")
            got1 = received_blocks(first, 50, loop)
        finally:
            first.close()                                 # mid-stream: the service is publishing
        wait_until(lambda: not bus.has_subscribers("raw"), what="the service to see the client gone")
        gone_at = loop.sent
        time.sleep(0.3)
        assert loop.sent > gone_at + 20                    # nobody listening: the service went on
        second = stack.enter_context(BusClient(ZenohConfig.client(ep), "grad1", streams=["raw"]))
        back_s = wait_until(lambda: bus.has_subscribers("raw"), what="the second client")
        got2 = received_blocks(second, 50, loop)
        assert second.query_state(timeout=2.0)["unit"] == "grad1"
        loop.stop()
    # each client heard an unbroken run of blocks (BLOCK streams lose nothing), the second one later
    assert np.all(np.diff(got1) == 1) and np.all(np.diff(got2) == 1)
    assert got2[0] > got1[-1] + 20
    # every block was put, or not made while no subscriber matched the stream (counted: those the gap lost)
    assert bus.stats["publish_errors"] == 0 and bus.stats["published_raw"] + bus.stats["unheard_raw"] == loop.sent
    assert bus.stats["unheard_raw"] > 20
    assert loop.slowest_s < 1.0, loop.slowest_s
    print(f"client back: matched after {back_s:.3f} s; blocks {got1[0]}..{got1[-1]} then {got2[0]}..{got2[-1]} "
          f"of {loop.sent}; slowest publish {loop.slowest_s * 1e3:.1f} ms")


@pytest.mark.parametrize("unit_mode", ["client", "peer"])
def test_zenoh_router_closed_and_reopened_on_the_same_port_relays_again(unit_mode):
    """unit -> router <- dashboard; the router goes down and comes back on the same port: zenoh 1.x
    sessions reconnect to their configured connect endpoints by themselves."""
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    router_cfg = load_section(ZenohConfig, {"mode": "router", "listen": [router_ep]}, "zenoh")
    unit_table = {"mode": unit_mode, "connect": [router_ep]}
    if unit_mode == "peer":
        unit_table["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    u = sim_unit(duration_s=30.0)
    with ExitStack() as stack:
        router = open_session(router_cfg)
        stack.callback(lambda: router.close())
        bus = stack.enter_context(ServiceBus(load_section(ZenohConfig, unit_table, "zenoh"), "far1", per_probe=False))
        loop = ServiceLoop(bus, u)
        stack.callback(loop.stop)
        dash = stack.enter_context(BusClient(ZenohConfig.client(router_ep), "far1", streams=["raw"]))
        wait_until(lambda: bus.has_subscribers("raw"), what="the dashboard through the router")
        got1 = received_blocks(dash, 30, loop)

        router.close()                                     # the site's router goes down
        wait_until(lambda: not bus.has_subscribers("raw"), what="the service to lose the route")
        down_at = loop.sent
        time.sleep(0.3)
        assert loop.sent > down_at + 20 and loop.error is None      # publishing into the void, no error

        router = open_session(router_cfg)                  # and comes back on the same port
        back_s = wait_until(lambda: bus.has_subscribers("raw"), timeout=15.0,
                            what="the unit and the dashboard to reconnect to the router")
        dash.drain()
        got2 = received_blocks(dash, 30, loop)
        assert dash.alive() and dash.query_state(timeout=2.0)["unit"] == "far1"
        loop.stop()
    assert np.all(np.diff(got1) == 1) and np.all(np.diff(got2) == 1)
    assert got2[0] > got1[-1] + 20                          # what was published while it was down is gone
    # every block was put, or not made while no subscriber matched the stream (counted: those the gap lost)
    assert bus.stats["publish_errors"] == 0 and bus.stats["published_raw"] + bus.stats["unheard_raw"] == loop.sent
    assert bus.stats["unheard_raw"] > 20
    assert loop.slowest_s < 1.0, loop.slowest_s
    print(f"router back ({unit_mode}): relaying again {back_s:.3f} s after it reopened; blocks {got1[0]}..{got1[-1]} "
          f"then {got2[0]}..{got2[-1]}; slowest publish {loop.slowest_s * 1e3:.1f} ms")


_FROZEN_CLIENT = """
import sys, time
from fluxcal.service.io.bus import BusClient, ZenohConfig
with BusClient(ZenohConfig.client(sys.argv[1]), "grad1", streams=["raw"], lossless=True) as c:
    print("ready", flush=True)
    while True:
        c.recv(timeout=0.1)
"""


def test_a_frozen_dashboard_never_holds_the_service_back():
    # a dashboard process stopped dead (SIGSTOP: a hung laptop, a debugger) with a lossless subscription
    # on the raw stream: its TCP window closes and nothing it is sent gets read. The service's publishing
    # must go on at its pace, without errors, and a dashboard that connects afterwards hears it as usual
    ep = f"tcp/127.0.0.1:{free_port()}"
    u = sim_unit(duration_s=100.0, rate_hz=1000.0)                 # 500 blocks, sent over and over (BigBlocks)
    with ExitStack() as stack:
        bus = stack.enter_context(ServiceBus(ZenohConfig(listen=[ep]), "grad1", per_probe=False))
        proc = subprocess.Popen([sys.executable, "-c", _FROZEN_CLIENT, ep], stdout=subprocess.PIPE, text=True,
                                cwd=str(Path(__file__).resolve().parents[2]))
        stack.callback(lambda: (proc.kill(), proc.wait(10)))
        assert proc.stdout.readline().strip() == "ready"
        loop = BigBlocks(bus, u)
        stack.callback(loop.stop)
        wait_until(lambda: bus.has_subscribers("raw"), what="the dashboard")
        healthy_at, t0 = loop.sent, time.monotonic()
        time.sleep(2.0)
        healthy_rate = (loop.sent - healthy_at) / (time.monotonic() - t0)
        os.kill(proc.pid, signal.SIGSTOP)
        frozen_at, t0 = loop.sent, time.monotonic()
        time.sleep(5.0)
        sent_frozen, wall = loop.sent - frozen_at, time.monotonic() - t0
        payload = len(encode_raw(loop.block(0)))
        proc.kill()
        proc.wait(10)
        late = stack.enter_context(BusClient(ZenohConfig.client(ep), "grad1", streams=["raw"]))
        wait_until(lambda: bus.has_subscribers("raw"), what="a new dashboard")
        got = received_blocks(late, 30, loop)
        loop.stop()
    # at its pace: as many blocks a second as while the dashboard was reading (within the machine's noise)
    assert sent_frozen / wall > 0.7 * healthy_rate, (sent_frozen / wall, healthy_rate)
    assert sent_frozen * payload > 5e6                                   # megabytes the frozen one never read
    assert loop.slowest_s < 0.5, loop.slowest_s
    # every block was put, or not made while no subscriber matched the stream (counted)
    assert bus.stats["publish_errors"] == 0 and bus.stats["published_raw"] + bus.stats["unheard_raw"] == loop.sent
    assert np.all(np.diff(got) == 1)
    # what the frozen reader held up beyond the bus's 16 MB backlog was dropped from the bus (never from the
    # recording) and counted
    assert bus.stats["send_dropped"] < sent_frozen / 2               # a bounded loss, not the whole stream
    print(f"frozen dashboard: {sent_frozen} blocks ({sent_frozen * payload / 1e6:.1f} MB) published in {wall:.1f} s "
          f"while it was stopped ({sent_frozen / wall:.0f}/s; {healthy_rate:.0f}/s before); slowest publish "
          f"{loop.slowest_s * 1e3:.1f} ms; {bus.stats['send_dropped']} blocks dropped from the bus's backlog")


class BigBlocks(ServiceLoop):
    """ServiceLoop with 200-sample blocks (about 10 kB each): a frozen reader's buffers fill in seconds. The
    unit's samples are sent over and over, seq carried on, for as long as the test runs."""

    BLOCK = 200
    REPEAT = True


# --- 7. damaged MCAP recordings (hypothesis) -------------------------------------------------------------

PROPERTY = settings(max_examples=int(os.environ.get("FLUXCAL_PROPERTY_EXAMPLES", "150")), deadline=None,
                    derandomize=True, suppress_health_check=[HealthCheck.too_slow])


class SmallRecording:
    """The intact file written by the project's own logger, what was written into it block by block,
    the byte offsets of its records' headers (u8 opcode, u64 length) and where its data section ends
    (after the Data End record). Not a dataclass: hypothesis prints its arguments, and these are big."""

    def __init__(self, path: Path, data: bytes, raw: list, corrected: list, heads: list[int], data_end: int,
                 workdir: Path) -> None:
        self.path, self.data, self.raw, self.corrected = path, data, raw, corrected
        self.heads, self.data_end, self.workdir = heads, data_end, workdir

    def __repr__(self) -> str:
        return f"SmallRecording({self.path.name}, {len(self.data)} bytes, {len(self.heads)} records)"


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory) -> SmallRecording:
    """1 s of the simulated gradiometer through the pipeline into McapLogger: 20 raw and 20 corrected
    blocks in some 20 lz4 chunks of 2 kB, plus metadata, events and health."""
    d = tmp_path_factory.mktemp("mcap-faults")
    u = sim_unit(duration_s=1.0, rate_hz=200.0)
    data = u.digitise(0, u.n_samples).to_block()
    pl = pipeline_for(u, initial=truth_calibration(u))
    log = McapLogger(d / "rec.mcap", unit="u", chunk_size=2048, flush_interval_s=60.0, epoch_ns=0,
                     metadata={"probe_names": json.dumps(["s1", "s2"])})
    raw, corrected = [], []
    for i in range(0, data.n_samples, 10):
        b = data.slice(i, i + 10)
        out = pl.process(b)
        log.write_raw(b)
        log.write_corrected(out.corrected)
        raw.append(b)
        corrected.append(out.corrected)
        if i == 100:
            log.write_event({"kind": "command", "seq": int(b.seq[-1]) + 1, "name": "freeze"})
            log.write_health({"frames_accepted": i + 10})
    log.close()
    path = Path(log.files[0])
    blob = path.read_bytes()
    heads, pos = [], 8
    while pos + 9 <= len(blob) - 8:                      # the records between the two magics
        heads.append(pos)
        pos += 9 + int.from_bytes(blob[pos + 1:pos + 9], "little")
    rec = read_recording(path)                           # the intact file reads back whole
    assert len(rec.raw_blocks) == len(raw) == 20 and not rec.truncated
    assert sum(1 for h in heads if blob[h] == 0x06) >= 10                  # chunks (opcode 6)
    end = [h + 9 + int.from_bytes(blob[h + 1:h + 9], "little") for h in heads if blob[h] == 0x0F]   # Data End
    return SmallRecording(path, blob, raw, corrected, heads, end[0], d)


def assert_same_block(got, want) -> None:
    for name in ("t_s", "seq", "field_nT", "temp_C", "flags", "corrected_nT", "diff_nT", "center_nT"):
        if hasattr(want, name) and getattr(want, name) is not None:
            a, b = getattr(got, name), getattr(want, name)
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name


def read_or_refuse(path: Path) -> "Any | None":
    """read_recording(path), or None when it refused with the project's error naming the file; any other
    exception fails the test."""
    try:
        return read_recording(path)
    except FluxcalError as e:                              # RecordingError is one
        assert isinstance(e, RecordingError), type(e)
        assert path.name in str(e) and len(str(e)) > len(str(path)) + 10, str(e)
        return None


def assert_prefix(rec, small: SmallRecording, noted: bool = True) -> None:
    """The recording holds the first k raw blocks written (and corrected ones), exactly; if some are
    missing, the reader says so (a cut tail in `truncated`, or a warning) unless `noted` is False."""
    assert len(rec.raw_blocks) <= len(small.raw) and len(rec.corrected_blocks) <= len(small.corrected)
    if noted and (len(rec.raw_blocks) < len(small.raw) or len(rec.corrected_blocks) < len(small.corrected)):
        assert rec.truncated or rec.warnings, "blocks lost without a word"
    for got, want in zip(rec.raw_blocks, small.raw):
        assert_same_block(got, want)
    for got, want in zip(rec.corrected_blocks, small.corrected):
        assert_same_block(got, want)


def assert_subsequence(rec, small: SmallRecording) -> None:
    """Every block read is one written, exactly, in the order written (a repaired file may lack chunks)."""
    for got_blocks, written in ((rec.raw_blocks, small.raw), (rec.corrected_blocks, small.corrected)):
        index = {int(b.seq[0]): k for k, b in enumerate(written)}
        ks = [index.get(int(b.seq[0]), -1) for b in got_blocks]
        assert -1 not in ks and ks == sorted(set(ks))
        for b, k in zip(got_blocks, ks):
            assert_same_block(b, written[k])


def assert_said(rec, small: SmallRecording) -> None:
    """Every block read is one written, exactly, in order (damage is read past: blocks may be missing in the
    middle), and if any is missing the reader says so (a cut tail, damage, a hole)."""
    assert_subsequence(rec, small)
    if len(rec.raw_blocks) < len(small.raw) or len(rec.corrected_blocks) < len(small.corrected):
        assert rec.truncated or rec.warnings, "blocks lost without a word"


def check_damaged(small: SmallRecording, damaged: bytes, name: str) -> tuple[object, object]:
    path = small.workdir / f"{name}.mcap"
    path.write_bytes(damaged)
    rec = read_or_refuse(path)
    if rec is not None:
        assert_said(rec, small)
    # and the salvage: repair_recording either refuses with RecordingError or writes a finished file
    # that reads back without complaint, holding only blocks that were written, in order
    fixed = small.workdir / "fixed" / f"{name}.mcap"
    try:
        repair_recording(path, fixed)
    except FluxcalError as e:
        assert isinstance(e, RecordingError) and str(e), type(e)
        return rec, None
    again = read_or_refuse(fixed)
    if again is not None:
        assert not again.truncated and not again.report.damaged
        assert_subsequence(again, small)
    return rec, again


@PROPERTY
@given(data=st.data())
def test_a_truncated_recording_reads_as_a_prefix_or_is_refused(small_recording, data):
    small = small_recording
    cut = data.draw(st.one_of(st.integers(0, len(small.data)),
                              st.sampled_from(small.heads).flatmap(lambda h: st.integers(max(0, h - 2), h + 12))),
                    label="cut")
    rec, again = check_damaged(small, small.data[:cut], "cut")
    if rec is not None:
        assert_prefix(rec, small)                          # a cut loses the tail only
        # a cut file is a killed writer's: what was complete is there, and a cut in the data is reported
        assert bool(rec.truncated) == (cut < small.data_end)
        if cut >= small.data_end:                          # only the summary (index) was lost
            assert len(rec.raw_blocks) == len(small.raw)
        if again is not None:                              # the repair keeps exactly what was readable
            assert len(again.raw_blocks) == len(rec.raw_blocks)
            assert_prefix(again, small, noted=False)       # the repair's own report said what was cut


@PROPERTY
@given(data=st.data())
def test_a_recording_with_flipped_bytes_is_read_past_said_or_refused(small_recording, data):
    small = small_recording
    anywhere = st.integers(8, len(small.data) - 1)
    # record headers (opcode and length) and the start of record bodies are where damage misleads most
    structure = st.sampled_from(small.heads).flatmap(lambda h: st.integers(h, h + 24))
    flips = data.draw(st.lists(st.tuples(st.one_of(anywhere, structure), st.integers(1, 255)),
                               min_size=1, max_size=4), label="flips")
    blob = bytearray(small.data)
    for pos, mask in flips:
        if pos < len(blob):
            blob[pos] ^= mask
    check_damaged(small, bytes(blob), "flipped")


def test_every_change_of_a_record_header_byte_is_read_past_and_reported(small_recording):
    """Deterministic companion of the property above, on the bytes that mislead a reader most: the
    opcode of a chunk, of its message index, of the metadata, header and data end records, turned into
    every other opcode and flipped bit by bit. A chunk read as a message index (0x06 ^ 0x01), a footer
    (^ 0x04), a message (^ 0x03) or a data end (^ 0x09) used to vanish without a word. The file is finished:
    its chunk index says where each record is, so every one is read whole and the damage said."""
    small = small_recording
    chunks = [h for h in small.heads if small.data[h] == 0x06]
    middle = chunks[len(chunks) // 2]
    after = [h for h in small.heads if h > middle]
    targets = [middle, after[0]] + [h for h in small.heads if small.data[h] in (0x01, 0x0C, 0x0F)]
    assert small.data[after[0]] == 0x07                              # the chunk's message index
    outcomes = {"refused": 0, "whole": 0, "lost, reported": 0}
    path = small.workdir / "opcode.mcap"
    for h in targets:
        op = small.data[h]
        for mask in sorted({op ^ v for v in range(0x01, 0x10)} | {1 << b for b in range(8)} | {0xFF}):
            blob = bytearray(small.data)
            blob[h] ^= mask
            path.write_bytes(blob)
            rec = read_or_refuse(path)
            if rec is None:
                outcomes["refused"] += 1
                continue
            assert_said(rec, small)
            outcomes["whole" if len(rec.raw_blocks) == len(small.raw) else "lost, reported"] += 1
            if len(rec.raw_blocks) == len(small.raw) and rec.raw_blocks and blob[h] != op:
                assert rec.report.damaged, f"damage read past without a word: opcode {op:#x} at {h} -> {blob[h]:#x}"
    assert outcomes["whole"] == sum(outcomes.values()) > 100
    print(f"record header bytes: {len(targets)} records, {outcomes}")
