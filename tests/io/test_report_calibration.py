"""The calibration report of `fit --report` and `diagnose --report`: the parameter table holds the fitted
offsets (checked against the simulator's truth), the maps are real PNGs, and a motion that never brings
the field near a direction is named in the text."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from fluxcal.service.numerics.calib.sky import residual_by_direction, unvisited_directions
from fluxcal.service.wiring import cli

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.io.report.calibration", "fluxcal.service.io.report.page", "fluxcal.service.wiring.calib_report")

ROOT = Path(__file__).resolve().parents[2]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

#: a one-probe turntable about z, y, x from a 45° heel in a field of 54.74° inclination: at the start the
#: field lies along +x+y+z of the platform, each turn keeps one component at 1/√3, so no sample comes
#: nearer than ~67° to -x-y-z while every other named direction is passed within 40°
TURNTABLE = """[unit]
n_probes = 1
[sim]
seed = {seed}
rate_hz = 50.0
duration_s = 60.0
[sim.field]
total_nT = 52500.0
inclination_deg = 54.74
declination_deg = 0.0
[sim.reference]
enabled = true
noise_nT = 0.05
[sim.motion]
kind = "turntable"
axes = ["z", "y", "x"]
initial_deg = [45.0, 0.0, 0.0]
rate_deg_s = 30.0
dwell_s = 1.0
[[sim.probes]]
name = "s1"
position_m = [0.0, 0.0, 0.0]
scale = [1.021, 0.984, 1.012]
nonorth_deg = [0.8, -1.4, 2.1]
misalign_deg = [1.5, -2.2, 3.1]
offset_nT = [215.0, -340.0, 120.0]
noise_nT = 0.6
"""

_ROW = re.compile(r'<tr><td>([^<]*)</td><td>([^<]*)</td><td class="num">([^<]*)</td><td class="num">([^<]*)</td>'
                  r'<td>([^<]*)</td><td[^>]*>([^<]*)</td></tr>')


def table(page: str) -> dict[tuple[str, str], tuple[float, float | None, str]]:
    """(owner, parameter) -> (value, SE or None, warning / note) from the report's parameter table."""
    return {(o, n): (float(v), None if s == "n/a" else float(s), w) for o, n, v, s, _, w in _ROW.findall(page)}


def simulate(tmp_path: Path, config_text: str, name: str) -> tuple[Path, dict]:
    cfg = tmp_path / f"{name}.toml"
    cfg.write_text(config_text)
    out = tmp_path / f"{name}.csv"
    assert cli.main(["simulate", "--config", str(cfg), "--out", str(out)]) == 0
    return out, json.loads((tmp_path / f"{name}.truth.json").read_text())


