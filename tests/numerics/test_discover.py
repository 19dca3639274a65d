"""Discovery beyond the catalogue (issue 30), on worlds made for it (tests/discovery_worlds.py: the simulated unit with
an effect the catalogue has no term for, and logged columns beside it), white and 1/f noise:

- each kind is found: the discovered groups bring the held-out error within 1.3x the floor, the verdict names the
  observable and the physical group, and the parameters come back as the world put them;
- effect-free worlds, discovery forced on: nothing claimed;
- the groups found, written as an effect module, are taken back by `--effects FILE.py:Class`, pass register_effect
  and give the discovered error again within 2 %;
- real recordings with a logged column and an effect of it added: found; their copy without it: nothing claimed;
- a probe whose temperature is another's says so; a coupling seen only through the field's direction is named.

A representative subset: bench/bench_discovery.py sweeps 6 kinds x 3 seeds x white and 1/f, 30 controls and the
real recordings, and prints the counts."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest
from discovery_worlds import F_TOTAL, named, world

from fluxcal.service.numerics.diagnose import diagnose, summary_text
from fluxcal.service.numerics.diagnose.write_effect import effect_classes, effect_source
from fluxcal.service.numerics.effects import known_effects, register_effect

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.diagnose.discover", "fluxcal.service.numerics.diagnose.selection",
          "fluxcal.service.numerics.diagnose.weak", "fluxcal.service.numerics.diagnose.spectra")

FLOOR = 1.3
#: the worlds' samples (20 Hz): 8,000 where each figure asserted holds with its margin on it (the rotation within 0.6 %
#: of its 3 %, the loop 2.1 % of 5 %, the supply's scale 1.8 % of 5 %, the fan's amplitudes 0.13 of 0.25 nT, as on
#: 12,000); the lagged heater's 12,000 (its 60-s lag under 1/f noise: its coefficients 24 % of 25 % off already there)
N, N_LAGGED = 8000, 12000
#: the round trips' worlds: what they assert is that the written effect gives the fit again (within 1e-7 of 2 %,
#: parameters within 0.14 of their bound), which the world's size does not decide; on 6,000 samples each kind's group
#: is found as on 12,000 (the supply's as a scale group, the loop's rate over 5 samples)
N_ROUND_TRIP = 6000


def _group(d, kind):
    return next(g for g in d.discovery.groups if g.group.kind == kind)


def _values(g):
    return np.array([p.value for p in g.parameters])


@pytest.mark.slow
@pytest.mark.parametrize("kind, seed, pink", [("temperature rotation", 1, 0.0), ("fan phase", 2, 0.1),
                                              ("core loop", 3, 0.0), ("lagged heater", 1, 0.1),
                                              ("supply scale", 2, 0.0), ("common line", 3, 0.1)])
def test_an_effect_outside_the_catalogue_is_found_named_and_brought_to_the_floor(kind, seed, pink):
    d = diagnose(world(kind, seed, pink=pink, n=N_LAGGED if kind == "lagged heater" else N))
    text = summary_text(d)
    f = d.discovery
    assert f is not None and f.claimed, text
    assert d.heldout_rms_nT > FLOOR * d.noise_nT or max(d.channel_rms_nT / d.channel_noise_nT) > FLOOR, text
    assert f.heldout_rms_nT <= FLOOR * d.noise_nT, text
    assert named(d, kind), text
    assert f.cv_gain >= 0.02 and f.cv_log_ratio > 2 * f.cv_log_ratio_se, text
    assert "beyond the catalogue" in text and "log " not in (d.verdict["advice"] or ""), text
    js = json.loads(json.dumps(d.as_dict(), allow_nan=False))["discovery"]          # the contract's JSON
    assert js["claimed"] and js["groups"][0]["reading"] == f.groups[0].reading and js["sentence"] in js["sentence"]
    if kind == "temperature rotation":                      # 40 µrad/degC about the platform's z, in the differences
        rot = _group(d, "matrix").parts["rotation"]
        assert rot["values"][2] == pytest.approx(40.0, rel=0.03) and rot["significant"], rot
        assert "alignment" in d.verdict["advice"] and "µrad/degC" in d.verdict["advice"]
    elif kind == "fan phase":                               # 3 nT turning in x-y, 0.9 nT on z
        amp = _group(d, "wave").parts["amplitude_platform_frame_nT"]
        assert amp == pytest.approx([3.0, 3.0, 0.9], abs=0.25), amp
    elif kind == "core loop":
        assert _values(_group(d, "loop")) == pytest.approx([4.0, -3.0, 3.0], rel=0.05)
    elif kind == "lagged heater":                           # 8, -6, 4 nT/A through a lag of 60 s
        g = _group(d, "offset")
        assert _values(g) == pytest.approx([8.0, -6.0, 4.0], rel=0.25)
        assert 35.0 <= g.group.feature.recipe["low_pass_s"] <= 100.0
    elif kind == "supply scale":                            # 300, -200, 250 ppm/V of the probe's axes
        g = next(g for g in f.groups if g.group.kind in ("scale", "matrix"))
        sc = g.parts["scale"]
        assert sc["values"] == pytest.approx([300.0, -200.0, 250.0], rel=0.05), sc
    else:                                                   # 6 nT at 1.37 Hz, common: the scalar channels only
        g = _group(d, "common wave")
        assert abs(g.group.feature.recipe["hz"] - 1.37) < 0.002
        assert np.linalg.norm(g.parts["amplitude_platform_frame_nT"]) == pytest.approx(6.0, rel=0.1)


@pytest.mark.slow
@pytest.mark.parametrize("which, seed, pink", [("discovery", 101, 0.0), ("discovery", 111, 0.3),
                                               ("sim-gradiometer.toml", 90005, 5.0), ("sim-cross.toml", 90004, 1.0)])
def test_nothing_is_claimed_on_effect_free_worlds(which, seed, pink):
    from discovery_worlds import config_world

    data = (world(None, seed, pink=pink) if which == "discovery" else
            config_world(which, seed, pink=pink, seconds=300.0 if which == "sim-gradiometer.toml" else None))
    d = diagnose(data, discover=True)
    assert d.discovery is not None and d.discovery.tried > 20
    assert not d.discovery.claimed, summary_text(d)
    assert "nothing claimed" in summary_text(d)


@pytest.fixture(scope="module")
def found_worlds():
    """Diagnoses whose discovery the round trips below write out: a per-sample matrix (raw frame), a lag and a
    phase (not per sample), a field common to the probes (aligned frame, shared), an offset and scale following a
    column, a loop whose sign is taken from the reading less its steps."""
    out = {}
    for kind, seed in (("temperature rotation", 4), ("lagged heater", 5), ("common line", 6), ("supply scale", 4),
                       ("core loop", 4)):
        data = world(kind, seed, n=N_ROUND_TRIP)
        out[kind] = (data, diagnose(data))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["temperature rotation", "lagged heater", "common line", "supply scale", "core loop"])
def test_the_groups_found_written_as_an_effect_are_taken_back_and_give_the_same_error(kind, found_worlds, tmp_path,
                                                                                     clean_registry):
    from fluxcal.service.wiring.user_effects import resolve_effects

    data, d = found_worlds[kind]
    f = d.discovery
    assert f.claimed, summary_text(d)
    if kind == "supply scale":
        assert f.groups[0].group.kind == "scale", summary_text(d)
    elif kind == "core loop":                      # the sign taken again from the reading less the steps found,
        recipe = f.groups[0].group.feature.recipe   # its rate over a window chosen on the data: written with it
        assert "less_nT" in recipe and recipe["window_samples"] >= 5, recipe
    source = effect_source(f, data_name="a test world")
    compile(source, "found.py", "exec")
    path = tmp_path / "found.py"
    path.write_text(source)
    classes = effect_classes([g.group for g in f.groups])
    assert classes == ["Discovered"]                                  # one class holds every group found
    names = resolve_effects([f"{path}:Discovered"])                   # register_effect took it, with `beside`
    catalogue = [c.effect for c in d.candidates if c.significant]
    assert names == catalogue + ["discovered"], (names, catalogue)
    cls = known_effects()["discovered"]
    assert register_effect(cls) == "discovered"                       # again: the same class passes
    term = cls()
    assert term.frame == "raw" and term.per_sample == all(g.group.per_sample for g in f.groups)
    # a group common to the probes: shared parameters, in the aligned frame; a probe's own: in its raw frame
    assert bool(term.shared_names(data)) == any(g.group.common for g in f.groups)
    again = diagnose(data, effects=names, discover=False)
    assert again.rms_nT == pytest.approx(f.rms_nT, rel=0.02)
    assert again.heldout_rms_nT == pytest.approx(f.heldout_rms_nT, rel=0.02)
    ours = {p.name: p for p in f.fit.parameters() if p.term.startswith("discovered-")}
    theirs = {p.name: p.value for p in again.parameters if p.term == "discovered"}
    assert ours.keys() == theirs.keys()
    # the same values: within 0.1 %, or 1 % of their standard errors where they are near zero (an offset part of a
    # scale group where the world has none: 0.0113 against 0.0112 nT/V, errors of 0.1)
    for k, p in ours.items():
        assert abs(theirs[k] - p.value) <= max(1e-3 * abs(p.value), 0.01 * (p.stderr or 0.0), 1e-6), (k, p, theirs[k])


def test_the_written_effect_says_what_it_is_and_is_refused_when_there_is_nothing():
    from fluxcal.service.numerics.diagnose.library import Feature, Group

    t = np.linspace(0, 10, 50)
    f = Feature("s2_temp", "s2_temp", "degC", "value", {"source": "temperature", "probe": 1, "centre": 0.0}, t)
    source = effect_source([Group("matrix", 1, "s2", f)])
    assert "class Discovered(EffectTerm)" in source and "frame = 'raw'" in source and "per_sample = True" in source
    assert "view.data.temperature(view.data.probe_names.index('s2'))" in source
    with pytest.raises(ValueError, match="no group"):
        effect_source([])


@pytest.mark.slow
def test_a_borrowed_temperature_is_said():
    data = world("temperature rotation", 7)
    data.temp_C[:, 2] = np.nan                        # s3 logs no temperature: the temperature terms take s1's and s2's
    d = diagnose(data)
    assert any("s3 has no temperature of its own" in n and "borrowed" in n for n in d.notes), d.notes
    assert d.discovery.borrowed == {"s3": "s1, s2"}
    assert named(d, "temperature rotation"), summary_text(d)


@pytest.mark.slow
def test_a_coupling_seen_only_through_the_field_direction_is_named():
    """A logged current coupled into one probe's axes: in its scalar channel it is the current times the field's
    direction, which no association with one observable sees."""
    from test_diagnose import TUMBLE, data_of, probe, sim_block

    probes = [probe(0)]
    block = sim_block(probes, n=8000, rate=20.0, motion=TUMBLE, seed=5)
    t = block.t_s - block.t_s[0]
    current = np.sin(2 * np.pi * t / 37.0) + 0.3 * np.sin(2 * np.pi * t / 11.0)
    block.extras["heater_A"] = current
    block.field_nT[:, 0, :] += current[:, None] * np.array([6.0, -5.0, 4.0])
    d = diagnose(data_of(block, probes), candidates=[])
    top = d.where[0]
    assert top["observable"] == "heater_A x field direction" and top["strength"] > 0.5, d.where[:4]
    alone = max((w["strength"] for w in d.where if w["observable"] == "heater_A"), default=0.0)
    assert alone < top["strength"] - 0.3, d.where[:4]
    assert "heater_A x field direction" in d.verdict["left"]
    assert "seen through the field's direction" in d.verdict["advice"] or "heater_A" in d.verdict["advice"]
    if d.discovery is not None and d.discovery.claimed:     # found: 'beside it' says what is left without it
        assert any(g.observable == "heater_A" for g in d.discovery.groups), summary_text(d)
        beside_it = d.verdict["advice"].partition("; beside it: ")[2]
        assert "heater_A" not in beside_it, d.verdict["advice"]


def test_a_gain_that_is_an_extrapolation_is_not_printed_as_a_percentage():
    from fluxcal.service.numerics.diagnose.text import gain_text

    assert gain_text(-947.88) == "<-100%" and gain_text(0.123) == " 12.3%"
    assert gain_text(0.5, {"reason": "separate turns"}) == "  weak"


@pytest.mark.slow
def test_separate_turns_make_the_held_out_test_weak_and_it_says_what_would_decide():
    """Three single turns, one about each axis, each in its own blocks: every block is predicted by extrapolation
    to orientations no other block saw."""
    from test_diagnose import probe

    from fluxcal.drivers.sim import Unit, load_sim_config
    from fluxcal.service.numerics.effects.base import EffectData

    probes = [probe(0), probe(1)]
    cfg = load_sim_config({"seed": 3, "rate_hz": 50.0, "duration_s": 40.0,
                           "field": {"total_nT": F_TOTAL, "inclination_deg": 62.0, "declination_deg": -5.0},
                           "reference": {"enabled": True, "noise_nT": 0.05},
                           "motion": {"kind": "turntable", "axes": ["z", "y", "x"], "rate_deg_s": 30.0, "turns": 1,
                                      "dwell_s": 0.5, "ramp_s": 1.0},
                           "probes": probes})
    data = EffectData.from_block(Unit(cfg).digitise(0, cfg.n_samples).to_block(),
                                 positions_m=np.array([p["position_m"] for p in probes]))
    d = diagnose(data)
    text = summary_text(d)
    assert d.heldout_weak is not None, text
    assert "the held-out test is weak here" in text and any("would decide" in n for n in d.notes), d.notes
    rows = [ln for ln in text.splitlines() if re.match(r"    [a-z]+ +[0-9.]+ nT ", ln)]
    assert rows and all("%" not in ln and " weak " in ln for ln in rows), rows
    assert all("SIGNIFICANT" in ln or "no: " in ln or "undecided" in ln for ln in rows), rows


def test_a_line_that_only_a_held_out_block_holds_is_hidden_from_that_folds_selection():
    """The residual chooses the lines the library follows: a 20 nT field at 2.3 Hz in one of discovery's 16 blocks
    alone is a line of the whole residual, but the selection that holds that block out must not follow it (its own
    noise would have helped choose it); every other fold's training blocks show it."""
    from fluxcal.service.numerics.diagnose.discover import fold_waves
    from fluxcal.service.numerics.diagnose.library import build_library
    from fluxcal.service.numerics.diagnose.selection import blocks_of

    data = world(None, 104)
    fit = diagnose(data, discover=False).fit
    lo, hi = blocks_of(fit)[5]
    rows = fit.problem.rows
    burst = (data.t_s >= data.t_s[rows[lo]]) & (data.t_s <= data.t_s[rows[hi - 1]])
    t = data.t_s[burst] - data.t_s[0]
    data.raw_nT[burst, 0, :] += 20.0 * np.outer(np.cos(2 * np.pi * 2.3 * t), [1.0, 0.5, -0.3])
    data._cache.clear()
    d = diagnose(data, discover=False)
    lib = build_library(data, d.fit, d.channel_noise_nT)
    main = [i for i, g in enumerate(lib.groups) if g.feature.how == "line" and abs(g.feature.recipe["hz"] - 2.3) < 0.01]
    assert main, lib.lines_hz
    _, owner, hidden = fold_waves(data, d.fit, d.channel_noise_nT, lib.groups, blocks_of(d.fit))
    lines = {i for i, g in enumerate(lib.groups) if g.feature.how == "line"}
    assert hidden[5] >= lines and 5 not in owner                 # the fold without the burst follows no line
    assert all(not (h & set(main)) for b, h in enumerate(hidden) if b != 5), [sorted(h) for h in hidden]


