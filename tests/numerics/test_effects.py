"""Effect terms: composition, names, and each term's parameters recovered from simulated data whose every
parameter is known (fluxcal.drivers.sim), through `fit_with_effects`."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.errors import CalibrationRefused, ConfigError, DataError
from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.numerics.effects import (
    EFFECTS,
    Baseline,
    Drift,
    Eddy,
    EffectData,
    Lag,
    Model,
    Temperature,
    make_model,
)
from fluxcal.service.numerics.effects.gradient import gradient_basis
from fluxcal.service.numerics.effects.hysteresis import detect_steps
from fluxcal.service.numerics.effects.platform import Platform
from fluxcal.service.numerics.engine import LinearCalibration, Parameter, fit_with_effects
from fluxcal.service.numerics.noise import robust_noise

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.effects.crossfield", "fluxcal.service.numerics.effects.nonlinearity", "fluxcal.service.numerics.effects.platform", "fluxcal.service.numerics.effects.thermal", "fluxcal.service.numerics.engine.jacobian", "fluxcal.service.numerics.engine.residuals", "fluxcal.service.numerics.engine.state",
          "fluxcal.service.numerics.effects.attitude")

F_TOTAL = 52000.0


def probe(**kw):
    p = {"scale": [1.02, 0.985, 1.01], "nonorth_deg": [0.6, -1.1, 1.4], "offset_nT": [210.0, -330.0, 95.0],
         "noise_nT": 0.8}
    p.update(kw)
    return p


def sim(probes, *, n=8000, rate=100.0, motion=None, temperature=None, seed=5, reference=True, field=None):
    """(EffectData, truth dict, UnitSamples) of a simulated run; attitude columns included."""
    cfg = load_sim_config({
        "seed": seed, "rate_hz": rate, "duration_s": n / rate,
        "field": field or {"total_nT": F_TOTAL, "inclination_deg": 57.0, "declination_deg": -4.0},
        "reference": {"enabled": reference, "noise_nT": 0.05},
        "motion": motion or {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 6.0},
        "temperature": temperature or {"start_C": 20.0, "amplitude_C": 5.0, "period_s": n / rate / 1.5},
        "probes": probes})
    unit = Unit(cfg)
    s = unit.digitise(0, cfg.n_samples)
    block = s.to_block()
    r = s.world.attitude
    block.extras["heel_deg"] = np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2]))
    block.extras["pitch_deg"] = np.degrees(-np.arcsin(np.clip(r[:, 2, 0], -1, 1)))
    block.extras["azimuth_deg"] = np.degrees(np.arctan2(r[:, 1, 0], r[:, 0, 0]))
    pos = np.array([p.get("position_m", [0.0, 0.0, 0.0]) for p in probes], dtype=float)
    data = EffectData.from_block(block, positions_m=pos)
    return data, unit.world.truth(), s


def params(fit, term=None):
    return {p.name: p for p in fit.parameters if term is None or p.term == term}


# --- composition ------------------------------------------------------------------------------------------

def test_terms_compose_with_plus_and_print_their_names():
    model = Baseline() + Temperature() + Eddy()
    assert isinstance(model, Model)
    assert str(model) == "Baseline + Temperature + Eddy"
    assert model.effects == ["temperature", "eddy"] and model.has_baseline
    assert repr(Baseline() + Drift(degree=1)) == "Baseline() + Drift(degree=1)"
    assert str(model + Lag()) == "Baseline + Temperature + Eddy + Lag"
    with pytest.raises(ConfigError, match="eddy given twice"):
        model + Eddy()


def test_catalogue_has_the_contract_names_and_rejects_typos():
    for name in ("temperature", "eddy", "lag", "nonlinearity", "drift"):
        assert name in EFFECTS and EFFECTS[name].name == name
    assert set(EFFECTS) >= {"gradient", "crossfield", "hysteresis", "platform"}
    with pytest.raises(ConfigError, match="'temprature' is not an effect .*allowed: temperature"):
        make_model(["temprature"])
    assert not make_model(["drift"], baseline=False).has_baseline


def test_parameter_names_carry_probe_axis_and_unit():
    data, _, _ = sim([probe(), probe()], n=2000)
    fit, _ = fit_with_effects(data, ["temperature", "lag", "eddy"])
    names = [p.name for p in fit.parameters]
    assert "s1.x nT/degC" in names and "s2.z ppm/degC" in names
    assert "s2.lag s" in names and "s1.lag s" not in names       # lag is relative to probe 1
    assert "s1.eddy[xy] s" in names
    assert all(p.term in ("temperature", "lag", "eddy") for p in fit.parameters)


# --- each term against the simulator's truth ------------------------------------------------------------------

def test_temperature_coefficients_recovered():
    beta, kappa = [3.0, -2.0, 1.2], [25.0, -12.0, 8.0]
    data, truth, _ = sim([probe(temp_offset_nT_per_C=beta, temp_scale_ppm_per_C=kappa)], n=8000)
    fit, ch = fit_with_effects(data, ["temperature"])
    p = params(fit)
    for a, axis in enumerate("xyz"):
        b, k = p[f"s1.{axis} nT/degC"], p[f"s1.{axis} ppm/degC"]
        assert abs(b.value - beta[a]) < 5 * b.stderr + 0.02, (axis, b)
        assert abs(k.value - kappa[a]) < 5 * k.stderr + 0.3, (axis, k)
    noise = truth["sensors"][0]["noise_nT"][0]
    assert ch.total_rms_nT < 1.1 * noise


def test_nonlinearity_coefficients_recovered_exactly_not_to_first_order():
    q, c = [1.0e-7, -0.6e-7, 0.8e-7], [2.0e-13, -1.5e-13, 1.0e-13]
    data, truth, _ = sim([probe(nonlin_quadratic_per_nT=q, nonlin_cubic_per_nT2=c)], n=8000, rate=50.0)
    fit, ch = fit_with_effects(data, ["nonlinearity"])
    p = params(fit)
    for a, axis in enumerate("xyz"):
        # a first-order inversion would be off by 2 q^2 = 1.3e-14..2e-14 in the cubic
        assert p[f"s1.{axis} quadratic 1/nT"].value == pytest.approx(q[a], rel=0.02)
        assert p[f"s1.{axis} cubic 1/nT2"].value == pytest.approx(c[a], rel=0.03, abs=3e-15)
    assert ch.total_rms_nT < 1.1 * 0.8


def test_offset_drift_recovered_in_nT_per_hour():
    d = [300.0, -150.0, 80.0]
    data, _, _ = sim([probe(position_m=[-0.2, 0, 0]), probe(position_m=[0.2, 0, 0], drift_offset_nT_per_h=d)],
                     n=8000)
    fit, ch = fit_with_effects(data, ["drift"])
    p = params(fit)
    for a, axis in enumerate("xyz"):
        got = p[f"s2.{axis} drift nT/h"]
        assert abs(got.value - d[a]) < 5 * got.stderr + 3.0, (axis, got)
        assert abs(p[f"s1.{axis} drift nT/h"].value) < 5 * p[f"s1.{axis} drift nT/h"].stderr + 3.0


def test_ambient_drift_without_reference_is_a_shared_parameter():
    data, _, _ = sim([probe()], n=6000, reference=False,
                     field={"total_nT": F_TOTAL, "inclination_deg": 60.0, "drift_nT_per_h": [400.0, 0.0, 700.0]})
    data.total_nT = F_TOTAL
    fit, ch = fit_with_effects(data, ["drift"])
    p = params(fit)
    # d|B|/dt = B.(dB/dt)/|B| with I = 60 deg: 400 cos60 + 700 sin60 nT/h
    expected = 400.0 * np.cos(np.radians(60)) + 700.0 * np.sin(np.radians(60))
    assert p["ambient drift nT/h"].value == pytest.approx(expected, rel=0.05)


def test_lag_recovered_relative_to_probe_1():
    data, _, _ = sim([probe(position_m=[-0.2, 0, 0], lag_s=0.004),
                      probe(position_m=[0.2, 0, 0], lag_s=0.016, offset_nT=[-90, 40, 15])], n=6000, rate=100.0,
                     motion={"kind": "tumble", "rate_deg_s": 40.0, "tumble_period_s": 5.0})
    fit, ch = fit_with_effects(data, ["lag"])
    assert params(fit)["s2.lag s"].value == pytest.approx(0.012, abs=2e-5)
    assert ch.total_rms_nT < 1.1 * 0.8 * np.sqrt(1.6)      # scalar ~0.8, differences ~0.8 sqrt(2)


def test_eddy_matrix_recovered_in_the_raw_frame():
    e2 = np.array([[0.004, 0.002, 0.0], [-0.001, -0.003, 0.0015], [0.002, 0.0, 0.001]])
    data, truth, _ = sim([probe(position_m=[-0.2, 0, 0]),
                          probe(position_m=[0.2, 0, 0], eddy_s=e2.tolist(), offset_nT=[-90, 40, 15])], n=8000)
    fit, _ = fit_with_effects(data, ["eddy"])
    p = params(fit)
    est = {k: np.array([[p[f"s{k}.eddy[{a}{b}] s"].value for b in "xyz"] for a in "xyz"]) for k in (1, 2)}
    # raw frame: E' = F E F^-1 with F = C A the forward matrix (no misalignment here)
    fwd = np.array(truth["sensors"][1]["forward_matrix"])
    want2 = fwd @ e2 @ np.linalg.inv(fwd)
    # a common isotropic part of all probes acts like a common time shift: not observable, so compare
    # probe 2 minus probe 1 and each probe's deviatoric part
    diff = est[2] - est[1]
    assert np.max(np.abs(diff - want2)) < 1.5e-4
    dev1 = est[1] - np.trace(est[1]) / 3 * np.eye(3)
    assert np.max(np.abs(dev1)) < 1.5e-4


def test_site_gradient_recovered_with_attitude_and_positions():
    g = np.array([[20.0, 5.0, -8.0], [5.0, -12.0, 6.0], [-8.0, 6.0, -8.0]])     # symmetric, traceless, nT/m
    pos = [[0.3, 0, 0], [0, 0.3, 0], [-0.3, 0, 0.1], [0, -0.3, -0.1]]
    data, _, _ = sim([probe(position_m=p, offset_nT=list(np.add([210.0, -330.0, 95.0], 40 * k)))
                      for k, p in enumerate(pos)], n=6000,
                     field={"total_nT": F_TOTAL, "inclination_deg": 57.0, "gradient_nT_m": g.tolist()})
    fit, ch = fit_with_effects(data, ["gradient"])
    p = params(fit)
    got = sum(p[f"gradient G{n} nT/m"].value * e for n, e in zip(("xx", "yy", "xy", "xz", "yz"), gradient_basis()))
    assert np.max(np.abs(got - g)) < 0.5


def test_gradient_needs_attitude_and_positions():
    data, _, _ = sim([probe(position_m=[0.3, 0, 0])], n=2000)
    del data.extras["heel_deg"]
    data._cache.clear()
    with pytest.raises(CalibrationRefused, match="attitude"):
        fit_with_effects(data, ["gradient"])
    data.positions_m = None
    with pytest.raises(CalibrationRefused, match="positions"):
        fit_with_effects(data, ["gradient"])
    # both missing: both said at once (the advice sent a user to --config, and then to the attitude)
    from fluxcal.service.numerics.effects.gradient import Gradient

    why = Gradient().why_unavailable(data)
    assert why.startswith("needs the probe positions (--config") and "and the platform attitude in the data" in why


def test_crossfield_against_a_private_forward_model():
    # in one probe's scalar channel only some combinations show; the difference to a second probe sees
    # the vector, except for the combinations that involve u_x u_y u_z (see the assertion below)
    data, truth, s = sim([probe(position_m=[-0.2, 0, 0]), probe(position_m=[0.2, 0, 0], offset_nT=[-90, 40, 15])],
                         n=6000, temperature={"start_C": 20.0})
    fwd = np.array(truth["sensors"][1]["forward_matrix"])
    off = np.array(truth["sensors"][1]["offset_nT"])
    b = s.world.field_platform_nT[:, 1, :]
    xcoef = np.array([[2e-8, 0.0, -1e-8], [0.0, 1.5e-8, 0.0], [-1e-8, 0.0, 2.5e-8]])   # per axis: xy, xz, yz
    u = b @ fwd.T
    prods = np.stack([u[:, 0] * u[:, 1], u[:, 0] * u[:, 2], u[:, 1] * u[:, 2]], axis=1)
    data.raw_nT[:, 1, :] = u + prods @ xcoef.T + off + s.world.noise_nT[:, 1, :]     # u_a += x_a,bc u_b u_c
    data._cache.clear()
    fit, ch = fit_with_effects(data, ["crossfield"])
    p = params(fit)
    for a, axis in enumerate("xyz"):
        for j, pair in enumerate(("xy", "xz", "yz")):
            got = p[f"s2.{axis} cross {pair} 1/nT"]
            if axis not in pair:
                # x.yz, y.xz and z.xy multiply the same monomial u_x u_y u_z in probe 1's scalar channel,
                # and probe 1's trade against probe 2's through the difference: reported undetermined
                assert got.stderr is None
            else:
                # (a parameter that leans slightly on the undetermined combination takes a small bias from
                # the minimum-norm choice there: allow 2 % of the coefficients' scale)
                assert abs(got.value - xcoef[a, j]) < 5 * got.stderr + 5e-10, (axis, pair, got)
                assert got.stderr < 1e-9                 # a tenth of the coefficients
    assert ch.total_rms_nT < 1.1 * 0.8 * np.sqrt(1.6)


def test_platform_fields_seen_through_a_fixed_lab_calibration():
    data, truth, s = sim([probe()], n=6000, temperature={"start_C": 20.0})
    fwd = np.array(truth["sensors"][0]["forward_matrix"])
    off = np.array(truth["sensors"][0]["offset_nT"])
    b = s.world.field_platform_nT[:, 0, :]
    perm = np.array([35.0, -20.0, 12.0])
    ind = np.array([[0.004, 0.001, 0.0005], [0.001, -0.002, 0.003], [0.0005, 0.003, 0.002]])
    data.raw_nT[:, 0, :] = (b + perm + b @ ind.T) @ fwd.T + off + s.world.noise_nT[:, 0, :]
    data._cache.clear()
    lab = LinearCalibration(off[None, :], np.array(truth["sensors"][0]["matrix"])[None])
    fit, ch = fit_with_effects(data, ["platform"], lab, fix_linear=True)
    p = params(fit)
    got = np.array([[p[f"s1.platform induced[{a}{b}]"].value for b in "xyz"] for a in "xyz"])
    for a, axis in enumerate("xyz"):
        assert p[f"s1.platform permanent {axis} nT"].value == pytest.approx(perm[a], abs=0.3)
    # a scalar channel sees the symmetric part of the induced matrix (its rotation part is a frame change)
    assert np.max(np.abs((got + got.T) / 2 - ind)) < 3e-5
    assert np.allclose(fit.offset_nT, off) and ch.total_rms_nT < 1.1 * 0.8
    assert Platform().rules_out(fit.parameters) is None                  # a platform's small induced field


def test_a_platform_term_that_cancels_the_field_is_ruled_out():
    """With A = I and |p| the total field the platform term fits any data exactly: the corrected field is -p. On a
    real flight log held to a poor calibration the fit went there (A's diagonal 0.95-0.99, 19 nT left under a noise
    floor of 296 nT) and diagnose called it 'explained by platform'. Ruled out by its physics now."""
    a = np.diag([0.946, 0.949, 0.992]) + 0.01
    pars = [Parameter(f"s1.platform permanent {x} nT", v, None, "platform", "s1", ("permanent", i))
            for i, (x, v) in enumerate(zip("xyz", (-834, 8593, 21713)))]
    pars += [Parameter(f"s1.platform induced[{x}{y}]", a[i, j], 0.03, "platform", "s1", ("induced", i, j))
             for i, x in enumerate("xyz") for j, y in enumerate("xyz")]
    why = Platform().rules_out(pars)
    assert why is not None and why.startswith("s1's induced field would be 1.0") and "cancels the measured field" in why
    v0 = np.random.default_rng(1).normal(0.0, 20000.0, (50, 3))
    p = np.array([0.0, 0.0, 50000.0])
    corrected = v0 - Platform().correction(None, np.concatenate([p, np.eye(3).ravel()]), v0)
    assert np.allclose(np.linalg.norm(corrected, axis=1), 50000.0)          # any data, fitted exactly


def test_perming_steps_found_at_their_instants_and_not_in_noise():
    rng = np.random.default_rng(3)
    n = 20000
    t = np.arange(n) * 0.01
    ang = 0.5 * t
    gain = np.stack([np.cos(ang) * np.cos(0.3 * t), np.sin(ang) * np.cos(0.3 * t), np.sin(0.3 * t)], axis=1)
    noise = rng.standard_normal(n)
    steps = detect_steps(t, noise, gain, window=500)
    assert steps == []
    r = noise + gain @ np.array([3.0, -2.0, 1.0]) * (t >= 71.3) + gain @ np.array([0.0, 4.0, 0.0]) * (t >= 150.0)
    found = sorted(ts for ts, _ in detect_steps(t, r, gain, window=500))
    assert len(found) == 2
    assert found[0] == pytest.approx(71.3, abs=0.3) and found[1] == pytest.approx(150.0, abs=0.3)
    assert robust_noise(noise * 2.5) == pytest.approx(2.5, rel=0.03)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_step_is_found_beside_a_ramp_and_a_ramp_is_no_step(seed):
    """A warm-up or a ramp keeps the window statistic high along its length: its peaks are judged (a step must fit
    better than a line, and a jump better than a bend) and rejected without using up the steps allowed, so a
    weaker true step later is still found (the review's case: a 100 nT ramp over 10-40 s hid a 6 nT step)."""
    rng = np.random.default_rng(seed)
    n = 24000
    t = np.arange(n) / 200.0
    a, b = 2 * np.pi * 0.13 * t, 2 * np.pi * 0.071 * t + 1.0
    gain = np.column_stack([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)])
    ramp = np.zeros((n, 3))
    ramp[:, 0] = 100.0 * np.clip((t - 10.0) / 30.0, 0.0, 1.0)
    warm = np.outer(1.0 - np.exp(-t / 15.0), [25.0, -20.0, 15.0])
    step = np.outer(t >= 90.0, [0.0, 6.0, 0.0])
    for smooth in (ramp, warm):
        r = np.einsum("ni,ni->n", gain, smooth + step) + 0.5 * rng.standard_normal(n)
        assert [round(ts, 1) for ts, _ in detect_steps(t, r, gain, window=800)] == [90.0]
        r = np.einsum("ni,ni->n", gain, smooth) + 0.5 * rng.standard_normal(n)
        assert detect_steps(t, r, gain, window=800) == []


