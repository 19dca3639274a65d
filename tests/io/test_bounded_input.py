"""Bounded input (issue 27): a lab CSV, capture, CAN log or configuration that is no regular file (/dev/zero
behind a symlink, a FIFO, a directory) is refused before it is read; a file beyond the size limit or a line
beyond the line limit stops at once; values whose square would overflow are refused with the bound; the
configuration's numbers that size memory or time have upper bounds; SIGTERM stops a read between pieces."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import fluxcal.drivers.inputs as inputs
from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.config import MAX_CONFIG_BYTES, read_toml
from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.drivers.ringbuffer import RingBuffer
from fluxcal.drivers.sim.config import MAX_RUN_SAMPLES, load_sim_config
from fluxcal.service.io.recordings.labdata import MAX_MAGNITUDE, load_csv
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.wiring.cli import _sigterm_to_keyboard_interrupt, main
from fluxcal.service.wiring.config import WINDOW_BUDGET_BYTES, config_from_dict, sample_bytes

ROOT = Path(__file__).resolve().parents[2]
HEADER = "t,s1_x,s1_y,s1_z"


def lab_rows(n: int, seed: int = 1) -> list[str]:
    v = np.random.default_rng(seed).normal(size=(n, 3))
    v *= 50_000.0 / np.linalg.norm(v, axis=1, keepdims=True)
    return [f"{i * 0.01:.2f},{x + 200:.3f},{y - 300:.3f},{z + 100:.3f}" for i, (x, y, z) in enumerate(v)]


def fluxcal(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """The CLI as a user runs it; the timeout only guards against the hang this file is about."""
    return subprocess.run([sys.executable, "-m", "fluxcal.service.wiring.cli", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


# --- the red-team cases, end to end -------------------------------------------------------------------------

@pytest.mark.slow
def test_the_zero_device_as_a_csv_is_refused_before_it_is_read(tmp_path):
    link = tmp_path / "zero.csv"
    link.symlink_to("/dev/zero")
    for command in ("fit", "diagnose"):
        r = fluxcal(command, str(link), cwd=tmp_path)
        assert r.returncode == 2
        line = one_line(r.stderr)
        assert "zero.csv: is a character device (/dev/zero), not a regular file" in line


@pytest.mark.slow
def test_a_fifo_is_refused_without_hanging_in_open(tmp_path):
    for name in ("lab.csv", "rec.mcap"):            # the CSV reader and the dispatch to the MCAP reader
        fifo = tmp_path / name
        os.mkfifo(fifo)
        r = fluxcal("fit", str(fifo), cwd=tmp_path)   # open() of a FIFO without a writer would block
        assert r.returncode == 2
        assert f"{name}: is a FIFO (named pipe), not a regular file" in one_line(r.stderr)


@pytest.mark.slow
def test_values_whose_square_overflows_are_refused_with_the_bound(tmp_path):
    p = tmp_path / "huge.csv"
    p.write_text("\n".join([HEADER] + [f"{i * 0.01:.2f},1e308,1.0,2.0" for i in range(3000)]) + "\n")
    r = fluxcal("fit", str(p), cwd=tmp_path)
    assert r.returncode == 2
    line = one_line(r.stderr)
    assert "line 2, column 's1_x': 1e+308 is beyond the largest magnitude read, 1e15" in line
    assert "and 2990 more" in line


@pytest.mark.slow
def test_a_window_of_1e12_seconds_is_refused_naming_key_value_and_budget(tmp_path):
    cfg = tmp_path / "w.toml"
    cfg.write_text('[unit]\nname = "u1"\nn_probes = 2\n[source]\nkind = "sim"\nrun_s = 1\n[sim]\nrealtime = false\n'
                   '[estimator]\nwindow_s = 1e12\n[mcap]\nenabled = false\n[zenoh]\nlisten = ["tcp/127.0.0.1:0"]\n')
    r = fluxcal("run", "--config", str(cfg), cwd=tmp_path)
    assert r.returncode == 2
    line = one_line(r.stderr)
    top = (WINDOW_BUDGET_BYTES - 100 * sample_bytes(2)) // sample_bytes(2) / 200.0     # 0.5 s chunks at 200 Hz
    assert "estimator.window_s: 1e+12 is not allowed: 2e+14 samples of 2 probe(s) at 200 Hz" in line
    assert f"allowed: up to {top:.6g} s at this rate and probe count" in line and "within 1 GiB" in line


def test_decode_refuses_devices_fifos_and_directories(tmp_path, capsys):
    (tmp_path / "zero.bin").symlink_to("/dev/zero")
    (tmp_path / "zero.log").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "fifo.bin")
    (tmp_path / "dir.bin").mkdir()
    for name, kind in (("zero.bin", "a character device"), ("zero.log", "a character device"),
                       ("fifo.bin", "a FIFO (named pipe)"), ("dir.bin", "a directory")):
        extra = ["--can"] if name.endswith(".log") else []
        assert main(["decode", str(tmp_path / name), "--probes", "2", *extra, "--out", str(tmp_path / "o.csv")]) == 2
        assert f"{name}: is {kind}" in one_line(capsys.readouterr().err)
    assert not (tmp_path / "o.csv").exists()


def test_a_configuration_that_is_no_regular_file_or_too_big_or_too_deep_is_refused(tmp_path):
    (tmp_path / "zero.toml").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "fifo.toml")
    with pytest.raises(ConfigError, match=r"zero.toml: is a character device \(/dev/zero\)"):
        read_toml(tmp_path / "zero.toml")
    with pytest.raises(ConfigError, match=r"fifo.toml: is a FIFO"):
        read_toml(tmp_path / "fifo.toml")
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * MAX_CONFIG_BYTES + "\n")
    with pytest.raises(ConfigError, match=r"big.toml: larger than 1 MiB \(allowed: a configuration up to 1 MiB\)"):
        read_toml(big)
    deep = tmp_path / "deep.toml"
    deep.write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")      # RecursionError in tomllib
    with pytest.raises(ConfigError, match="nested too deeply"):
        read_toml(deep)
    latin = tmp_path / "latin.toml"
    latin.write_bytes(b'name = "\xe9"\n')
    with pytest.raises(ConfigError, match="not UTF-8 text"):
        read_toml(latin)


# --- the limits themselves -----------------------------------------------------------------------------------

def test_a_huge_file_without_a_line_break_stops_at_the_first_piece(tmp_path, monkeypatch):
    p = tmp_path / "flat.csv"
    with open(p, "wb") as f:
        f.truncate(200 << 20)                        # 200 MiB of zero bytes (sparse), no line break
    reads = []
    real = inputs._read_chunk
    monkeypatch.setattr(inputs, "_read_chunk", lambda f, n: reads.append(n) or real(f, n))
    with pytest.raises(DataError, match=r"flat.csv: line 1 is longer than 1 MiB without a line break \(allowed: "
                                        r"lines up to 1 MiB\): not a lab CSV"):
        load_csv(p)
    assert len(reads) == 1 and reads[0] == inputs.CHUNK_BYTES == 4 << 20


def test_the_size_limit_is_said_with_the_way_beyond_it(tmp_path, monkeypatch):
    p = tmp_path / "lab.csv"
    p.write_text("\n".join([HEADER, *lab_rows(40_000)]) + "\n")        # 1.4 MiB
    size = p.stat().st_size
    assert 1 << 20 < size < 2 << 20
    reads = []
    real = inputs._read_chunk
    monkeypatch.setattr(inputs, "_read_chunk", lambda f, n: reads.append(n) or real(f, n))
    monkeypatch.setenv("FLUXCAL_MAX_INPUT_MB", "1")
    with pytest.raises(DataError, match=rf"lab.csv: {size:,} bytes is beyond the size limit for a lab CSV, 1 MiB "
                                        r"\(allowed: up to 1 MiB; it is read into memory\): to read it anyway set "
                                        r"FLUXCAL_MAX_INPUT_MB=2 or more"):
        load_csv(p)
    assert reads == []                                                  # refused before reading
    monkeypatch.setenv("FLUXCAL_MAX_INPUT_MB", "2")
    assert load_csv(p).block.n_samples == 40_000
    monkeypatch.delenv("FLUXCAL_MAX_INPUT_MB")
    assert inputs.max_input_bytes() == inputs.DEFAULT_MAX_INPUT_MB << 20 == 1 << 30
    for bad in ("0", "-3", "lots", "1.5"):
        monkeypatch.setenv("FLUXCAL_MAX_INPUT_MB", bad)
        with pytest.raises(ConfigError, match=rf"FLUXCAL_MAX_INPUT_MB: '{bad}' is not allowed \(allowed: a whole "
                                              rf"number of MiB, at least 1; default 1024\)"):
            load_csv(p)


def test_a_sparse_file_beyond_the_size_limit_is_refused_before_any_read(tmp_path, monkeypatch):
    p = tmp_path / "sparse.csv"
    with open(p, "wb") as f:
        f.truncate(20 << 30)                         # 20 GiB, no blocks on disk
    monkeypatch.setattr(inputs, "_read_chunk", lambda f, n: pytest.fail("read"))
    with pytest.raises(DataError, match=r"20,480 MiB is beyond the size limit for a lab CSV, 1,024 MiB .* "
                                        r"FLUXCAL_MAX_INPUT_MB=20480 or more"):
        load_data(p)


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6])
def test_the_long_line_is_named_by_its_number_across_pieces_and_line_endings(tmp_path, monkeypatch, seed):
    """Line numbers as str.splitlines counts them (\\r\\n one break, \\r and \\n each one), with pieces of a few
    bytes so that lines and \\r\\n pairs straddle them."""
    rng = np.random.default_rng(seed)
    n = 60
    lengths = rng.integers(0, 30, n)
    if seed % 3:                                      # one line beyond the limit of 40 bytes (or none)
        lengths[rng.integers(5, n)] = 41 + rng.integers(0, 50)
    ends = rng.choice(["\n", "\r\n", "\r"], n)
    text = "".join("a" * int(k) + e for k, e in zip(lengths, ends))
    p = tmp_path / f"lines{seed}.txt"
    p.write_bytes(text.encode())
    monkeypatch.setattr(inputs, "CHUNK_BYTES", int(rng.integers(3, 17)))
    long = [i for i, line in enumerate(text.splitlines()) if len(line) > 40]
    if not long:
        assert bytes(inputs.read_bytes(p, max_line=40)) == text.encode()
        return
    with pytest.raises(DataError, match=rf"line {long[0] + 1} is longer than 40 bytes"):
        inputs.read_bytes(p, max_line=40)


def test_sigterm_stops_a_read_between_two_pieces(tmp_path, monkeypatch):
    """The CLI turns SIGTERM into KeyboardInterrupt, which a Python handler raises only between bytecodes:
    Path.read_text() of /dev/zero never gave it a turn. The reader reads in pieces; a SIGTERM that arrives during
    the second piece ends the read before the third."""
    p = tmp_path / "lab.csv"
    p.write_text("\n".join([HEADER, *lab_rows(20_000)]) + "\n")
    monkeypatch.setattr(inputs, "CHUNK_BYTES", 64 << 10)
    reads = []
    real = inputs._read_chunk

    def read_and_signal(f, n):
        reads.append(n)
        if len(reads) == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(f, n)

    monkeypatch.setattr(inputs, "_read_chunk", read_and_signal)
    before = signal.signal(signal.SIGTERM, _sigterm_to_keyboard_interrupt)
    try:
        with pytest.raises(KeyboardInterrupt):
            load_csv(p)
    finally:
        signal.signal(signal.SIGTERM, before)
    assert len(reads) == 2 and p.stat().st_size > 4 * (64 << 10)


def test_the_magnitude_bound_refuses_beyond_and_keeps_at_it(tmp_path):
    head = (HEADER + ",ref_total").split(",")
    rows = [(r + ",50000").split(",") for r in lab_rows(50)]

    def write(name: str, cells: list[list[str]]) -> Path:
        p = tmp_path / name
        p.write_text("\n".join([",".join(head), *(",".join(c) for c in cells)]) + "\n")
        return p

    at = [c[:4] + ["1e15" if i % 2 else "-1e15"] for i, c in enumerate(rows)]
    assert MAX_MAGNITUDE == 1e15 and np.all(np.abs(load_csv(write("ok.csv", at)).ref_total) == 1e15)
    # the first row for t, so that time still increases
    for row, column, value in ((7, "s1_y", "1.0000001e15"), (0, "t", "-1e300"), (30, "ref_total", "-2e15")):
        cells = [c[:] for c in rows]
        cells[row][head.index(column)] = value
        with pytest.raises(DataError, match=rf"line {row + 2}, column '{column}': {re.escape(f'{float(value):.10g}')} is beyond the "
                                            rf"largest magnitude read, 1e15 \(allowed: \|value\| <= 1e15"):
            load_csv(write(f"{column}.csv", cells))
    cells = [c[:] for c in rows]                      # NaN and inf in a probe's axis stay a saturated sample
    cells[3][1], cells[4][1] = "nan", "-inf"
    assert np.isnan(load_csv(write("nan.csv", cells)).block.field_nT[3:5, 0, 0]).all()


# --- the configuration's upper bounds ------------------------------------------------------------------------

def _sim_config(**estimator) -> dict:
    return {"unit": {"n_probes": 2}, "source": {"kind": "sim"}, "estimator": estimator}


def test_the_window_is_bounded_by_memory_at_the_units_rate_and_probe_count():
    per = sample_bytes(2)
    chunk = 100 * per                                                  # update_every_s 0.5 at 200 Hz
    top = (WINDOW_BUDGET_BYTES - chunk) // per / 200.0
    assert config_from_dict(_sim_config(window_s=top)).estimator.window_s == top
    with pytest.raises(ConfigError, match=rf"estimator.window_s: {top * 1.001:g} is not allowed: .* \(allowed: up to "
                                          rf"{top:.6g} s at this rate and probe count"):
        config_from_dict(_sim_config(window_s=top * 1.001))
    with pytest.raises(ConfigError, match=r"window_s: 1e\+308 is not allowed: inf samples .* more than any memory"):
        config_from_dict(_sim_config(window_s=1e308))
    # eight probes at 100 kHz: the default 60 s window is 2.76 GiB, the update chunk of 60 s 2.76 GiB too
    fast = {"unit": {"n_probes": 8}, "source": {"kind": "sim"}, "sim": {"rate_hz": 100_000.0, "probes": [{}] * 8}}
    with pytest.raises(ConfigError, match=r"estimator.window_s: 60 is not allowed: 6e\+06 samples of 8 probe\(s\) at "
                                          r"100000 Hz, 281 bytes a sample, 1.57 GiB in memory"):
        config_from_dict(fast)
    with pytest.raises(ConfigError, match=r"estimator.update_every_s: 60 is not allowed: 1.57 GiB a chunk .* "
                                          r"\(allowed: up to 19.11 s, a chunk within 512 MiB\)"):
        config_from_dict({**fast, "estimator": {"window_s": 1.0, "update_every_s": 60.0}})
    slow = {"unit": {"n_probes": 1}, "source": {"kind": "replay", "path": "x.mcap", "rate_hz": 0.01}}
    with pytest.raises(ConfigError, match=r"window_s: 10 is not allowed: it holds no sample at 0.01 Hz \(allowed: at "
                                          r"least 100 s at this rate\)"):
        config_from_dict({**slow, "estimator": {"window_s": 10.0}})


def test_sample_bytes_is_what_the_ring_buffer_takes():
    for probes in (1, 2, 8):
        ring = RingBuffer(capacity=1000, n_probes=probes)
        n = 10
        ring.append(SampleBlock(t_s=np.arange(n, dtype=float), seq=np.arange(n), field_nT=np.zeros((n, probes, 3)),
                                temp_C=np.zeros((n, probes)), flags=np.zeros(n, np.uint8),
                                extras={"ref_total": np.zeros(n)}))
        arrays = [ring._t_s, ring._seq, ring._field_nT, ring._temp_C, ring._flags, *ring._extras.values()]
        assert sum(a.nbytes for a in arrays) == 1000 * sample_bytes(probes)


@pytest.mark.parametrize("section, key, value, bound", [
    ("estimator", "min_samples", 10**9 + 1, "1000000000"),
    ("estimator", "check_every_s", 86401.0, "86400.0"),
    ("mcap", "rotate_mb", 2e6, "1000000.0"),
    ("mcap", "rotate_s", 2e7, "10000000.0"),
    ("source", "run_s", 2e9, "1000000000.0"),
])
def test_other_numbers_that_size_memory_or_time_have_an_upper_bound(section, key, value, bound):
    raw = {"unit": {"n_probes": 2}, "source": {"kind": "sim"}}
    raw[section] = {**raw.get(section, {}), key: value}
    with pytest.raises(ConfigError, match=rf"cfg.toml: {section}.{key}: {value!r} is above the maximum {bound}"):
        config_from_dict(raw, "cfg.toml")


def test_a_simulated_run_is_bounded_in_samples():
    top = MAX_RUN_SAMPLES / 200.0
    assert load_sim_config({"duration_s": top}).n_samples == MAX_RUN_SAMPLES
    with pytest.raises(ConfigError, match=r"sim.duration_s: 1e\+09 is not allowed: 2e\+11 samples at rate_hz = 200 "
                                          r"\(allowed: up to 5e\+06 s at this rate, at most 1e\+09 samples a run"):
        load_sim_config({"duration_s": 1e9})


def test_the_example_configurations_are_within_the_bounds():
    from fluxcal.service.wiring.config import load_config

    for p in sorted((ROOT / "configs").glob("*.toml")):
        assert load_config(p).estimator.window_s > 0


# --- decode's CAN logs: held whole, so bounded ---------------------------------------------------------------

def test_a_can_log_beyond_the_limits_is_refused(tmp_path, capsys, monkeypatch):
    flat = tmp_path / "flat.log"
    flat.write_bytes(b"(1.0) can0 201#" + b"0" * (2 << 20))
    assert main(["decode", str(flat), "--can", "--probes", "2", "--out", str(tmp_path / "o.csv")]) == 2
    assert "flat.log: line 1 is longer than 1 MiB without a line break" in one_line(capsys.readouterr().err)
    big = tmp_path / "big.log"
    big.write_text("".join(f"({1.0 + i * 1e-3:.6f}) can0 201#0000000000000000\n" for i in range(40_000)))
    monkeypatch.setenv("FLUXCAL_MAX_INPUT_MB", "1")
    assert main(["decode", str(big), "--can", "--probes", "2", "--out", str(tmp_path / "o.csv")]) == 2
    size = big.stat().st_size
    assert f"big.log: {size:,} bytes is beyond the size limit for a CAN log, 1 MiB" in one_line(capsys.readouterr().err)
    assert not (tmp_path / "o.csv").exists()


# --- garbage refused within its first piece, in every reader (issue 38, build 9) ------------------------------

GARBAGE = {".csv": r"not a text file \(invalid start byte at byte 0\): not a lab CSV",
           ".ulg": r"not a PX4 ULog: it begins [0-9a-f ]+, where a ULog begins 55 4c 6f 67 01 12 35",
           ".BIN": r"not an ArduPilot DataFlash log: it begins [0-9a-f ]+, where a DataFlash log begins a3 95 80",
           ".db3": r"not a rosbag2 SQLite file: it begins",
           ".mcap": r"not an MCAP file \(starts with"}


@pytest.mark.parametrize("suffix", list(GARBAGE))
def test_a_garbage_file_is_refused_after_its_first_piece_in_every_reader(tmp_path, monkeypatch, suffix):
    """24 MiB of random bytes (the first one not what any format begins with) named as each reader's input: refused
    in one line after at most one piece (HEAD_BYTES) is read, the reader's library never given the file. Before, a
    1 GB one as CSV was read whole, then decoded: 2.06 GB at the peak (bench/bench_garbage_input.py)."""
    p = tmp_path / f"garbage{suffix}"
    data = bytearray(np.random.default_rng(38).bytes(24 << 20))
    data[0] = 0x9A
    p.write_bytes(bytes(data))
    if suffix == ".db3":
        (tmp_path / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    reads: list[int] = []
    real = inputs._read_chunk
    monkeypatch.setattr(inputs, "_read_chunk", lambda f, n: reads.append(n) or real(f, n))
    with pytest.raises(Exception) as e:
        load_data(p)
    assert re.search(GARBAGE[suffix], str(e.value)) and len(str(e.value).splitlines()) == 1, str(e.value)
    assert sum(reads) <= inputs.HEAD_BYTES + 1, reads


def test_a_csv_whose_rows_turn_to_garbage_is_refused_in_the_piece_where_they_do(tmp_path, monkeypatch):
    good = ("\n".join([HEADER, *lab_rows(2000)]) + "\n").encode()
    p = tmp_path / "half.csv"
    p.write_bytes(good + b"\x9a" + np.random.default_rng(1).bytes(40 << 20))
    reads: list[int] = []
    real = inputs._read_chunk
    monkeypatch.setattr(inputs, "_read_chunk", lambda f, n: reads.append(n) or real(f, n))
    with pytest.raises(DataError, match=rf"not a text file \(invalid start byte at byte {len(good)}\)"):
        load_csv(p)
    assert len(reads) == 1                                        # its first piece holds the turn: no other read
    # a header that is no CSV's, or rows that do not parse, are refused in the first piece too
    for text, said in ((b"time,x\n1,2\n", "no 't' column"), (HEADER.encode() + b"\n0,1,2,x3\n", "'x3' is not a number")):
        p.write_bytes(text + b"0,1,2,3\n" * (3 << 20))
        reads.clear()
        with pytest.raises(DataError, match=said):
            load_csv(p)
        assert len(reads) == 1
