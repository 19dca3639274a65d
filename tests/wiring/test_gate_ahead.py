"""A replay whose gate checks are worked out ahead in a second process (gate_ahead.py) is the replay of one process,
bit for bit: the corrected output, the calibrations and where they were replaced, the state, with commands
(freeze, unfreeze, reset, apply) between the checks. A second process that stops, or sends the checks of other
samples, costs the replay its help, never a result: the replay works those checks out itself and says why."""

from __future__ import annotations

import json
import os
import sys
import threading

import numpy as np
from test_replay_commands import SAMPLE, _live_run_with_a_command

from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.wiring.commands import replay, replay_run
from fluxcal.service.wiring.config import config_from_dict
from fluxcal.service.wiring.daemon import build_pipeline
from fluxcal.service.wiring.gate_ahead import MIN_CHECKS, gate_ahead_worth
from fluxcal.service.wiring.sinks import Sinks

LAB = ArrayCalibration("ellipsoid", "rotation", [ProbeCalibration(n, np.array([3.0, -2.0, 1.0]), np.eye(3))
                                                 for n in ("s1", "s2")])


def _replayed(path, ahead: bool):
    """replay's own loop over the recording: (samples, corrected seq and values as bytes, calibrations replaced,
    the state at the end as JSON, the gate)."""
    rec = read_recording(path)
    cfg = config_from_dict(json.loads(rec.metadata["config"]), "sample")
    initial, _, commands = replay._initial_and_commands(rec)
    pl = build_pipeline(cfg, initial)
    blocks = replay._coalesce(rec.raw, [c["seq"] for c in commands])
    errors: list[str] = []
    samples, seqs, vals, replaced = replay_run.run_blocks(pl, cfg, blocks, commands, Sinks([], errors.append),
                                                       ahead=ahead)
    assert not errors
    got = (samples, b"".join(s.tobytes() for s in seqs), b"".join(v.tobytes() for v in vals), replaced,
           json.dumps(pl.state(), sort_keys=True))
    return got, pl.gate


def test_the_checks_of_a_second_process_give_the_replay_of_one_bit_for_bit(tmp_path):
    """The sample's 6,000 samples are checked every 1,000, the first candidate usable at 5,000."""
    replaced = 0
    for k, commands in enumerate([((1500, "freeze", None), (2500, "unfreeze", None), (5500, "reset", None)),
                                  ((2500, "apply", LAB), (4500, "reset", None))]):
        live = tmp_path / f"live-{k}.mcap"
        _live_run_with_a_command(live, commands)
        alone, _ = _replayed(live, ahead=False)
        ahead, gate = _replayed(live, ahead=True)
        assert gate.fallback is None
        checks = [r for r in alone[3] if r[3] == "calibration"]
        replaced += len(checks)
        assert gate.taken >= max(1, 2 * len(checks))           # a candidate and its evaluation, from the second
        assert ahead == alone                                  # output, calibrations, state: bit for bit
    assert replaced >= 2                                       # candidates replaced the calibration on the way


def test_a_second_process_that_stops_or_strays_costs_help_never_a_result(tmp_path, monkeypatch):
    live = tmp_path / "live.mcap"
    _live_run_with_a_command(live)
    alone, _ = _replayed(live, ahead=False)
    feed = replay_run.feed

    def stops(pl, cfg, blocks, commands):
        feed(pl, cfg, blocks[:2], commands)
        raise RuntimeError("the second process was stopped")

    def strays(pl, cfg, blocks, commands):
        feed(pl, cfg, blocks[1:], commands)                    # its checks fall on other samples

    for run, why in ((stops, "RuntimeError: the second process was stopped"), (strays, "for another check")):
        monkeypatch.setattr(replay_run, "feed", run)
        got, gate = _replayed(live, ahead=True)
        assert gate.fallback is not None and why in gate.fallback, gate.fallback
        assert got == alone


def test_the_second_process_is_forked_only_where_it_is_safe_and_pays():
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    safe = sys.platform.startswith("linux") and cores >= 2 and threading.active_count() == 1
    assert gate_ahead_worth(MIN_CHECKS * 400, 400) is safe
    assert not gate_ahead_worth(MIN_CHECKS * 400 - 1, 400)       # too few checks to pay for the fork
    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    other.start()
    try:
        assert not gate_ahead_worth(10 ** 9, 400)               # a thread the fork would not copy: never
    finally:
        stop.set()
        other.join()


def test_the_sample_recording_replays_with_the_gate_ahead_as_alone():
    alone, _ = _replayed(SAMPLE, ahead=False)
    ahead, gate = _replayed(SAMPLE, ahead=True)
    assert gate.fallback is None and gate.taken > 0
    assert ahead == alone
