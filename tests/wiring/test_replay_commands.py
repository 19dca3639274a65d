"""A replay's own recording (`replay --out`) replays again, bit for bit, when the live run had commands:
the copy carries the initial calibration and every command at its seq. A replay that compares nothing
says so, and one whose live run had corrected output that the replay does not give fails (found by
trying the workflow with --help alone, issue 16)."""

from __future__ import annotations

import json
from pathlib import Path

from fluxcal.service.io.calfile import calibration_to_dict
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.io.recordings.writer import McapLogger
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.config import config_from_dict
from fluxcal.service.wiring.daemon import build_pipeline

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "grad1-sim-30s.mcap"


def _live_run_with_a_command(path: Path, commands=((2000, "freeze", None), (4000, "unfreeze", None)),
                             legacy: bool = False) -> None:
    """What the daemon records, with a freeze 2000 samples in and an unfreeze at 4000 (or `commands`: (sample,
    verb, payload)); legacy: as a service before applied calibrations were held (its apply events carry no note)."""
    src = read_recording(SAMPLE)
    cfg = config_from_dict(json.loads(src.metadata["config"]), "sample")
    initial = None
    for ev in src.events:
        if ev.get("kind") == "initial" and ev.get("calibration"):
            from fluxcal.service.io.calfile import calibration_from_dict

            initial = calibration_from_dict(ev["calibration"], "initial")
    pl = build_pipeline(cfg, initial)
    log = McapLogger(path.parent, unit=cfg.unit.name, filename=path.name, metadata=dict(src.metadata))
    log.write_event({"kind": "initial", "seq": 0,
                     "calibration": None if initial is None else calibration_to_dict(initial)})
    done = 0
    for block in src.raw_blocks:
        for at, verb, payload in commands:
            if done < at <= done + block.n_samples:
                head = block.slice(0, at - done)
                r = pl.process(head)
                log.write_raw(head)
                if r.corrected is not None:
                    log.write_corrected(r.corrected)
                seq = int(block.seq[at - done])
                ev = pl.command(verb, payload, seq=seq, t_s=float("nan"))
                if verb == "apply":
                    ev.detail["calibration"] = calibration_to_dict(payload)
                    if legacy:
                        pl.held = False
                        ev.detail.pop("note")
                log.write_event({"kind": "command", "seq": seq, **ev.detail})
                block = block.slice(at - done, block.n_samples)
                done = at
        r = pl.process(block)
        log.write_raw(block)
        if r.corrected is not None:
            log.write_corrected(r.corrected)
        done += block.n_samples
    log.close()


def test_a_replays_copy_replays_identically_with_the_commands_in_it(tmp_path, capsys):
    live = tmp_path / "live.mcap"
    _live_run_with_a_command(live)
    assert main(["replay", str(live), "--out", str(tmp_path / "again.mcap")]) == 0
    first = capsys.readouterr().out
    again = read_recording(tmp_path / "again.mcap")
    assert [e["name"] for e in again.events if e.get("kind") == "command"] == ["freeze", "unfreeze"]
    assert any(e.get("kind") == "initial" for e in again.events)
    assert main(["replay", str(tmp_path / "again.mcap")]) == 0
    out = capsys.readouterr().out
    n = int(first.split("compared with the recording: ")[1].split(",")[0])
    assert n >= 1000 and f"compared with the recording: {n}, bit-identical: {n}" in out       # made here


def test_nothing_to_compare_is_said(tmp_path, capsys):
    src = read_recording(SAMPLE)
    bare = tmp_path / "bare.mcap"
    log = McapLogger(tmp_path, unit="grad1", filename=bare.name, metadata=dict(src.metadata))
    for b in src.raw_blocks[:20]:                    # a short stretch: never usable, no corrected output
        log.write_raw(b)
    log.close()
    assert main(["replay", str(bare)]) == 0
    assert "nothing to compare" in capsys.readouterr().err


def test_an_apply_replays_as_its_live_run_had_it_held_or_not(tmp_path, capsys):
    """An applied calibration is held until reset; a recording made before that (its apply event has no note)
    replays as its live run went, the next usable candidate replacing the applied one. Both bit for bit."""
    import numpy as np

    from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration

    lab = ArrayCalibration("ellipsoid", "rotation", [ProbeCalibration(n, np.array([3.0, -2.0, 1.0]), np.eye(3))
                                                     for n in ("s1", "s2")])
    for legacy in (False, True):
        live = tmp_path / f"live-{legacy}.mcap"
        _live_run_with_a_command(live, ((3000, "apply", lab),), legacy=legacy)
        capsys.readouterr()
        assert main(["replay", str(live)]) == 0
        out = capsys.readouterr().out
        n = int(out.split("compared with the recording: ")[1].split(",")[0])
        assert n >= 2900 and f"compared with the recording: {n}, bit-identical: {n}" in out   # made here
        # held: the applied offsets correct every later sample; legacy: a candidate took over before the end
        last = read_recording(live).corrected_blocks[-1]
        assert (last.cal_id == 1) is (not legacy), last.cal_id