def test_correct_applies_calibration_and_effects_to_other_data():
    kw = {"temp_offset_nT_per_C": [3.0, -2.0, 1.0], "drift_offset_nT_per_h": [200.0, 0.0, -100.0]}
    data, truth, _ = sim([probe(**kw)], n=6000, seed=5)
    fit, _ = fit_with_effects(data, ["temperature", "drift"])
    consts = {n: v for _, n, v, _ in fit.constants()}
    assert consts["s1 reference temperature"] == pytest.approx(float(np.mean(data.temp_C)), abs=1e-9)
    assert fit.calibration().effect_params["drift"]["s1 drift time origin"]["unit"] == "s"
    # other data 8 degC warmer: the coefficients stay referenced to the fit's mean temperature
    other, _, s2 = sim([probe(**kw)], n=3000, seed=9, temperature={"start_C": 28.0, "amplitude_C": 5.0,
                                                                     "period_s": 20.0})
    corrected = fit.correct(other)
    # corrected is in probe 1's frame: compare magnitudes with the true field
    err = np.linalg.norm(corrected[:, 0, :], axis=1) - np.linalg.norm(s2.world.field_platform_nT[:, 0, :], axis=1)
    assert np.sqrt(np.mean(err[50:-50] ** 2)) < 1.2 * 0.8


