"""Real sensors: hard-iron offsets several times the field, partial coverage, and answers that do not
depend on where the origin is or what the unit is.

The recordings are public data in ../shared/real-data (its README): hand-turned hobby boards with
their authors' published calibrations. They are read from there (or $FLUXCAL_REAL_DATA: tests/real_data.py),
never copied into the project.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from real_data import find, mend, real, real_nT

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.numerics.calib.coverage import coverage
from fluxcal.service.numerics.calib.ellipsoid import fit_ellipsoid
from fluxcal.service.numerics.calib.model import triangular_matrix
from fluxcal.service.numerics.calib.rls import RlsEllipsoid
from fluxcal.service.numerics.calib.tmi import fit_tmi
from fluxcal.service.numerics.calib.twostep import fit_two_step_full
from fluxcal.service.wiring.pipeline import Pipeline

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.calib.excitation",)

ROOT = Path(__file__).resolve().parents[2]
FULL_SPHERE = ["qmc5883l_suarez", "imu_freeimucal", "hmc5883l_sensorfusion_sphere"]
PARTIAL = ["hmc5883l_nliaudat", "hmc5883l_sensorfusion_turn_x", "hmc5883l_sensorfusion_turn_y",
           "hmc5883l_sensorfusion_turn_z"]


def raw_of(name: str) -> np.ndarray:
    return load_data(real_nT(f"{name}.csv")).block.field_nT[:, 0, :]


def spread(b: np.ndarray) -> float:
    """Relative spread of the calibrated magnitude: std |b| / mean |b|, the figure hobby tools report."""
    m = np.linalg.norm(b, axis=1)
    return float(np.std(m) / np.mean(m))


def authors_calibrated(name: str, raw_nT: np.ndarray) -> np.ndarray | None:
    """The recording calibrated as its authors published (None where they published nothing)."""
    path = find(f"{name}.published.json")
    if path is None:
        return None
    pub = json.loads(path.read_text())
    raw = raw_nT / (pub["data"]["scale_to_nT"] * mend(name))     # back to the source's own units
    if "A" in pub:                                       # m = A raw + B
        return raw @ np.asarray(pub["A"]).T + np.asarray(pub["B"])
    if "diag" in pub:                                    # (raw − offset) diag(c)
        return (raw - np.asarray(pub["offset"])) * np.asarray(pub["diag"])
    return (raw - np.asarray(pub["hard_iron"])) @ np.asarray(pub["soft_iron"]).T


def reference_fit(raw: np.ndarray) -> np.ndarray:
    """A closed-form reference written apart from the product: the ten-term homogeneous quadric of
    the centred, scaled samples as the smallest right singular vector (‖v‖ = 1, no right side), then
    centre and shape. Returns the calibrated samples."""
    c = raw.mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((raw - c) ** 2, axis=1))))
    x, y, z = ((raw - c) / s).T
    d = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z, np.ones_like(x)])
    v = np.linalg.svd(d, full_matrices=False)[2][-1]
    a = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    centre = -np.linalg.solve(a, v[6:9])
    k = centre @ a @ centre - v[9]
    q = a / k                                            # (u − centre)ᵀ q (u − centre) = 1, either sign of v
    w, e = np.linalg.eigh(q)
    m = e @ np.diag(np.sqrt(w)) @ e.T
    return ((raw - c) / s - centre) @ m.T


# --- the full-sphere recordings, raw ---------------------------------------------------------------


@pytest.mark.parametrize("name", FULL_SPHERE)
def test_a_full_sphere_with_a_large_offset_fits_raw_as_well_as_the_best_reference(name):
    raw = raw_of(name)
    fit = fit_ellipsoid(raw)
    cal = fit.calibration
    ours = spread(cal.apply(raw))
    refs = {"closed-form reference": spread(reference_fit(raw))}
    authors = authors_calibrated(name, raw)
    if authors is not None:
        refs["authors"] = spread(authors)
    assert ours <= min(refs.values()) * 1.02, (ours, refs)
    # the offset is several times the field's radius: the origin lies far outside the data's ellipsoid
    assert np.linalg.norm(cal.offset_nT) > 0.15 * np.sqrt(fit.f2_ref)
    assert fit.order == "full" and coverage(raw, centre_nT=cal.offset_nT).fraction > 0.9


def test_the_suarez_board_matches_its_authors_calibration():
    """2.906 % against the authors' 2.904 % spread of |B| (measured; their fit minimised it directly)."""
    raw = raw_of("qmc5883l_suarez")
    ours = spread(fit_ellipsoid(raw).calibration.apply(raw))
    assert abs(ours - spread(authors_calibrated("qmc5883l_suarez", raw))) < 0.0005


