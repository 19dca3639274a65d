"""`fluxcal decode` through fluxcal.service.wiring.cli.main: a serial capture that starts mid-frame with noise and
CAN logs written by python-can give exactly the intact samples; bad input gives one line on
stderr, exit status 2, and no output file."""

from __future__ import annotations

import csv
from pathlib import Path

import can
import numpy as np
import pytest

from fluxcal.drivers import icd
from fluxcal.drivers.block import FLAG_TEMP_INVALID
from fluxcal.service.wiring.cli import main


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open() as f:
        rows = list(csv.reader(f))
    return rows[0], np.array([[float(v) for v in r] for r in rows[1:]])


def expected_columns(n: int) -> list[str]:
    return (["t"] + [f"s{k}_{a}" for k in range(1, n + 1) for a in "xyz"] + [f"s{k}_temp" for k in range(1, n + 1)]
            + ["seq", "flags"])


def run(capsys, *argv: str) -> tuple[int, str]:
    rc = main(["decode", *map(str, argv)])
    return rc, capsys.readouterr().err


def test_serial_capture_mid_frame_with_noise(tmp_path, capsys, icd_truth):
    n, lsb = 2, 0.005
    truth = icd_truth(500, n, seed=21)
    truth.counts[10, 0, 1] = 2147483647                      # saturated: nan in the CSV
    truth.flags[12] = FLAG_TEMP_INVALID
    fl = icd.frame_length(n)
    frames = [truth.take(slice(i, i + 1)).serial_bytes() for i in range(len(truth))]
    rng = np.random.default_rng(1)
    capture = bytearray(frames[0][30:])                      # the recording began mid-frame
    for i, f in enumerate(frames[1:], start=1):
        if i == 200:
            f = f[:5] + bytes([f[5] ^ 0x40]) + f[6:]       # a bit error: CRC failure
        if i % 97 == 0:
            capture += rng.integers(0, 256, 33, dtype=np.uint8).tobytes()   # line noise
        capture += f
    capture += frames[0][:40]                                # and ended mid-frame
    path = tmp_path / "capture.bin"
    path.write_bytes(bytes(capture))
    out = tmp_path / "out.csv"
    rc, err = run(capsys, path, "--probes", n, "--lsb-nT", lsb, "--out", out)
    assert rc == 0, err
    keep = np.ones(len(truth), bool)
    keep[[0, 200]] = False
    t = truth.take(keep)
    header, table = read_csv(out)
    assert header == expected_columns(n)
    assert len(table) == len(t)
    assert np.array_equal(np.round(table[:, 0] * 1e6).astype(np.int64), t.t_us)   # exact microseconds
    fields = table[:, 1:1 + 3 * n].reshape(-1, n, 3)
    sat = t.counts == 2147483647
    assert np.isnan(fields[sat]).all() and sat.sum() == 1
    assert np.array_equal(np.round(fields[~sat] / lsb).astype(np.int64), t.counts[~sat])
    temps = table[:, 1 + 3 * n:1 + 4 * n]
    bad_temp = (t.flags & FLAG_TEMP_INVALID) != 0
    assert np.isnan(temps[bad_temp]).all()
    assert np.array_equal(np.round(temps[~bad_temp] * 100).astype(np.int64), t.temp_raw[~bad_temp])
    assert np.array_equal(table[:, -2].astype(np.int64), t.seq)
    assert np.array_equal(table[:, -1].astype(np.int64), t.flags)
    assert f"frames accepted {len(t)}, CRC failures 1" in err
    assert "sequence gaps 1 (1 samples missed)" in err and "saturated axes 1" in err
    assert set(tmp_path.iterdir()) == {path, out}                 # no temporary file left behind


def write_can_log(path: Path, truth, rate_hz: float, lose: int | None, rng: np.random.Generator) -> None:
    ids, payloads = truth.can_frames()
    per = ids.size // len(truth)
    sample_of = np.repeat(np.arange(len(truth)), per)
    order = np.argsort(sample_of + rng.uniform(0, 3, sample_of.size), kind="stable")   # neighbours interleave
    # the host stamps frames as they come: evenly spread, with some jitter
    stamps = 1_700_000_000.0 + np.arange(ids.size) / (rate_hz * per) + rng.uniform(0, 50e-6, ids.size)
    with can.Logger(str(path)) as log:
        for pos, j in enumerate(order.tolist()):
            if j == lose:
                continue
            log.on_message_received(can.Message(timestamp=float(stamps[pos]), arbitration_id=int(ids[j]),
                                                data=payloads[j].tobytes(), is_extended_id=False, channel="can0"))


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf", ".csv"])
def test_can_log_every_format(tmp_path, capsys, icd_truth, suffix):
    n, rate = 2, 500.0
    truth = icd_truth(300, n, seed=4)
    log = tmp_path / f"bus{suffix}"
    lose = 100 * 6 + 3                                         # sample 100 misses a frame
    write_can_log(log, truth, rate, lose, np.random.default_rng(2))
    out = tmp_path / "out.csv"
    rc, err = run(capsys, log, "--can", "--probes", n, "--out", out)
    assert rc == 0, err
    keep = np.arange(len(truth)) != 100
    t = truth.take(keep)
    header, table = read_csv(out)
    assert header == expected_columns(n)
    assert np.array_equal(table[:, -2].astype(np.int64), t.seq)
    assert np.array_equal(np.round(table[:, 1:7].reshape(-1, n, 3) / 0.001).astype(np.int64), t.counts)
    assert np.array_equal(np.round(table[:, 7:9] * 100).astype(np.int64), t.temp_raw)
    # no unit clock on CAN: t = seq / rate, the rate taken from the log's timestamps
    assert np.array_equal(table[:, 0], np.round(t.seq / rate, 9))
    assert "incomplete CAN samples 1" in err and "sequence gaps 1 (1 samples missed)" in err
    assert "t = seq / 500 Hz" in err


