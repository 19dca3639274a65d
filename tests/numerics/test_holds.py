"""Held values (service/numerics/holds.py): a logger that repeats a probe's previous value when no new sample came.
A channel with 75 % held rows: kept, its noise floor collapses to the diagnosis's smallest (0.001 nT) and a staircase
band shows in its spectrum; left out, its floor is within 20 % of the same channel's without holds and no band shows
at 50-96 Hz (or anywhere the unheld channel has none). A quantised sensor's chance repeats are kept; real recordings'
repeats counted."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from real_data import needs_real, real

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.numerics.diagnose import diagnose
from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.holds import find_holds, without_holds


def _tumbling(seed: int, pink: float) -> SampleBlock:
    cfg = load_sim_config({"seed": seed, "rate_hz": 200.0, "duration_s": 120.0,
                           "motion": {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 9.0},
                           "probes": [{"position_m": [0, 0, 0], "offset_nT": [300, -200, 150],
                                       "scale": [1.01, 0.99, 1.0], "noise_nT": 1.0, "pink_nT_rtHz": [pink] * 3}]})
    return Unit(cfg).digitise(0, cfg.n_samples).to_block()


def _held(b: SampleBlock, seed: int, fresh_fraction: float = 0.25) -> SampleBlock:
    """The logger's view: a new value at a random quarter of the rows, the previous one repeated at the others."""
    fresh = np.random.default_rng(seed).random(b.n_samples) < fresh_fraction
    fresh[0] = True
    last = np.maximum.accumulate(np.where(fresh, np.arange(b.n_samples), 0))
    return SampleBlock(t_s=b.t_s, seq=b.seq, field_nT=b.field_nT[last], temp_C=b.temp_C, flags=b.flags)


def _bands(result) -> list[tuple[float, float]]:
    text = json.dumps(result.as_dict())
    return [(float(a), float(b)) for a, b in re.findall(r"([0-9.]+)-([0-9.]+) Hz", text)]


@pytest.mark.parametrize("seed, pink", [(1, 0.0), (2, 0.0), (3, 0.3)])
def test_a_channel_with_75_percent_held_rows(seed, pink):
    b = _tumbling(seed, pink)
    held = _held(b, seed)
    unheld = diagnose(EffectData.from_block(b, ["s1"]))
    kept = diagnose(EffectData.from_block(held, ["s1"]))
    out, h = without_holds(held, ["s1"])
    left_out = diagnose(EffectData.from_block(out, ["s1"]))
    floor0, floor_kept, floor = (float(r.channel_noise_nT[0]) for r in (unheld, kept, left_out))
    assert 0.74 < h.counts["s1"] / b.n_samples < 0.76 and h.by_chance["s1"] < 1.0
    assert floor_kept < 0.01 * floor0                       # the problem: the floor of a staircase
    assert abs(floor / floor0 - 1.0) < 0.20, (floor, floor0)
    assert not any(lo <= 96.0 and hi >= 50.0 for lo, hi in _bands(left_out)), _bands(left_out)
    # no band the unheld channel does not have (the 1/f noise's own, at tenths of a Hz, it has)
    assert all(hi < 1.0 for lo, hi in _bands(left_out)) and all(hi < 1.0 for lo, hi in _bands(unheld))
    assert h.notes[0].startswith("s1: 17,9") or h.notes[0].startswith("s1: 18,0")
    assert "left out of the noise floor, the fits and the spectra" in h.notes[0]
    print(f"seed {seed}, 1/f {pink}: floor {floor0:.4f} nT without holds, {floor_kept:.4f} with them kept, "
          f"{floor:.4f} with them left out ({floor / floor0 - 1:+.1%}); bands {_bands(left_out)}")


def test_chance_repeats_of_a_quantised_sensor_are_kept():
    rng = np.random.default_rng(4)
    n = 20_000
    # at rest, noise 0.3 counts: most readings repeat by chance on every axis
    f = np.round(rng.normal(0.0, 0.3, (n, 1, 3)) + np.array([120.0, -40.0, 300.0])) * 91.7
    h = find_holds(f, ["s1"])
    assert h.counts["s1"] > 0.2 * n and not h.held.any()
    assert "about as many as the sensor's resolution gives by chance" in h.notes[0]
    two = np.concatenate([f, f + rng.normal(0, 1.0, (n, 1, 3))], axis=1)
    two[5, 1] = two[4, 1]                                    # one real hold on s2, whose floats never repeat by chance
    g = find_holds(two, ["s1", "s2"])
    assert np.flatnonzero(g.held[:, 1]).tolist() == [5] and not g.held[:, 0].any()
    assert g.keep.sum() == n - 1


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("sigma", [0.1, 0.15, 0.2, 0.3, 0.5])
def test_a_coarse_sensor_at_rest_keeps_its_samples(sigma, seed):
    """A sensor of 100-nT steps (ArduPilot's whole milligauss) at rest, axes independent, noise `sigma` steps: its
    chance repeats (up to all but one sample of 20,000 at 0.1) are counted as chance, none left out. The per-axis
    rates taken where another axis moved; taken over the pairs that are not whole repeats, they were biased low and
    left out 95 % of the samples at sigma 0.1 (review of stop 32)."""
    rng = np.random.default_rng(seed)
    n = 20_000
    f = np.round(rng.normal(0.0, sigma, (n, 1, 3)) + np.array([120.0, -40.0, 300.0])) * 100.0
    h = find_holds(f, ["s1"])
    assert not h.held.any(), (h.counts, h.by_chance)
    assert h.by_chance["s1"] == pytest.approx(h.counts["s1"], rel=0.05)     # chance is what was seen