def test_effect_data_drops_saturated_rows_and_reads_quaternions():
    data, _, s = sim([probe()], n=600)
    block = s.to_block()
    block.field_nT[10, 0, 1] = np.nan
    d2 = EffectData.from_block(block)
    assert d2.dropped_rows == 1 and d2.n_samples == data.n_samples - 1
    # the same attitude as a quaternion
    r = s.world.attitude
    w = np.sqrt(np.clip(1 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2], 1e-12, None)) / 2
    block.extras.update({"q_w": w, "q_x": (r[:, 2, 1] - r[:, 1, 2]) / (4 * w), "q_y": (r[:, 0, 2] - r[:, 2, 0]) / (4 * w),
                         "q_z": (r[:, 1, 0] - r[:, 0, 1]) / (4 * w)})
    block.field_nT[10, 0, 1] = 1.0
    d3 = EffectData.from_block(block)
    assert np.allclose(d3.attitude(), data.attitude(), atol=1e-9)
    with pytest.raises(DataError, match="too few"):
        EffectData.from_block(block.slice(0, 10))


def test_fit_with_effects_takes_and_returns_array_calibrations():
    from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
    from fluxcal.service.numerics.calib.model import ArrayCalibration

    beta = [2.0, -1.0, 0.5]
    data, truth, _ = sim([probe(temp_offset_nT_per_C=beta)], n=5000)
    base = ArrayCalibration(method="ellipsoid", align=None,
                            probes=[fit_ellipsoid(data.raw_nT[:, 0, :], data.ref_total_nT).calibration])
    fit, ch = fit_with_effects(data, ["temperature"], base)
    cal = fit.calibration()
    assert isinstance(cal, ArrayCalibration) and cal.method == "ellipsoid" and cal.effects == ["temperature"]
    got = cal.effect_params["temperature"]["s1.x nT/degC"]
    assert got["unit"] == "nT/degC" and got["value"] == pytest.approx(beta[0], abs=5 * got["se"] + 0.02)
    # the linear part: matrix (raw - offset) has the true field's magnitude
    corr = cal.apply_linear(data.raw_nT)
    assert np.median(np.abs(np.linalg.norm(corr[:, 0], axis=1) - data.ref_total_nT)) < 20.0
    with pytest.raises(DataError, match=r"holds effect terms \(temperature\) that read more than the field"):
        cal.apply(data.raw_nT)                     # the field alone cannot carry its effects: never dropped silently
    assert np.all(np.isfinite(cal.probes[0].offset_se_nT))
    assert fit.as_dict()["effect_parameters"][0]["unit"] == "nT/degC"


