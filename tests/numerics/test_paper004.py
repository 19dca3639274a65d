"""[TwoStep] (equivalent two-step calibration for heading): its experiment's grid, simulated.

Grid (tests/sims_003_004.py): level, roll ±30/±60/+90°, pitch ±30/±60/+90°, headings 0-330° every
30°; step 1 on all 132 points, step 2 on the level, roll +90° and pitch +90° sweeps; heading
errors on the 108 points of the paper's figures. [TwoStep] reports max/RMS heading error 0.40/0.21°
(two-step), 180.00/102.90° (no sign correction), 1.39/0.62° (no orthogonality correction).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from sims_003_004 import P004_TOTAL_NT, attitude, heading_error_deg, paper004, tilt_compensated_heading_deg

from fluxcal.drivers.errors import CalibrationRefused
from fluxcal.service.numerics.calib.model import ProbeCalibration
from fluxcal.service.numerics.calib.twostep import align_pca, fit_two_step, fit_two_step_full, orthogonality_correction


def fit(sim, **kw):
    extra = sim.raw_nT[~np.isin(sim.state, [0, 9, 10])]          # every point but the three turns
    return fit_two_step_full(sim.turns(), extra_nT=extra, **kw)


def heading_errors(sim, matrix, offset):
    corr = (sim.raw_nT - offset) @ matrix.T
    e = heading_error_deg(tilt_compensated_heading_deg(corr, sim.roll_deg, sim.pitch_deg), sim.heading_deg)
    return e[sim.evaluated]


def max_rms(e):
    return float(np.abs(e).max()), float(np.sqrt(np.mean(e ** 2)))


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_two_step_heading_error_within_half_a_degree(seed):
    s = paper004(seed)
    r = fit(s)
    mx, rms = max_rms(heading_errors(s, r.calibration.matrix, r.calibration.offset_nT))
    # [TwoStep]: 0.40° max, 0.21° RMS; measured here 0.17-0.41° max, 0.06-0.19° RMS over seeds 0-19
    assert mx <= 0.5 and rms <= 0.25, (mx, rms)
    # step 1 + 2 together are the sensor model up to the (0.1°-class) misalignment left by the turns
    assert np.allclose(np.linalg.det(r.v), 1.0) and np.allclose(r.v.T @ r.v, np.eye(3), atol=1e-12)


def test_step1_gives_u_d_b_of_the_ellipsoid_and_step2_v():
    s = paper004(0)
    r = fit(s)
    # b̂ (eq. 9) is the hard-iron offset; Û D̂ V̂ (eq. 2) is the forward model M up to a small rotation
    assert np.abs(r.offset_nT - s.b_true_nT).max() < 5.0
    assert np.allclose(r.u.T @ r.u, np.eye(3), atol=1e-12) and np.linalg.det(r.u) > 0
    m_hat = r.u @ np.diag(r.d) @ r.v
    scale = np.cbrt(np.linalg.det(s.m_true) / np.linalg.det(m_hat))  # [TwoStep] leaves the scale k free
    assert np.abs(scale * m_hat - s.m_true).max() < 0.01
    # with the total field given, the calibrated vectors are in nT and undo M within ~0.3°
    r_nt = fit(s, total_nT=P004_TOTAL_NT)
    err = r_nt.calibration.matrix @ s.m_true - np.eye(3)
    assert np.abs(err).max() < 0.006


def test_without_sign_correction_heading_fails_like_the_paper_and_the_sign_correction_fixes_it():
    s = paper004(0)
    raw_pca = fit(s, sign_correction=False)
    mx, rms = max_rms(heading_errors(s, raw_pca.calibration.matrix, raw_pca.calibration.offset_nT))
    # [TwoStep]: 180.00° max, 102.90° RMS. Here the eigensolver returns V̂_x and V̂_y negated: 180° max, 133° RMS
    assert mx > 179.0 and rms > 90.0, (mx, rms)
    fixed = fit(s)
    assert fixed.pca.flipped == [True, True, False]
    # the flipped columns are exactly those the eigensolver got wrong against the true V
    v_true = fixed.equivalent_matrix @ s.m_true                     # ĥ_c = V h_b
    wrong = np.einsum("ij,ij->j", fixed.pca.v_pca, v_true) < 0
    assert list(wrong) == fixed.pca.flipped
    assert max_rms(heading_errors(s, fixed.calibration.matrix, fixed.calibration.offset_nT))[0] < 0.5


def test_every_wrong_sign_of_the_pca_axes_gives_errors_up_to_180_deg():
    s = paper004(0)
    r = fit(s, orth_correction=False)
    results = {}
    for signs in itertools.product([1, -1], repeat=3):
        m = np.linalg.solve(r.v * np.array(signs), r.equivalent_matrix)
        results[signs] = max_rms(heading_errors(s, m, r.offset_nT))
    assert results[(1, 1, 1)][0] < 0.5
    assert all(mx > 179.0 for signs, (mx, _) in results.items() if signs != (1, 1, 1))
    # one flipped horizontal axis (x or y) turns ψ into ±(180° − ψ): RMS ≈ 98°, the paper's 102.9°
    assert 90.0 < results[(-1, 1, 1)][1] < 105.0 and 90.0 < results[(1, -1, 1)][1] < 105.0


def test_sign_correction_holds_over_seeds_where_the_eigensolver_is_wrong():
    fails = 0
    for seed in range(12):
        s = paper004(seed)
        r = fit(s)
        v_true = r.equivalent_matrix @ s.m_true
        assert np.all(np.einsum("ij,ij->j", r.v, v_true) > 0)
        fails += any(r.pca.flipped)
    assert fails >= 8                      # measured: 10 of 12 seeds need at least one flip


def test_orthogonality_correction_lowers_the_heading_error():
    # the wobble of the hand-locked +90° sweeps leaves V̂ ~0.2° out of square; the variance
    # contribution finds the clean level sweep, the correction keeps it and rebuilds the others
    worse = []
    for seed in range(10):
        s = paper004(seed)
        full = fit(s)
        no_orth = fit(s, orth_correction=False)
        e_full = max_rms(heading_errors(s, full.calibration.matrix, full.calibration.offset_nT))
        e_no = max_rms(heading_errors(s, no_orth.calibration.matrix, no_orth.calibration.offset_nT))
        worse.append(e_no[0] > e_full[0])
        assert no_orth.calibration.params["v_non_orthogonality_deg"]["value"] > 0.02
        assert int(np.argmin(full.pca.contribution)) == 2          # the level sweep (about z) is the cleanest
        if seed == 0:
            # measured: 0.40° max / 0.15° RMS without, 0.23° / 0.09° with ([TwoStep]: 1.39 / 0.62 vs 0.40 / 0.21)
            assert e_no[0] > 1.5 * e_full[0] and e_no[1] > e_full[1]
    assert sum(worse) >= 9, worse


def test_orthogonality_correction_is_eq18_for_the_papers_order():
    rng = np.random.default_rng(5)
    v = np.eye(3) + rng.normal(0, 0.01, (3, 3))
    vc, order = orthogonality_correction(v, np.array([2e-4, 3e-4, 1e-4]))     # α_z < α_x < α_y
    assert order == [2, 0, 1]
    vz = v[:, 2] / np.linalg.norm(v[:, 2])
    vcy = np.cross(vz, v[:, 0])
    vcy /= np.linalg.norm(vcy)
    vcx = np.cross(vcy, vz)
    assert np.allclose(vc[:, 2], vz) and np.allclose(vc[:, 1], vcy) and np.allclose(vc[:, 0], vcx / np.linalg.norm(vcx))
    assert np.allclose(vc.T @ vc, np.eye(3)) and np.linalg.det(vc) > 0


def test_a_turn_with_the_field_in_its_plane_warns_that_the_sign_is_unreliable():
    s = paper004(0)
    turns = s.turns()
    # a turn about z with the platform arranged so the field lies in the x-y plane: h_s,z ≈ 0
    h_n = np.array([P004_TOTAL_NT, 0.0, 0.0])
    about_z = np.array([s.m_true @ (attitude(0.0, 0.0, np.radians(h)).T @ h_n) + s.b_true_nT
                        for h in range(0, 360, 30)])
    cal = fit_two_step([turns[0], turns[1], about_z], extra_nT=s.raw_nT, name="s1")
    assert "about z" in cal.params["sign_warning"] and cal.params["pca_sign_share"]["value"][2] < 0.2


def test_a_turn_with_too_few_samples_is_refused():
    s = paper004(0)
    t = s.turns()
    with pytest.raises(CalibrationRefused, match="turn about y has 2 samples"):
        fit_two_step([t[0], t[1][:2], t[2]], extra_nT=s.raw_nT)


def test_align_pca_turns_two_probes_onto_the_platform_frame():
    # two probes, each already calibrated in its own (triangular, arbitrary) orthogonal frame
    rng = np.random.default_rng(11)
    s1, s2 = paper004(3), paper004(4)
    h_n = s1.field_ned_nT
    att = [attitude(np.radians(r), np.radians(p), np.radians(h))
           for r, p, h in zip(s1.roll_deg, s1.pitch_deg, s1.heading_deg)]
    h_b = np.array([a.T @ h_n for a in att])
    raws, probes = [], []
    for k, s in enumerate((s1, s2)):
        raw = h_b @ s.m_true.T + s.b_true_nT + rng.normal(0, 2.0, h_b.shape)
        raws.append(raw)
        q = np.linalg.inv(s.m_true).T @ np.linalg.inv(s.m_true)
        m_tri = np.linalg.cholesky(q).T                  # a correction in the probe's own frame
        probes.append(ProbeCalibration(f"s{k + 1}", s.b_true_nT, m_tri))
    field = np.stack(raws, axis=1)
    turn = np.full(len(h_b), -1)
    turn[(s1.roll_deg == 0) & (s1.pitch_deg == 90)] = 0
    turn[(s1.roll_deg == 90) & (s1.pitch_deg == 0)] = 1
    turn[(s1.roll_deg == 0) & (s1.pitch_deg == 0)] = 2
    aligned = align_pca(probes, field, turn)
    for k, p in enumerate(aligned):
        s = (s1, s2)[k]
        assert np.abs(p.matrix @ s.m_true - np.eye(3)).max() < 1e-3     # back to the platform axes
        assert "misalign_pca" in p.params
    diff = aligned[1].apply(field[:, 1]) - aligned[0].apply(field[:, 0])
    assert np.sqrt(np.mean(diff ** 2)) < 5.0                            # noise of two probes: 2.8 nT


def test_fluxcal_fit_two_step_from_a_lab_csv(tmp_path, capsys):
    # docs/csv.md, docs/cli.md: a lab CSV with a 'turn' column (0/1/2 = about x/y/z, -1 = not a turn);
    # `fit` uses the three turns for both steps (36 points)
    import json

    from fluxcal.service.wiring.cli import main

    s = paper004(0)
    turn = np.full(len(s.raw_nT), -1)
    turn[s.state == 10], turn[s.state == 9], turn[s.state == 0] = 0, 1, 2
    path = tmp_path / "heading.csv"
    rows = [f"{i},{x:.3f},{y:.3f},{z:.3f},{k}" for i, ((x, y, z), k) in enumerate(zip(s.raw_nT, turn))]
    path.write_text("# 004 grid, simulated\nt,s1_x,s1_y,s1_z,turn\n" + "\n".join(rows) + "\n")
    capsys.readouterr()
    assert main(["fit", str(path), "--method", "two-step", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    sensor = out["sensors"][0]
    e = heading_errors(s, np.array(sensor["matrix"]), np.array(sensor["offset_nT"]))
    assert out["method"] == "two-step" and max_rms(e)[0] < 0.5, max_rms(e)
