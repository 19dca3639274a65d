"""`fluxcal simulate`: the lab CSV and the truth JSON beside it, checked against the simulated world and
[FastRotation]; configuration errors name the key; the example configurations stay complete and in sync."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.drivers.sim.config import GRADIOMETER
from fluxcal.service.io.recordings.labdata import load_csv
from fluxcal.service.wiring.cli import main as cli

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"


def test_default_simulation_writes_csv_and_truth(tmp_path, capsys):
    out = tmp_path / "grad.csv"
    assert cli(["simulate", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "12000 samples of 2 probe(s)" in err and str(tmp_path / "grad.truth.json") in err
    lines = out.read_text().splitlines()
    assert lines[0].startswith("# fluxcal simulate: simulated unit 'grad1'")
    assert any("truth: grad.truth.json" in ln for ln in lines if ln.startswith("#"))
    header = next(ln for ln in lines if not ln.startswith("#"))
    assert header == "t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z,s1_temp,s2_temp,ref_total,seq,flags"

    data = load_csv(out)                                 # the project's own CSV reader accepts it
    blk = data.block
    assert blk.n_samples == 12000 and blk.n_probes == 2
    unit = Unit(load_sim_config(GRADIOMETER))
    s = unit.digitise(0, 12000)
    np.testing.assert_allclose(blk.t_s, np.arange(12000) / 200.0, atol=1e-9)
    np.testing.assert_array_equal(np.rint(blk.field_nT / 1e-3), s.counts)   # counts x 0.001, every digit
    np.testing.assert_allclose(blk.temp_C, 22.0)
    np.testing.assert_allclose(blk.extras["ref_total"], s.ref_total_nT, atol=5e-5)
    np.testing.assert_array_equal(blk.seq, np.arange(12000))

    truth = json.loads((tmp_path / "grad.truth.json").read_text())
    assert truth["unit"] == "grad1" and truth["data_file"] == "grad.csv" and truth["effects"] == []
    assert truth["field"]["frame"] == "NED" and truth["field"]["total_nT"] == 52500.0
    for k, sensor in enumerate(truth["sensors"]):
        m, off = np.array(sensor["matrix"]), np.array(sensor["offset_nT"])
        corrected = (blk.field_nT[:, k] - off) @ m.T
        resid = corrected - s.world.field_platform_nT[:, k]
        # the truth calibration turns the CSV into the platform-frame field, to the probe noise
        assert np.sqrt(np.mean(resid ** 2)) < 1.1 * max(sensor["noise_nT"])
        scalar = np.linalg.norm(corrected, axis=1) - blk.extras["ref_total"]
        assert np.sqrt(np.mean(scalar ** 2)) < 1.1 * max(sensor["noise_nT"])
        raw_scalar = np.linalg.norm(blk.field_nT[:, k], axis=1) - blk.extras["ref_total"]
        assert np.sqrt(np.mean(raw_scalar ** 2)) > 300.0              # uncalibrated it is far off
    assert [s["position_m"] for s in truth["sensors"]] == [[-0.25, 0.0, 0.0], [0.25, 0.0, 0.0]]


def test_cross_config_reproduces_paper001_before_calibration(tmp_path, capsys):
    out = tmp_path / "cross.csv"
    assert cli(["simulate", "--config", str(CONFIGS / "sim-cross.toml"), "--out", str(out)]) == 0
    blk = load_csv(out).block
    assert blk.n_samples == 1728 and blk.n_probes == 4
    tmi = np.sqrt(np.mean((np.linalg.norm(blk.field_nT, axis=-1) - 60000.0) ** 2, axis=0))
    np.testing.assert_allclose(tmi, [8994.31, 6714.99, 9041.56, 8723.06], atol=0.5)      # [FastRotation] Table 2
    np.testing.assert_allclose(blk.extras["ref_total"], 60000.0, atol=0.05)
    truth = json.loads((tmp_path / "cross.truth.json").read_text())
    assert truth["unit"] == "cross1" and truth["motion"]["n_attitudes"] == 1728
    assert truth["sensors"][0]["misalign_deg"] == [-21.97, 12.88, 13.64]


def test_bad_config_key_exits_2_naming_the_key(tmp_path, capsys):
    text = (CONFIGS / "sim-gradiometer.toml").read_text().replace("rate_hz = 200.0", "rate_hx = 200.0")
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "x.csv"
    assert cli(["simulate", "--config", str(cfg), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "sim.rate_hx: unknown key" in err and "rate_hz" in err
    assert list(tmp_path.iterdir()) == [cfg]                    # nothing written

    cfg.write_text(text.replace("rate_hx = 200.0", "rate_hz = 200.0").replace("noise_nT = 0.6", "noise_nT = -0.6"))
    assert cli(["simulate", "--config", str(cfg), "--out", str(out)]) == 2
    assert "sim.probes[0].noise_nT" in capsys.readouterr().err


def test_usage_errors_exit_2(tmp_path, capsys):
    assert cli(["simulate", "--out", str(tmp_path / "x.txt")]) == 2
    assert "(allowed: FILE.csv, FILE.mcap, FILE.bin, FILE.log" in capsys.readouterr().err
    assert cli(["simulate", "--out", str(tmp_path / "missing" / "x.csv")]) == 2
    assert "does not exist" in capsys.readouterr().err
    cfg = tmp_path / "forever.toml"
    cfg.write_text((CONFIGS / "sim-gradiometer.toml").read_text().replace("duration_s = 60.0", "duration_s = 0.0"))
    assert cli(["simulate", "--config", str(cfg), "--out", str(tmp_path / "x.csv")]) == 2
    assert "sim.duration_s" in capsys.readouterr().err
    assert cli(["simulate", "--config", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "x.csv")]) == 2
    assert "configuration file not found" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["forever.toml"]


def test_mcap_output(tmp_path, capsys):
    out = tmp_path / "grad.mcap"
    rc = cli(["simulate", "--out", str(out)])
    assert rc == 0 and out.exists() and (tmp_path / "grad.truth.json").exists()
    from fluxcal.service.io.recordings.reader import read_recording

    rec = read_recording(out)
    assert sum(b.n_samples for b in rec.raw_blocks) == 12000 and "ref_total" in rec.raw_blocks[0].extras


def test_gradiometer_config_is_the_builtin_world():
    raw = tomllib.loads((CONFIGS / "sim-gradiometer.toml").read_text())
    assert load_sim_config(raw["sim"]) == load_sim_config(GRADIOMETER)
    assert raw["unit"]["name"] == "grad1" and raw["unit"]["n_probes"] == len(raw["sim"]["probes"])
    assert [p["position_m"] for p in raw["probes"]] == [p["position_m"] for p in raw["sim"]["probes"]]


@pytest.mark.parametrize("name", ["sim-gradiometer.toml", "sim-cross.toml", "serial-example.toml",
                                  "can-example.toml"])
def test_example_configs_are_complete_and_commented(name):
    text = (CONFIGS / name).read_text()
    raw = tomllib.loads(text)
    assert {"unit", "source", "estimator", "calibration", "zenoh", "mcap"} <= set(raw)
    assert raw["source"]["kind"] in ("sim", "serial", "can")
    if raw["source"]["kind"] == "sim":
        sim = load_sim_config(raw["sim"])
        assert sim.n_probes == raw["unit"]["n_probes"] == len(raw["probes"])
    # every key line carries a comment (continuation lines of a table are the exception)
    for line in text.splitlines():
        s = line.strip()
        if s and not s.startswith(("#", "[")) and "=" in s.split("#")[0] and line == line.lstrip():
            assert "#" in s or _key_documented_above(text, s.split("=")[0].strip()), line


def _key_documented_above(text: str, key: str) -> bool:
    """Later [[sim.probes]] tables repeat keys commented in the first one."""
    return sum(1 for ln in text.splitlines() if ln.strip().startswith(key) and "#" in ln) >= 1


@pytest.mark.parametrize("name", ["sim-gradiometer.toml", "sim-cross.toml", "serial-example.toml",
                                  "can-example.toml"])
def test_example_config_sections_validate(name):
    """Each section against the dataclass that reads it (the drivers' [source], the service's others)."""
    from fluxcal.drivers.config import load_section
    from fluxcal.drivers.registry import source_kind
    from fluxcal.service.wiring.config import CalibrationConfig, EstimatorConfig, McapConfig, ProbeConfig, UnitConfig

    raw = tomllib.loads((CONFIGS / name).read_text())
    source = load_section(source_kind(raw["source"]["kind"]).table_class(), raw["source"], "source")
    unit = load_section(UnitConfig, raw["unit"], "unit")
    for sec, cls in (("estimator", EstimatorConfig), ("calibration", CalibrationConfig), ("mcap", McapConfig)):
        load_section(cls, raw[sec], sec)
    probes = [load_section(ProbeConfig, t, f"probes[{i}]") for i, t in enumerate(raw["probes"])]
    assert len(probes) == unit.n_probes
    assert getattr(source, "n_probes", unit.n_probes) == unit.n_probes
    assert getattr(source, "lsb_nT", unit.lsb_nT) == unit.lsb_nT
    if "sim" in raw:
        assert load_sim_config(raw["sim"]).lsb_nT == unit.lsb_nT


def test_example_configs_pass_the_service_loader():
    """The whole file, every section, as `fluxcal run` reads it."""
    from fluxcal.service.wiring.config import load_config

    for name in ("sim-gradiometer.toml", "sim-cross.toml", "serial-example.toml", "can-example.toml"):
        cfg = load_config(CONFIGS / name)
        assert cfg.unit.n_probes == len(cfg.probes)


def test_two_outputs_of_one_name_keep_both_truths(tmp_path, capsys):
    """run.csv, then run.mcap of another world: the first truth is not overwritten (the second goes to
    run.mcap.truth.json, said), and writing run.csv again replaces its own truth in place."""
    cfg = tmp_path / "other.toml"
    cfg.write_text((CONFIGS / "sim-gradiometer.toml").read_text().replace("seed = 2024 ", "seed = 7 ", 1))
    assert "seed = 7 " in cfg.read_text()
    assert cli(["simulate", "--out", str(tmp_path / "run.csv")]) == 0
    first = json.loads((tmp_path / "run.truth.json").read_text())
    capsys.readouterr()
    assert cli(["simulate", "--config", str(cfg), "--out", str(tmp_path / "run.mcap")]) == 0
    err = capsys.readouterr().err
    assert "run.truth.json describes another data file beside it: this run's truth is run.mcap.truth.json" in err
    assert json.loads((tmp_path / "run.truth.json").read_text()) == first
    second = json.loads((tmp_path / "run.mcap.truth.json").read_text())
    assert second["data_file"] == "run.mcap" and second["seed"] == 7 and first["seed"] == 2024
    assert cli(["simulate", "--out", str(tmp_path / "run.csv")]) == 0
    assert "describes another" not in capsys.readouterr().err
    assert json.loads((tmp_path / "run.truth.json").read_text()) == first
