"""Discovery of shape (issue 36), on worlds whose missing term is a smooth, non-linear function of something the file
logs (tests/shape_worlds.py), white and 1/f noise:

- each shape is found and brings the held-out error within 1.3 times the floor; where a law made the data the law is
  named and its parameters cover the truth within 2 standard errors; a field that turns with a logged angle is read
  as turning about its axis;
- one source at two probes is one law with one shape (the same direction, the second probe's share);
- the residual's lines that the logged angle's motion makes (2 f1, f1 + f2) are never called unfollowed, and no
  discovered wave chases them;
- controls: twenty wandering columns logged and no effect: nothing claimed;
- the law written as an effect module is taken back alone by --effects (with the catalogue effects it was found
  beside), passes register_effect, names its parameters with units, and gives the figure again within 2 %.

A representative subset: bench/bench_discovery.py --part shapes sweeps the five shapes x seeds x white and 1/f and
the controls, and prints the counts (bench/results/)."""

from __future__ import annotations

import numpy as np
import pytest
from shape_worlds import LAWS, shape_world

from fluxcal.service.numerics.diagnose import diagnose, summary_text
from fluxcal.service.numerics.diagnose.write_effect import effect_source

#: what this file tests besides what it imports (tests/index.py)
COVERS = ("fluxcal.service.numerics.diagnose.shapes", "fluxcal.service.numerics.diagnose.laws", "fluxcal.service.numerics.diagnose.forms",
          "fluxcal.service.numerics.diagnose.shape_reading", "fluxcal.service.numerics.diagnose.harmonics",
          "fluxcal.service.numerics.diagnose.effect_code")

FLOOR = 1.3
#: the worlds of the tests: 5,000 samples at 20 Hz, three probes (the bench sweeps 12,000)
N = 5000


def law_of(d):
    return next((g for g in d.discovery.groups if g.group.kind == "law"), None)


def covers(got, truth: float) -> bool:
    """The parameter (value, stderr) covers the truth within two standard errors."""
    return got["stderr"] is not None and abs(got["value"] - truth) <= 2.0 * got["stderr"]


def _param(g, key: str):
    return next(v for name, v in g.parts["parameters"].items() if name.split()[1] == key)


@pytest.fixture(scope="module")
def found():
    """The diagnoses the tests read: every shape at one seed (white noise) and the flap at 1/f noise."""
    out = {}
    for kind, seed, pink in (("flap magnet", 1, 0.0), ("temperature square", 2, 0.0), ("saturating coil", 3, 0.0),
                             ("exponential supply", 4, 0.0), ("gimbal turn", 5, 0.0), ("flap magnet", 6, 0.1),
                             ("temperature square", 9, 0.3)):
        data = shape_world(kind, seed, pink=pink, n=N)
        out[(kind, pink)] = (data, diagnose(data))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("kind, pink", [("flap magnet", 0.0), ("temperature square", 0.0), ("saturating coil", 0.0),
                                        ("exponential supply", 0.0), ("flap magnet", 0.1)])
def test_a_shape_is_found_as_the_law_that_made_it(found, kind, pink):
    data, d = found[(kind, pink)]
    text = summary_text(d)
    f = d.discovery
    assert f is not None and f.claimed, text
    assert f.heldout_rms_nT <= FLOOR * d.noise_nT, text
    obs, probes, law, truth = LAWS[kind]
    g = law_of(d)
    assert g is not None and g.parts["law"] == law, text
    assert g.group.feature.observable == obs and set(g.parts["probes"]) == set(probes), text
    for key, value in truth.items():
        assert covers(_param(g, key), value), (key, value, g.parts["parameters"], text)
    assert law in g.reading, g.reading
    assert obs in d.verdict["advice"], d.verdict["advice"]


@pytest.mark.slow
def test_a_finding_that_leaves_the_probes_own_flicker_is_the_explanation(found):
    """Under 1/f noise of 0.3 nT/sqrt(Hz) the law is found, and what it leaves is each probe's own slow noise above
    the white floor: the headline said "unexplained: no catalogue effect explains the rest" above "what would explain
    it: discovered ...; beside it: each probe's own slow noise (flicker): not a missing effect" (a field trial, four
    shapes, three seeds each). It now says that the finding explains the data and the rest is flicker."""
    from test_one_story import disagreements

    data, d = found[("temperature square", 0.3)]
    text = summary_text(d)
    assert d.discovery.claimed and law_of(d).parts["law"] == LAWS["temperature square"][2], text
    assert d.verdict["kind"] == "explained beyond the catalogue" and d.verdict.get("rest") == "flicker", text
    assert ("the rest is each probe's own slow noise (flicker, spectrum about 1/f) above its "
            f"{d.noise_nT:.3f} nT white floor, not a missing effect") in text
    assert "unexplained" not in text and not disagreements(text), text


