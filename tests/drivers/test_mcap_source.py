"""Replay of MCAP recordings through the Source contract, and the recovery of damaged or killed files:
rotated directories replay in order bit for bit, a writer killed with SIGKILL leaves a file that reads
back to its last flush, a file cut at any byte reads as a prefix, damage is refused or salvaged."""

from __future__ import annotations

import json
import logging
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_refused
from mcap.reader import make_reader

from fluxcal.drivers.block import FLAG_TEMP_INVALID, SampleBlock
from fluxcal.drivers.errors import ConfigError, DriverError, RecordingError
from fluxcal.drivers.mcap_source import McapSource, iter_records
from fluxcal.drivers.source import open_source
from fluxcal.service.io.recordings.reader import read_recording, repair_recording
from fluxcal.service.io.recordings.writer import McapLogger

ROOT = Path(__file__).resolve().parents[2]


def blocks(n_blocks: int, n: int = 50, p: int = 2, seed: int = 0, skip: tuple[int, ...] = ()) -> list[SampleBlock]:
    """1 kHz blocks; every 7th sample flags its temperature invalid, a few axes are NaN (saturated);
    the samples of blocks in `skip` are never produced (a gap in seq)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_blocks):
        if i in skip:
            continue
        k = i * n + np.arange(n)
        f = rng.normal(0, 3e4, (n, p, 3))
        f[::11, -1, 2] = np.nan
        out.append(SampleBlock(t_s=k / 1000.0, seq=k.astype(np.int64), field_nT=f, temp_C=rng.normal(20, 1, (n, p)),
                               flags=np.where(k % 7 == 0, FLAG_TEMP_INVALID, 0).astype(np.uint8)))
    return out


def record(path: Path, bs: list[SampleBlock], unit: str = "u", **kw) -> McapLogger:
    log = McapLogger(path, unit=unit, **kw)
    for b in bs:
        log.write_raw(b)
    log.close()
    return log


def drain(src) -> list[SampleBlock]:
    out = []
    while not src.exhausted:
        b = src.read(0.1)
        assert b is not None                       # a file never makes the reader wait
        out.append(b)
    return out


def same_block(a: SampleBlock, b: SampleBlock) -> bool:
    return all(getattr(a, k).tobytes() == getattr(b, k).tobytes() and getattr(a, k).dtype == getattr(b, k).dtype
               for k in ("t_s", "seq", "field_nT", "temp_C", "flags"))


def test_replay_of_rotated_files_is_the_recorded_blocks_bit_for_bit(tmp_path):
    bs = blocks(200, skip=(50, 51, 120))
    log = record(tmp_path / "rec", bs, rotate_mb=0.05, chunk_size=8192)
    assert len(log.files) >= 4
    src = open_source("replay", path=tmp_path / "rec")                # through the registry
    assert isinstance(src, McapSource) and src.n_probes == 2 and not src.exhausted
    got = drain(src)
    assert len(got) == len(bs) and all(same_block(g, w) for g, w in zip(got, bs))
    assert src.exhausted and src.read(0.1) is None                    # exhausted with the last block
    c = src.counters
    assert c.frames_accepted == sum(b.n_samples for b in bs)
    assert c.seq_gaps == 2 and c.samples_missed == 150                # the skipped blocks, as the live source counts
    assert c.saturated_axes == sum(int(np.isnan(b.field_nT).sum()) for b in bs)
    assert c.temp_invalid == sum(int((b.flags & FLAG_TEMP_INVALID != 0).sum()) for b in bs)
    assert not src.report.warnings and len(src.report.files) == len(log.files)
    src.close()
    src.close()
    with pytest.raises(DriverError, match="read after close"):
        src.read()


def test_open_source_takes_a_path_or_a_config_and_names_what_is_missing(tmp_path):
    record(tmp_path / "a.mcap", blocks(3))

    class ReplayConfig:
        kind, path = "replay", str(tmp_path / "a.mcap")

    with open_source("replay", ReplayConfig()) as src:
        assert len(drain(src)) == 3
    with open_source("replay", str(tmp_path / "a.mcap")) as src:
        assert src.metadata["unit"] == "u"
    with pytest.raises(ConfigError, match="source.path"):
        open_source("replay")


def test_several_units_in_one_directory_need_a_unit(tmp_path):
    record(tmp_path / "a.mcap", blocks(4, seed=1), unit="north")
    record(tmp_path / "b.mcap", blocks(6, seed=2), unit="south")
    with pytest.raises(RecordingError, match="several units"):
        drain(McapSource(tmp_path))
    with pytest.raises(RecordingError, match="several units"):
        read_recording(tmp_path)
    got = drain(McapSource(tmp_path, unit="south"))
    assert len(got) == 6 and all(same_block(g, w) for g, w in zip(got, blocks(6, seed=2)))
    assert read_recording(tmp_path, unit="north").raw.n_samples == 200
    with pytest.raises(RecordingError, match="no raw samples of unit 'east'"):
        read_recording(tmp_path, unit="east")


def test_foreign_missing_and_empty_files_are_refused_clearly(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"PK\x03\x04 a zip file, not a recording")
    assert_refused(McapSource, tmp_path / "x.mcap", "not an MCAP file")
    assert_refused(read_recording, tmp_path / "nope.mcap", "no such recording")
    (tmp_path / "empty").mkdir()
    with pytest.raises(RecordingError, match="no .mcap files"):
        McapSource(tmp_path / "empty")
    (tmp_path / "zero.mcap").write_bytes(b"")
    with pytest.raises(RecordingError, match="no raw samples.*empty"):
        read_recording(tmp_path / "zero.mcap")


def test_a_file_cut_at_any_byte_reads_as_a_prefix_of_what_was_written(tmp_path):
    bs = blocks(12)
    record(tmp_path / "full.mcap", bs, flush_interval_s=0)           # one chunk per block
    data = (tmp_path / "full.mcap").read_bytes()
    cut_file = tmp_path / "cut.mcap"
    counts = []
    for cut in range(0, len(data), 97):
        cut_file.write_bytes(data[:cut])
        try:
            rec = read_recording(cut_file)
        except RecordingError as e:
            assert "no raw samples" in str(e)                           # cut before the first chunk ended
            counts.append(0)
            continue
        # cut after the data section (in the summary), nothing is missing and nothing needs saying
        assert rec.truncated or len(rec.raw_blocks) == 12
        assert all(same_block(g, w) for g, w in zip(rec.raw_blocks, bs))
        counts.append(len(rec.raw_blocks))
    assert counts == sorted(counts) and counts[-1] == 12 and counts.count(0) < len(counts) // 4


def chunk_spans(path: Path) -> list[tuple[int, int]]:
    with open(path, "rb") as f:
        return [(c.chunk_start_offset, c.chunk_length) for c in make_reader(f).get_summary().chunk_indexes]


def test_a_damaged_chunk_is_read_past_and_said_and_repair_records_the_hole(tmp_path, caplog):
    bs = blocks(10)
    record(tmp_path / "ok.mcap", bs, flush_interval_s=0)
    spans = chunk_spans(tmp_path / "ok.mcap")
    data = bytearray((tmp_path / "ok.mcap").read_bytes())
    start, length = spans[4]                                          # the chunk holding block 4
    data[start + length - 100] ^= 0xFF                                # one flipped byte in its data
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match=rf"bad.mcap: an unreadable chunk record .* at byte {start}: .*damaged"):
        read_recording(bad, strict=True)
    with pytest.raises(RecordingError, match="damaged"):
        drain(McapSource(bad, strict=True))
    rec = read_recording(bad)                                         # by default: the other 9 blocks, and said
    assert [int(b.seq[0]) // 50 for b in rec.raw_blocks] == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    assert len(rec.report.damaged) == 1 and "crc" in rec.report.damaged[0].lower()
    assert "not a stopped writer" in rec.report.damaged[0] and not rec.truncated
    assert len(rec.holes) == 1 and rec.holes[0].seq_span() == (200, 249)
    with caplog.at_level(logging.WARNING, logger="fluxcal.replay"):
        assert len(drain(McapSource(bad))) == 9
    assert "crc" in caplog.text.lower() and "a hole of 50 samples at seq 200-249" in caplog.text
    report = repair_recording(bad, tmp_path / "fixed.mcap")
    assert report.damaged and report.messages == 9 and len(report.holes) == 1
    with open(tmp_path / "fixed.mcap", "rb") as f:
        assert make_reader(f).get_summary().statistics.message_count == 9
    fixed = read_recording(tmp_path / "fixed.mcap")                   # whole now, and it says what it lost
    assert not fixed.truncated and not fixed.report.damaged and fixed.report.repaired["repaired_from"] == "bad.mcap"
    assert [h.seq_span() for h in fixed.holes] == [(200, 249)] and fixed.holes[0].recorded
    assert fixed.warnings == [fixed.holes[0].describe()] and "a hole of 50 samples at seq 200-249" in fixed.warnings[0]


WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    sys.path.insert(0, {root!r})
    from fluxcal.drivers.block import SampleBlock
    from fluxcal.service.io.recordings.writer import McapLogger
    log = McapLogger({out!r}, unit="u", flush_interval_s=0.2, metadata={{"probe_names": ["a", "b"]}})
    rng = np.random.default_rng(5)
    for i in range(100000):
        k = i * 50 + np.arange(50)
        log.write_raw(SampleBlock(t_s=k / 1000.0, seq=k, field_nT=rng.normal(size=(50, 2, 3)),
                                  temp_C=np.full((50, 2), 20.0), flags=np.zeros(50, np.uint8)))
        st = log.status()
        print(i + 1, st["messages_written"], flush=True)
        time.sleep(0.004)
""")


