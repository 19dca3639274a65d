"""MCAP replay as a Source: the "replay" registry entry, `exhausted`, recorded commands with their seq,
rotation by age replayed in order, killed and cut files read to their last chunk, corrupted chunks
refused (or skipped on request), repaired files indexed for mcap's own reader, and `write_recording`
storing probe names and the simulator's truth. (Encoding round trips: test_encoding.py; the logger's
channels, vectors and full disk: test_mcap_sink.py and test_recording.py.)"""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import drain
from mcap.reader import make_reader

import fluxcal.service.io.recordings.writer as sink
from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError, RecordingError
from fluxcal.drivers.mcap_source import McapSource
from fluxcal.drivers.source import open_source
from fluxcal.service.io.recordings.reader import FluxcalDecoderFactory, read_recording, repair_recording
from fluxcal.service.io.recordings.writer import McapLogger, write_recording

RATE_HZ = 1000.0


def blocks(n_blocks: int, n: int = 50, p: int = 3, seed: int = 1) -> list[SampleBlock]:
    """1 kHz blocks with random fields, a NaN payload per block and a reference column."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_blocks):
        k = i * n + np.arange(n)
        f = rng.normal(0, 3e4, (n, p, 3))
        f[3, 0, 2] = np.uint64(0x7FF80000DEADBEEF).view(np.float64)
        out.append(SampleBlock(t_s=10.0 + k / RATE_HZ, seq=k.astype(np.int64), field_nT=f,
                               temp_C=rng.normal(20, 2, (n, p)), flags=(k % 7 == 0).astype(np.uint8),
                               extras={"ref_total": rng.normal(5e4, 1, n)}))
    return out


def same_block(a: SampleBlock, b: SampleBlock) -> bool:
    def eq(x: np.ndarray, y: np.ndarray) -> bool:
        return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()

    return (eq(a.t_s, b.t_s) and eq(a.seq, b.seq) and eq(a.field_nT, b.field_nT) and eq(a.temp_C, b.temp_C)
            and eq(a.flags, b.flags) and a.extras.keys() == b.extras.keys()
            and all(eq(a.extras[k], b.extras[k]) for k in a.extras))




def test_replay_source_from_the_registry_yields_the_same_blocks_and_the_commands(tmp_path):
    want = blocks(40)
    log = McapLogger(tmp_path / "rec.mcap", unit="u1")
    log.write_event({"kind": "initial", "seq": 0})
    for i, b in enumerate(want):
        log.write_raw(b)
        if i in (9, 24):            # a command logged after the block it arrived in, applying from the next
            log.write_event({"kind": "command", "name": "freeze" if i == 9 else "thaw", "seq": int(b.seq[-1]) + 1})
    log.close()

    src = open_source("replay", path=str(tmp_path / "rec.mcap"))
    assert isinstance(src, McapSource) and src.n_probes == 3 and not src.exhausted
    got = drain(src)
    assert src.exhausted and src.read(0.0) is None
    assert len(got) == 40 and all(same_block(g, w) for g, w in zip(got, want))
    assert src.counters.frames_accepted == 2000 and src.counters.seq_gaps == 0
    assert src.counters.saturated_axes == 40                        # one NaN axis per block
    assert [e["kind"] for e in src.events] == ["initial", "command", "command"]
    assert [e["seq"] for e in src.events] == [0, 500, 1250]
    # take_events hands each event once, before the sample it applies from
    assert [e["seq"] for e in src.take_events(0)] == [0]
    assert src.take_events(499) == []
    assert [e["name"] for e in src.take_events(500)] == ["freeze"]
    assert [e["name"] for e in src.take_events(10_000)] == ["thaw"] and src.take_events(10_000) == []
    src.close()
    src.close()


def test_replay_needs_a_path_and_refuses_a_recording_without_samples(tmp_path):
    with pytest.raises(ConfigError, match="source.path"):
        open_source("replay")
    log = McapLogger(tmp_path / "events_only.mcap", unit="u1")
    log.write_event({"kind": "command", "seq": 3})
    log.close()
    with pytest.raises(RecordingError, match="no raw samples"):
        open_source("replay", path=str(tmp_path / "events_only.mcap"))


def test_rotation_by_age_replays_in_order_without_loss_or_duplicates(tmp_path, monkeypatch):
    clock = [0.0]
    monkeypatch.setattr(sink, "_monotonic", lambda: clock[0])
    want = blocks(60)
    log = McapLogger(tmp_path, unit="u1", rotate_s=1.0, flush_interval_s=0.25)
    for b in want:
        log.write_raw(b)
        clock[0] += 0.05                                            # 20 blocks per second of wall time
    log.close()
    names = [p.name for p in sorted(tmp_path.glob("*.mcap"))]
    assert len(names) >= 3 and names == sorted(names)
    assert all(n.startswith("u1-") and n.endswith(f"-{k + 1:04d}.mcap") for k, n in enumerate(names))
    got = drain(McapSource(tmp_path))
    assert len(got) == 60 and all(same_block(g, w) for g, w in zip(got, want))
    assert log.status()["files"] == len(names) and log.status()["errors"] == 0


def test_a_host_clock_stepped_back_mid_run_keeps_the_run_in_order(tmp_path, monkeypatch):
    """A time sync stepped the host's clock back two hours during a run: its rotated files were named at 11:08 where
    its first was 13:08, sorted before it, and the run replayed as two, the continuation failing alone (a field
    trial). Every file of a run now carries its first file's time: one run, in order, every block once."""
    from fluxcal.service.io.recordings import writer

    clock, wall = [0.0], [1_796_648_880.0e9]
    monkeypatch.setattr(sink, "_monotonic", lambda: clock[0])
    monkeypatch.setattr(writer, "_wall_ns", lambda: int(wall[0]))
    want = blocks(60)
    log = McapLogger(tmp_path, unit="u1", rotate_s=1.0, flush_interval_s=0.25)
    for k, b in enumerate(want):
        log.write_raw(b)
        clock[0] += 0.05
        wall[0] += 0.05e9 if k != 25 else -7200e9                  # two hours back in the middle of the run
    log.close()
    names = [p.name for p in sorted(tmp_path.glob("*.mcap"))]
    assert len(names) >= 3 and len({n.rsplit("-", 1)[0] for n in names}) == 1, names
    assert all(n.endswith(f"-{k + 1:04d}.mcap") for k, n in enumerate(names))
    from fluxcal.service.io.recordings.runs import runs_in

    assert [len(r) for r in runs_in(tmp_path)] == [len(names)]
    got = drain(McapSource(tmp_path))
    assert len(got) == 60 and all(same_block(g, w) for g, w in zip(got, want))