def test_the_f_tests_tail_holds_below_the_smallest_float():
    """A strong effect's groups all had p = 0 (ln p = -inf) and were ranked by their sum of squares, which the larger
    group always wins: the tail's logarithm by the incomplete beta's continued fraction, equal to scipy's where
    scipy's is finite, and going on beyond."""
    from scipy import special, stats

    from fluxcal.service.numerics.diagnose.selection import DENORMAL_LOG, f_logsf, log_betainc

    for a in (1.5, 3.0, 50.0, 4000.0):
        for b in (1.5, 3.0, 4.5):
            for x in np.linspace(0.01, 0.99, 25):
                ref = special.betainc(a, b, x)
                if x < (a + 1) / (a + b + 2) and ref > 0:
                    assert log_betainc(a, b, x) == pytest.approx(np.log(ref), rel=1e-10, abs=1e-10)
    f = np.linspace(280.0, 2000.0, 200)
    got = np.array([f_logsf(v, 3, 8000) for v in f])
    assert np.all(np.isfinite(got)) and np.all(np.diff(got) < 0)
    ref = stats.f.logsf(f, 3, 8000)
    finite = np.isfinite(ref)
    assert finite.any() and not finite.all()                      # the range crosses scipy's underflow
    normal = ref > DENORMAL_LOG                                   # below, scipy's figure is a denormal float
    assert normal.any() and (finite & ~normal).any()
    assert np.allclose(got[normal], ref[normal], rtol=1e-10)
    # in scipy's denormal range its figure keeps a few digits (-711.74408 where the tail is -711.74332)
    assert np.allclose(got[finite & ~normal], ref[finite & ~normal], rtol=1e-5)
    # an offset (3 parameters) and its offset and scale (6) with the same sum of squares, far in the tail: the
    # smaller is the stronger test
    assert f_logsf(3000.0, 3, 8000) < f_logsf(1500.0, 6, 8000)