def test_reference_vector_gives_vector_channels_and_probe_1_lag():
    data, truth, s = sim([probe(lag_s=0.01)], n=5000, motion={"kind": "tumble", "rate_deg_s": 40.0,
                                                              "tumble_period_s": 5.0})
    ref = s.world.field_origin_nT + 0.05 * np.random.default_rng(1).standard_normal((data.n_samples, 3))
    for a, c in enumerate(("ref_x", "ref_y", "ref_z")):
        data.extras[c] = ref[:, a]
    fit, ch = fit_with_effects(data, ["lag"])
    assert ch.names == ["s1.scalar", "s1-ref.x", "s1-ref.y", "s1-ref.z"]
    assert params(fit)["s1.lag s"].value == pytest.approx(0.01, abs=5e-5)
    # with a vector reference the probe's rotation is determined: its matrix is the truth calibration
    assert np.allclose(fit.matrix[0], truth["sensors"][0]["matrix"], atol=2e-4)
    assert ch.total_rms_nT < 1.1 * 0.8


def test_a_column_logged_but_never_changing_is_named_not_asked_for():
    """A battery monitor that read 0 A throughout (a real flight's): the column effect said 'log the heater or motor
    currents' of data that log one; it names the column and says it does not change."""
    import numpy as np

    from fluxcal.service.numerics.effects.base import EffectData
    from fluxcal.service.numerics.effects.column import Column

    n = 200
    d = EffectData(t_s=np.arange(n) * 0.1, raw_nT=np.ones((n, 1, 3)), temp_C=np.full((n, 1), np.nan),
                   probe_names=["s1"], extras={"battery_current_a": np.zeros(n)})
    why = Column().why_unavailable(d)
    assert "battery_current_a" in why and "do not change" in why and "log the" not in why
    bare = EffectData(t_s=np.arange(n) * 0.1, raw_nT=np.ones((n, 1, 3)), temp_C=np.full((n, 1), np.nan),
                      probe_names=["s1"], extras={})
    assert "log the" in Column().why_unavailable(bare)


