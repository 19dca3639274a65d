"""`repair_recording`: a killed writer's or a damaged recording copied into a finished, indexed one that says
what its original lost ("fluxcal.repair" metadata: the holes with their seq and time spans, the cut tail)."""

from __future__ import annotations

import json
from pathlib import Path

from fluxcal.drivers.errors import RecordingError
from fluxcal.drivers.mcap_source import HoleTracker, ReadReport, iter_file_records, recording_files, unit_of_topic
from fluxcal.drivers.outputs import refuse_linked_folder, temp_beside
from fluxcal.service.io.encoding import RAW_ENCODING

#: the metadata record a repaired copy carries
REPAIR_RECORD = "fluxcal.repair"


def _repair_record(f: Path, report: ReadReport, first_hole: int, first_cut: int, cut_bytes: int,
                   last: dict[str, tuple[int, float]], earlier: dict[str, str]) -> dict[str, str]:
    """The "fluxcal.repair" record of the copy of `f`: the holes (an earlier repair's too), the cut tail with
    the last sample kept per unit, and the damage found, as JSON strings."""
    try:
        holes = json.loads(earlier.get("holes", "[]"))
    except json.JSONDecodeError:
        holes = []
    holes += [h.to_json() for h in report.holes[first_hole:]]
    cut = report.truncated[first_cut:]
    record = {"repaired_from": f.name, "holes": json.dumps(holes),
              "damaged": json.dumps([d for d in report.damaged if d.startswith(f"{f}:")])}
    if cut:
        record["cut"] = json.dumps({"lines": cut, "bytes": cut_bytes,
                                    "last": {u: {"seq": s, "t_s": t} for u, (s, t) in last.items()}})
    elif earlier.get("cut"):
        record["cut"] = earlier["cut"]
    return record


def repair_notes(report: ReadReport) -> list[str]:
    """What a repaired copy says of its original's cut tail (its holes are in report.holes): one line or none."""
    text = report.repaired.get("cut")
    if not text:
        return []
    try:
        cut = json.loads(text)
        last = "; ".join(f"{u}'s last sample kept: seq {v['seq']} (unit time {float(v['t_s']):.3f} s)"
                         for u, v in (cut.get("last") or {}).items())
        return [f"repaired copy of {report.repaired.get('repaired_from', '?')}, whose writer was stopped: "
                f"{cut.get('bytes', 0)} bytes at its end held no complete record and were cut"
                + (f"; {last}" if last else "")]
    except (json.JSONDecodeError, AttributeError, KeyError, TypeError, ValueError):
        return [f"repaired copy of {report.repaired.get('repaired_from', '?')}: its record of the cut is damaged"]


def repair_recording(src: str | Path, dst: str | Path, *, compression: str = "lz4") -> ReadReport:
    """Copy every readable record of `src` (a killed writer's file, a damaged one, or a directory of them) into
    a finished, indexed MCAP file `dst` (or directory `dst`, same file names): schemas, channels, messages with
    their log_time, publish_time and sequence, metadata, attachments. Damage is read past (by the chunk index
    where the file has one, else by resynchronising on the next readable record), so every intact chunk is
    kept; what was lost (`holes`, with the samples' seq and time spans, `damaged`) and the cut tail (`truncated`)
    are in the returned report and in the copy's "fluxcal.repair" metadata record."""
    files = recording_files(src)
    src_is_dir = Path(src).is_dir()
    out_dir = Path(dst) if src_is_dir else Path(dst).parent
    refuse_linked_folder(out_dir, "repair: the destination")
    out_dir.mkdir(parents=True, exist_ok=True)
    report = ReadReport()
    for f in files:
        target = out_dir / f.name if src_is_dir else Path(dst)
        if target.resolve() == f.resolve():
            raise RecordingError(f"{target}: is the recording to repair: the repaired copy is written beside it, never over it; give another destination")
        _repair_file(f, target, report, compression)
    return report


def _repair_file(f: Path, target: Path, report: ReadReport, compression: str) -> None:
    """The repaired copy of one file `f` at `target` (written as target.partial, then renamed), ending with its
    "fluxcal.repair" record; what reading it lost is added to `report`."""
    from mcap.writer import Writer

    from .writer import COMPRESSIONS

    report.files.append(str(f))
    first_hole, first_cut, cut_bytes = len(report.holes), len(report.truncated), report.truncated_bytes
    holes = HoleTracker(report)
    tmp = None
    try:
        tmp = temp_beside(target)                   # never a link planted at the name: renamed onto `target`
        with open(tmp, "wb") as fh:
            w = Writer(fh, compression=COMPRESSIONS[compression])
            started, earlier = _copy_records(f, w, report, holes)
            holes.finish()
            if not started:
                w.start(profile="", library="fluxcal repair")
            w.add_metadata(REPAIR_RECORD, _repair_record(f, report, first_hole, first_cut,
                                                         report.truncated_bytes - cut_bytes, holes.last(), earlier))
            w.finish()
        tmp.replace(target)
    except OSError as e:
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        raise RecordingError(f"{target}: cannot write the repaired file: {e}") from None


def _copy_records(f: Path, w, report: ReadReport, holes: HoleTracker) -> tuple[bool, dict[str, str]]:
    """Every readable record of `f` written by the MCAP writer `w` (schemas and channels under new ids), the raw
    messages' samples shown to `holes`, the counts in `report`: (whether `w` was started, the metadata of an
    earlier repair's record, which the new one merges, or {})."""
    from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema

    started = False
    earlier: dict[str, str] = {}
    schema_ids: dict[int, int] = {0: 0}
    channel_ids: dict[int, int] = {}
    raw_units: dict[int, str] = {}          # channel id -> unit, of the raw channels
    for rec in iter_file_records(f, report, strict=False):
        holes.sync()
        if isinstance(rec, Header):
            if not started:
                w.start(profile=rec.profile, library=rec.library)
                started = True
            continue
        if not started:
            w.start(profile="", library="fluxcal repair")
            started = True
        if isinstance(rec, Schema):
            if rec.id not in schema_ids:
                schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
        elif isinstance(rec, Channel):
            if rec.id not in channel_ids and rec.schema_id in schema_ids:
                channel_ids[rec.id] = w.register_channel(rec.topic, rec.message_encoding,
                                                         schema_ids[rec.schema_id], rec.metadata)
                unit = unit_of_topic(rec.topic)
                if rec.message_encoding == RAW_ENCODING and unit is not None:
                    raw_units[rec.id] = unit
        elif isinstance(rec, Message):
            ch = channel_ids.get(rec.channel_id)
            if ch is None:
                report.skipped_messages += 1
                continue
            if rec.channel_id in raw_units:
                holes.raw(raw_units[rec.channel_id], rec.data)
            w.add_message(ch, log_time=rec.log_time, data=rec.data, publish_time=rec.publish_time,
                          sequence=rec.sequence)
            report.messages += 1
        elif isinstance(rec, Metadata):
            if rec.name == REPAIR_RECORD:      # a repaired file repaired again: one record, merged
                earlier = dict(rec.metadata)
                continue
            w.add_metadata(rec.name, rec.metadata)
            if rec.name == "fluxcal":
                report.metadata.update(rec.metadata)
        elif isinstance(rec, Attachment):
            w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
    return started, earlier