@pytest.mark.slow
@pytest.mark.parametrize("name, kind", [("qmc5883l_suarez", "fan phase"), ("imu_freeimucal", "lagged heater"),
                                        ("hmc5883l_sensorfusion_sphere", "supply scale"),
                                        ("hmc5883l_sensorfusion_sphere", "lagged heater"),
                                        ("hmc5883l_sensorfusion_sphere", "core loop")])
def test_an_effect_added_to_a_real_recording_is_found_and_its_untouched_copy_claims_nothing(name, kind):
    """Each case sized by one rule (tests/real_effects.py: the held-out error grows 1.4 times). A supply scale found as
    the probe's offset and scale following the supply (the matrix's 9 parameters, or its scale alone, did not predict
    held-out blocks of a hand-turned board), a heater's lagged offset judged with errors that hold on a bursty board
    (engine/coloured.py) and on the hour-long imu board, a core's loop whose rate's window and sign are refined on the
    data (discover.refine_loops: over the board's own 0.1-s window, 1.13 times the untouched board's)."""
    from real_data import real
    from real_effects import CASES, GROWTH, with_effect

    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.engine import as_effect_data

    size = next(s for n, k, s in CASES if (n, k) == (name, kind))
    touched, control = with_effect(as_effect_data(load_data(real(f"{name}.csv"))), kind, size)
    d0 = diagnose(control, discover=True)
    assert not d0.discovery.claimed, summary_text(d0)
    d1 = diagnose(touched)
    assert d1.heldout_rms_nT == pytest.approx(GROWTH * d0.heldout_rms_nT, rel=0.01)     # the rule the case is sized by
    assert d1.discovery.claimed and named(d1, kind, probe="s1"), summary_text(d1)
    assert d1.discovery.heldout_rms_nT <= 1.1 * d0.heldout_rms_nT, summary_text(d1)


