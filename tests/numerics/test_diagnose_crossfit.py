"""Nuisance choices inside the training blocks (issue 14): a term that finds its regressors in the residual
(perming step instants) is judged on each held-out block with regressors found without that block; a true
step is still found and judged significant, a smooth offset wander is not called perming."""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose import TUMBLE, data_of, probe, sim_block

import fluxcal.service.numerics.effects.hysteresis as hysteresis
from fluxcal.service.numerics.diagnose import diagnose, summary_text

#: test_perming_step's jump: a private forward model adds it to probe 2's offset at 61.7 s
JUMP = np.array([6.0, -4.0, 3.0])


def stepped(seed: int, *, wander: bool, pink: float = 0.0):
    probes = [probe(0), probe(1)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    block = sim_block(probes, n=10000, rate=100.0, motion=TUMBLE, seed=seed)
    t = block.t_s - block.t_s[0]
    if wander:       # smooth: a slow swing and a gentle 16-s transition, no jump
        block.field_nT[:, 1, :] += np.outer(3.0 * np.sin(2 * np.pi * t / 45.0) + 2.0 * np.tanh((t - 60) / 8.0),
                                            [1.0, -0.6, 0.4])
    else:
        block.field_nT[t >= 61.7, 1, :] += JUMP
    return data_of(block, probes)


@pytest.mark.slow
def test_each_held_out_block_gets_steps_found_without_it(monkeypatch):
    data = stepped(21, wander=False)
    seen: list[np.ndarray] = []
    real = hysteresis.detect_steps

    def spy(t_s, residual, gain, **kw):
        seen.append(np.isnan(residual))
        return real(t_s, residual, gain, **kw)

    monkeypatch.setattr(hysteresis, "detect_steps", spy)
    d = diagnose(data, candidates=["hysteresis"])
    pr = d.fit.problem
    blocks = [pr.rows[sl] for sl in pr.blocks]
    # per probe: once in the whole residual (the fit shown), then once per block with that block left out
    masked = [m for m in seen if m[pr.rows].any()]
    for rows in blocks:
        assert any(m[rows].all() and not m[np.setdiff1d(pr.rows, rows)].any() for m in masked), rows[:3]
    first = d.candidates[0]
    assert first.effect == "hysteresis" and first.significant, summary_text(d)
    assert first.gain > 0.5


@pytest.mark.slow
@pytest.mark.parametrize("seed", [22, 23])
def test_a_smooth_offset_wander_is_not_called_perming(seed):
    d = diagnose(stepped(seed, wander=True))
    hyst = next(c for c in d.candidates if c.effect == "hysteresis")
    assert not hyst.significant, summary_text(d)
    assert d.verdict["kind"] in ("unexplained", "partly explained"), d.verdict
    assert d.verdict["effect"] != "hysteresis"


def warmed(seed: int, tau_s: float, pink: float = 0.0, n: int = 10000, rate: float = 100.0):
    """stepped's world, probe 2's offset warming up instead: 25, -20, 15 nT x (1 - exp(-t / tau_s)), none of the
    catalogue's terms (drift is a polynomial)."""
    probes = [probe(0), probe(1)]
    for p in probes:
        p["pink_nT_rtHz"] = pink
    block = sim_block(probes, n=n, rate=rate, motion=TUMBLE, seed=seed)
    t = block.t_s - block.t_s[0]
    block.field_nT[:, 1, :] += np.outer(1.0 - np.exp(-t / tau_s), [25.0, -20.0, 15.0])
    return data_of(block, probes)


@pytest.mark.parametrize("seed, tau_s, pink, n, rate", [(31, 6.0, 0.0, 10000, 100.0), (32, 15.0, 0.0, 10000, 100.0),
                                                      (33, 15.0, 0.1, 10000, 100.0), (34, 30.0, 0.0, 10000, 100.0),
                                                      (35, 15.0, 0.0, 24000, 200.0)])
def test_a_warm_up_is_not_called_perming(seed, tau_s, pink, n, rate):
    """A user's warm-up (a 25 nT rise over tau_s) was called perming, significant, two steps placed on the rise:
    a step must fit its stretch better than an offset moving linearly across it (hysteresis._steplike)."""
    d = diagnose(warmed(seed, tau_s, pink, n, rate), candidates=["hysteresis", "drift"])
    hyst = next(c for c in d.candidates if c.effect == "hysteresis")
    assert not hyst.significant, summary_text(d)
    assert d.verdict.get("effect") != "hysteresis", d.verdict
    if d.verdict["kind"] == "unexplained":      # what is left is said as what it is: probe 2's own, in time
        assert "moves along one direction of the platform frame" in d.verdict["left"], d.verdict
        assert "turns with the platform" not in d.verdict["left"]
        assert "so the sensor changed, not the field" in d.verdict["advice"], d.verdict


@pytest.mark.parametrize("seed", [36, 37, 38])
def test_a_fast_warm_up_is_said_as_one_probes_own_offset_changing(seed):
    """A 6-s warm-up of probe 2 that no term follows: what is left is said as what it is (an offset changing
    in time along one direction of the platform frame, not a field of the site) and the advice uses the
    probes and the reference the data have (the sensor changed), where it told the user to log them."""
    d = diagnose(warmed(seed, 6.0), candidates=["hysteresis", "drift"])
    assert d.verdict["kind"] == "unexplained", d.verdict
    # and where no step was fitted, the perming row says what it saw: a change beyond the noise, in s2 alone, no jump
    hyst = next(c for c in d.candidates if c.effect == "hysteresis")
    assert hyst.testable or "but smoothly" in hyst.reason and "s2 at " in hyst.reason and "s1" not in hyst.reason, hyst.reason
    assert not hyst.significant
    assert "moves along one direction of the platform frame" in d.verdict["left"]
    assert "an offset changing in time, not a field of the site" in d.verdict["left"]
    assert "turns with the platform" not in d.verdict["left"]
    assert "so the sensor changed, not the field" in d.verdict["advice"]
    assert "without a second probe or a reference" not in d.verdict["advice"]


def test_a_smooth_change_across_a_held_out_block_is_no_step_at_its_edge():
    """Searched across the hole a held-out block leaves, a smooth change over it looks like a jump at its edge;
    with the block as a barrier each side is searched on its own (the review's case: a tanh ramp)."""
    rng = np.random.default_rng(3)
    n = 100_000
    t = np.arange(n) * 0.01                                           # 1,000 s at 100 Hz
    ang = np.cumsum(rng.normal(0, 0.02, (n, 2)), axis=0)
    gain = np.column_stack([np.cos(ang[:, 0]) * np.cos(ang[:, 1]), np.sin(ang[:, 0]) * np.cos(ang[:, 1]),
                            np.sin(ang[:, 1])])
    ramp = 4.0 * np.tanh((t - 450.0) / 60.0)
    r = gain @ np.array([1.0, -0.5, 0.3]) * ramp + 0.5 * rng.standard_normal(n)
    hole = (t >= 400.0) & (t <= 500.0)
    masked = np.where(hole, np.nan, r)
    kw = dict(window=300, threshold=50.0, max_steps=3)
    across = hysteresis.detect_steps(t, masked, gain, **kw)
    around = hysteresis.detect_steps(t, masked, gain, barrier=(400.0, 500.0), **kw)
    at_edge = [ts for ts, _ in across if 395.0 <= ts <= 505.0]
    assert at_edge, across                                            # the artefact the barrier removes
    assert not [ts for ts, _ in around if 395.0 <= ts <= 505.0], around
    # and a true jump on one side is still found there
    jumped = masked + np.where(t >= 700.0, gain @ np.array([5.0, -3.0, 2.0]), 0.0)
    found = hysteresis.detect_steps(t, jumped, gain, barrier=(400.0, 500.0), **kw)
    assert any(abs(ts - 700.0) < 1.0 for ts, _ in found), found


@pytest.mark.slow
def test_a_perming_step_is_found_and_placed_in_every_one_of_ten_worlds():
    """Ten seeds, white noise: one step on probe 2, no other, its size within 0.3 nT. The calibration fitted
    across the step had taken part of it and left a residual that follows the direction: before the step
    was looked for beside the calibration's share (hysteresis.without_calibration_share), seven of these ten
    were placed, two misplaced by 8 and 11 s and one missed (and diagnose named drift there). Seeds 22 and 29
    place it 0.8 and 3.2 s late: there the jump is nearly square to the field direction, and the scalar
    residual does not see it until then."""
    from fluxcal.service.numerics.engine import fit_with_effects

    for seed in range(20, 30):
        ef, _ = fit_with_effects(stepped(seed, wander=False), ["hysteresis"])
        steps = [p for p in ef.parameters if "step@" in p.name]
        assert [p.name.split(".")[0] for p in steps] == ["s2"] * 3, (seed, [p.name for p in steps])
        at = float(steps[0].name.split("@")[1].split("s")[0])
        assert 61.7 <= at <= 65.0, (seed, at)
        assert np.allclose([p.value for p in steps], JUMP, atol=0.3), (seed, [p.value for p in steps])


@pytest.mark.slow
@pytest.mark.parametrize("seed", [22, 25])
def test_where_the_step_was_missed_diagnose_now_explains_it_by_hysteresis(seed):
    """The two worlds of the ten where diagnose had named drift (22, "explained") or nothing (25)."""
    data = stepped(seed, wander=False)
    d = diagnose(data)
    first = d.candidates[0]
    assert first.effect == "hysteresis" and first.significant, summary_text(d)
    assert d.verdict["kind"] == "explained" and d.verdict["effect"] == "hysteresis", d.verdict
    d2 = diagnose(data, effects=["hysteresis"])
    assert d2.rms_nT <= 1.3 * d2.noise_nT


def test_the_step_search_beside_the_calibration_never_looks_into_the_held_out_block():
    """detect_steps with the calibration's share refitted (centred) and a held-out block (barrier): what the
    block holds changes nothing, and a step outside it is found where it is."""
    rng = np.random.default_rng(4)
    n = 10000
    t = np.arange(n) / 100.0
    ph = 2 * np.pi * t / 6.0
    g = np.column_stack([np.cos(ph) * np.cos(ph / 3.1), np.sin(ph) * np.cos(ph / 3.1), np.sin(ph / 3.1)])
    r = 0.5 * rng.standard_normal(n) + (t >= 61.7) * (g @ JUMP)
    barrier = (20.0, 30.0)
    found = hysteresis.detect_steps(t, r, g, window=333, barrier=barrier, centred=50000.0 * g)
    spoiled = r.copy()
    inside = (t >= barrier[0]) & (t <= barrier[1])
    spoiled[inside] = 1e3 * rng.standard_normal(int(inside.sum()))
    assert hysteresis.detect_steps(t, spoiled, g, window=333, barrier=barrier, centred=50000.0 * g) == found
    assert [round(s, 1) for s, _ in found] == [61.7], found


def test_a_refused_linear_part_costs_the_first_fit_only():
    """diagnose's check of the refitted linear part (the command refuses a single-axis turn with it) runs as soon
    as the model is fitted, before any candidate: the refusal of an hour of turning no longer waits for the whole
    diagnosis. It sees the refitted linear part, and is not asked where the linear part is held."""
    data = data_of(sim_block([probe(0)], n=3000, rate=100.0, motion=TUMBLE, seed=41), [probe(0)])
    seen, told = [], []

    class Refused(Exception):
        pass

    def check(lin):
        seen.append(np.array(lin.offset_nT))
        raise Refused

    with pytest.raises(Refused):
        diagnose(data, progress=lambda frac, msg: told.append(frac), check_linear=check)
    assert len(seen) == 1 and seen[0].shape == (1, 3)
    assert max(told) <= 0.05                     # no candidate was tried (they report from 0.1 on)
    full = diagnose(data, candidates=["drift"])
    assert np.allclose(seen[0], full.fit.state.linear.offset_nT)      # the very linear part the diagnosis refits
    # held: the check is asked of the refit made for comparison only, and its refusal is words, never the diagnosis'
    from fluxcal.drivers.errors import CalibrationRefused

    def refuse(lin):
        seen.append(np.array(lin.offset_nT))
        raise CalibrationRefused("s1: one cone")

    held = diagnose(data, calibration=full.fit.state.linear, candidates=["drift"], check_linear=refuse)
    assert held.fit is not None and len(seen) == 2


def test_a_calibration_held_that_is_off_is_not_sent_to_a_refit_the_data_do_not_determine():
    """A real copter log held to the autopilot's calibration: 'refitting its linear part alone brings the residual
    from 6,382 to 1,888 nT (diagnose without --calibration, or fit again)', where diagnose without --calibration
    refuses those data (one cone). The refit's figure stays, with why it is not determined, never the advice."""
    from fluxcal.drivers.errors import CalibrationRefused

    data = data_of(sim_block([probe(0)], n=3000, rate=100.0, motion=TUMBLE, seed=43), [probe(0)])
    lin = diagnose(data, candidates=[]).fit.state.linear
    off = {"sensors": [{"name": data.probe_names[0], "offset_nT": (lin.offset_nT[0] + [400.0, -300.0, 200.0]).tolist(),
                        "matrix": lin.matrix[0].tolist()}]}

    def refuse(linear):
        refused = CalibrationRefused("s1: within one cone about z; or hold one made from a fuller turn fixed")
        refused.problem = "s1: within one cone about z"
        raise refused

    for check, says in ((None, "(diagnose without --calibration, or fit again)"),
                        (refuse, "in-sample, but these data do not determine that refit (s1: within one cone about z)"
                                 ": a calibration of the same sensor from a fuller turn, held here, would tell")):
        d = diagnose(data, calibration=off, candidates=[], check_linear=check)
        assert d.verdict["kind"] == "unexplained" and d.linear_refit_rms_nT < 0.5 * d.rms_nT
        assert says in d.verdict["advice"], d.verdict["advice"]
        assert (check is None) == ("diagnose without --calibration" in d.verdict["advice"])
        assert d.linear_refit_refused == (None if check is None else "s1: within one cone about z")
        assert d.as_dict().get("linear_refit_refused") == d.linear_refit_refused
        assert ("in-sample, but these data do not determine that refit" in summary_text(d)) == (check is not None)
