"""`fluxcal simulate` writes what a user needs to try the other commands: the unit's serial bytes and a
candump log of its CAN frames for `decode`, and turntable runs with their angle and turn columns for
`fit --method sinefit` and `two-step`."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.wiring.cli import main

TURNTABLE = """[unit]
n_probes = 1
[sim]
duration_s = {seconds}
rate_hz = 50.0
[sim.motion]
kind = "turntable"
axes = {axes}
rate_deg_s = 30.0
turns = 1
dwell_s = 2.0
initial_deg = [20.0, 10.0, 0.0]
[[sim.probes]]
offset_nT = [150.0, -80.0, 60.0]
scale = [1.01, 0.99, 1.02]
nonorth_deg = [0.3, -0.2, 0.4]
noise_nT = 1.0
"""


@pytest.mark.parametrize("suffix, decode", [(".bin", []), (".log", ["--can"])])
def test_captures_decode_to_the_simulated_samples(tmp_path, suffix, decode):
    ref, cap, out = tmp_path / "ref.csv", tmp_path / f"cap{suffix}", tmp_path / "decoded.csv"
    assert main(["simulate", "--out", str(ref)]) == 0
    assert main(["simulate", "--out", str(cap)]) == 0
    assert main(["decode", str(cap), "--probes", "2", *decode, "--out", str(out)]) == 0
    a, b = load_data(ref).block, load_data(out).block
    assert a.n_samples == b.n_samples == 12000
    assert np.allclose(a.field_nT, b.field_nT, rtol=0, atol=1e-9) and np.array_equal(a.seq, b.seq)


def test_a_turntable_run_carries_angle_and_turn_for_sinefit_and_two_step(tmp_path, capsys):
    three = tmp_path / "three.toml"
    three.write_text(TURNTABLE.format(seconds=48.0, axes='["x", "y", "z"]'))
    csv = tmp_path / "three.csv"
    assert main(["simulate", "--config", str(three), "--out", str(csv)]) == 0
    data = load_data(csv).block
    turn = data.extras["turn"]
    assert set(np.unique(turn).tolist()) == {-1, 0, 1, 2}
    assert main(["fit", str(csv), "--method", "two-step", "--json"]) == 0
    one = tmp_path / "one.toml"
    one.write_text(TURNTABLE.format(seconds=14.0, axes='["z"]'))
    csv1 = tmp_path / "one.csv"
    assert main(["simulate", "--config", str(one), "--out", str(csv1)]) == 0
    angle = load_data(csv1).block.extras["angle_deg"]
    assert angle.min() == 0.0 and 359.0 < angle.max() <= 360.0
    capsys.readouterr()
    assert main(["fit", str(csv1), "--method", "sinefit", "--json"]) == 0