def test_a_writer_killed_with_sigkill_loses_at_most_its_last_flush_interval(tmp_path, caplog):
    out = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", WRITER.format(root=str(ROOT), out=str(out))],
                            stdout=subprocess.PIPE, text=True)
    written = flushed = 0
    times: dict[int, float] = {}
    try:
        deadline = time.monotonic() + 30
        while written < 250 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            written, flushed = map(int, line.split())
            times[written] = time.monotonic()
    finally:
        killed_at = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        proc.stdout.close()
    assert written >= 250, "the writer did not start"
    rec = read_recording(out)                                         # no footer, maybe a cut chunk: read anyway
    assert rec.truncated and rec.probe_names == ["a", "b"]
    n = len(rec.raw_blocks)
    seq = rec.raw.seq
    assert np.array_equal(seq, np.arange(n * 50))                     # whole blocks, in order, from the first
    assert flushed <= n <= written + 5                                # everything flushed survived the kill
    # what is missing was written within about one flush interval (0.2 s) before the kill
    lost_since = times.get(n + 1, killed_at)
    assert killed_at - lost_since < 0.2 + 0.5                         # 0.5 s margin for a loaded machine
    with caplog.at_level(logging.WARNING, logger="fluxcal.replay"):
        replayed = drain(McapSource(out))
    assert len(replayed) == n and ("no footer" in caplog.text or "cut inside" in caplog.text)
    report = repair_recording(out, tmp_path / "repaired.mcap")
    assert report.messages == n and report.truncated
    with open(tmp_path / "repaired.mcap", "rb") as f:                 # indexed and finished now
        reader = make_reader(f)
        assert reader.get_summary().statistics.message_count == n
        assert json.loads(next(m for m in reader.iter_metadata() if m.name == "fluxcal").metadata["probe_names"]) \
            == ["a", "b"]
    again = read_recording(tmp_path / "repaired.mcap")
    assert not again.warnings and np.array_equal(again.raw.seq, seq)