@pytest.mark.parametrize("name", FULL_SPHERE)
def test_coverage_is_counted_about_the_fitted_centre(name):
    """About zero a board with a large offset 'sees' one direction (8 % reported before); about its
    fitted centre it saw them all, and no turn is advised."""
    raw = raw_of(name)
    cal = fit_ellipsoid(raw).calibration
    about_zero, about_centre = coverage(raw), coverage(raw, centre_nT=cal.offset_nT)
    assert about_centre.fraction > 0.9 and about_centre.usable and about_centre.regions == []
    if name != "hmc5883l_sensorfusion_sphere":           # its offset is a fifth of the field: zero is inside
        assert about_zero.fraction < 0.3


# --- invariance: origin and unit ---------------------------------------------------------------------


def _moved(raw: np.ndarray, shift: np.ndarray, factor: float):
    return (raw + shift) * factor


@pytest.mark.parametrize("name", FULL_SPHERE)
def test_moving_a_real_recording_moves_only_the_offset(name):
    raw = raw_of(name)
    base = fit_ellipsoid(raw).calibration
    radius = float(np.mean(np.linalg.norm(base.apply(raw), axis=1)))
    rng = np.random.default_rng(7)
    for _ in range(3):
        shift = rng.normal(size=3) * 100 * radius
        factor = 10 ** rng.uniform(-3, 3)
        moved = fit_ellipsoid(_moved(raw, shift, factor)).calibration
        assert np.allclose(moved.offset_nT / factor - shift, base.offset_nT, rtol=0, atol=1e-6 * radius)
        assert np.allclose(moved.matrix, base.matrix, rtol=1e-6, atol=1e-9)
        assert moved.model_order == base.model_order


def _distorted_sphere(seed: int, n: int = 400, noise: float = 1e-3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = rng.uniform(0.7, 1.4, 3)
    angles = rng.uniform(-4, 4, 3)
    raw_of_b = np.linalg.inv(triangular_matrix(angles, c))
    return d @ raw_of_b.T + rng.normal(size=3) * rng.uniform(0, 5) + rng.normal(scale=noise, size=(n, 3))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), shift_fields=st.floats(-100, 100), log_factor=st.floats(-3, 3),
       axis=st.integers(0, 2))
def test_any_offset_and_unit_give_the_same_calibration(seed, shift_fields, log_factor, axis):
    raw = _distorted_sphere(seed)
    shift = np.zeros(3)
    shift[axis] = shift_fields
    shift += np.random.default_rng(seed + 1).normal(size=3) * abs(shift_fields)
    factor = 10.0 ** log_factor
    moved = _moved(raw, shift, factor)
    for fit in (lambda r, k: fit_ellipsoid(r).calibration, lambda r, k: fit_ellipsoid(r, k).calibration,
                lambda r, k: fit_tmi(r, k)):
        a, b = fit(raw, 1.0), fit(moved, factor)
        # the field is of size one here: 1e-6 of it, whatever the shift (up to 100 fields) and unit
        assert np.allclose(b.offset_nT / factor - shift, a.offset_nT, rtol=0, atol=1e-6)
        assert np.allclose(b.matrix, a.matrix, rtol=1e-6, atol=1e-9)
        assert b.model_order == a.model_order


# --- partial coverage: fit what is determined, name the rest, or refuse naming the turn ---------------


def _run_fit(path: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fluxcal.service.wiring.cli", "fit", str(path), "--json", *extra],
                          capture_output=True, text=True, cwd=ROOT, timeout=120)