def test_a_file_cut_anywhere_reads_up_to_its_last_complete_chunk(tmp_path):
    want = blocks(50)
    log = McapLogger(tmp_path / "full.mcap", unit="u1", flush_interval_s=0.0)   # a chunk per message
    for b in want:
        log.write_raw(b)
    log.close()
    data = (tmp_path / "full.mcap").read_bytes()
    counts = []
    for frac in (0.2, 0.5, 0.77, 0.99):
        cut = tmp_path / f"cut{frac}.mcap"
        cut.write_bytes(data[: int(len(data) * frac)])
        src = McapSource(cut)
        got = drain(src)
        # says the tail is cut, does not raise (a cut inside the summary, after DataEnd, loses nothing)
        assert src.report.truncated or len(got) == len(want)
        assert all(same_block(g, w) for g, w in zip(got, want))       # a prefix, bit for bit
        counts.append(len(got))
    # chunks are ~4 kB of 50: a cut loses at most the chunk it fell in (plus the index at the end)
    assert counts == sorted(counts) and counts[-1] == 50 and abs(counts[1] - 25) <= 2


def test_a_corrupted_chunk_is_read_past_and_said_or_refused_on_request(tmp_path):
    want = blocks(20)
    log = McapLogger(tmp_path / "ok.mcap", unit="u1", flush_interval_s=0.0, compression="none")
    for b in want:
        log.write_raw(b)
    log.close()
    data = bytearray((tmp_path / "ok.mcap").read_bytes())
    payload = want[10].field_nT.tobytes()[:64]
    at = data.find(payload)
    assert at > 0
    data[at + 5] ^= 0xFF                                             # one flipped byte inside block 10's chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="bad.mcap.*damaged"):
        read_recording(bad, strict=True)
    rec = read_recording(bad)                                        # by default: read past, and said
    assert len(rec.raw_blocks) == 19 and len(rec.report.damaged) == 1 and "not a stopped writer" in rec.warnings[0]
    seqs = np.concatenate([b.seq for b in rec.raw_blocks])
    assert not np.isin(want[10].seq, seqs).any() and np.isin(want[11].seq, seqs).all()
    first, last = int(want[10].seq[0]), int(want[10].seq[-1])
    assert rec.holes[0].seq_span() == (first, last)
    assert f"a hole of {last - first + 1} samples at seq {first}-{last}" in rec.warnings[-1]


