"""McapLogger: self-describing channels, bit-for-bit round trips, the time base, the 10 Hz vectors channel,
rotation by size and by age, flushing, and a full disk (fault-injecting file) that is counted, never
raised, loses only what arrived while nothing could be written, and resumes in the next file."""

from __future__ import annotations

import errno
import json
import re
from pathlib import Path

import numpy as np
import pytest
from helpers import write_raw
from mcap.reader import make_reader

import fluxcal.service.io.recordings.writer as sink
from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError, RecordingError
from fluxcal.service.io.encoding import CORRECTED_LAYOUT, RAW_LAYOUT
from fluxcal.service.io.recordings.reader import FluxcalDecoderFactory, read_recording
from fluxcal.service.io.recordings.writer import McapLogger
from fluxcal.service.numerics.outputs import CorrectedBlock

RATE_HZ = 1000.0


def blocks(n_blocks: int, n: int = 50, p: int = 4, seed: int = 0, t0: float = 100.0) -> list[SampleBlock]:
    """1 kHz blocks with random fields (some NaN payloads), temperatures and a reference."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_blocks):
        k = i * n + np.arange(n)
        f = rng.normal(0, 3e4, (n, p, 3))
        f[::17, 0, 1] = np.uint64(0x7FF8000000000BAD).view(np.float64)
        out.append(SampleBlock(t_s=t0 + k / RATE_HZ, seq=k.astype(np.int64), field_nT=f,
                               temp_C=rng.normal(20, 2, (n, p)), flags=(k % 5 == 0).astype(np.uint8),
                               extras={"ref_total": rng.normal(5e4, 1, n)}))
    return out


def corrected(b: SampleBlock, cal_id: int = 1) -> CorrectedBlock:
    c = b.field_nT * 1.001 + 3.0
    return CorrectedBlock(b.t_s, b.seq, c, c[:, 1:] - c[:, :1], None, c.mean(axis=1), cal_id)


def same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


class Clock:
    """Replaces the logger's monotonic clock: tests move time instead of sleeping."""

    def __init__(self, monkeypatch) -> None:
        self.t = 1000.0
        monkeypatch.setattr(sink, "_monotonic", lambda: self.t)


def test_channels_schemas_and_metadata_describe_the_file(tmp_path):
    log = McapLogger(tmp_path, unit="grad1", metadata={"probe_names": json.dumps(["fore", "aft"]), "lsb_nT": "0.001"})
    for b in blocks(10, p=2):
        log.write_raw(b)
        log.write_corrected(corrected(b))
    log.write_calibration({"kind": "calibration", "seq": 100, "t_s": 100.1, "state": {"cal_id": 1}})
    log.write_event({"kind": "command", "seq": 200, "name": "freeze"})
    log.write_health({"frames_accepted": 500})
    log.close()
    (path,) = log.files
    assert re.fullmatch(r"grad1-\d{8}T\d{6}-0001\.mcap", Path(path).name)
    with open(path, "rb") as f:                      # the official indexed reader: the file is finished
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: (c.message_encoding, summary.schemas[c.schema_id]) for c in summary.channels.values()}
        counts = {summary.channels[k].topic: v for k, v in summary.statistics.channel_message_counts.items()}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert set(topics) == {f"/fluxcal/grad1/{s}" for s in ("raw", "corrected", "vectors", "diff", "tensor", "error",
                                                           "params", "calibration", "events", "health")}
    enc, schema = topics["/fluxcal/grad1/raw"]
    assert enc == "fluxcal.raw.v1" and schema.encoding == "fluxcal.layout" and schema.data.decode() == RAW_LAYOUT
    enc, schema = topics["/fluxcal/grad1/corrected"]
    assert enc == "fluxcal.corrected.v1" and schema.data.decode() == CORRECTED_LAYOUT
    enc, schema = topics["/fluxcal/grad1/vectors"]
    vec_schema = json.loads(schema.data)
    assert enc == "json" and schema.encoding == "jsonschema"
    assert {"fore", "aft", "center"} <= set(vec_schema["properties"])
    assert {"aft"} <= set(json.loads(topics["/fluxcal/grad1/diff"][1].data)["properties"])
    for s in ("diff", "tensor", "error", "params", "calibration", "events", "health"):
        assert topics[f"/fluxcal/grad1/{s}"][1].encoding == "jsonschema"
    assert counts["/fluxcal/grad1/raw"] == 10 and counts["/fluxcal/grad1/vectors"] == 5     # 0.5 s at 10 Hz
    assert counts["/fluxcal/grad1/diff"] == 5 and counts["/fluxcal/grad1/params"] == 1
    assert "/fluxcal/grad1/tensor" not in counts                                          # two probes: no tensor
    assert meta["fluxcal"]["unit"] == "grad1" and meta["fluxcal"]["lsb_nT"] == "0.001"
    assert meta["fluxcal"]["raw_encoding"] == "fluxcal.raw.v1" and meta["fluxcal"]["file_index"] == "1"
    assert "epoch_ns + round(t_s * 1e9)" in meta["fluxcal.time"]["log_time"]


