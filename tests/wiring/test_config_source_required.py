"""A configuration file must name its source: an emptied file (or one missing [source] kind) is an error
naming the key and what is allowed, never a simulated unit "unit1" publishing on 7447 beside the file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.config import config_from_dict, load_config, require_source

ROOT = Path(__file__).resolve().parents[2]
REQUIRED = "[source] kind is required (allowed: 'sim', 'can', 'replay', 'serial')"


@pytest.mark.parametrize("text, what", [
    ("", "the file is empty"),
    ("# all commented out\n", "the file is empty"),
    ('[unit]\nname = "grad1"\n', "it has no [source] section"),
    ('[source]\ntransport = "pty"\n', "its [source] names no kind"),
])
def test_run_refuses_a_config_without_a_source_kind_and_starts_nothing(tmp_path, capsys, text, what):
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    assert main(["run", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fluxcal run: {cfg}: {REQUIRED}: {what};") and len(err.splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.toml"]          # no recordings, no state


def test_the_example_configs_load_and_a_stored_dict_still_defaults_to_the_simulator():
    kinds = {p.stem: load_config(p).source.kind for p in sorted((ROOT / "configs").glob("*.toml"))}
    assert kinds == {"can-example": "can", "serial-example": "serial", "sim-cross": "sim", "sim-gradiometer": "sim"}
    assert config_from_dict({}).source.kind == "sim"        # a recording's stored configuration of an older run
    with pytest.raises(ConfigError, match=r"x.toml: \[source\] kind is required .*: it has no \[source\] section"):
        require_source({"unit": {}}, "x.toml")


def test_diagnose_refuses_an_empty_config_it_would_take_geometry_from(tmp_path, capsys):
    """diagnose's --config gives only positions and the total field (no [source] needed); an emptied file gives
    neither and is refused, as fit and run refuse it, instead of running as without it."""
    empty = tmp_path / "empty.toml"
    empty.write_text("# nothing left\n")
    data = tmp_path / "d.csv"
    data.write_text("t,s1_x,s1_y,s1_z\n" + "".join(f"{i},1,2,3\n" for i in range(20)))
    assert main(["diagnose", str(data), "--config", str(empty)], install_signals=False) == 2
    err = capsys.readouterr().err
    assert f"{empty}: the file is empty" in err and "total_nT" in err and "position_m" in err


def test_fit_takes_an_array_description_without_a_source(tmp_path, capsys):
    """fit's --config describes an array (the total field, probe positions): no source to name. The review
    found such a file refused after the [source] rule; an empty one still is."""
    cfg = tmp_path / "array.toml"
    cfg.write_text("[estimator]\ntotal_nT = 50000.0\n")
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d = 50000.0 * d / np.linalg.norm(d, axis=1, keepdims=True) + [300.0, -200.0, 100.0]
    data = tmp_path / "d.csv"
    np.savetxt(data, np.column_stack([np.arange(400) * 0.01, d + rng.normal(0, 1.0, d.shape)]), delimiter=",",
               header="t,s1_x,s1_y,s1_z", comments="")
    assert main(["fit", str(data), "--config", str(cfg), "--json"], install_signals=False) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.allclose(out["sensors"][0]["offset_nT"], [300.0, -200.0, 100.0], atol=1.0)
    assert abs(np.mean(out["sensors"][0]["params"]["scale"]["value"]) - 1.0) < 1e-3   # in the configured field
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    assert main(["fit", str(data), "--config", str(empty)], install_signals=False) == 2
    assert "the file is empty" in capsys.readouterr().err