def test_missing_capture(tmp_path, capsys):
    rc, err = run(capsys, tmp_path / "nope.bin", "--probes", 2, "--out", tmp_path / "o.csv")
    assert rc == 2
    assert err.count("\n") == 1 and "nope.bin: capture file not found" in err
    assert list(tmp_path.iterdir()) == []


def test_capture_without_frames(tmp_path, capsys):
    path = tmp_path / "noise.bin"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    rc, err = run(capsys, path, "--probes", 2, "--out", tmp_path / "o.csv")
    assert rc == 2
    assert err.count("\n") == 1 and "no intact 2-probe ICD frame" in err and "--probes" in err
    assert list(tmp_path.iterdir()) == [path]                  # nothing half-written


def test_wrong_probe_count_says_which_is_right(tmp_path, capsys, icd_truth):
    path = tmp_path / "cap.bin"
    path.write_bytes(icd_truth(50, 2).serial_bytes())
    rc, err = run(capsys, path, "--probes", 4, "--out", tmp_path / "o.csv")
    assert rc == 2 and "it holds 2-probe frames: use --probes 2" in err
    assert err.count("\n") == 1


@pytest.mark.parametrize("argv, message", [
    (["--probes", "0"], "--probes: 0 is not allowed (allowed: 1..8"),
    (["--probes", "9"], "--probes: 9 is not allowed"),
    (["--probes", "2", "--lsb-nT", "-1"], "--lsb-nT: -1.0 is not allowed"),
    (["--probes", "2", "--can", "--base-id", "0x7FA"], "--base-id: 0x7fa is not allowed for 2 probes"),
])
def test_bad_options(tmp_path, capsys, icd_truth, argv, message):
    path = tmp_path / "cap.log"
    path.write_bytes(icd_truth(5, 2).serial_bytes())
    rc, err = run(capsys, path, *argv, "--out", tmp_path / "o.csv")
    assert rc == 2 and message in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == [path]


def test_bad_output_suffix(tmp_path, capsys, icd_truth):
    path = tmp_path / "cap.bin"
    path.write_bytes(icd_truth(5, 2).serial_bytes())
    rc, err = run(capsys, path, "--probes", 2, "--out", tmp_path / "o.txt")
    assert rc == 2 and "must end in .csv or .mcap" in err


def test_can_log_problems(tmp_path, capsys, icd_truth):
    log = tmp_path / "bus.log"
    write_can_log(log, icd_truth(20, 1), 100.0, None, np.random.default_rng(0))
    rc, err = run(capsys, log, "--can", "--probes", 1, "--base-id", "0x300", "--out", tmp_path / "o.csv")
    assert rc == 2 and "no CAN frame with the ids of a 1-probe unit (0x300..0x303)" in err
    rc, err = run(capsys, log, "--can", "--probes", 2, "--out", tmp_path / "o.csv")
    assert rc == 2 and "no complete sample" in err and "6 frames" in err
    bad = tmp_path / "bad.log"
    bad.write_text("this is not a candump log\n")
    rc, err = run(capsys, bad, "--can", "--probes", 1, "--out", tmp_path / "o.csv")
    assert rc == 2 and "bad.log: not a readable .log CAN log" in err
    other = tmp_path / "bus.txt"
    other.write_text("x")
    rc, err = run(capsys, other, "--can", "--probes", 1, "--out", tmp_path / "o.csv")
    assert rc == 2 and "unknown CAN log format '.txt'" in err
    assert not (tmp_path / "o.csv").exists()


def test_mcap_output(tmp_path, capsys, icd_truth):
    path = tmp_path / "cap.bin"
    path.write_bytes(icd_truth(50, 2).serial_bytes())
    out = tmp_path / "cap.mcap"
    rc, err = run(capsys, path, "--probes", 2, "--out", out)
    assert rc == 0, err
    assert "50 samples" in err and set(tmp_path.iterdir()) == {path, out}
    from fluxcal.service.io.recordings.reader import read_recording

    rec = read_recording(out)
    assert sum(b.n_samples for b in rec.raw_blocks) == 50 and rec.probe_names == ["s1", "s2"]
