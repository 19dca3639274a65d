"""A recording cut by a killed writer: fit, diagnose and replay read what is complete and say on stderr
what was lost and how to mend it; `fluxcal repair` writes the finished copy."""

from __future__ import annotations

import json

import numpy as np
from helpers import write_raw

from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.source import SimSource
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.wiring.cli import main


def _cut_recording(tmp_path):
    cfg = load_sim_config({"duration_s": 30.0, "rate_hz": 200.0, "motion": {"kind": "tumble"},
                           "probes": [{}, {"position_m": [0.5, 0, 0]}]})
    src = SimSource(cfg, realtime=False)
    blocks = []
    while not src.exhausted:
        b = src.read(0.1)
        if b is not None:
            blocks.append(b)
    log = write_raw(tmp_path / "rec", blocks, chunk_size=16_384, flush_interval_s=1e9)
    data = open(log.files[0], "rb").read()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    return cut, sum(b.n_samples for b in blocks)


def test_a_cut_recording_is_fitted_from_what_is_complete_and_the_loss_is_said(tmp_path, capsys):
    cut, n_all = _cut_recording(tmp_path)
    assert main(["fit", str(cut), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["sensors"]                                # a calibration from what was complete
    assert 0 < read_recording(cut).raw.n_samples < n_all
    assert "fluxcal fit: warning:" in err and "cut inside" in err and "bytes" in err
    assert f"fluxcal repair {cut}" in err
    assert main(["diagnose", str(cut), "--json"]) == 0
    assert "fluxcal diagnose: warning:" in capsys.readouterr().err


def test_repair_writes_a_finished_copy_that_reads_without_warnings(tmp_path, capsys):
    cut, _ = _cut_recording(tmp_path)
    n_read = read_recording(cut).raw.n_samples
    fixed = tmp_path / "fixed.mcap"
    assert main(["repair", str(cut), str(fixed)]) == 0
    out = capsys.readouterr().out
    assert "lost:" in out and "copied" in out
    again = read_recording(fixed)
    assert again.raw.n_samples == n_read and not again.truncated
    assert main(["fit", str(fixed), "--json"]) == 0
    assert "warning" not in capsys.readouterr().err
    assert np.isfinite(again.raw.field_nT).all()
