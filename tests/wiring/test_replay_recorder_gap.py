"""Replay says recorder gaps (issue 38, build 8): a live run whose recorder lost 15 s to a full disk (the recording's
own health counts the messages dropped) replays with the gap said before the comparison, only what both have
compared, and exit status 0 where the only differences are the gap's.

Before: replay exited 1 with "14,057 corrected samples differ ... more than rounding can explain", blaming the
pipeline, with no word of the 15 s missing.
"""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from test_recording import service_config

from fluxcal.service.io.recordings import writer as writer_mod
from fluxcal.service.io.recordings.gaps import recorder_gaps
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon

DISK_FULL_S = (30.0, 45.0)         # of unit time: after the calibration is usable (about 15 s)


def disk_full(monkeypatch) -> None:
    """Every message the recorder is handed within DISK_FULL_S of unit time is dropped as a full disk drops it
    (counted, the error kept: what ChunkedLog does while no file can be written), the health messages too."""
    real = writer_mod.ChunkedLog._write

    def write(self, stream, data, t_s):
        if t_s is not None:
            self._test_t = t_s
        if DISK_FULL_S[0] <= getattr(self, "_test_t", 0.0) < DISK_FULL_S[1]:
            self.messages += 1
            self.dropped += 1
            self.errors += 1
            self.last_error = "OSError: [Errno 28] No space left on device"
            return
        return real(self, stream, data, t_s)

    monkeypatch.setattr(writer_mod.ChunkedLog, "_write", write)


@pytest.fixture(scope="module")
def gapped(tmp_path_factory):
    """A live run of 60 s of the simulated unit (as fast as it reads) whose recorder lost 15 s in the middle."""
    tmp = tmp_path_factory.mktemp("gapped")
    mp = pytest.MonkeyPatch()
    try:
        disk_full(mp)
        cfg = load_config(service_config(tmp, run_s=60, realtime=False))
        daemon = Daemon(cfg, say=lambda m: None)
        result: list = []
        t = threading.Thread(target=lambda: result.append(daemon.run()))
        t.start()
        t.join(120)
        assert result == [0]
    finally:
        mp.undo()
    return Path(cfg.mcap.dir), cfg


def test_the_gap_is_found_from_the_recordings_own_health_and_sequence(gapped):
    rec_dir, cfg = gapped
    rec = read_recording(rec_dir)
    gaps = recorder_gaps(rec.raw_blocks, rec.health, rec.health_at)
    assert len(gaps) == 1
    g = gaps[0]
    rate = cfg.sim.rate_hz
    # the messages dropped are whole blocks (of a few hundred ms when the service reads as fast as it can)
    assert DISK_FULL_S[1] - DISK_FULL_S[0] - 1.0 < g.t_after - g.t_before < DISK_FULL_S[1] - DISK_FULL_S[0] + 1.0
    assert g.seq_after - g.seq_before - 1 == round((g.t_after - g.t_before) * rate) - 1
    assert g.samples == g.seq_after - g.seq_before - 1 and g.unit_missed == 0 and g.dropped > 100
    assert "No space left on device" in g.describe()


def test_every_command_reading_the_recording_says_the_gap_in_the_same_words(gapped, capsys):
    """Only replay said the gap: inspect gave the recording's samples over its span (136 Hz for a 200 Hz unit) and
    fit nothing (a field trial). Both readers (read_recording, read_samples) find it from the same messages, so
    inspect, fit and diagnose say it as replay does."""
    from fluxcal.service.io.recordings.reader import read_samples

    rec_dir, _ = gapped
    whole, samples = read_recording(rec_dir), read_samples(rec_dir)
    assert len(whole.gaps) == len(samples.gaps) == 1 and whole.gaps == samples.gaps
    said = whole.gaps[0].describe()
    assert said in whole.warnings and said in samples.warnings
    for command in (["inspect"], ["fit"], ["diagnose", "--max-samples", "20000"]):
        capsys.readouterr()
        main([*command, str(rec_dir)])
        out, err = capsys.readouterr()
        assert said in out + err, (command, out[-400:], err[-800:])


def test_replay_says_the_gap_compares_what_both_have_and_exits_0(gapped, capsys):
    rec_dir, _ = gapped
    assert main(["replay", str(rec_dir)]) == 0
    out, err = capsys.readouterr()
    said = err.split("\n")
    gap = next(i for i, line in enumerate(said) if "a recorder gap: the recording's own health says" in line)
    assert "raw sample(s) between seq" in said[gap] and "of unit time) are not in the recording" in said[gap]
    assert any("are not compared; those before are" in line for line in said[gap:])
    assert "differ" not in err, err
    compared = [line for line in out.split("\n") if line.startswith("corrected samples compared with the recording: ")]
    assert compared and int(compared[0].split(": ")[1].split(",")[0]) > 1000, out


def test_a_unit_that_lost_samples_itself_is_no_recorder_gap():
    """A jump of the counter across which the unit's own samples_missed grew as much: the unit's loss, which the live
    estimator did not see either; no health at all: nothing said."""
    import numpy as np

    from fluxcal.drivers.block import SampleBlock

    def block(a, b):
        n = b - a
        return SampleBlock(t_s=np.arange(a, b) / 100.0, seq=np.arange(a, b), field_nT=np.zeros((n, 1, 3)),
                           temp_C=np.zeros((n, 1)), flags=np.zeros(n, np.uint8))

    blocks = [block(0, 100), block(300, 400)]
    health = [{"counters": {"samples_missed": 0}, "recording": {"dropped": 0}},
              {"counters": {"samples_missed": 200}, "recording": {"dropped": 0}}]
    assert recorder_gaps(blocks, health, [1, 2]) == []
    assert recorder_gaps(blocks, [], []) == []
    health[1]["recording"]["dropped"] = 5                  # the recorder dropped messages too: only the excess
    assert recorder_gaps(blocks, health, [1, 2]) == []
    health[1]["counters"]["samples_missed"] = 150
    (g,) = recorder_gaps(blocks, health, [1, 2])
    assert (g.seq_before, g.seq_after, g.unit_missed, g.samples) == (99, 300, 150, 50)