def _check_honest(proc: subprocess.CompletedProcess) -> dict | None:
    """Exit 0 with every parameter whose standard error exceeds its size flagged, or exit 2 naming the
    missing directions; never anything else."""
    if proc.returncode == 2:
        assert any(w in proc.stderr for w in ("not covered", "one plane", "one cone")), proc.stderr
        assert "turn about" in proc.stderr, proc.stderr
        return None
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    for sensor in out["sensors"]:
        for key in ("offset_nT", "scale", "nonorth_deg"):
            p = sensor["params"][key]
            if p["se"] is None:
                continue
            names = p.get("names") or list("xyz")
            for lab, v, se in zip(names, p["value"], p["se"]):
                if se is not None and se > abs(v):
                    assert any(f"{key}.{lab}" in w for w in out["warnings"]), (key, lab, v, se, out["warnings"])
        if sensor["model_order"] != "full":
            assert any("not determined" in w for w in out["warnings"]), out["warnings"]
        if sensor["coverage"]["missing"]:
            assert any("turn about" in w for w in out["warnings"]), out["warnings"]
    return out


@pytest.mark.parametrize("name", PARTIAL)
def test_partial_real_recordings_are_fitted_honestly_or_refused_with_the_turn(name):
    out = _check_honest(_run_fit(real(f"{name}.csv")))
    if out is not None:
        assert out["warnings"], "partial coverage must never pass without a word"


@pytest.mark.parametrize("name", ["qmc5883l_suarez", "imu_freeimucal"])
@pytest.mark.parametrize("keep", ["+z", "-x", "plane"])
def test_cuts_of_real_recordings_are_fitted_honestly_or_refused(tmp_path, name, keep):
    """A hemisphere or a band around one plane, cut about the full fit's centre."""
    raw = raw_of(name)
    cal = fit_ellipsoid(raw).calibration
    d = cal.apply(raw)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if keep == "plane":
        mask = np.abs(d[:, 2]) < 0.1
    else:
        axis = "xyz".index(keep[1])
        mask = (d[:, axis] > 0) if keep[0] == "+" else (d[:, axis] < 0)
    path = tmp_path / f"{name}-{keep}.csv"
    t = np.arange(mask.sum()) * 0.02
    np.savetxt(path, np.column_stack([t, raw[mask]]), delimiter=",", header="t,s1_x,s1_y,s1_z", comments="")
    _check_honest(_run_fit(path))


@pytest.mark.parametrize("axis", "xyz")
def test_a_real_single_axis_turn_is_refused_naming_its_axis_wherever_the_origin(axis):
    """A hand turn about one axis wobbles a few degrees; fitted anyway, the offset along the axis came out
    1,500-12,800 nT from the same board's full-sphere fit, 4-35 times its standard error (x: 9,417 ± 588
    against −643). The directions about the fit stay within a narrow cone about the axis: refused, naming
    it and the turns that would fill the gap, and the same refusal wherever the origin and whatever the unit."""
    raw = raw_of(f"hmc5883l_sensorfusion_turn_{axis}")
    others = " or ".join(a for a in "xyz" if a != axis)
    bands = []
    for shift, factor in ((np.zeros(3), 1.0), (np.array([3e6, -1e6, 5e5]), 1e-3)):
        with pytest.raises(CalibrationRefused, match=rf"one cone about {axis} \(a turn about {axis}.*turn about the "
                                                       rf"{others} axis") as e:
            fit_ellipsoid((raw + shift) * factor)
        bands.append(float(str(e.value).split("±")[1].split("°")[0]))
    assert 3.0 < bands[0] < 9.0 and bands[0] == bands[1]


@pytest.mark.parametrize("method", ["tmi", "rls"])
def test_every_method_that_fits_the_offsets_refuses_a_real_single_axis_turn(method, capsys):
    """The cone refusal guarded the default method only: `fit --method tmi` gave turn_x's x offset 9,417 ± 590
    nT (the sphere: −643) and `--method rls` 9,417 ± 1,900, exit 0 and a calibration written (a user's trial).
    The same turns, and the nliaudat board's, are now refused by both; a full sphere is still fitted."""
    from fluxcal.service.wiring.cli import main

    for name, axis in (("hmc5883l_sensorfusion_turn_x", "x"), ("hmc5883l_sensorfusion_turn_z", "z"),
                       ("hmc5883l_nliaudat", "z")):
        assert main(["fit", str(real(f"{name}.csv")), "--method", method, "--site", "46.5,6.6,400"]) == 2
        assert f"one cone about {axis} (a turn about {axis})" in capsys.readouterr().err
    # (the suarez board, fitted here before, is in an 8,946 nT field at its stated unit: 5.3 times below the site's
    # 47,800 nT, a scale no sensor has, refused now; the HMC5883L board's sphere reads 53,200 nT)
    assert main(["fit", str(real("hmc5883l_sensorfusion_sphere.csv")), "--method", method, "--site", "46.5,6.6,400",
                 "--json"]) == 0
    off = np.asarray(json.loads(capsys.readouterr().out)["sensors"][0]["offset_nT"])
    assert np.allclose(off, [-643.5, -10545.8, 2025.5], atol=1.0)            # the ellipsoid fit's, as the README says