@pytest.mark.parametrize("sigma", [0.5, 1.0])
def test_a_coarse_sensors_holds_are_found(sigma):
    """The same sensor logged at four times its rate (three rows in four held): found where chance repeats are rarer
    than holds (sigma 0.5 and 1 step), every whole repeat left out."""
    rng = np.random.default_rng(7)
    n = 20_000
    f = np.round(rng.normal(0.0, sigma, (n, 1, 3)) + np.array([120.0, -40.0, 300.0])) * 100.0
    fresh = rng.random(n) < 0.25
    fresh[0] = True
    h = find_holds(f[np.maximum.accumulate(np.where(fresh, np.arange(n), 0))], ["s1"])
    assert int(h.held.sum()) == h.counts["s1"] > 0.74 * n
    assert h.by_chance["s1"] < 0.2 * n


@needs_real("hmc5883l_sensorfusion_sphere.csv", "qmc5883l_suarez.csv")
def test_real_bursty_board_repeats():
    """The HMC5883L board read in bursts faster than the sensor converts: 239 exact repeats of 8,190, 20 by chance."""
    from fluxcal.service.io.recordings.load import load_data

    lab = load_data(real("hmc5883l_sensorfusion_sphere.csv"))
    h = find_holds(lab.block.field_nT, lab.probe_names)
    assert h.counts["s1"] == 239 and h.by_chance["s1"] == pytest.approx(19.8, abs=0.1)
    assert int(h.held.sum()) == 239
    q = load_data(real("qmc5883l_suarez.csv"))
    assert not find_holds(q.block.field_nT, q.probe_names).held.any()


def test_a_sensor_that_never_changes_is_refused_not_a_crash(tmp_path, capsys):
    """A real ArduPilot log (erlerobot/logs pxf/copter/31-3-2015/83.BIN) logged one compass value 784 times (its
    offsets on a zero reading): counted as chance repeats of a coarse sensor, kept, and diagnose divided by a median
    field of zero. It says what the samples are now."""
    from fluxcal.service.wiring.cli import main

    path = tmp_path / "stuck.csv"
    t = np.arange(800) * 0.1
    path.write_text("t,s1_x,s1_y,s1_z\n" + "".join(f"{x:.1f},-3600,100,-5600\n" for x in t))
    cal = tmp_path / "identity.json"                  # held: it said 'the model explains the data down to the noise'
    cal.write_text('{"sensors": [{"name": "s1", "offset_nT": [0, 0, 0], "matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}]}')
    for command in (["diagnose"], ["diagnose", "--calibration", str(cal)], ["fit"], ["fit", "--method", "rls"]):
        capsys.readouterr()
        assert main([*command, str(path)]) == 2
        err = capsys.readouterr().err
        assert "s1: all 800 samples are the same vector (-3600, 100, -5600 nT): the sensor did not measure" in err
        assert "turn" not in err
        assert "the file holds no other probe" in err and "--mags" not in err     # no other compass to choose
        assert "kept as measurements" not in err         # one story: not 'chance repeats', then 'did not measure'
    capsys.readouterr()
    assert main(["inspect", str(path), "--json"]) == 0          # what was read is said beside the refusal
    seen = json.loads(capsys.readouterr().out)
    assert seen["samples"] == 800 and seen["fit_refuses"].startswith("s1: all 800 samples are the same vector")
    two = tmp_path / "two.csv"                                   # a working probe beside the stuck one
    rng = np.random.default_rng(1)
    moving = rng.normal(size=(800, 3)) * 20000.0
    two.write_text("t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z\n" + "".join(
        f"{x:.1f},-3600,100,-5600,{m[0]:.1f},{m[1]:.1f},{m[2]:.1f}\n" for x, m in zip(t, moving)))
    assert main(["fit", str(two)]) == 2
    assert "leave its columns out (a PX4 or ArduPilot log: --mags with the other compasses' instances)" in \
        capsys.readouterr().err