@pytest.mark.slow
def test_one_source_at_two_probes_is_one_law_with_one_direction(found):
    _, d = found[("flap magnet", 0.0)]
    g = law_of(d)
    assert g.parts["probes"] == ["s2", "s1"], g.parts
    share = np.linalg.norm(g.parts["field_nT"][1]) / np.linalg.norm(g.parts["field_nT"][0])
    assert share == pytest.approx(0.15, abs=0.02) and g.parts["angle_to_direction_deg"][1] < 3.0, g.parts
    assert "0.15 of s2's" in g.reading and "closes as flap_deg rises" in g.reading


@pytest.mark.slow
def test_a_field_that_turns_with_a_logged_angle_is_read_as_turning_about_its_axis(found):
    _, d = found[("gimbal turn", 0.0)]
    text = summary_text(d)
    g = next(g for g in d.discovery.groups if g.group.feature.how == "turn")
    assert g.group.feature.observable == "gimbal_deg" and g.group.probe_name == "s1", text
    axis = np.asarray(g.parts["turn_axis"])
    assert abs(axis[2]) > 0.99 and g.parts["amplitude_nT"] == pytest.approx([9.0, 9.0], rel=0.05), g.parts
    assert d.discovery.heldout_rms_nT <= FLOOR * d.noise_nT, text


@pytest.mark.slow
def test_the_lines_an_angles_motion_makes_are_its_shape_never_unfollowed(found):
    for kind in ("flap magnet",):
        _, d = found[(kind, 0.0)]
        text = summary_text(d)
        assert "no logged column" not in text or "flap_deg" not in text.split("no logged column")[1].split(")")[0]
        assert not any(g.group.kind in ("wave", "common wave") and g.group.feature.how == "line"
                       for g in d.discovery.groups), text


@pytest.mark.slow
@pytest.mark.parametrize("seed, pink", [(11, 0.0), (12, 0.1)])
def test_nothing_is_claimed_beside_twenty_wandering_columns(seed, pink):
    d = diagnose(shape_world(None, seed, pink=pink, n=N, wander=20), discover=True)
    assert d.discovery is not None and d.discovery.tried > 200, summary_text(d)
    assert not d.discovery.claimed, summary_text(d)


@pytest.mark.slow
def test_the_law_written_as_an_effect_gives_the_figure_again_alone(found, tmp_path, clean_registry):
    from fluxcal.service.numerics.effects import known_effects, register_effect
    from fluxcal.service.wiring.user_effects import resolve_effects

    data, d = found[("saturating coil", 0.0)]
    f = d.discovery
    source = effect_source(f, data_name="a test world")
    path = tmp_path / "coil.py"
    path.write_text(source)
    assert "def law_1(x, p, ref, span)" in source and "'coil_A s A'" in source and "'s1.coil_A field x nT'" in source
    names = resolve_effects([f"{path}:Discovered"])
    assert names[-1] == "discovered" and register_effect(known_effects()["discovered"]) == "discovered"
    again = diagnose(data, effects=names, discover=False)
    assert again.rms_nT == pytest.approx(f.rms_nT, rel=0.02)
    assert again.heldout_rms_nT == pytest.approx(f.heldout_rms_nT, rel=0.02)
    ours = {p.name: p.value for p in f.fit.parameters() if p.term.startswith("discovered-")}
    theirs = {p.name: p.value for p in again.parameters if p.term == "discovered"}
    assert ours.keys() == theirs.keys() and all(theirs[k] == pytest.approx(v, rel=1e-3, abs=1e-6)
                                                 for k, v in ours.items()), (ours, theirs)


@pytest.mark.slow
@pytest.mark.parametrize("name, kind", [("hmc5883l_sensorfusion_sphere", "flap magnet"),
                                        ("qmc5883l_suarez", "saturating coil"), ("imu_freeimucal", "flap magnet")])
