"""Data in the wrong unit are said, not silently calibrated: a CSV in µT fitted as nT gave
`total_nT_assumed 52.7722 nT` without a word, and with a configured total field of 52,500 nT a matrix of
about 1000. fit and diagnose now warn (a warning, never a refusal), loudly when the total field given and
the data's scale differ by more than TOTAL_RATIO_LIMIT (1.25: a total 1.9 times off, within the refusal's 2, was
fitted without a word, the matrix giving every axis a gain of 1.9)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fluxcal.service.numerics.field_scale import TOTAL_RATIO_LIMIT, field_scale_warnings, sphere_centre
from fluxcal.service.wiring.cli import main

#: what this file tests besides what it imports (tests/index.py): the notes fit and diagnose say, through the CLI
COVERS = ("fluxcal.service.wiring.scale_notes",)


def sphere(n: int = 2000, radius: float = 52_500.0, offset=(250.0, -400.0, 120.0), seed: int = 3) -> np.ndarray:
    """(n, 1, 3) samples of a tumbling probe: a sphere about an offset, with noise."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    b = u * radius + np.asarray(offset) + rng.normal(scale=1e-5 * radius, size=(n, 3))
    return b[:, None, :]


def write_csv(path, field: np.ndarray) -> str:
    t = np.arange(field.shape[0]) * 0.01
    np.savetxt(path, np.column_stack([t, field[:, 0]]), delimiter=",", header="t,s1_x,s1_y,s1_z", comments="",
               fmt="%.6f")
    return str(path)


@pytest.mark.parametrize("unit, factor, guess", [("µT", 1e-3, "µT? (x 1000"), ("mG", 1e-2, "mG? (x 100"),
                                                 ("G", 1e-5, "G? (x 100000"), ("pT", 1e3, "pT? (x 0.001")])
def test_a_field_in_another_unit_is_named(unit, factor, guess):
    b = sphere() * factor
    warnings, loud = field_scale_warnings(b, ["s1"], [sphere_centre(b[:, 0])])
    assert len(warnings) == 1 and loud == []
    assert "implausible for nT" in warnings[0] and guess in warnings[0] and "the CSV contract is nT" in warnings[0]
    assert f"s1 {52.5e3 * factor:.3g}" in warnings[0]


def test_nT_data_and_shielded_or_strong_fields_within_the_bounds_are_quiet():
    for radius in (52_500.0, 22_000.0, 1_500.0, 800_000.0):          # Earth's range, a partial shield, coils
        b = sphere(radius=radius)
        assert field_scale_warnings(b, ["s1"], total_nT=radius, total_source="x") == ([], [])
    w, _ = field_scale_warnings(sphere(radius=7.0), ["s1"])
    assert "raw counts? (counts x lsb_nT gives nT)" in w[0]          # no unit makes 7 an Earth field


def test_a_given_total_far_from_the_data_is_said_loudly():
    b = sphere() * 1e-3
    _, loud = field_scale_warnings(b, ["s1"], total_nT=52_500.0, total_source="configuration from c.toml")
    assert len(loud) == 1 and "(52,500 nT, configuration from c.toml) is 1,000 times" in loud[0], loud
    assert "are the data in µT? the CSV contract is nT" in loud[0]
    b = sphere()                                                      # nT data, a total 6 times too large
    _, loud = field_scale_warnings(b, ["s1"], total_nT=6 * 52_500.0, total_source="x")
    assert len(loud) == 1 and "the field given (the site, the configuration, the reference column) is wrong" in loud[0]
    for ratio in (0.53, 1.3, 1.9, 1 / 1.3):                           # a wrong site or total, within the refusal's 2
        _, loud = field_scale_warnings(b, ["s1"], total_nT=ratio * 52_500.0, total_source="x")
        assert len(loud) == 1 and f"is {ratio:.3g} times the data's median |B|" in loud[0], loud
        assert f"scales the data by about {ratio:.3g} on every axis" in loud[0]
        # what it says is what is done: the calibration is made with the factor (a field trial read "a gain no
        # magnetometer has" above a calibration written with exit 0)
        assert "the calibration is made with the factor in its matrix (refused beyond 2 times)" in loud[0]
        assert "no magnetometer" not in loud[0]
    for ratio in (1 / (0.95 * TOTAL_RATIO_LIMIT), 1.0, 1.02, 0.95 * TOTAL_RATIO_LIMIT):   # a gain a sensor can have
        assert field_scale_warnings(b, ["s1"], total_nT=ratio * 52_500.0, total_source="x") == ([], [])


