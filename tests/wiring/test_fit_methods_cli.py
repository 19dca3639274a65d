"""`fluxcal fit --method sinefit | two-step` from lab CSVs of [SineFit] and [TwoStep]'s own simulations."""

from __future__ import annotations

import json

import numpy as np
from sims_003_004 import P003_ALPHA_DEG, P003_BETA_DEG, P003_GAMMA_DEG, paper003, paper004

from fluxcal.service.wiring.cli import main


def test_sinefit_from_a_turntable_csv(tmp_path):
    s = paper003(noise_nT=30.0, seed=1)
    csv = tmp_path / "turn.csv"
    np.savetxt(csv, np.column_stack([s.t_s, s.raw_nT, np.degrees(s.theta_rad)]), delimiter=",",
               header="t,s1_x,s1_y,s1_z,angle_deg", comments="")
    out = tmp_path / "cal.json"
    assert main(["fit", str(csv), "--method", "sinefit", "--out", str(out)]) == 0
    angles = json.loads(out.read_text())["probes"][0]["params"]["nonorth_deg"]["value"]
    assert np.allclose(angles, [P003_ALPHA_DEG, P003_BETA_DEG, P003_GAMMA_DEG], atol=0.35)


def test_two_step_from_three_marked_turns(tmp_path, capsys):
    p = paper004(seed=1)
    turns = p.turns()
    raw = np.concatenate(turns)
    turn = np.concatenate([np.full(len(t), k) for k, t in enumerate(turns)])
    csv = tmp_path / "turns.csv"
    np.savetxt(csv, np.column_stack([np.arange(len(raw)), raw, turn]), delimiter=",",
               header="t,s1_x,s1_y,s1_z,turn", comments="")
    capsys.readouterr()
    assert main(["fit", str(csv), "--method", "two-step", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == "two-step"
    assert out["sensors"][0]["scalar_rms_nT"] < 2 * 2.0                # the simulation's 2 nT noise
    assert np.allclose(out["sensors"][0]["offset_nT"], p.b_true_nT, atol=5.0)


def test_two_step_without_turn_marks_is_refused(tmp_path, capsys):
    csv = tmp_path / "plain.csv"
    rng = np.random.default_rng(0)
    d = rng.normal(size=(100, 3))
    d = 50000 * d / np.linalg.norm(d, axis=1, keepdims=True)
    np.savetxt(csv, np.column_stack([np.arange(100), d]), delimiter=",", header="t,s1_x,s1_y,s1_z", comments="")
    assert main(["fit", str(csv), "--method", "two-step"]) == 2
    assert "'turn'" in capsys.readouterr().err


def test_two_step_fits_its_ellipsoid_to_every_row_and_gives_no_turn_advice(tmp_path, capsys):
    """[TwoStep] step 1 uses all samples: rows marked with no turn (here tilted sweeps, turn = -1) count too; the
    summary does not advise turning about another axis, the turns being the design."""
    p = paper004(seed=1)
    turns = p.turns()
    rng = np.random.default_rng(2)
    sweeps = turns[0][rng.choice(len(turns[0]), 200)] + rng.normal(scale=2.0, size=(200, 3))
    raw = np.concatenate(turns + [sweeps])
    turn = np.concatenate([np.full(len(t), k) for k, t in enumerate(turns)] + [np.full(200, -1)])
    csv = tmp_path / "turns.csv"
    np.savetxt(csv, np.column_stack([np.arange(len(raw)), raw, turn]), delimiter=",",
               header="t,s1_x,s1_y,s1_z,turn", comments="")
    capsys.readouterr()
    assert main(["fit", str(csv), "--method", "two-step", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["sensors"][0]["params"]["samples"]["value"] == len(raw)
    assert not any("turn about" in w for w in out["warnings"])
    assert main(["fit", str(csv), "--method", "two-step"]) == 0
    text = capsys.readouterr().out
    assert "by design" in text and "turn about the" not in text