def assert_png(path: Path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE and len(data) > 5000, path
    import matplotlib.image

    img = matplotlib.image.imread(str(path))
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 300
    assert float(np.ptp(img[..., :3])) > 0.5                     # drawn on, not a blank canvas


@pytest.mark.parametrize("seed", [3, 11])
def test_fit_report_offsets_match_the_truth_and_maps_are_images(tmp_path, capsys, seed):
    text = (ROOT / "configs" / "sim-gradiometer.toml").read_text().replace("seed = 2024", f"seed = {seed}")
    csv, truth = simulate(tmp_path, text, "grad")
    rep = tmp_path / "rep"
    assert cli.main(["fit", str(csv), "--report", str(rep)]) == 0
    assert f"report: {rep / 'index.html'}" in capsys.readouterr().out
    page = (rep / "index.html").read_text()
    rows = table(page)
    for sensor in truth["sensors"]:
        for axis, want in zip("xyz", sensor["offset_nT"]):
            got, se, _ = rows[(sensor["name"], f"offset_nT.{axis}")]
            assert se is not None and 0 < se < 1.0
            assert abs(got - want) < 5 * se + 0.05, (sensor["name"], axis, got, want, se)
    # probe 1's own fit names its scale factors ([FastRotation] eq. 11), as simulated
    for label, want in zip(("c_x", "c_y", "c_z"), truth["sensors"][0]["scale"]):
        got, se, _ = rows[("s1", f"scale.{label}")]
        assert got == pytest.approx(want, abs=1e-4)
    for name in ("coverage_s1.png", "residual_s1.png", "coverage_s2.png", "residual_s2.png"):
        assert_png(rep / name)
    assert page.count("data:image/png;base64,") == 4
    assert "Coverage: <b>" in page and "Scalar residual RMS" in page


@pytest.mark.parametrize("seed", [5, 17])
def test_fit_and_diagnose_reports_name_the_direction_never_visited(tmp_path, capsys, seed):
    csv, truth = simulate(tmp_path, TURNTABLE.format(seed=seed), "turn")
    # the premise, from the data and the true offset: -x-y-z is the one named direction left unvisited
    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.calib.sky import nearest_angles_deg, unit_directions

    dirs = unit_directions(load_data(str(csv)).block.field_nT[:, 0], np.array(truth["sensors"][0]["offset_nT"]))
    corner = -np.ones((1, 3)) / np.sqrt(3.0)
    assert nearest_angles_deg(dirs, corner)[0] > 55.0
    assert nearest_angles_deg(dirs, np.vstack([np.eye(3), -np.eye(3)])).max() < 40.0

    for command in ("fit", "diagnose"):
        rep = tmp_path / command
        assert cli.main([command, str(csv), "--report", str(rep)]) == 0
        capsys.readouterr()
        page = (rep / "index.html").read_text()
        assert "<h2>Calibration</h2>" in page
        said = re.findall(r"no field within 40° of (\S+) in the sensor frame", page)
        assert said == ["-x-y-z"], (command, said)
        assert "tilt the unit so -x-y-z points along the field" in page
        got, se, _ = table(page)[("s1", "offset_nT.x")]
        assert abs(got - 215.0) < 5 * se + 0.05
        assert_png(rep / "coverage_s1.png")
        assert_png(rep / "residual_s1.png")


def test_fit_report_without_matplotlib_keeps_text_and_tables(tmp_path, capsys, monkeypatch):
    csv, _ = simulate(tmp_path, TURNTABLE.format(seed=1), "turn")
    monkeypatch.setitem(sys.modules, "matplotlib", None)            # import matplotlib -> ImportError
    rep = tmp_path / "rep"
    assert cli.main(["fit", str(csv), "--report", str(rep)]) == 0
    out, err = capsys.readouterr()
    assert "offset nT" in out and "needs matplotlib" in err and "pip install matplotlib" in err
    page = (rep / "index.html").read_text()
    assert "needs matplotlib" in page and "no field within 40° of -x-y-z" in page
    assert ("s1", "offset_nT.z") in table(page) and not list(rep.glob("*.png"))


def test_unvisited_cap_and_binned_residual():
    rng = np.random.default_rng(4)
    v = rng.normal(size=(20000, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    cap = v[v[:, 2] < np.cos(np.radians(60.0))]                    # nothing within 60° of +z
    missing = unvisited_directions(cap)
    assert [u.label for u in missing] == ["+z"]                     # its edges and corners belong to it
    assert missing[0].nearest_deg == pytest.approx(60.0, abs=1.5)
    assert "tilt the unit so +z points along the field" in missing[0].sentence()
    # residual +1 nT in the upper hemisphere, -1 nT below: each bin's mean says which
    res = np.where(v[:, 2] > 0, 1.0, -1.0)
    m = residual_by_direction(v, res, n_az=12, n_el=6)
    assert m.count.sum() == v.shape[0]
    assert np.allclose(m.mean_nT[3:], 1.0) and np.allclose(m.mean_nT[:3], -1.0)
    assert m.count.min() > 0.6 * m.count.mean()                    # equal-area bins: similar counts