@pytest.mark.slow
def test_an_offset_and_scale_whose_scale_factors_are_within_their_errors_is_claimed_as_its_offset():
    """The hand-turned board with a heater's lagged offset (growth 1.4, the columns' seed 7): the selection took the
    offset and scale group (it predicted the training blocks better), whose scale factors then stood within their
    errors; read as an offset, it was named as a scale group and the offset's claim was lost (found 7 of 10 seeds at
    this growth). Taken as its offset alone (discover.offset_alone), it is the effect, within 1.1 times the untouched
    board's held-out error."""
    from real_data import real
    from real_effects import size_for, with_effect

    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.diagnose.reading import scale_parts
    from fluxcal.service.numerics.engine import as_effect_data

    data = as_effect_data(load_data(real("hmc5883l_sensorfusion_sphere.csv")))
    touched, control = with_effect(data, "lagged heater", size_for(data, "lagged heater", 1.4, 7, 1350.0), 7)
    d0, d1 = diagnose(control, discover=True), diagnose(touched, discover=True)
    f = d1.discovery
    assert f.claimed and [g.group.kind for g in f.groups] == ["offset"], summary_text(d1)
    assert named(d1, "lagged heater", probe="s1") and f.heldout_rms_nT <= 1.1 * d0.heldout_rms_nT, summary_text(d1)
    # the rule itself: scale factors 1 error from zero are within their errors, an offset 10 errors away is not
    parts = scale_parts(np.array([100.0, -50.0, 20.0, 1.0, -1.0, 0.5]), np.diag([1.0, 1.0, 1.0, 1.0, 1.0, 1.0]) * 100)
    assert parts["offset"]["significant"] and not parts["scale"]["significant"]