def test_repair_gives_an_indexed_file_that_mcap_reads_with_our_decoders(tmp_path):
    want = blocks(30)
    log = McapLogger(tmp_path / "live.mcap", unit="u1", flush_interval_s=0.0, metadata={"site": "lab"})
    for b in want:
        log.write_raw(b)
    log.write_event({"kind": "command", "seq": 7})
    log.flush()
    killed = tmp_path / "killed.mcap"
    killed.write_bytes((tmp_path / "live.mcap").read_bytes())       # as a SIGKILL would leave it: no footer
    log.close()
    with open(killed, "rb") as f, pytest.raises(Exception):
        make_reader(f).get_summary()                                 # mcap's indexed reader cannot use it

    report = repair_recording(killed, tmp_path / "fixed.mcap")
    assert report.messages == 31 and report.truncated
    with open(tmp_path / "fixed.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[FluxcalDecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 31
        topics = {c.topic for c in summary.channels.values()}
        assert {"/fluxcal/u1/raw", "/fluxcal/u1/events", "/fluxcal/u1/corrected", "/fluxcal/u1/vectors",
                "/fluxcal/u1/calibration", "/fluxcal/u1/health"} <= topics
        got = [decoded for _, _, _, decoded in reader.iter_decoded_messages(topics=["/fluxcal/u1/raw"])]
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert len(got) == 30 and all(same_block(g, w) for g, w in zip(got, want))
    assert meta["fluxcal"]["site"] == "lab" and meta["fluxcal"]["unit"] == "u1"
    again = read_recording(tmp_path / "fixed.mcap")
    assert not again.truncated and again.events == [{"kind": "command", "seq": 7}]


def test_write_recording_stores_probe_names_and_truth(tmp_path):
    want = blocks(12, p=2)
    truth = {"offset_nT": [[1.5, -2.0, 0.25], [0.0, 3.0, -1.0]], "lsb_nT": 0.01}
    out = tmp_path / "sim.mcap"
    write_recording(out, iter(want), unit="sim", probe_names=["fore", "aft"], truth=truth)
    assert out.exists() and not list(tmp_path.glob("*.partial"))
    rec = read_recording(out)
    assert rec.probe_names == ["fore", "aft"] and rec.n_probes == 2 and rec.unit == "sim"
    assert json.loads(rec.metadata["truth"]) == truth
    assert same_block(rec.raw, SampleBlock.concat(want))
    with open(out, "rb") as f:                                        # finished and indexed
        assert make_reader(f).get_summary().statistics.message_count == 12


def test_non_mcap_inputs_name_the_file(tmp_path):
    d = tmp_path / "empty_dir"
    d.mkdir()
    with pytest.raises(RecordingError, match="empty_dir: no .mcap files"):
        McapSource(d)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(RecordingError, match=r"junk\.mcap: not an MCAP file"):
        open_source("replay", path=str(junk))
    with pytest.raises(RecordingError, match=r"junk\.mcap"):
        repair_recording(junk, tmp_path / "out.mcap")
