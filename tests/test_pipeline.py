"""The shared pipeline: the quality gate, and outputs that do not depend on how input is cut."""

from __future__ import annotations

import numpy as np

from drivers.sim.config import load_sim_config
from service.numerics.calib.ellipsoid import fit_ellipsoid
from service.numerics.calib.model import ArrayCalibration
from service.wiring.pipeline import Pipeline
from drivers.block import SampleBlock


def block_of(world_cfg: dict) -> SampleBlock:
    cfg = load_sim_config(world_cfg)
    from drivers.sim.unit import Unit

    return Unit(cfg).digitise(0, cfg.n_samples).to_block()


def pipeline(initial=None, **kw) -> Pipeline:
    return Pipeline(n_probes=1, probe_names=["s1"], positions_m=None, forgetting=0.999, total_nT=52500.0,
                    min_samples=500, check_every_samples=400, window_samples=4000, chunk_samples=100,
                    initial=initial, **kw)


PROBE = {"offset_nT": [150.0, -80.0, 40.0], "scale": [1.02, 0.99, 1.01], "noise_nT": 0.5}


def test_a_single_axis_turn_never_replaces_a_good_calibration():
    good = block_of({"duration_s": 60.0, "probes": [PROBE]})
    cal = fit_ellipsoid(good.field_nT[:, 0], 52500.0).calibration
    pl = pipeline(ArrayCalibration("ellipsoid", None, [cal]))
    turn = block_of({"duration_s": 60.0, "probes": [PROBE],
                     "motion": {"kind": "turntable", "axes": ["z"], "rate_deg_s": 20.0}})
    reasons = []
    for i in range(0, turn.n_samples, 50):
        out = pl.process(turn.slice(i, i + 50))
        reasons += [r for ev in out.events if ev.kind == "gate" for r in ev.detail["reasons"]]
        assert not any(ev.kind == "calibration" for ev in out.events)
    assert pl.cal_id == 1 and pl.calibration.probes[0] is cal
    assert reasons and all("s1" in r for r in reasons)              # refused, naming the probe and why
    st = pl.state()
    assert st["usable"] and np.all(np.isfinite(st["probes"][0]["offset_nT"]))


def test_outputs_do_not_depend_on_block_boundaries():
    data = block_of({"duration_s": 40.0, "probes": [PROBE]})
    outs = []
    for sizes in ([7, 13, 50], [2000]):
        pl = pipeline()
        got, i, k = [], 0, 0
        while i < data.n_samples:
            n = sizes[k % len(sizes)]
            r = pl.process(data.slice(i, i + n))
            if r.corrected is not None:
                got.append(r.corrected.corrected_nT)
            i, k = i + n, k + 1
        outs.append(np.concatenate(got))
    assert outs[0].shape == outs[1].shape and outs[0].shape[0] > 1000
    assert np.array_equal(outs[0], outs[1])                          # bit for bit