def _heater_world(seed: int, heater_mean_A: float):
    """Two probes tumbling; a heater current (a slow random walk about heater_mean_A, logged) puts a field common to
    both, fixed in the platform frame: (30, -20, 10) nT per A."""
    from fluxcal.drivers.sim import Unit, load_sim_config
    from fluxcal.service.numerics.effects.base import EffectData

    cfg = load_sim_config({"seed": seed, "rate_hz": 50.0, "duration_s": 240.0,
                           "motion": {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 9.0},
                           "probes": [{"position_m": [0, 0, 0], "noise_nT": 0.3},
                                      {"position_m": [0.5, 0, 0], "noise_nT": 0.3}]})
    block = Unit(cfg).digitise(0, cfg.n_samples).to_block()
    rng = np.random.default_rng(seed)
    walk = np.cumsum(rng.normal(0.0, 1.0, block.n_samples))
    heater = heater_mean_A + (walk - walk.mean()) / np.ptp(walk) * 2.0
    block = dataclasses.replace(block, field_nT=block.field_nT + (heater[:, None] * [30.0, -20.0, 10.0])[:, None, :],
                                extras={**block.extras, "heater_A": heater})
    return EffectData.from_block(block, ["s1", "s2"])


@pytest.mark.parametrize("seeds", [(1, 2), (3, 4), (5, 6)])
def test_a_written_common_effect_keeps_its_reference_on_other_data(seeds, tmp_path, clean_registry):
    """A group common to the probes, written as an effect, fitted on one recording and applied to another whose
    heater runs 10 A higher: the coefficient stays referenced to the fitted data's mean (a `ref:` key that travels
    with the calibration, as a probe's references do), so the other recording is corrected to its noise. Centred
    again on the other data's own mean it was left 10 A x 37 nT/A off (review of stop 32)."""
    from fluxcal.service.numerics.diagnose.library import Feature, Group
    from fluxcal.service.numerics.engine import fit_with_effects
    from fluxcal.service.wiring.user_effects import resolve_effects

    a, b = _heater_world(seeds[0], 1.0), _heater_world(seeds[1], 11.0)
    feature = Feature("heater_A", "heater_A", "heater_A", "value", {"source": "column", "column": "heater_A"},
                      np.zeros(a.n_samples))
    path = tmp_path / "heater.py"
    path.write_text(effect_source([Group("common offset", None, "common", feature)]))
    names = resolve_effects([f"{path}:Discovered"])
    fit, _ = fit_with_effects(a, names)
    values = {p.name: p.value for p in fit.result.parameters()}
    per_A = [v for k, v in values.items() if k.startswith("common")]
    assert np.allclose(sorted(np.abs(per_A)), [10.0, 20.0, 30.0], rtol=0.05), values
    # the field's magnitude is constant in the simulated world: what varies in |corrected| is error
    spread_b = np.std(np.linalg.norm(fit.correct(b), axis=2), axis=0)
    spread_a = np.std(np.linalg.norm(fit.correct(a), axis=2), axis=0)
    print(f"|corrected| spread on the fitted data {spread_a} nT, on the other data {spread_b} nT")
    assert np.all(spread_b < 1.5 * spread_a + 0.2), (spread_a, spread_b)