def test_raw_and_corrected_round_trip_bit_for_bit(tmp_path):
    bs = blocks(40)
    with McapLogger(tmp_path / "r.mcap", unit="u") as log:
        for b in bs:
            log.write_raw(b)
            log.write_corrected(corrected(b, cal_id=3))
    rec = read_recording(tmp_path / "r.mcap")
    assert rec.unit == "u" and not rec.warnings and len(rec.raw_blocks) == 40
    for got, want in zip(rec.raw_blocks, bs):
        for name in ("t_s", "seq", "field_nT", "temp_C", "flags"):
            assert same(getattr(got, name), getattr(want, name)), name
        assert same(got.extras["ref_total"], want.extras["ref_total"])
    whole = rec.corrected
    want = [corrected(b, 3) for b in bs]
    assert same(whole.corrected_nT, np.concatenate([c.corrected_nT for c in want]))
    assert same(whole.diff_nT, np.concatenate([c.diff_nT for c in want])) and whole.tensor_nT_m is None
    assert np.all(rec.corrected_cal_id == 3) and rec.raw.n_samples == 2000
    # mcap's own reader with fluxcal's decoders gives the same blocks
    with open(tmp_path / "r.mcap", "rb") as f:
        got = [m for _, _, _, m in make_reader(f, decoder_factories=[FluxcalDecoderFactory()])
               .iter_decoded_messages(topics=["/fluxcal/u/raw"])]
    assert len(got) == 40 and same(got[7].field_nT, bs[7].field_nT)


def test_log_time_is_unit_time_placed_on_the_wall_clock(tmp_path):
    bs = blocks(5)
    log = McapLogger(tmp_path / "a.mcap", unit="u")
    for b in bs:
        log.write_raw(b)
    log.write_event({"kind": "mark"})                             # no t_s: placed at the last block
    log.close()
    log0 = McapLogger(tmp_path / "b.mcap", unit="u", epoch_ns=0)  # plain unit time
    log0.write_raw(bs[0])
    log0.close()
    with open(tmp_path / "a.mcap", "rb") as f:
        msgs = [(c.topic, m) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]
    raw = [m for t, m in msgs if t.endswith("/raw")]
    epoch = raw[0].log_time - round(bs[0].t_s[0] * 1e9)
    assert [m.log_time for m in raw] == [epoch + round(b.t_s[0] * 1e9) for b in bs]   # unit-clock spacing
    assert abs(raw[0].publish_time - epoch - round(bs[0].t_s[0] * 1e9)) < 5e9          # wall clock, near now
    assert [m.sequence for m in raw] == [1, 2, 3, 4, 5]
    assert [m.log_time for t, m in msgs if t.endswith("/events")] == [raw[-1].log_time]
    with open(tmp_path / "b.mcap", "rb") as f:
        (_, _, m), = make_reader(f).iter_messages()
    assert m.log_time == round(bs[0].t_s[0] * 1e9)


