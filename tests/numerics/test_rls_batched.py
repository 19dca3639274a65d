"""One online estimator for every probe gives, bit for bit, what one estimator per probe gave: the
accumulated information, every solve (the gate reads each probe as an estimator of its own) and the
pipeline's corrected output and events, with white and 1/f probe noise, NaN rows and any total field;
and so does correcting in spans of one calibration instead of chunk by chunk, in live or replay blocks."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.drivers.sim.config import load_sim_config
from fluxcal.drivers.sim.unit import Unit
from fluxcal.service.numerics.calib.rls import RlsEllipsoid
from fluxcal.service.wiring.pipeline import Pipeline

STATE = ("info", "eta", "y2", "weight", "n", "origin", "scale", "f2_ref", "assumed_total", "last_dir",
         "direction_centre")
POSITIONS = [[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]]


def world(seed: int, pink: bool, reference: bool = False, seconds: float = 60.0) -> SampleBlock:
    """Four probes tumbling at 200 Hz, white (0.5 nT) or 1/f (0.3 nT/√Hz at 1 Hz on top of 0.2 nT) noise."""
    probes = [{"name": f"s{k + 1}", "position_m": p, "offset_nT": [120.0 * k - 90.0, 60.0 - 40.0 * k, 35.0 * k],
               "scale": [1.0 + 0.01 * k, 0.99, 1.01 - 0.005 * k],
               "noise_nT": 0.2 if pink else 0.5, "pink_nT_rtHz": 0.3 if pink else 0.0}
              for k, p in enumerate(POSITIONS)]
    cfg = load_sim_config({"seed": seed, "rate_hz": 200.0, "duration_s": seconds, "probes": probes,
                           "reference": {"enabled": reference, "noise_nT": 0.05},
                           "motion": {"kind": "tumble", "rate_deg_s": 60.0, "tumble_period_s": 5.0}})
    return Unit(cfg).digitise(0, cfg.n_samples).to_block()


def with_nan_rows(block: SampleBlock, seed: int) -> SampleBlock:
    """A saturated axis here and there on one probe, a dropout of another, a few rows lost on all."""
    rng = np.random.default_rng(seed)
    f = block.field_nT.copy()
    f[rng.random(f.shape[0]) < 0.02, 1, 2] = np.nan
    f[3000:3350, 3] = np.nan
    f[rng.random(f.shape[0]) < 0.003] = np.nan
    return SampleBlock(t_s=block.t_s, seq=block.seq, field_nT=f, temp_C=block.temp_C, flags=block.flags,
                       extras=dict(block.extras))


def same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and bool(np.all((a == b) | (np.isnan(a) & np.isnan(b))))


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("pink", [False, True])
def test_one_estimator_of_all_probes_equals_one_per_probe_bit_for_bit(seed, pink):
    field = world(seed, pink, seconds=30.0).field_nT
    total = None if seed == 3 else 52500.0                  # seed 3: no total field given (the first mean)
    multi = RlsEllipsoid(forgetting=0.9995, n_probes=4)
    views = multi.probes()
    singles = [RlsEllipsoid(forgetting=0.9995) for _ in range(4)]
    for i in range(0, field.shape[0], 150):
        multi.partial_fit(field[i:i + 150], total)
        for k, s in enumerate(singles):
            s.partial_fit(field[i:i + 150, k], total)
        if i % 1500 == 0:                                  # the gate's reads, probe by probe, stopping at a refusal
            for s, v in zip(singles, views):
                try:
                    a = s.snapshot()
                except CalibrationRefused:
                    with pytest.raises(CalibrationRefused):
                        v.snapshot()
                    break
                b = v.snapshot()
                assert same(a.offset_nT, b.offset_nT) and same(a.matrix, b.matrix)
                assert same(a.offset_se_nT, b.offset_se_nT) and same(a.matrix_se, b.matrix_se)
                assert s.condition_ == v.condition_
    for k, s in enumerate(singles):
        for name in STATE:
            assert same(getattr(s._acc, name)[0], getattr(multi._acc, name)[k]), (k, name)
        assert same(s.offset_, views[k].offset_) and same(s.matrix_, views[k].matrix_)


class PerProbePipeline(Pipeline):
    """The pipeline as it was: one estimator per probe, each given its own finite rows; corrected chunk by chunk."""

    CORRECT_BY_CHUNK = True

    def reset(self) -> None:
        self._estimators = [RlsEllipsoid(forgetting=self.forgetting) for _ in range(self.n_probes)]
        self._fill = 0
        self._chunks = 0

    def _update_estimators(self, field_nT: np.ndarray, ref: np.ndarray) -> None:
        ok_rows = np.isfinite(field_nT).all(axis=2)
        have_ref = bool(np.isfinite(ref).all())
        for k, est in enumerate(self._estimators):
            rows = ok_rows[:, k]
            if rows.any():
                est.partial_fit(field_nT[rows, k], total_nT=ref[rows] if have_ref else self.total_nT)


def run(cls, block: SampleBlock, total_nT, commands=(), sizes=(20, 7, 333, 64)):
    pl = cls(n_probes=4, probe_names=["s1", "s2", "s3", "s4"], positions_m=np.array(POSITIONS, float),
             forgetting=0.9995, total_nT=total_nT, min_samples=1500, check_every_samples=600,
             window_samples=4000, chunk_samples=100)
    seqs, vals, events = [], [], []
    i, k = 0, 0
    while i < block.n_samples:
        m = sizes[k % len(sizes)]
        cut = [at for at, _ in commands if i < at < i + m]
        m = cut[0] - i if cut else m                    # a command applies before its sample, as replay cuts
        for at, name in commands:
            if at == i:
                pl.command(name, None, seq=at, t_s=float("nan"))
        r = pl.process(block.slice(i, i + m))
        if r.corrected is not None:
            seqs.append(r.corrected.seq)
            c = r.corrected
            vals.append(np.concatenate([c.corrected_nT.reshape(c.n_samples, -1), c.diff_nT.reshape(c.n_samples, -1),
                                        c.tensor_nT_m.reshape(c.n_samples, -1), c.center_nT], axis=1))
        events += [(e.kind, e.seq, repr(e.detail)) for e in r.events]
        i, k = i + m, k + 1
    return np.concatenate(seqs), np.concatenate(vals), events, pl.state()


@pytest.mark.parametrize("seed, pink, nan_rows, total", [
    (1, False, False, 52500.0), (2, True, False, 52500.0), (3, False, True, 52500.0),
    (4, True, True, None), (5, False, False, "reference"), (6, True, True, "reference")])
def test_the_pipeline_gives_its_per_probe_output_bit_for_bit(seed, pink, nan_rows, total):
    block = world(seed, pink, reference=total == "reference", seconds=30.0)
    if nan_rows:
        block = with_nan_rows(block, seed)
    total_nT = None if total == "reference" else total
    commands = [(2600, "freeze"), (3000, "unfreeze"), (3800, "reset")]
    old = run(PerProbePipeline, block, total_nT, commands)
    assert old[0].size > 1500 and any(e[0] == "calibration" for e in old[2])   # a calibration was learned
    for sizes in ((20, 7, 333, 64), (20000,)):                                 # live blocks; replay's
        new = run(Pipeline, block, total_nT, commands, sizes)
        assert np.array_equal(old[0], new[0]) and same(old[1], new[1])
        assert old[2] == new[2]
        assert repr(old[3]) == repr(new[3])