def test_fit_with_a_wrong_total_within_the_refusal_says_the_gain_it_took(tmp_path, capsys):
    """nT data, a configured total of 28,000 nT where the field is 52,500 nT: fitted (exit 0, within the refusal's 2
    times), with scale factors of about 1.9 and the loud warning in the text, on stderr and in --json."""
    data = write_csv(tmp_path / "nt.csv", sphere())
    cfg = tmp_path / "c.toml"
    cfg.write_text('[source]\nkind = "sim"\n[unit]\nn_probes = 1\n[estimator]\ntotal_nT = 28000.0\n'
                   '[[sim.probes]]\nnoise_nT = 0.5\n')
    assert main(["fit", data, "--config", str(cfg), "--json"]) == 0
    out, err = capsys.readouterr()
    got = json.loads(out)
    loud = [w for w in got["warnings"] if "(28,000 nT," in w]
    assert len(loud) == 1 and "is 0.533 times the data's median |B|" in loud[0], got["warnings"]
    assert loud[0] in err
    scale = got["sensors"][0]["params"]["scale"]["value"]
    assert all(1.85 < c < 1.9 for c in scale), scale                  # 52,500 / 28,000 = 1.875
    assert main(["fit", data, "--config", str(cfg)]) == 0
    assert "is 0.533 times the data's median |B|" in capsys.readouterr().out


def test_fit_refuses_microtesla_data_naming_the_unit_with_or_without_a_total(tmp_path, capsys):
    """Data in µT were fitted with a warning (no total: a total field of 52.5 'nT' assumed) or scaled 1,000 times to a
    configured total, exit 0 both: no magnetometer on Earth gives that calibration. Refused now (issue 37), the unit
    guess in the advice, in the text and in --json; the same data in nT are fitted."""
    ut = write_csv(tmp_path / "ut.csv", sphere() * 1e-3)
    assert main(["fit", ut, "--json"]) == 2
    out, err = capsys.readouterr()
    refused = json.loads(out)["refused"]
    assert "assumes a total field of 52.5 nT" in refused["reason"] and "outside the Earth's" in refused["reason"]
    assert refused["advice"].startswith("are the data in µT? (x 1000: 52,") and refused["file"] == ut
    assert refused["reason"] in err and refused["advice"] in err
    cfg = tmp_path / "c.toml"
    cfg.write_text('[source]\nkind = "sim"\n[unit]\nn_probes = 1\n[estimator]\ntotal_nT = 52500.0\n'
                   '[[sim.probes]]\nnoise_nT = 0.5\n')
    assert main(["fit", ut, "--config", str(cfg), "--json"]) == 2
    refused = json.loads(capsys.readouterr().out)["refused"]
    assert f"1,000 times below the total field given (52,500 nT, configuration from {cfg})" in refused["reason"]
    assert "are the data in µT?" in refused["advice"]
    nt = write_csv(tmp_path / "nt.csv", sphere())
    assert main(["fit", nt, "--config", str(cfg)]) == 0
    out, err = capsys.readouterr()
    assert "median |B|" not in out + err


def test_diagnose_refuses_them_alike(tmp_path, capsys):
    ut = write_csv(tmp_path / "ut.csv", sphere(n=1500) * 1e-3)
    assert main(["fit", ut, "--json"]) == 2
    fit = json.loads(capsys.readouterr().out)["refused"]
    assert main(["diagnose", ut, "--json"]) == 2
    assert json.loads(capsys.readouterr().out)["refused"] == fit

@pytest.mark.parametrize("seed", [3, 4])
def test_fit_diagnose_and_inspect_say_the_datas_scale_in_one_sentence(tmp_path, capsys, seed):
    """A site whose field is 1.4 times the data's: fit said the data's median |B| about its calibration's offset and
    'the site (WMM-2015v2)', diagnose about a sphere of its own and 'the site' (two figures, two sources), inspect
    nothing. Now each says it about the determinacy gate's centre, in the same words."""
    data = write_csv(tmp_path / "off.csv", sphere(radius=37_000.0, seed=seed))
    site = ["--site", "40,-75,0,2015-01-01"]                     # about 51,800 nT there (WMM-2015)
    said = []
    for command in ("fit", "diagnose", "inspect"):
        capsys.readouterr()
        assert main([command, data, *site]) == 0
        out, err = capsys.readouterr()
        found = {line.split("the total field given ", 1)[1] for line in (out + err).splitlines()
                 if "the total field given (" in line}
        assert len(found) == 1, (command, found)
        said.append(found.pop())
    assert said[0] == said[1] == said[2], said
    assert "the site (WMM-2015" in said[0] and "about the fitted centre (37,0" in said[0]