def test_repair_keeps_every_record_exactly(tmp_path):
    log = McapLogger(tmp_path / "src.mcap", unit="u", flush_interval_s=0)
    for b in blocks(5):
        log.write_raw(b)
    log.write_event({"kind": "mark", "t_s": 0.1})
    log.close()
    repair_recording(tmp_path / "src.mcap", tmp_path / "dst.mcap")
    a = [(r.topic, r.encoding, r.data, r.log_time_ns, r.publish_time_ns) for r in iter_records(tmp_path / "src.mcap")]
    b = [(r.topic, r.encoding, r.data, r.log_time_ns, r.publish_time_ns) for r in iter_records(tmp_path / "dst.mcap")]
    assert a == b and len(a) == 6
    with pytest.raises(RecordingError, match="another destination"):
        repair_recording(tmp_path / "src.mcap", tmp_path / "src.mcap")


def test_the_committed_sample_recording_replays(tmp_path):
    src = McapSource(ROOT / "recordings" / "grad1-sim-30s.mcap")
    got = drain(src)
    assert src.n_probes == 2 and sum(b.n_samples for b in got) == src.counters.frames_accepted > 5000
    assert not src.report.warnings and src.metadata["unit"] == "grad1"


def test_the_chunk_reader_gives_the_mcap_librarys_records(tmp_path):
    # the reader's own parse of a chunk's records equals mcap.stream_reader.breakup_chunk on every chunk of a
    # recording with schemas, channels and messages of several streams, lz4 and zstd alike
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk

    from fluxcal.drivers.mcap_records import chunk_records as _chunk_records
    from fluxcal.service.io.recordings.writer import McapLogger

    for compression in ("lz4", "zstd", "none"):
        log = McapLogger(tmp_path, unit="u", filename=f"c-{compression}.mcap", compression=compression,
                         chunk_size=50_000)
        for k, b in enumerate(blocks(40, n=25)):
            log.write_raw(b)
            log.write_event({"kind": "command", "seq": k})
        log.close()
        with open(tmp_path / f"c-{compression}.mcap", "rb") as fh:
            chunks = [r for r in StreamReader(fh, emit_chunks=True).records if isinstance(r, Chunk)]
        assert len(chunks) >= 2
        for ch in chunks:
            assert _chunk_records(ch) == breakup_chunk(ch, validate_crc=True)


