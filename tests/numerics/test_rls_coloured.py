"""`fit --method rls` gets the coloured-noise standard errors of the batch fit: without forgetting the online
estimate is the batch ellipsoid fit, and its offsets' errors were the white-noise ones alone (on the suarez
board ± 3.7 / 2.8 / 5.5 nT where `fit` said ± 14 / 14 / 20: the two methods disagreed about one estimate)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from real_data import needs_real, real_nT

from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.coloured_fit import coloured_offsets
from fluxcal.service.wiring.fitting import fit_array

ROOT = Path(__file__).resolve().parents[2]

PINK = """[unit]
n_probes = 1
[source]
kind = "sim"
[sim]
seed = 11
rate_hz = 20.0
duration_s = 600.0
[sim.reference]
enabled = false
[sim.motion]
kind = "tumble"
rate_deg_s = 10.0
tumble_period_s = 20.0
[[sim.probes]]
offset_nT = [300.0, -200.0, 150.0]
scale = [1.01, 0.99, 1.0]
noise_nT = 0.1
pink_nT_rtHz = 0.3
"""


def test_rls_offsets_under_1_over_f_noise_gain_the_wander_within_the_record(tmp_path, capsys):
    cfg = tmp_path / "pink.toml"
    cfg.write_text(PINK)
    csv = tmp_path / "pink.csv"
    assert main(["simulate", "--config", str(cfg), "--out", str(csv)]) == 0
    data = load_data(csv)
    cal, total = fit_array(data, method="rls")
    white = np.array(cal.probes[0].offset_se_nT, float)
    found = coloured_offsets(data, cal, total)
    assert len(found) == 1 and found[0].covered and found[0].alpha < -0.8
    coloured = np.array(cal.probes[0].offset_se_nT, float)
    assert np.all(coloured > 2.0 * white), (white, coloured)            # 1/f: several times the white figure
    assert cal.probes[0].params["offset_nT"]["se"] == coloured.tolist()
    capsys.readouterr()
    assert main(["fit", str(csv), "--method", "rls", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.allclose(out["sensors"][0]["offset_se_nT"], coloured, rtol=1e-9)
    assert any("standard errors include that wander within the record" in w for w in out["warnings"])
    assert not any("take them as lower bounds" in w for w in out["warnings"])


@needs_real("qmc5883l_suarez.csv")
def test_rls_and_the_batch_fit_state_the_same_errors_on_a_real_board():
    def fit(method: str) -> dict:
        proc = subprocess.run([sys.executable, "-m", "fluxcal.service.wiring.cli", "fit", str(real_nT("qmc5883l_suarez.csv")),
                               "--json", "--method", method], capture_output=True, text=True, cwd=ROOT, timeout=300,
                              check=False)
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout)["sensors"][0]

    batch, rls = fit("ellipsoid"), fit("rls")
    assert np.allclose(rls["offset_nT"], batch["offset_nT"], rtol=0, atol=0.01)
    assert np.allclose(rls["offset_se_nT"], batch["offset_se_nT"], rtol=1e-3)
    assert np.all(np.asarray(rls["offset_se_nT"]) > 10.0)                # ± 14 / 14 / 20, not the white ± 3.7 / 2.8 / 5.5