@pytest.mark.parametrize("name", FULL_SPHERE)
def test_wide_cuts_of_real_spheres_are_still_fitted(name):
    """What the cone rule must not refuse: hemispheres and a ±17° band about a plane (read 17-39°)."""
    raw = raw_of(name)
    d = fit_ellipsoid(raw).calibration.apply(raw)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for mask in (d[:, 2] > 0, d[:, 0] < 0, np.abs(d[:, 2]) < 0.3):
        assert fit_ellipsoid(raw[mask]).calibration.is_finite()


def test_a_simulated_hemisphere_is_fitted_honestly():
    rng = np.random.default_rng(3)
    d = rng.normal(size=(3000, 3))
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    raw = 50000 * d @ np.linalg.inv(triangular_matrix([0.5, -0.3, 0.2], [1.02, 0.98, 1.01])).T
    raw += np.array([3e5, -1e5, 2e5]) + rng.normal(scale=5.0, size=raw.shape)
    fit = fit_ellipsoid(raw, 50000.0)
    cov = coverage(raw, centre_nT=fit.calibration.offset_nT)
    assert "-z" in cov.missing and np.allclose(fit.calibration.offset_nT, [3e5, -1e5, 2e5], atol=50)


def test_a_sparse_plane_is_refused_naming_the_turn():
    t = np.linspace(0, 2 * np.pi, 243)
    raw = np.column_stack([4e4 * np.cos(t), 4e4 * np.sin(t), np.full_like(t, 3e4)]) + [6e5, 1e5, -2e5]
    raw += np.random.default_rng(0).normal(scale=20.0, size=raw.shape)
    with pytest.raises(CalibrationRefused, match="one plane.*turn about the x or y axis"):
        fit_ellipsoid(raw)


def test_two_step_on_three_real_turns_calibrates_the_sphere_recording_and_ignores_the_origin():
    """[TwoStep] on the board's three single-axis turns (offset ~ a fifth of the field): the turns'
    calibration, applied to the same board's full-sphere recording, leaves 0.66 % spread of |B| (the
    sphere's own fit 0.46 %, raw about its mean 15 %); moved by millions of nT and rescaled, the same answer."""
    turns = [raw_of(f"hmc5883l_sensorfusion_turn_{a}") for a in "xyz"]
    fit = fit_two_step_full(turns)
    sphere = raw_of("hmc5883l_sensorfusion_sphere")
    assert spread(fit.calibration.apply(sphere)) < 0.01 < 0.1 < spread(sphere - sphere.mean(axis=0) + 1e-9)
    shift, factor = np.array([3e6, -1e6, 5e5]), 7.0
    moved = fit_two_step_full([(t + shift) * factor for t in turns])
    assert np.allclose(moved.calibration.offset_nT / factor - shift, fit.calibration.offset_nT, atol=1e-3)
    assert np.allclose(moved.calibration.matrix, fit.calibration.matrix, rtol=1e-6, atol=1e-9)
    assert moved.pca.flipped == fit.pca.flipped


# --- the online estimator and the service's gate on the same recordings -------------------------------


