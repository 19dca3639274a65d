"""The service's outputs behind one contract: adding an output is one class, given to the daemon, which it tells
of everything the recording and the bus get; a failing output costs only itself."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_recording import service_config

from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon
from fluxcal.service.wiring.sinks import Sink


class Counting(Sink):
    """Counts what it is told: the test's new output."""

    name = "counting"

    def __init__(self) -> None:
        self.raw_samples = self.raw_blocks = self.corrected_samples = self.errors = self.health = 0
        self.events: list[str] = []
        self.turns: list[str] = []            # raw, corrected and flush in the order told
        self.closed = False

    def on_raw(self, block) -> None:
        self.raw_blocks += 1
        self.raw_samples += block.n_samples
        self.turns.append("raw")

    def on_corrected(self, block) -> None:
        self.corrected_samples += block.n_samples
        self.turns.append("corrected")

    def on_error(self, rms_nT, *, seq, t_s, n) -> None:
        self.errors += 1

    def on_event(self, record) -> None:
        self.events.append(record["kind"])

    def on_health(self, counters, faults) -> None:
        self.health += 1

    def on_flush(self) -> None:
        self.turns.append("flush")

    def close(self) -> None:
        self.closed = True


class Broken(Sink):
    name = "broken"

    def on_raw(self, block) -> None:
        raise OSError("the output's disk went away")


def _run(tmp_path: Path, sinks) -> tuple[list[str], object]:
    text = (Path(service_config(tmp_path, run_s=40, realtime=False)).read_text()
            .replace('transport = "pty"', 'transport = "direct"'))
    (tmp_path / "c.toml").write_text(text)
    said: list[str] = []
    assert Daemon(load_config(tmp_path / "c.toml"), say=said.append, sinks=sinks).run() == 0
    return said, read_recording(tmp_path / "rec")


def test_a_new_output_is_one_class_told_what_the_recording_gets(tmp_path):
    counter = Counting()
    said, rec = _run(tmp_path, [counter])
    # the recording gathers the blocks of a tenth of a second into one message (McapSink.GATHER_S): fewer messages,
    # the same samples
    assert counter.raw_blocks > len(rec.raw_blocks) > 0
    assert counter.raw_samples == sum(b.n_samples for b in rec.raw_blocks) == 8000       # 40 s at 200 Hz
    assert counter.corrected_samples == sum(b.n_samples for b in rec.corrected_blocks) > 0
    assert counter.events.count("calibration") == sum(e.get("kind") == "calibration" for e in rec.calibration) >= 1
    assert len(counter.events) == len(rec.calibration)
    assert counter.errors > 0 and counter.health >= 1 and counter.closed
    # each block's messages are flushed (the bus sends them together) before the next block is read
    turns = "".join(t[0] for t in counter.turns)
    assert turns.count("r") == counter.raw_blocks and turns.count("c") > 0
    assert all("f" in between for between in turns.split("r")[1:-1])

def test_a_failing_output_costs_only_itself(tmp_path):
    counter = Counting()
    said, rec = _run(tmp_path, [Broken(), counter])
    n = sum(b.n_samples for b in rec.raw_blocks)
    assert n == counter.raw_samples == 8000                   # the recording and the next output got every block
    failures = [m for m in said if m.startswith("output broken failed on raw")]
    assert len(failures) == 1 and "the other outputs carry on" in failures[0]      # said once, not per block
    seq = np.concatenate([b.seq for b in rec.raw_blocks])
    assert np.all(np.diff(seq) == 1)
    # the loss is said at stop as well, with its count, and not as "no loss and no fault seen"
    summary = [m for m in said if m.startswith("summary")]
    assert not any("no loss and no fault seen" in m for m in summary), summary
    blocks = counter.raw_blocks
    assert f"summary: outputs failed: broken {blocks:,} message(s) not taken (each said as it began)" in summary
    assert rec.health[-1]["counters"]["output_failures"] == blocks
    assert rec.health[-1]["counters"]["output_failures.broken"] == blocks          # by output, where people look
    assert "output_failures.recording" not in rec.health[-1]["counters"]           # only the outputs that failed


def test_a_replay_whose_output_fails_fails(tmp_path):
    """replay to an output that fails: exit status 1, and the verdict (the fleet table's column) is the failure, not
    the comparison's last line."""
    from fluxcal.service.wiring.commands.replay import ReplayOptions, execute
    from fluxcal.service.wiring.result import Said

    _run(tmp_path, [])
    out = execute(str(tmp_path / "rec"), ReplayOptions(), Said("replay"), sinks=[Broken()])
    assert out.status == 1
    assert out.verdict.startswith("an output failed, so what it holds is incomplete: broken ")
    assert out.compared > 0 and out.beyond == 0                       # the comparison itself held


def test_an_output_that_cannot_open_leaves_the_recording_finished(tmp_path):
    """[ros2] dir under a plain file: the service refuses to start (exit by ConfigError naming ros2.dir), and the MCAP
    recording it had opened already is closed with its footer, not left as a killed writer's."""
    import pytest

    from fluxcal.drivers.errors import ConfigError

    (tmp_path / "blocker").write_text("a file, not a folder")
    text = (Path(service_config(tmp_path, run_s=5, realtime=False)).read_text()
            .replace('transport = "pty"', 'transport = "direct"') + f'\n[ros2]\nenabled = true\ndir = "{tmp_path}/blocker/x"\n')
    (tmp_path / "c.toml").write_text(text)
    with pytest.raises(ConfigError, match="ros2.dir"):
        Daemon(load_config(tmp_path / "c.toml"), say=lambda m: None).run()
    files = sorted((tmp_path / "rec").glob("*.mcap"))
    assert len(files) == 1
    from mcap.reader import make_reader

    with open(files[0], "rb") as f:
        summary = make_reader(f).get_summary()                    # None for a file without its footer
    assert summary is not None and summary.statistics is not None