def test_a_nonlinearity_that_folds_the_transfer_back_within_the_readings_is_ruled_out():
    """A real copter log's compass held to a poor calibration: the nonlinearity term fitted q = -2e-4 /nT over
    readings of +-20,000 nT and took the verdict ('partly explained'); its transfer r = u + q u^2 + c u^3 would fold
    back within those readings (slope 1 + 2 q u = -7 at 20,000 nT). A real fluxgate's stays within 1e-3 of 1."""
    from fluxcal.service.numerics.effects import make_term
    from fluxcal.service.numerics.effects.span import ReadingSpan

    term = make_term("nonlinearity")
    span = ReadingSpan(["s1"], np.array([[-20000.0, -15000.0, -3000.0]]), np.array([[21000.0, 14000.0, 2500.0]]))

    def params(q, c):
        return [Parameter(f"s1.{a} quadratic 1/nT", q, 1e-9, "nonlinearity", "s1", ("quadratic", i))
                for i, a in enumerate("xyz")] + \
               [Parameter(f"s1.{a} cubic 1/nT2", c, 1e-14, "nonlinearity", "s1", ("cubic", i)) for i, a in enumerate("xyz")]

    why = term.rules_out_over(params(-2e-4, 0.0), span)
    assert why is not None and "s1's x transfer would fold back" in why and "21,000 nT" in why
    assert term.rules_out_over(params(2e-7, -1e-12), span) is None         # a fluxgate's: slope within 1e-2 of 1
    # a cubic alone: 1 + 3 c u^2 with c = -4e-10 is 0.47 at 21,000 nT (x's upper end), below MIN_SLOPE; on narrow
    # readings (-3,000..2,500 nT: 0.99) it passes
    why = term.rules_out_over(params(0.0, -4e-10), span)
    assert why is not None and "s1's x transfer would lose 53% of its gain" in why and "21,000 nT" in why
    narrow = ReadingSpan(["s1"], np.array([[-3000.0] * 3]), np.array([[2500.0] * 3]))
    assert term.rules_out_over(params(0.0, -4e-10), narrow) is None
    # a slope whose least value lies between the ends (c > 0: at u = -q / 3c = 2,000 nT, 1 - q^2 / 3c = 0.4) while
    # both ends pass (1.75 at -1,000 nT, 0.55 at 3,000 nT): judged at its turning point
    inside = ReadingSpan(["s1"], np.array([[-1000.0] * 3]), np.array([[3000.0] * 3]))
    why = term.rules_out_over(params(-3e-4, 5e-8), inside)
    assert why is not None and "slope 0.4 at 2,000 nT" in why


