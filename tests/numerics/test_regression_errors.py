"""The second probe's offset errors under regression alignment (wiring/coloured_fit.py): they include the reference
probe's, also where those are widened after the alignment (a misfit tied to the field direction: here the main
field falling under a climb that the one total cannot follow), and they cover the scalar fit of that probe on the same
data; on white noise they did and still do."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.wiring import cli


def _fit(capsys, path, *args):
    capsys.readouterr()
    assert cli.main(["fit", str(path), "--json", *args]) == 0
    return json.loads(capsys.readouterr().out)["sensors"]


def _write(path, t, f):
    cols = ["t"] + [f"s{k + 1}_{a}" for k in range(f.shape[1]) for a in "xyz"]
    np.savetxt(path, np.column_stack([t, f.reshape(len(t), -1)]), delimiter=",", header=",".join(cols),
               comments="", fmt="%.17g")


def _pair(seed: int, climb: bool):
    rng = np.random.default_rng(seed)
    probes = [{"position_m": [0.3 * k, 0, 0], "offset_nT": rng.uniform(-500, 500, 3).tolist(),
               "scale": (1 + 0.01 * rng.standard_normal(3)).tolist(), "nonorth_deg": rng.uniform(-1, 1, 3).tolist(),
               "misalign_deg": rng.uniform(-2, 2, 3).tolist(), "noise_nT": 1.0} for k in range(2)]
    cfg = {"seed": seed, "rate_hz": 10.0, "duration_s": 1000.0, "probes": probes,
           "motion": {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 11.0}}
    if climb:
        cfg["track"] = {"enabled": True, "latitude_deg": 45.0, "longitude_deg": 7.0, "climb_m_s": 25.0,
                        "year": 2026.0}
    b = Unit(load_sim_config(cfg)).digitise(0, int(cfg["rate_hz"] * cfg["duration_s"])).to_block()
    return b.t_s, b.field_nT


@pytest.mark.parametrize("seed, climb", [(1, True), (2, True), (3, False), (4, False)])
def test_second_probe_errors_include_the_reference_and_cover_its_scalar_fit(tmp_path, capsys, seed, climb):
    t, f = _pair(seed, climb)
    _write(tmp_path / "pair.csv", t, f)
    _write(tmp_path / "second.csv", t, f[:, 1:2])
    reg = _fit(capsys, tmp_path / "pair.csv", "--align", "regression")
    scalar = _fit(capsys, tmp_path / "second.csv")[0]
    ref_se, se = np.array(reg[0]["offset_se_nT"]), np.array(reg[1]["offset_se_nT"])
    # the reference's offset error moves the second probe's one to one (its matrix is about the reference's)
    assert np.all(se >= 0.9 * ref_se), (se, ref_se)
    diff = np.array(reg[1]["offset_nT"]) - np.array(scalar["offset_nT"])
    z = diff / np.hypot(se, scalar["offset_se_nT"])
    assert np.all(np.abs(z) < 3.0), z
    print(f"seed {seed}{' climb' if climb else ''}: second probe's se {np.round(se, 3)} nT (reference's "
          f"{np.round(ref_se, 3)}); regression minus scalar fit {np.round(z, 2)} combined standard errors")
