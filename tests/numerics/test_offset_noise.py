"""The linear calibration's offsets under coloured noise (numerics/calib/offset_noise.py): the weights each
offset gives every raw axis's noise, and the variance they give under a known 1/f spectrum against a Monte
Carlo of the fits themselves, on two tumbles."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.sim.streams import PinkNoise
from fluxcal.service.numerics.calib.alignment import regression_calibration
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.model import triangular_params
from fluxcal.service.numerics.calib.offset_noise import (
    ellipsoid_weights,
    record_se,
    regression_weights,
    wander_per_decade,
)

F = 50000.0


def tumble(seed: int, n: int = 4000, turns: int = 7, top: float = 0.95) -> np.ndarray:
    """(n, 3) unit directions turning `turns` times about z while the polar angle swings twice between 9 degrees
    and `top` x 180: slow, so 1/f noise at the record's own periods matters."""
    ph = 2 * np.pi * np.arange(n) / n + np.random.default_rng(seed).uniform(0, 2 * np.pi)
    polar = np.pi * (0.05 + (top - 0.05) * (0.5 - 0.5 * np.cos(2 * ph)))
    return np.column_stack([np.cos(turns * ph) * np.sin(polar), np.sin(turns * ph) * np.sin(polar), np.cos(polar)])


def probe(seed: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    m = np.eye(3) + 0.03 * rng.standard_normal((3, 3))
    o = rng.uniform(-400, 400, 3)
    return np.linalg.solve(m, (F * d).T).T + o, m, o


@pytest.mark.parametrize("seed", [1, 2])
def test_each_offset_takes_a_constant_in_its_own_axis_one_to_one_whatever_the_origin_and_unit(seed):
    raw, m, o = probe(seed, tumble(seed))
    m = np.linalg.qr(m)[1] * np.sign(np.diag(np.linalg.qr(m)[1]))[:, None]    # the fit's triangular form
    w, w_m = ellipsoid_weights(raw, o, m, "full", F)
    assert np.allclose(w.sum(axis=0), np.eye(3), atol=1e-6)
    assert np.allclose(w_m.sum(axis=0), 0.0, atol=1e-9)             # a constant moves the offset alone
    shift, factor = np.array([3e5, -2e5, 1e5]), 1e-3                # moved and in other units: the same weights
    moved = ellipsoid_weights((raw + shift) * factor, (o + shift) * factor, m, "full", F * factor)[0]
    assert np.allclose(moved, w, rtol=0, atol=1e-9 * np.abs(w).max())
    w2, w2_m = regression_weights(raw, m, o)                         # on the regression's residual: -A^-1
    assert np.allclose(w2.sum(axis=0), -np.linalg.inv(m), atol=1e-9)
    assert np.allclose(w2_m.sum(axis=0), 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", [1, 2])
def test_the_offsets_record_error_under_flicker_noise_matches_a_monte_carlo_of_the_fits(seed):
    """200 fits of one tumble with 1/f noise of 0.5 nT/sqrt(Hz) per raw axis (the simulator's, 1e-5 Hz up):
    the spread of offset - truth - the noise's mean over the record, and of the matrix's named parameters
    (ellipsoid) and elements (regression), against record_se's figure for the known law, within 20 %."""
    n, dt, s = 4000, 0.1, 0.5
    d = tumble(seed, n)
    raw, m, o = probe(seed, d)
    grid = np.arange(n)
    law = [(0.0, s ** 2, -1.0)] * 3
    w_o, w_m = ellipsoid_weights(raw, o, m, "full", F)
    want = record_se(w_o, grid, dt, law)
    want_m = record_se(w_m, grid, dt, law)[9:]                        # nonorth_deg, then scale
    # the regression's offsets are immune to first order where the directions average to zero (its weights
    # are then uniform): a probe that saw mostly the upper half
    d2 = tumble(seed, n, top=0.6)
    raw2, m2, o2 = probe(seed + 10, d2)
    w2_o, w2_m = regression_weights(raw2, m2, o2)
    want2, want2_m = record_se(w2_o, grid, dt, law), record_se(w2_m, grid, dt, law)
    errs, errs2, shapes, mats2 = [], [], [], []
    for k in range(200):
        noise = PinkNoise(100 * seed + k, 7, np.full(3, s), 1e-5, 0.5 / dt, 1 / dt).draw(0, n)
        fit = fit_ellipsoid(raw + noise, F, order="full").calibration
        errs.append(fit.offset_nT - o - noise.mean(axis=0))
        shapes.append(np.concatenate(triangular_params(fit.matrix)))
        reg = regression_calibration("s2", F * d2 + noise, raw2)       # the noise in the residual: the reference's
        errs2.append(reg.offset_nT - o2 + np.linalg.solve(m2, noise.mean(axis=0)))
        mats2.append(reg.matrix.ravel())
    assert np.std(errs, axis=0) == pytest.approx(want, rel=0.2)
    assert np.std(errs2, axis=0) == pytest.approx(want2, rel=0.2)
    assert np.std(shapes, axis=0) == pytest.approx(want_m, rel=0.2)
    assert np.std(mats2, axis=0) == pytest.approx(want2_m, rel=0.2)
    # the record's own mean is what the record cannot know: a decade of time beyond it, sqrt(a ln 10) under 1/f
    assert wander_per_decade(law[0], n * dt) == pytest.approx(s * np.sqrt(np.log(10)))
    assert wander_per_decade((0.0, s ** 2, -1.2), n * dt) > wander_per_decade(law[0], n * dt)


def _pair(n: int, pink: float, seed: int = 3):
    """test_stderr's pair of probes, n samples at 20 Hz, as `fit` sees it: (data, calibration, total field)."""
    from test_stderr import pair_unit

    from fluxcal.service.io.recordings.labdata import LabData
    from fluxcal.service.wiring.fitting import fit_array

    unit = pair_unit(seed, pink)
    block = unit.digitise(0, n).to_block()
    data = LabData(block=block, probe_names=["s1", "s2"], path="mem")
    cal, total = fit_array(data)
    return data, cal, total


def test_a_failure_of_the_coloured_errors_keeps_the_white_ones_and_says_they_are_lower_bounds(monkeypatch):
    from fluxcal.service.numerics.calib import offset_noise
    from fluxcal.service.wiring.coloured_fit import coloured_offsets
    from fluxcal.service.wiring.commands.fit import coloured_warnings

    data, cal, total = _pair(18000, 0.3)
    white = cal.probes[0].offset_se_nT.copy()

    def broken(*args, **kwargs):
        raise np.linalg.LinAlgError("singular")

    monkeypatch.setattr(offset_noise, "ellipsoid_weights", broken)
    found = {c.probe: c for c in coloured_offsets(data, cal, total)}
    assert not found["s1"].covered and found["s2"].covered
    assert np.array_equal(cal.probes[0].offset_se_nT, white)
    said = coloured_warnings(found.values())
    assert any(w.startswith("s1:") and "lower bounds" in w for w in said), said
    assert any(w.startswith("s2:") and "wander within the record" in w for w in said), said


def test_a_regression_aligned_probe_inherits_the_reference_offset_errors_on_any_record():
    """Even where no spectrum can be taken (400 samples): probe 2's offset errors are the regression's and
    probe 1's carried over, -A^-1 M_1 delta o_1; where probe 1 has none (NaN), the regression's alone."""
    from fluxcal.service.numerics.calib.alignment import regression_calibration
    from fluxcal.service.wiring.coloured_fit import coloured_offsets

    data, cal, total = _pair(400, 0.0)
    p1, p2 = cal.probes
    own = regression_calibration("s2", p1.apply(data.block.field_nT[:, 0]), data.block.field_nT[:, 1]).offset_se_nT
    assert np.allclose(p2.offset_se_nT, own)
    assert coloured_offsets(data, cal, total) == []
    carry = np.linalg.solve(p2.matrix, p1.matrix)
    assert np.allclose(p2.offset_se_nT, np.sqrt(own ** 2 + np.diag(carry @ np.diag(p1.offset_se_nT ** 2) @ carry.T)))
    assert p2.params["offset_nT"]["se"] == pytest.approx(p2.offset_se_nT.tolist())
    data, cal, total = _pair(400, 0.0)
    cal.probes[0].offset_se_nT = np.full(3, np.nan)
    before = cal.probes[1].offset_se_nT.copy()
    coloured_offsets(data, cal, total)
    assert np.array_equal(cal.probes[1].offset_se_nT, before)


def test_tmi_gets_the_errors_of_the_ellipsoid_fit_it_equals():
    """`fit --method tmi` is the ellipsoid fit with the total given: the same offsets and matrix (to 1e-9 here), so
    the same coloured-noise and direction errors. It kept the white-noise ones: on a flight's cabin fluxgate
    (MagNav, public) +-280 nT where the ellipsoid said +-2,200 and an attitude-based check lay 4-10 of them away."""
    from fluxcal.service.wiring.coloured_fit import coloured_offsets, direction_offsets
    from fluxcal.service.wiring.fitting import fit_array

    data, ell, total = _pair(18000, 0.3)
    tmi, _ = fit_array(data, method="tmi")
    white = np.array(tmi.probes[0].offset_se_nT, float)
    for cal in (ell, tmi):
        coloured_offsets(data, cal, total)
        direction_offsets(data, cal, total)
    for pe, pt in zip(ell.probes, tmi.probes):
        assert np.allclose(pt.offset_nT, pe.offset_nT, rtol=0, atol=1e-9 * 50_000)
        assert np.allclose(pt.offset_se_nT, pe.offset_se_nT, rtol=1e-6)
        assert np.allclose(pt.matrix_se, pe.matrix_se, rtol=1e-6)
    assert np.all(np.asarray(tmi.probes[0].offset_se_nT) > 1.5 * white)        # the 1/f noise's wander, taken


def test_rls_errors_are_those_of_the_fit_it_equals_with_a_reference_column(monkeypatch):
    """`fit --method rls` takes a ref_total column's level only (its mean square sets the scale): its offsets are
    the ellipsoid fit's without the reference (to 1e-6 nT here, with the reference moved by 400 nT), and the noise's
    and the directions' errors are asked of that fit, not of the reference-constrained one. They were: on a
    flight (MagNav, public) +-709 nT for an offset whose own fit says +-7,388."""
    import dataclasses

    from fluxcal.service.numerics.calib import misfit, offset_noise
    from fluxcal.service.wiring.coloured_fit import coloured_offsets, direction_offsets
    from fluxcal.service.wiring.fitting import fit_array

    data, _, _ = _pair(18000, 0.3)
    b = data.block
    moved = {**b.extras, "ref_total": np.asarray(b.extras["ref_total"], float)
             + 400.0 * np.sin(np.linspace(0.0, 3.0, b.n_samples))}
    given = dataclasses.replace(data, block=dataclasses.replace(b, extras=moved))
    without = dataclasses.replace(data, block=dataclasses.replace(
        b, extras={k: v for k, v in b.extras.items() if k != "ref_total"}))
    rls, total = fit_array(given, method="rls", align="none")
    alone, _ = fit_array(without, method="rls", align="none")
    assert np.allclose(rls.probes[0].offset_nT, alone.probes[0].offset_nT, rtol=0, atol=1e-6)
    asked = []
    weights, jackknife = offset_noise.ellipsoid_weights, misfit.direction_jackknife
    monkeypatch.setattr(offset_noise, "ellipsoid_weights", lambda *a: asked.append(("weights", a[4])) or weights(*a))
    monkeypatch.setattr(misfit, "direction_jackknife",
                        lambda raw, tot, *a, **k: asked.append(("directions", tot)) or jackknife(raw, tot, *a, **k))
    coloured_offsets(given, rls, total)
    direction_offsets(given, rls, total)
    assert {w for w, _ in asked} == {"weights", "directions"} and all(t is None for _, t in asked)
    ell, total = fit_array(given, method="ellipsoid", align="none")
    asked.clear()
    coloured_offsets(given, ell, total)
    direction_offsets(given, ell, total)
    assert asked and all(t is not None for _, t in asked)              # the ellipsoid fit takes the reference
