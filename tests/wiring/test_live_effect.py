"""An effect added to the running pipeline (the `add-effect` command): refit over the ring buffer,
the error metric falls to the noise, and a replay applying the recorded command gives the same output."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.errors import FluxcalError
from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.unit import Unit
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.model import ArrayCalibration
from fluxcal.service.wiring.pipeline import Pipeline

PROBE = {"offset_nT": [150.0, -80.0, 40.0], "noise_nT": 0.5, "temp_offset_nT_per_C": [3.0, -2.0, 1.5]}


def data():
    cfg = load_sim_config({"duration_s": 120.0, "reference": {"enabled": True, "noise_nT": 0.02},
                           "temperature": {"start_C": 20.0, "amplitude_C": 6.0, "period_s": 40.0,
                                           "reference_C": 20.0},
                           "probes": [PROBE]})
    return Unit(cfg).digitise(0, cfg.n_samples).to_block()


def run(block, add_at: int | None, sizes=(37,)):
    first = block.slice(0, 12000)
    cal = fit_ellipsoid(first.field_nT[:, 0], first.extras["ref_total"]).calibration
    pl = Pipeline(n_probes=1, probe_names=["s1"], positions_m=None, total_nT=None, min_samples=500,
                  check_every_samples=400, window_samples=6000, chunk_samples=100,
                  initial=ArrayCalibration("ellipsoid", None, [cal]))
    errors, corrected, i, k = [], [], 0, 0
    while i < block.n_samples:
        if add_at is not None and i >= add_at and "temperature" not in pl.effects:
            pl.command("add-effect", "temperature", seq=int(block.seq[i]), t_s=float(block.t_s[i]))
        n = sizes[k % len(sizes)] if add_at is None or i >= add_at else min(sizes[k % len(sizes)], add_at - i)
        out = pl.process(block.slice(i, i + n))
        errors.append((i, out.error.get("s1.scalar", np.nan), n))
        corrected.append(out.corrected.corrected_nT)
        i, k = i + n, k + 1
    return pl, errors, np.concatenate(corrected)


def rms_between(errors, a, b):
    e = [(err, n) for i, err, n in errors if a <= i < b]
    return float(np.sqrt(sum(err ** 2 * n for err, n in e) / sum(n for _, n in e)))


def test_added_effect_brings_the_error_to_the_noise_and_replays_identically():
    block = data()
    pl, errors, live = run(block, add_at=12000)
    assert pl.effects == ["temperature"]
    before = rms_between(errors, 6000, 12000)
    after = rms_between(errors, 13000, 24000)
    assert before > 4 * 0.5                                          # the temperature effect dominates
    assert after < 1.2 * 0.5                                         # down to the probe's noise
    _, _, again = run(block, add_at=12000, sizes=(500, 11))          # other blocking, same command point
    assert np.array_equal(live, again)


def test_effects_that_need_neighbouring_samples_are_refused_live():
    block = data()
    first = block.slice(0, 12000)
    cal = fit_ellipsoid(first.field_nT[:, 0], first.extras["ref_total"]).calibration
    pl = Pipeline(n_probes=1, probe_names=["s1"], positions_m=None, initial=ArrayCalibration("e", None, [cal]))
    pl.process(first)
    with pytest.raises(FluxcalError, match="cannot be added to the running service") as e:
        pl.command("add-effect", "eddy", seq=4000, t_s=20.0)
    assert "fluxcal fit --effects eddy" in str(e.value)
    # a name that is no effect at all is not sent to `fit --effects`, which would refuse it too
    with pytest.raises(FluxcalError, match="not an effect at all") as e:
        pl.command("add-effect", "bogus", seq=4000, t_s=20.0)
    assert "fit --effects" not in str(e.value)