def test_vectors_are_10_hz_means_per_probe_and_centre(tmp_path):
    # 37-sample blocks: the 0.1 s intervals cut across blocks; NaNs must not poison the means
    bs = blocks(1, n=37 * 40, p=3, t0=0.0)[0]
    cs = [corrected(bs.slice(i, i + 37)) for i in range(0, bs.n_samples, 37)]
    log = McapLogger(tmp_path / "v.mcap", unit="u")
    for c in cs:
        log.write_corrected(c)
    log.close()
    vec = [r for r in read_recording_json(tmp_path / "v.mcap", "vectors")]
    assert len(vec) == 15                                          # 1.48 s of data: 14 whole intervals + 1
    c = np.concatenate([x.corrected_nT for x in cs])
    for k, rec in enumerate(vec):
        rows = slice(100 * k, min(100 * (k + 1), c.shape[0]))
        assert rec["seq"] == 100 * k and rec["n"] == rows.stop - rows.start and rec["cal_id"] == 1
        for p in range(3):
            m = np.nanmean(c[rows, p], axis=0)
            tot = np.nanmean(np.linalg.norm(c[rows, p], axis=1))
            got = rec[f"s{p + 1}"]
            assert np.allclose([got["x"], got["y"], got["z"], got["total"]], [*m, tot], rtol=1e-12, atol=1e-9)
        center = np.concatenate([x.center_nT for x in cs])[rows]
        assert np.allclose([rec["center"][a] for a in "xyz"], np.nanmean(center, axis=0), rtol=1e-12)
        assert np.isclose(rec["center"]["total"], np.nanmean(np.linalg.norm(center, axis=1)), rtol=1e-12)


def read_recording_json(path: Path, stream: str) -> list[dict]:
    from fluxcal.drivers.mcap_source import iter_records

    return [json.loads(r.data) for r in iter_records(path) if r.topic.endswith("/" + stream)]


def test_a_new_calibration_starts_a_new_vectors_interval(tmp_path):
    b = blocks(1, n=100, p=1, t0=0.0)[0]
    log = McapLogger(tmp_path / "v.mcap", unit="u")
    log.write_corrected(corrected(b.slice(0, 30), cal_id=1))
    log.write_corrected(corrected(b.slice(30, 100), cal_id=2))
    log.close()
    vec = read_recording_json(tmp_path / "v.mcap", "vectors")
    assert [(v["cal_id"], v["n"], v["seq"]) for v in vec] == [(1, 30, 0), (2, 70, 30)]


def test_rotation_by_size_gives_numbered_files_that_replay_in_order(tmp_path):
    bs = blocks(120)
    log = write_raw(tmp_path, bs, rotate_mb=0.1, chunk_size=32_768)
    assert len(log.files) >= 4
    assert [int(Path(f).stem[-4:]) for f in log.files] == list(range(1, len(log.files) + 1))
    assert sorted(log.files) == log.files                           # name order is time order
    for f in log.files:
        with open(f, "rb") as fh:
            assert make_reader(fh).get_summary() is not None         # every file finished and indexed
        assert Path(f).stat().st_size < 0.1e6 + 40_000              # rotated within about one chunk
    rec = read_recording(tmp_path)
    assert np.array_equal(rec.raw.seq, np.arange(120 * 50)) and not rec.warnings    # nothing lost or doubled
    assert log.status()["bytes_written"] == sum(Path(f).stat().st_size for f in log.files)


