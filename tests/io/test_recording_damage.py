"""A damaged record in the middle of a recording is damage, not a stopped writer (issue 27): one bit flipped in
any chunk's length, or the length lowered by 1000, loses at most that chunk, in a finished file (its chunk index
places every chunk) and in a killed writer's (no footer: reading resynchronises on the next readable record);
replay says damage, `repair` keeps every other chunk; a chunk whose contents are lost is a hole, which replay
reports as a hole (its seq span) and not as corrected samples that differ from the live run, and which a repaired
copy records, as it records a cut tail."""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers import drain
from mcap.reader import make_reader

from fluxcal.drivers.mcap_records import RECORD_HEAD, chunk_records, parse_chunk
from fluxcal.drivers.mcap_source import McapSource
from fluxcal.service.io.recordings.reader import read_recording, repair_recording
from fluxcal.service.io.recordings.writer import McapLogger
from fluxcal.service.wiring.cli import main

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.io.recordings.repair", "fluxcal.drivers.mcap_scan")

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "grad1-sim-30s.mcap"
DAMAGES = ("bit 0", "bit 17", "bit 63", "minus 1000")


def _damage(data: bytes, start: int, how: str) -> bytes:
    """The file with the length field of the record at `start` damaged: one bit flipped, or lowered by 1000."""
    blob = bytearray(data)
    length = int.from_bytes(blob[start + 1:start + RECORD_HEAD], "little")
    length = (length - 1000) % (1 << 64) if how == "minus 1000" else length ^ (1 << int(how.split()[1]))
    blob[start + 1:start + RECORD_HEAD] = length.to_bytes(8, "little")
    return bytes(blob)


class Written:
    """The sample recording written again as the service writes a run, in ~20 chunks: its bytes, the chunks'
    (start, length) and the raw seqs in each, and the same file as a killed writer leaves it (no summary)."""

    def __init__(self, path: Path) -> None:
        src = read_recording(SAMPLE)
        keep = {k: v for k, v in src.metadata.items() if k in ("n_probes", "lsb_nT", "probe_names", "positions_m",
                                                                 "config")}
        # corrected output computed where the sample was made: the copy names that arithmetic (unknown)
        log = McapLogger(path.parent, unit="grad1", filename=path.name, chunk_size=24 << 10, flush_interval_s=1e9,
                         vectors_period_s=0, metadata=keep, arithmetic=src.arithmetic)
        for ev in src.events:
            log.write_event(ev)
        cor, cal = iter(src.corrected_blocks), iter(src.calibration)
        nxt_c, nxt_e = next(cor, None), next(cal, None)
        for b in src.raw_blocks:
            log.write_raw(b)
            while nxt_c is not None and nxt_c.seq[-1] <= b.seq[-1]:
                log.write_corrected(nxt_c)
                nxt_c = next(cor, None)
            while nxt_e is not None and nxt_e["seq"] <= b.seq[-1] + 1:
                log.write_calibration(nxt_e)
                nxt_e = next(cal, None)
        log.close()
        self.path, self.data = path, path.read_bytes()
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        raw_ids = {i for i, c in summary.channels.items() if c.topic.endswith("/raw")}
        self.chunks: list[tuple[int, int]] = []
        self.seqs: list[set[int]] = []                      # the raw samples in each chunk
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            s, n = ci.chunk_start_offset, ci.chunk_length
            recs = chunk_records(parse_chunk(self.data[s + RECORD_HEAD:s + n]))
            seq: set[int] = set()
            for m in recs:
                if getattr(m, "channel_id", None) in raw_ids:
                    k = int.from_bytes(m.data[8:12], "little")
                    seq.update(np.frombuffer(m.data, "<i8", k, 12 + 8 * k).tolist())
            self.chunks.append((s, n))
            self.seqs.append(seq)
        at = len(self.data) - 8 - RECORD_HEAD - 20
        summary_start = struct.unpack_from("<Q", self.data, at + RECORD_HEAD)[0]
        self.killed = self.data[:summary_start - RECORD_HEAD - 4]       # up to its data end: no summary, no footer
        self.all = set().union(*self.seqs)


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> Written:
    w = Written(tmp_path_factory.mktemp("damage") / "live.mcap")
    assert len(w.chunks) >= 12 and len(w.all) == 6000
    return w


def _seqs(rec) -> set[int]:
    return set(rec.raw.seq.tolist())


@pytest.mark.parametrize("layout", ["finished", "killed"])
def test_a_damaged_chunk_length_loses_at_most_that_chunk_for_every_chunk(written, layout, tmp_path):
    bad, fixed = tmp_path / "bad.mcap", tmp_path / "fixed.mcap"
    data = written.data if layout == "finished" else written.killed
    kept_whole = 0
    for k, (start, _) in enumerate(written.chunks):
        others = written.all - written.seqs[k]
        for how in DAMAGES:
            bad.write_bytes(_damage(data, start, how))
            rec = read_recording(bad)
            got = _seqs(rec)
            assert others <= got <= written.all, (k, how)                  # at most that chunk lost
            said = rec.report.damaged
            assert said and all("not a stopped writer" in d for d in said), (k, how, said)
            assert (rec.truncated == []) if layout == "finished" else all("no footer" in t for t in rec.truncated)
            kept_whole += got == written.all
            report = repair_recording(bad, fixed)                         # every other chunk kept
            again = read_recording(fixed)
            assert others <= _seqs(again) == got and report.damaged and not again.report.damaged, (k, how)
    # the damaged chunk itself is read too: by its index entry, or as the chunk between the damage and the next
    # readable record, its CRC intact
    assert kept_whole == len(written.chunks) * len(DAMAGES)