@pytest.mark.parametrize("name", FULL_SPHERE)
def test_the_online_estimate_from_any_offset_agrees_with_the_batch_fit(name):
    """Without forgetting the online estimate of a raw recording is the batch fit; with the service's
    forgetting it is the same whatever constant the recording is moved by (up to 100 fields). (With
    forgetting it follows the last minutes of turning, which on these boards differ from the whole
    recording's fit by up to ~7 of the online estimate's white-noise standard errors: the residual of a
    hand-turned board is not white; the closing note of the real-sensors work says more.)"""
    raw = raw_of(name)
    batch = fit_ellipsoid(raw, order="full").calibration
    radius = float(np.mean(np.linalg.norm(batch.apply(raw), axis=1)))
    exact = RlsEllipsoid(forgetting=1.0).fit(raw)
    assert np.allclose(exact.offset_, batch.offset_nT, rtol=0, atol=1e-6 * radius)
    assert np.allclose(exact.matrix_, batch.matrix, rtol=1e-6, atol=1e-9)
    snaps = []
    for shift in (np.zeros(3), np.array([1.0, -2.0, 0.5]) * 100 * radius):
        est = RlsEllipsoid(forgetting=0.9995)
        for i in range(0, raw.shape[0], 100):                      # blocks, as the service feeds it
            est.partial_fit(raw[i:i + 100] + shift)
        snaps.append((est.snapshot(), shift))
    (a, _), (b, shift) = snaps
    assert np.allclose(b.offset_nT - shift, a.offset_nT, rtol=0, atol=1e-6 * radius)
    assert np.allclose(b.matrix, a.matrix, rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(a.offset_nT - batch.offset_nT) < 0.02 * radius)


def _serve(block, check_every: int = 200, step: int = 100):
    """A one-probe service pipeline fed a recording in blocks of `step`: (the pipeline, its events)."""
    pl = Pipeline(n_probes=1, probe_names=["s1"], positions_m=None, min_samples=500, gate_rms_nT=1e9,
                  check_every_samples=check_every, window_samples=4000, chunk_samples=100)
    events = []
    for i in range(0, block.n_samples, step):
        events += pl.process(block.slice(i, i + step)).events
    return pl, events


@pytest.mark.parametrize("name", ["qmc5883l_suarez", "imu_freeimucal"])
def test_the_service_learns_a_real_board_raw_and_its_gate_passes(name):
    raw = raw_of(name)
    pl, events = _serve(load_data(real_nT(f"{name}.csv")).block, check_every=1000, step=250)
    assert any(e.kind == "calibration" for e in events), [e.detail for e in events][-3:]
    spread_service = spread(pl.calibration.apply(raw[:, None, :])[:, 0])
    assert spread_service < 1.3 * spread(fit_ellipsoid(raw).calibration.apply(raw))
    assert pl.last_gate.coverage > 0.9                               # counted about the estimate's centre


@pytest.mark.parametrize("name", FULL_SPHERE)
def test_fit_rls_succeeds_on_raw_real_recordings(name):
    proc = _run_fit(real_nT(f"{name}.csv"), "--method", "rls")
    assert proc.returncode == 0, proc.stderr
    s = json.loads(proc.stdout)["sensors"][0]
    raw = raw_of(name)
    cal = (raw - np.asarray(s["offset_nT"])) @ np.asarray(s["matrix"]).T
    refs = [spread(reference_fit(raw))] + ([spread(a)] if (a := authors_calibrated(name, raw)) is not None else [])
    assert spread(cal) <= min(refs) * 1.02


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), shift_fields=st.floats(-100, 100), log_factor=st.floats(-3, 3))
def test_the_online_estimator_ignores_the_origin_and_unit(seed, shift_fields, log_factor):
    """The RLS, fed in blocks with the service's forgetting: the same calibration wherever the origin
    and whatever the unit, the offset moved by the constant."""
    raw = 50000.0 * _distorted_sphere(seed, n=3000)
    shift = np.random.default_rng(seed + 2).normal(size=3) * shift_fields * 50000.0
    factor = 10.0 ** log_factor
    ests = [RlsEllipsoid(forgetting=0.999), RlsEllipsoid(forgetting=0.999)]
    for i in range(0, raw.shape[0], 100):
        ests[0].partial_fit(raw[i:i + 100])
        ests[1].partial_fit((raw[i:i + 100] + shift) * factor)
    a, b = (e.snapshot() for e in ests)
    assert np.allclose(b.offset_nT / factor - shift, a.offset_nT, rtol=0, atol=1e-6 * 50000.0)
    assert np.allclose(b.matrix, a.matrix, rtol=1e-6, atol=1e-9)