def test_rotation_by_age(tmp_path, monkeypatch):
    clock = Clock(monkeypatch)
    log = McapLogger(tmp_path, unit="u", rotate_s=10.0)
    for b in blocks(60):
        log.write_raw(b)
        clock.t += 1.0                                              # one block a second
    log.close()
    assert len(log.files) == 6
    per_file = [read_recording(f).raw.seq for f in log.files]
    assert [s.size // 50 for s in per_file] == [10] * 6
    assert np.array_equal(np.concatenate(per_file), np.arange(3000))


def test_chunks_reach_the_disk_once_per_flush_interval(tmp_path, monkeypatch):
    clock = Clock(monkeypatch)
    log = McapLogger(tmp_path / "f.mcap", unit="u", flush_interval_s=1.0)
    bs = blocks(30)
    for b in bs[:10]:
        log.write_raw(b)
        clock.t += 0.05
    assert log.status()["messages_written"] == 0 and log.status()["pending"] == 10
    with pytest.raises(RecordingError, match="no raw samples"):
        read_recording(tmp_path / "f.mcap")                         # nothing in the file yet but its header
    clock.t += 1.0
    log.write_raw(bs[10])                                           # the interval has passed: this write flushes
    assert log.status()["messages_written"] == 11
    rec = read_recording(tmp_path / "f.mcap")                       # readable while open (no footer yet)
    assert len(rec.raw_blocks) == 11 and rec.truncated and "no footer" in rec.truncated[0]
    log.write_raw(bs[11])
    clock.t += 1.5
    log.poll()                                                      # input stalled: poll() flushes too
    assert len(read_recording(tmp_path / "f.mcap").raw_blocks) == 12
    log.close()
    assert not read_recording(tmp_path / "f.mcap").truncated


class FillingDisk:
    """A file on a disk with `free` bytes left (shared by every file, like a real partition): a write
    beyond it writes what fits and then fails with ENOSPC, as write(2) does."""

    free = 10**9

    def __init__(self, path, mode):
        self.f = open(path, mode, buffering=0)

    def write(self, data):
        room = FillingDisk.free
        if room <= 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        n = self.f.write(memoryview(data)[:room])
        FillingDisk.free -= n
        return n

    def truncate(self, size):
        before = self.f.seek(0, 2)
        self.f.truncate(size)
        FillingDisk.free += before - size                            # cutting the file frees its tail

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_full_disk_is_counted_never_raised_and_logging_resumes(tmp_path, monkeypatch):
    clock = Clock(monkeypatch)
    FillingDisk.free = 10**9
    bs = blocks(100)
    log = McapLogger(tmp_path, unit="u", flush_interval_s=0.5, retry_s=2.0, opener=FillingDisk)
    for b in bs[:30]:
        log.write_raw(b)
        clock.t += 0.1
    FillingDisk.free = 20_000                                       # the disk fills in the middle of a chunk
    dropped_at = None
    for i, b in enumerate(bs[30:70], 30):
        log.write_raw(b)                                            # never raises
        clock.t += 0.1
        if dropped_at is None and log.dropped:
            dropped_at = i
        if i == 45:
            st = log.status()
            assert st["errors"] == 1 and "No space left" in st["last_error"] and st["current"] is None
            FillingDisk.free = 10**9                                # space freed: the next retry succeeds
    for b in bs[70:]:
        log.write_raw(b)
        clock.t += 0.1
    log.close()
    st = log.status()
    assert len(log.files) == 2 and st["dropped"] > 0 and st["messages"] == 100
    seqs = [b.seq for b in read_recording(log.files[0]).raw_blocks]   # the full file reads like a killed one
    rec = read_recording(tmp_path)
    got = rec.raw.seq
    assert np.all(np.diff(got) > 0)                                 # in order, nothing doubled
    # exactly the blocks that arrived while no file could be opened are missing, and they were counted
    missing = sorted(set(range(100)) - set((got // 50).tolist()))
    assert len(missing) == st["dropped"] and missing == list(range(dropped_at, dropped_at + len(missing)))
    assert len(seqs) < dropped_at                                   # the unfinished chunk went to file 2
    assert st["messages_written"] == 100 - st["dropped"] and st["pending"] == 0
    assert st["bytes_written"] == sum(Path(f).stat().st_size for f in log.files)


def test_a_disk_that_stays_full_keeps_memory_bounded_and_leaves_no_empty_files(tmp_path, monkeypatch):
    """Room for a file's header but never for a chunk: each retry fails; nothing piles up in memory
    or on disk, and once space returns every message not counted as dropped is in the recording."""
    clock = Clock(monkeypatch)
    FillingDisk.free = 10**9
    log = McapLogger(tmp_path, unit="u", chunk_size=16_384, backlog_mb=0.05, flush_interval_s=0.2, retry_s=1.0,
                     opener=FillingDisk)
    bs = blocks(300)
    for b in bs[:20]:
        log.write_raw(b)
        clock.t += 0.1
    on_disk = log.status()["messages_written"]
    FillingDisk.free = 3_000                                        # a header fits, a chunk never does
    worst = 0
    for b in bs[20:250]:
        log.write_raw(b)
        clock.t += 0.1
        worst = max(worst, log._pending_bytes)
    st = log.status()
    assert st["errors"] >= 10 and st["dropped"] > 100              # it kept trying, and counted the losses
    assert worst <= log.backlog_bytes + log.chunk_size + 20_000     # bounded: backlog + one chunk + one block
    FillingDisk.free = 10**9
    for b in bs[250:]:
        log.write_raw(b)
        clock.t += 0.1
    log.close()
    st = log.status()
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted(Path(f).name for f in log.files) and len(names) == 2   # no header-only leftovers
    got = read_recording(tmp_path).raw.seq
    assert np.all(np.diff(got) > 0) and got.size // 50 == 300 - st["dropped"] == st["messages_written"]
    # what was on disk stays; from the first retry after space returned (1 s = 10 blocks) all is there
    assert set(range(on_disk)) | set(range(260, 300)) <= set((got // 50).tolist())


def test_settings_are_checked_and_close_is_idempotent(tmp_path):
    with pytest.raises(ConfigError, match="unit 'a/b' is not allowed"):
        McapLogger(tmp_path, unit="a/b")
    with pytest.raises(ConfigError, match="compression: 'gzip' is not allowed"):
        McapLogger(tmp_path, unit="u", compression="gzip")
    with pytest.raises(ConfigError, match="rotate_mb"):
        McapLogger(tmp_path, unit="u", rotate_mb=0)
    log = McapLogger(tmp_path / "c.mcap", unit="u")
    log.write_raw(blocks(1)[0])
    log.close()
    log.close()
    log.write_raw(blocks(1)[0])                                     # after close: counted, not raised
    assert log.status()["dropped"] == 1 and log.status()["last_error"] == "write after close"
    assert len(read_recording(tmp_path / "c.mcap").raw_blocks) == 1


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_every_compression_reads_back(tmp_path, compression):
    b = blocks(1, n=2000, p=2)[0]
    b = SampleBlock(b.t_s, b.seq, np.round(b.field_nT), b.temp_C.round(1), b.flags)   # compressible, like ADC data
    with McapLogger(tmp_path / "x.mcap", unit="u", compression=compression) as log:
        log.write_raw(b)
    assert same(read_recording(tmp_path / "x.mcap").raw.field_nT, b.field_nT)
    with open(tmp_path / "x.mcap", "rb") as f:
        (chunk,) = list(make_reader(f).get_summary().chunk_indexes)
    assert chunk.compression == ("" if compression == "none" else compression)
    if compression != "none":
        assert chunk.compressed_size < 0.8 * chunk.uncompressed_size


def test_health_carries_the_counters_and_the_logger_status(tmp_path):
    log = McapLogger(tmp_path / "h.mcap", unit="u", flush_interval_s=0)
    log.write_raw(blocks(1)[0])
    log.write_health({"frames_accepted": 50, "crc_failures": 1})
    log.close()
    (h,) = read_recording(tmp_path / "h.mcap").health
    assert h["counters"] == {"frames_accepted": 50, "crc_failures": 1}
    assert h["recording"]["messages_written"] == 1 and h["recording"]["errors"] == 0