def test_the_chunk_reader_refuses_malformed_records_inside_a_chunk():
    # what a damaged chunk with a good CRC may hold: each is an error (the file reader reports it as damage),
    # never a loop or a record made of garbage; an unknown record is skipped, as the MCAP library does
    import struct

    from mcap.records import Chunk, Message

    from fluxcal.drivers.mcap_records import chunk_records as _chunk_records

    def chunk(data: bytes) -> Chunk:
        return Chunk(compression="", data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                     uncompressed_size=len(data))

    message = struct.pack("<BQHIQQ", 0x05, 22 + 3, 7, 1, 10, 11) + b"abc"
    assert _chunk_records(chunk(message)) == [Message(channel_id=7, log_time=10, data=b"abc", publish_time=11,
                                                      sequence=1)]
    assert _chunk_records(chunk(struct.pack("<BQ", 0x7F, 0) + message))[0].data == b"abc"
    for bad, why in [(message[:5], "header cut short"), (message[:-1], "runs past"),
                     (struct.pack("<BQ", 0x05, 10) + bytes(10), "message record of 10 bytes")]:
        with pytest.raises(ValueError, match=why):
            _chunk_records(chunk(bad))


def test_whole_recordings_are_decoded_a_bounded_batch_at_a_time(tmp_path, monkeypatch):
    # read_recording and read_samples hold at most RAW_BATCH_BYTES of undecoded messages (a recording of large
    # messages, as `simulate` writes, was once held twice over: fit of an hour at 1 kHz x 4 peaked at 2.3 GB)
    from fluxcal.drivers.encoding import encode_raw
    from fluxcal.service.io.recordings import reader
    from fluxcal.service.io.recordings.writer import McapLogger

    bs = blocks(10, n=1000)
    log = McapLogger(tmp_path, unit="u", filename="big.mcap")
    for b in bs:
        log.write_raw(b)
    log.close()
    size = len(encode_raw(bs[0]))
    monkeypatch.setattr(reader, "RAW_BATCH_BYTES", 3 * size)
    decoded = []
    real = reader.decode_raw_runs
    monkeypatch.setattr(reader, "decode_raw_runs", lambda payloads: decoded.append(len(payloads)) or real(payloads))
    rec = reader.read_recording(tmp_path / "big.mcap")
    assert decoded == [3, 3, 3, 1] and len(rec.raw_runs) == 4
    assert all(same_block(g, w) for g, w in zip(rec.raw_blocks, bs)) and len(rec.raw_blocks) == 10
    decoded.clear()
    whole = reader.read_samples(tmp_path / "big.mcap").raw
    assert decoded == [3, 3, 3, 1] * 2                       # two passes: count, then fill
    np.testing.assert_array_equal(whole.field_nT, np.concatenate([b.field_nT for b in bs]))