def test_the_replay_source_and_the_replay_say_damage_not_a_stopped_writer(written, tmp_path, capsys, caplog):
    bad = tmp_path / "bad.mcap"
    start, _ = written.chunks[len(written.chunks) // 2]
    bad.write_bytes(_damage(written.data, start, "bit 17"))
    with caplog.at_level(logging.WARNING, logger="fluxcal.replay"):
        blocks = drain(McapSource(bad))
    assert set(np.concatenate([b.seq for b in blocks]).tolist()) == written.all
    assert "not a stopped writer" in caplog.text and "writer was stopped" not in caplog.text
    assert main(["replay", str(bad)]) == 0
    out, err = capsys.readouterr()
    assert f"at byte {start}: damaged (not a stopped writer)" in err and "its CRC holds: nothing lost" in err
    assert "writer was stopped" not in err and "compared with the recording: 2000" in out


def test_a_lost_chunk_is_a_hole_in_replay_and_the_repaired_copy_records_it(written, tmp_path, capsys):
    """Its contents damaged (a byte of its compressed data), a chunk among the corrected samples is lost: replay
    says the hole and its seq span, compares the samples before it and does not call the rest a mismatch."""
    k = next(i for i, s in enumerate(written.seqs) if s and min(s) > 4600 and max(s) < 5600)
    start, n = written.chunks[k]
    lost = sorted(written.seqs[k])
    blob = bytearray(written.data)
    blob[start + n - 40] ^= 0x20
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(blob))
    rec = read_recording(bad)
    assert _seqs(rec) == written.all - set(lost) and [h.seq_span() for h in rec.holes] == [(lost[0], lost[-1])]
    hole = f"a hole of {len(lost)} samples at seq {lost[0]}-{lost[-1]}"
    assert main(["replay", str(bad)]) == 0
    out, err = capsys.readouterr()
    assert hole in err and "not a stopped writer" in err
    assert f"from seq {lost[0]} on are not compared" in err and "differ from the live run" not in err
    compared = int(out.split("compared with the recording: ")[1].split(",")[0])
    assert compared == lost[0] - 4000                                # the corrected samples before the hole
    fixed = tmp_path / "fixed.mcap"
    assert main(["repair", str(bad), str(fixed)]) == 0
    assert f"hole: {hole}" in capsys.readouterr().out
    again = read_recording(fixed)
    assert not again.report.damaged and [h.seq_span() for h in again.holes] == [(lost[0], lost[-1])]
    record = json.loads(again.report.repaired["holes"])
    assert record[0]["units"]["grad1"]["seq_before"] == lost[0] - 1 and record[0]["units"]["grad1"]["seq_after"] \
        == lost[-1] + 1 and record[0]["at_byte"] == start
    assert main(["replay", str(fixed)]) == 0                          # the repaired copy: the same hole, said
    out, err = capsys.readouterr()
    assert hole in err and "differ from the live run" not in err and f"compared with the recording: {compared}," in out


def test_a_repaired_copy_of_a_killed_writers_file_records_that_it_was_cut(written, tmp_path, capsys):
    cut = tmp_path / "cut.mcap"
    start, n = written.chunks[len(written.chunks) // 2]
    cut.write_bytes(written.killed[:start + n // 2])                 # the writer died inside this chunk
    before = read_recording(cut)
    assert before.truncated and not before.report.damaged and not before.holes
    fixed = tmp_path / "fixed.mcap"
    assert main(["repair", str(cut), str(fixed)]) == 0
    capsys.readouterr()
    again = read_recording(fixed)
    assert not again.truncated and not again.warnings                 # whole now, nothing missing in the middle
    last = int(before.raw.seq[-1])
    record = json.loads(again.report.repaired["cut"])
    assert record["last"]["grad1"]["seq"] == last and record["bytes"] == len(cut.read_bytes()) - start
    assert main(["replay", str(fixed)]) == 0
    err = capsys.readouterr().err
    assert "repaired copy of cut.mcap, whose writer was stopped" in err and f"last sample kept: seq {last}" in err


@pytest.mark.parametrize("command", ["fit", "diagnose", "inspect"])
def test_a_file_cut_within_its_first_40_bytes_is_said_in_one_line_never_a_traceback(command, tmp_path, capsys):
    """The head of a real recording, 0 to 40 bytes of it (the magic, the header record cut anywhere), and a few
    bytes that are no MCAP at all: every reader that sniffs the format says what is wrong with the file in one line
    naming it, with the exit status of any other damaged file (2), never a traceback (issue: `struct.error` from
    the format's sniffing on a 7-byte file)."""
    head = SAMPLE.read_bytes()[:41]                 # the magic (8 bytes), the header record (24), a metadata record
    cases = {f"head{n}.mcap": head[:n] for n in range(41)}
    cases.update({"garb.mcap": b"garbage", "one.mcap": b"\x00"})
    for name, blob in cases.items():
        path = tmp_path / name
        path.write_bytes(blob)
        assert main([command, str(path)], install_signals=False) == 2, name
        out, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"fluxcal {command}: {path}: "), (name, err)
        assert "Traceback" not in err and "struct.error" not in err and not out, (name, err)
        n = len(blob)
        said = ("not an MCAP file" if not head.startswith(blob) else "empty (0 bytes)" if not n else
                f"cut inside its magic ({n} of 8 bytes)" if n < 8 else "no footer" if n in (8, 32) else
                "cut inside a header record at byte 8" if n < 32 else "cut inside a metadata record at byte 32")
        assert said in err, (name, err)
