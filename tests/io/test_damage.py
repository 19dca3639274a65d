"""A damaged or cut flight log is said once, in fluxcal's words (service/io/recordings/damage.py): pyulog printed
"File corruption detected ..." on stdout, so `fit --json` was no longer one JSON object, and pymavlink's C indexer
printed a line per unreadable byte (419 lines for 400 damaged bytes), with nothing a user could act on; a log cut
short was read without a word, and one cut before its first compass message was refused with "LOG_BITMASK must log
compass". Built from the formats' specifications (tests/flightlogs.py), damaged and cut at known places, and on
pymavlink's own test log, which is cut at 64 KiB."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink", reason="the ArduPilot reader's optional package: pip install 'fluxcal[ardupilot]'")
pytest.importorskip("pyulog", reason="the PX4 reader's optional package: pip install 'fluxcal[px4]'")

from flightlogs import simulated_flight, write_dataflash, write_ulog
from real_data import needs_real, real

from fluxcal.service.io.recordings.damage import library_output, ulog_walk
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.wiring import cli


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    """A DataFlash log and a ULog of one compass tumbling (1,500 samples at 25 Hz), whole."""
    d = simulated_flight(n=1500, rate_hz=25.0, seed=11, current=False)
    us = 30_000_000 + np.round(d["t_s"] * 1e6).astype(np.int64)
    n = us.size
    where = tmp_path_factory.mktemp("damage")
    write_dataflash(where / "whole.bin", [
        ("MAG", "QBhhhhhhhhhBQ", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S",
         {"TimeUS": us, "I": np.zeros(n), **{f"Mag{a}": np.round(d["field_nT"][:, 0, c] / 100.0)
                                             for c, a in enumerate("XYZ")},
          **{f"{k}{a}": np.zeros(n) for k in ("Ofs", "MO") for a in "XYZ"}, "Health": np.ones(n), "S": us})])
    g = d["field_nT"][:, 0] / 1e5
    write_ulog(where / "whole.ulg", [("sensor_mag", 0,
                                      [("uint64_t", "timestamp"), ("uint32_t", "device_id"), ("float", "x"),
                                       ("float", "y"), ("float", "z")],
                                      {"timestamp": us, "device_id": np.full(n, 7), "x": g[:, 0], "y": g[:, 1],
                                       "z": g[:, 2]})])
    return {"bin": where / "whole.bin", "ulg": where / "whole.ulg"}


def _variant(src: Path, dst: Path, *, cut: int | None = None, garble: tuple[int, int] | None = None) -> Path:
    data = bytearray(src.read_bytes())
    if garble is not None:
        at, length = garble
        data[at:at + length] = bytes((7 * k + 1) % 251 for k in range(length))    # no message's header (a3 95)
    dst.write_bytes(bytes(data[:cut] if cut is not None else data))
    return dst


def _fit_json(capfd, path: Path) -> tuple[int, dict, str]:
    """fit --json: its status, the one JSON object on stdout (whatever the readers print, at the file descriptors
    too), and stderr."""
    capfd.readouterr()
    status = cli.main(["fit", str(path), "--json"])
    out, err = capfd.readouterr()
    return status, json.loads(out), err


def test_a_whole_log_is_said_whole(logs, capfd):
    for path in logs.values():
        status, obj, err = _fit_json(capfd, path)
        assert status == 0 and obj["sensors"][0]["name"] == "s1"
        assert "damaged" not in err and "cut short" not in err
    assert ulog_walk(logs["ulg"]) == (0, None)


def test_damaged_bytes_in_a_dataflash_log_are_one_warning_with_their_count(logs, tmp_path, capfd):
    size = logs["bin"].stat().st_size
    bad = _variant(logs["bin"], tmp_path / "bad.bin", garble=(size // 2, 300))
    status, obj, err = _fit_json(capfd, bad)
    assert status == 0 and obj["sensors"][0]["name"] == "s1"           # the rest read and fitted
    said = [line for line in err.splitlines() if "damaged:" in line]
    assert len(said) == 1 and "bad header" not in err and "Skipped" not in err, err
    skipped = int(said[0].split("damaged: ")[1].split(" byte(s)")[0].replace(",", ""))
    assert 300 <= skipped <= 300 + 2 * 34        # the damaged bytes and the parts of the two messages they cut
    whole = load_data(logs["bin"]).block.n_samples
    lost = whole - load_data(bad).block.n_samples
    assert 1 <= lost <= 300 // 34 + 2                                  # the MAG messages (34 bytes) in them, lost


def test_a_cut_log_says_so_and_a_log_cut_before_its_compass_is_refused_for_that(logs, tmp_path, capfd):
    for kind in ("bin", "ulg"):
        size = logs[kind].stat().st_size
        cut = _variant(logs[kind], tmp_path / f"cut.{kind}", cut=int(size * 0.6) + 5)
        status, obj, err = _fit_json(capfd, cut)
        assert status == 0, obj
        said = [line for line in err.splitlines() if "cut short: its last message lacks" in line]
        assert len(said) == 1, err
        assert 0.55 < load_data(cut).block.n_samples / load_data(logs[kind]).block.n_samples < 0.65
    head = _variant(logs["bin"], tmp_path / "head.bin", cut=120)         # in the FMT messages, before MAG's
    status, obj, _ = _fit_json(capfd, head)
    assert status == 2 and "no MAG messages in the log" in obj["refused"]["reason"]
    assert "the log is cut short" in json.dumps(obj) and "LOG_BITMASK" not in json.dumps(obj)


def test_a_corrupt_ulog_keeps_its_json_and_says_the_damage(logs, tmp_path, capfd):
    size = logs["ulg"].stat().st_size
    bad = _variant(logs["ulg"], tmp_path / "bad.ulg", garble=(size // 2, 200))
    status, obj, err = _fit_json(capfd, bad)
    assert status == 0 and obj["sensors"][0]["name"] == "s1"
    assert "File corruption" not in err
    said = [line for line in err.splitlines() if "damaged at byte" in line]
    assert len(said) == 1 and "the reader found messages it could not decode" in said[0], err
    at = int(said[0].split("damaged at byte ")[1].split(":")[0].replace(",", ""))
    assert size // 2 - 60 <= at <= size // 2 + 200                    # where the garbled bytes are (a message back)


def test_library_output_takes_python_and_file_descriptor_output(capfd):
    import os

    with library_output() as printed:
        print("from python")
        os.write(2, b"from C, at the descriptor\n")
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert printed == ["from python", "from C, at the descriptor"]


@needs_real("ardupilot_pymavlink_test.BIN")
def test_pymavlink_own_test_log_is_said_cut(capfd):
    """pymavlink's test log is 65,536 bytes: cut at 64 KiB inside a message, now said."""
    capfd.readouterr()
    assert cli.main(["inspect", str(real("ardupilot_pymavlink_test.BIN"))]) == 0
    assert "cut short: its last message lacks 21 byte(s)" in capfd.readouterr().out