def test_a_line_on_a_bursty_real_board_is_found_at_its_own_frequency():
    """The hand-turned sensorfusion board sends bursts of samples 2-3 ms apart with 20-60 ms between them (median
    interval 3.3 ms, mean 13 ms): its residual's spectra, taken over the samples in their order, were read on the
    median interval, and a 3.0 Hz field was a line at 12.39 Hz. On the mean interval (effects.timebase.sample_grid),
    as the effects' errors take it."""
    from real_data import real

    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.diagnose.spectra import spectral_lines
    from fluxcal.service.numerics.engine import as_effect_data

    data = as_effect_data(load_data(real("hmc5883l_sensorfusion_sphere.csv")))
    t = data.t_s - data.t_s[0]
    data.raw_nT[:, 0, :] += 600.0 * np.outer(np.cos(2 * np.pi * 3.0 * t), [1.0, 0.6, -0.4])
    data._cache.clear()
    d = diagnose(data, discover=False)
    lines = spectral_lines(d.fit, d.channel_noise_nT)
    assert lines and lines[0] == pytest.approx(3.0, abs=0.01), lines


@pytest.mark.slow
@pytest.mark.parametrize("seed", [7, 9])
def test_one_lag_is_read_as_one_lag_not_two_of_opposite_signs(seed):
    """A new user's world: a heater switched on and off every 15-45 s, s2's offset following it through a 3-s lag
    (exact for the current held between samples), 200 Hz for 180 s. Discovery read it as lags of 2.9 s and 1.7 s of
    opposite signs, (8.63, -6.53, 4.28) +- 0.06 and (-0.63, 0.54, -0.27): the second was the first's correction on the
    time-constant grid, and stayed once the first was refined. Now each group kept passes the held-out rule beside
    the others once refined (selection.prune): one lag, its coefficients within 4 errors of the truth."""
    from fluxcal.drivers.sim import Unit, load_sim_config
    from fluxcal.service.numerics.effects.base import EffectData

    cfg = load_sim_config({"seed": seed, "rate_hz": 200.0, "duration_s": 180.0,
                           "motion": {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 9.0},
                           "probes": [{"position_m": [0, 0, 0], "noise_nT": 0.5},
                                      {"position_m": [0.5, 0, 0], "noise_nT": 0.5}]})
    block = Unit(cfg).digitise(0, cfg.n_samples).to_block()
    t = block.t_s - block.t_s[0]
    rng = np.random.default_rng(seed)
    edges = np.cumsum(rng.uniform(15.0, 45.0, 20))
    current = 1.5 * (np.searchsorted(edges, t, side="right") % 2)
    lag = np.empty_like(t)
    lag[0] = current[0]
    k = np.exp(-np.diff(t) / 3.0)
    for i in range(1, t.size):                              # the current held between samples, exactly lagged
        lag[i] = current[i - 1] + (lag[i - 1] - current[i - 1]) * k[i - 1]
    truth = np.array([8.0, -6.0, 4.0])
    field = block.field_nT.copy()
    field[:, 1, :] += lag[:, None] * truth
    block = dataclasses.replace(block, field_nT=field, extras={**block.extras, "heater_A": current})
    d = diagnose(EffectData.from_block(block, ["s1", "s2"]))
    f = d.discovery
    assert f.claimed and len(f.groups) == 1, summary_text(d)
    g = f.groups[0]
    assert g.group.kind == "offset" and g.group.feature.how == "low-passed" and g.observable == "heater_A"
    assert 2.5 <= g.group.feature.recipe["low_pass_s"] <= 3.5
    values = np.array([p.value for p in g.parameters])
    errors = np.array([p.stderr for p in g.parameters])
    assert np.all(np.abs(values - truth) <= 4 * errors + 0.02 * np.abs(truth)), (values, errors)
