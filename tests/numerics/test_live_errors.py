"""The running service's calibration errors (what the dashboard shows as offset ± error): the online estimator's
own are white-noise ones; where the ring buffer's residual differs between stretches of time or regions of field
direction beyond chance, they are at least those of leaving one out (gate._add_spreads, misfit). Checked on real
boards against the calibrations their authors published, on simulated 1/f noise against the truth, and on white
noise, which keeps its errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from real_data import mend, real, real_nT

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.world import World
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.wiring.pipeline import Pipeline


def _serve(block: SampleBlock, *, spread: bool, total_nT: float | None = None, check_every: int = 1000,
           window: int = 4000, chunk: int = 100, step: int = 250) -> Pipeline:
    """A one-probe service pipeline fed a recording in blocks of `step`, its spread errors on or off."""
    pl = Pipeline(n_probes=1, probe_names=["s1"], positions_m=None, min_samples=500, gate_rms_nT=1e9,
                  check_every_samples=check_every, window_samples=window, chunk_samples=chunk, total_nT=total_nT)
    pl.gate.spread_errors = spread
    for i in range(0, block.n_samples, step):
        pl.process(block.slice(i, i + step))
    assert pl.calibration is not None
    return pl


def _published(name: str) -> np.ndarray:
    pub = json.loads(real(f"{name}.published.json").read_text())
    scale = pub["data"]["scale_to_nT"] * mend(name)           # as real_nT gives the data
    if "A" in pub:                                       # m = A raw + B: the offset is -A^-1 B
        return -np.linalg.solve(np.asarray(pub["A"]), np.asarray(pub["B"])) * scale
    return np.asarray(pub["offset"]) * scale


@pytest.mark.parametrize("name", ["qmc5883l_suarez", "imu_freeimucal"])
def test_the_services_offset_errors_cover_what_a_real_boards_authors_published(name):
    """The live offsets at the end of the recording were 3.4-7.4 of the estimator's own errors from the
    published ones; now within four of the stated errors, which rose several times."""
    # in nT, as the service's gate judges a field (the QMC board's file reads 8,946 nT, refused as no Earth field)
    block = load_data(real_nT(f"{name}.csv")).block
    white = _serve(block, spread=False).calibration.probes[0]
    live = _serve(block, spread=True).calibration.probes[0]
    assert np.array_equal(live.offset_nT, white.offset_nT)           # the estimate itself is untouched
    z_white = (white.offset_nT - _published(name)) / white.offset_se_nT
    z = (live.offset_nT - _published(name)) / live.offset_se_nT
    assert np.abs(z_white).max() > 3.0 and np.abs(z).max() < 4.0, (z_white, z)
    assert np.all(live.offset_se_nT >= white.offset_se_nT) and np.median(live.offset_se_nT / white.offset_se_nT) > 2


def _world(seed: int, pink: float):
    cfg = load_sim_config({"duration_s": 240.0, "rate_hz": 50.0, "seed": seed, "reference": {"enabled": False},
                           "probes": [{"offset_nT": [300.0, -100.0, 50.0], "noise_nT": 0.5, "pink_nT_rtHz": pink}]})
    w = World(cfg)
    s = w.samples(0, cfg.n_samples)
    block = SampleBlock(t_s=s.t_s, seq=np.arange(s.t_s.size), field_nT=s.raw_nT, temp_C=s.temp_C,
                        flags=np.zeros(s.t_s.size, np.uint8))
    return block, np.asarray(w.truth()["sensors"][0]["offset_nT"], float), cfg.field.total_nT


def test_the_services_offset_errors_under_1f_noise_and_white_noise():
    """A simulated tumble, 240 s at 50 Hz, three seeds: under 1/f noise (3 nT/√Hz) the live offsets were 10 of
    their stated errors from the truth (rms over the nine), now under 4 (the noise's mean over the ring buffer
    cannot be told from an offset, so some excess stays); under white noise the errors are the estimator's own."""
    z_white, z_live = [], []
    for seed in range(3):
        block, truth, total = _world(seed, 3.0)
        white = _serve(block, spread=False, total_nT=total, check_every=500, window=6000, chunk=25, step=100)
        live = _serve(block, spread=True, total_nT=total, check_every=500, window=6000, chunk=25, step=100)
        pw, pl = white.calibration.probes[0], live.calibration.probes[0]
        z_white.append((pw.offset_nT - truth) / pw.offset_se_nT)
        z_live.append((pl.offset_nT - truth) / pl.offset_se_nT)
        clean, truth, total = _world(seed, 0.0)
        a = _serve(clean, spread=False, total_nT=total, check_every=500, window=6000, chunk=25, step=100)
        b = _serve(clean, spread=True, total_nT=total, check_every=500, window=6000, chunk=25, step=100)
        assert np.array_equal(a.calibration.probes[0].offset_se_nT, b.calibration.probes[0].offset_se_nT)
    rms_white, rms_live = (float(np.sqrt(np.mean(np.square(z)))) for z in (z_white, z_live))
    assert rms_white > 6.0 and rms_live < 4.0, (rms_white, rms_live)


def test_the_services_spreads_are_of_fits_unconstrained_by_the_total_as_the_estimator_is(monkeypatch):
    """The online estimator takes a configured or logged total for its scale only: the fits left out in time and
    direction are unconstrained too (as `fit --method rls`'s errors), even with a total configured."""
    import fluxcal.service.wiring.gate as gate

    asked = []
    for name in ("add_time_spread", "add_direction_spread"):
        real = getattr(gate, name)
        monkeypatch.setattr(gate, name, lambda p, order, raw, total, nm, _real=real: asked.append(total)
                            or _real(p, order, raw, total, nm))
    block, _, total = _world(0, 3.0)
    _serve(block, spread=True, total_nT=total, check_every=500, window=6000, chunk=25, step=100)
    assert asked and all(t is None for t in asked)