@pytest.mark.parametrize("seed, lag_s, pink", [(1, 5.0, 0.0), (4, 0.0, 0.0), (6, 0.0, 0.0), (10, 0.0, 0.0),
                                               (11, 5.0, 0.0), (2, 5.0, 0.3)])
def test_thermal_lag_found_from_zero_up_and_held_at_its_floor(seed, lag_s, pink):
    """A core lagging its housing by 5 s, or not at all, over 40 s of tumbling: before, the fit stopped unconverged
    or at a wrong lag in 11 of 24 such worlds (12 seeds; these 5 among them), and printed lags below zero with a
    straight face (-6.9 +- 2.6 s). The lag never goes below zero: held there, it is said to be, without an error."""
    beta = [3.0, -2.0, 1.2]
    data, truth, _ = sim([probe(temp_offset_nT_per_C=beta, temp_lag_s=lag_s, pink_nT_rtHz=pink)], n=4000, seed=seed)
    fit, ch = fit_with_effects(data, ["thermal"])
    assert fit.result.converged
    p = params(fit)
    tau = p["s1.thermal lag s"]
    assert tau.value >= 0.0
    if tau.at_floor:
        assert lag_s == 0.0 and tau.value == 0.0 and tau.stderr is None
        assert any("held at 0 s, the lowest value it can take" in w for w in fit.size_warnings())
        assert fit.calibration().effect_params["thermal"]["s1.thermal lag s"]["at_floor"].startswith("a core cannot")
        from fluxcal.service.numerics.calib.param_table import effect_rows          # the report's table says it too

        row = {r.name: r for r in effect_rows(fit.calibration().effect_params)}["s1.thermal lag s"]
        assert row.warning == "" and row.note.startswith("at its floor: a core cannot"), row
    else:
        assert abs(tau.value - lag_s) < 3 * tau.stderr, tau
    for a, axis in enumerate("xyz"):
        b = p[f"s1.{axis} nT/degC"]
        assert abs(b.value - beta[a]) < 4 * b.stderr, (axis, b)
    assert ch.total_rms_nT < 1.1 * float(np.mean(truth["sensors"][0]["noise_nT"])) + pink


def test_a_fit_stopped_before_it_converged_says_so():
    data, _, _ = sim([probe(temp_offset_nT_per_C=[3.0, -2.0, 1.2], temp_lag_s=5.0)], n=2000, seed=3)
    fit, _ = fit_with_effects(data, ["thermal"])
    assert not any("before it converged" in w for w in fit.size_warnings())
    fit.result.converged, fit.result.iterations = False, 8
    assert fit.size_warnings()[0] == ("the fit with thermal stopped after 8 iterations, before it converged: its "
                                      "parameters are not the best these data give, nor their errors final")