def test_the_effects_fit_starts_and_ends_where_the_origin_does_not_matter():
    """The effects fit (its start: an ellipsoid per probe, aligned) moved with the data."""
    from fluxcal.drivers.sim.config import load_sim_config
    from fluxcal.drivers.sim.world import World
    from fluxcal.service.numerics.engine import fit_with_effects

    cfg = load_sim_config({"duration_s": 20.0, "rate_hz": 100.0, "seed": 3,
                           "probes": [{"offset_nT": [300.0, -100.0, 50.0]}, {"offset_nT": [-80.0, 40.0, 20.0]}]})
    s = World(cfg).samples(0, cfg.n_samples)
    block = SampleBlock(t_s=s.t_s, seq=np.arange(s.t_s.size), field_nT=s.raw_nT, temp_C=s.temp_C,
                        flags=np.zeros(s.t_s.size, np.uint8))
    shift = np.array([2e6, -1e6, 5e5])
    moved = SampleBlock(t_s=block.t_s, seq=block.seq, field_nT=block.field_nT + shift, temp_C=block.temp_C,
                        flags=block.flags)
    a, _ = fit_with_effects(block, ["drift"], total_nT=52500.0)
    b, _ = fit_with_effects(moved, ["drift"], total_nT=52500.0)
    assert np.allclose(b.offset_nT - shift, a.offset_nT, rtol=0, atol=1e-4)
    assert np.allclose(b.matrix, a.matrix, rtol=0, atol=1e-9)
    assert abs(a.rms_nT - b.rms_nT) < 1e-6


@pytest.mark.parametrize("name", ["imu_freeimucal", "qmc5883l_suarez"])
def test_fit_offset_errors_cover_the_offsets_the_authors_published(name):
    """Two calibrations of one recording by different methods differ by their errors: `fit`'s offsets against
    those the recording's authors published, within 2.5 of the stated errors. The residual of these hand-turned
    boards is coloured, and the white-noise errors alone were 4.6 (imu_freeimucal) and 5.7 (qmc5883l_suarez)
    times off (measured); `fit` says which the errors cover and how far the offsets wander beyond the record."""
    out = _check_honest(_run_fit(real_nT(f"{name}.csv")))
    pub = json.loads((real(f"{name}.published.json")).read_text())
    scale = pub["data"]["scale_to_nT"] * mend(name)
    if "A" in pub:                                       # m = A raw + B: the offset is -A^-1 B
        published = -np.linalg.solve(np.asarray(pub["A"]), np.asarray(pub["B"])) * scale
    else:
        published = np.asarray(pub["offset"]) * scale
    s = out["sensors"][0]
    z = (np.asarray(s["offset_nT"]) - published) / np.asarray(s["offset_se_nT"])
    assert np.all(np.abs(z) < 2.5), z
    assert any("wander within the record" in w and "nT per decade of time" in w for w in out["warnings"])


@pytest.mark.parametrize("axis", "xyz")
def test_the_services_gate_refuses_a_real_single_axis_turn(axis):
    """Fed a hand turn about one axis from an identity calibration, the online gate accepted 2-7 candidates,
    the last with the offset along the axis up to 63,000 nT from the board's full-sphere fit (x: −63,791
    against −643). It now refuses each, naming the cone and the turn to add; the board's full sphere is still
    learned, to within 2 % of the field of its batch fit."""
    pl, events = _serve(load_data(real(f"hmc5883l_sensorfusion_turn_{axis}.csv")).block)
    assert pl.calibration is None and not any(e.kind == "calibration" for e in events)
    refusals = [r for e in events if e.kind == "gate" for r in e.detail["reasons"]]
    assert any(f"one cone about {axis} (a turn about {axis})" in r for r in refusals), refusals[-3:]
    sphere = load_data(real("hmc5883l_sensorfusion_sphere.csv")).block
    pl, _ = _serve(sphere)
    raw = sphere.field_nT[:, 0]
    batch = fit_ellipsoid(raw)
    assert pl.calibration is not None
    assert np.all(np.abs(pl.calibration.probes[0].offset_nT - batch.calibration.offset_nT) < 0.02 * np.sqrt(batch.f2_ref))