def test_a_shape_added_to_a_real_recording_is_found_and_its_untouched_copy_claims_nothing(name, kind):
    """Each sized by the real cases' rule (tests/real_effects.py: the model's held-out error grows 1.4 times): found
    where the diagnosis (its discovered terms) brings the held-out error within 1.1 times the untouched copy's, the
    observable named. On the hour-long imu board, whose own residual wanders 8 times its floor, the flap's curvature is
    not determined and its straight line is what is found (the catalogue's column, 30 parameters, left 1.15 times)."""
    from real_data import real
    from real_effects import SHAPE_CASES, with_effect

    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.numerics.engine import as_effect_data

    size = next(s for n, k, s in SHAPE_CASES if (n, k) == (name, kind))
    touched, control = with_effect(as_effect_data(load_data(real(f"{name}.csv"))), kind, size)
    d0 = diagnose(control, discover=True)
    assert not d0.discovery.claimed, summary_text(d0)
    d1 = diagnose(touched)
    f = d1.discovery
    column = "flap_deg" if kind == "flap magnet" else "coil_A"
    assert f is not None and f.claimed and any(g.group.feature.observable == column for g in f.groups), summary_text(d1)
    assert f.heldout_rms_nT <= 1.1 * d0.heldout_rms_nT, summary_text(d1)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_columns_lines_and_the_residuals_scale_are_read_at_their_frequencies_on_a_bursty_time_base(seed):
    """A real hand-turned board's samples come 2-58 ms apart (median 3.3 ms, mean 13 ms): its spectra were read on
    the median interval, so a logged servo's lines at 0.031 and 0.083 Hz were said at 0.126 and 0.335 Hz, and the
    residual's band and time scale 4 times off (a field trial). They are read on the interval the coloured errors
    take (effects.timebase.sample_grid: a bursty time base's mean), within 3 %."""
    from fluxcal.service.numerics.diagnose.harmonics import motion_lines
    from fluxcal.service.numerics.diagnose.signature import _time_scale

    rng = np.random.default_rng(seed)
    dt = np.exp(rng.uniform(np.log(0.002), np.log(0.058), 8000))         # 2-58 ms, log-uniform: bursty
    t = np.concatenate([[0.0], np.cumsum(dt)])
    servo = 20 * np.sin(2 * np.pi * 0.031 * t) + 10 * np.sin(2 * np.pi * 0.083 * t + 1)
    lines = sorted(motion_lines(t, servo)[:2])
    assert lines == pytest.approx([0.031, 0.083], rel=0.03), lines
    resid = 50 * np.sin(2 * np.pi * 0.2 * t) + rng.normal(0, 1, t.size)        # half its power beyond 5 s
    period = _time_scale(t, resid, 1.0)[0]
    steady_t = np.arange(t.size) * np.mean(dt)                            # the same samples, evenly spaced
    assert period == pytest.approx(_time_scale(steady_t, resid, 1.0)[0], rel=0.01)
    assert 4.5 < period < 6.0, period                                     # on the median interval: about 1.4 s
    steady = np.arange(8001) * 0.005                                      # a steady time base: as before, bit for bit
    assert motion_lines(steady, np.sin(2 * np.pi * 0.031 * steady)) == motion_lines(
        steady, np.sin(2 * np.pi * 0.031 * steady))


def test_a_law_the_held_out_blocks_do_not_single_out_is_said_as_one_form_among_others():
    """A servo-driven distance power (power 3) added to a real board was read as "a polynomial of degree 2, x0 =
    -20.58 +- 3.2 deg", a vertex the truth does not have, while the distance power predicted the held-out blocks within
    1.6 % (a field trial). Where other laws are not significantly worse than the best, both the forms' line and the
    group's own reading (the JSON's, and so the verdict's sentence) say that its parameters are the form's own, with
    none of the law's physics read into them; where none is, nothing more is said."""
    from types import SimpleNamespace

    from fluxcal.service.numerics.diagnose.discover import Discovery
    from fluxcal.service.numerics.diagnose.shape_reading import as_form
    from fluxcal.service.numerics.diagnose.text import discovery_lines

    forms = [{"observable": "servo_deg", "chosen": "polynomial", "alike": ["distance power", "exponential"],
              "forms": [{"form": "polynomial", "parameters": 4, "heldout_rms_nT": 275.0},
                        {"form": "distance power", "parameters": 5, "heldout_rms_nT": 279.3}]}]
    group = SimpleNamespace(reading="a field that moves as servo_deg goes, as a polynomial of degree 2", term="g",
                            group=SimpleNamespace(kind="shape"))
    found = Discovery(tried=10, tried_params=90, claimed=True, groups=[group], base_rms_nT=900.0,
                       base_heldout_rms_nT=1100.0, floor_nT=140.0, rms_nT=270.0, heldout_rms_nT=275.0, forms=forms)
    lines = "\n".join(discovery_lines(SimpleNamespace(discovery=found)))
    assert "they do not tell it from distance power or exponential: its parameters are those of this form" in lines
    forms[0]["alike"] = []
    assert "do not tell" not in "\n".join(discovery_lines(SimpleNamespace(discovery=found)))
    # the group's own reading says it (the JSON's reading, the group's line and the verdict's sentence alike): the
    # form's parameters, and none of the physics the law would read into them
    formula = "as a polynomial of degree 2, (servo_deg - x0)^2 with x0 = -20.58 +- 3.2 deg"
    physics = "a quadratic in servo_deg about x0"
    said = as_form(formula, physics, ["distance power", "exponential"])
    assert said == ("as a polynomial of degree 2, (servo_deg - x0)^2 with x0 = -20.58 +- 3.2 deg (the held-out blocks "
                    "do not tell it from distance power or exponential: these are the form's parameters, not a law "
                    "these data single out)")
    assert as_form(formula, physics, []) == f"{formula}: {physics}"
    group.reading = f"a field that moves as servo_deg goes, {said}"
    assert group.reading in found.sentence() and found.sentence().count("single out") == 1
