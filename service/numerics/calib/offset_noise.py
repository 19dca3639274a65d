"""Standard errors of the linear calibration (offsets, matrix) under coloured noise (`fluxcal fit`).

The ellipsoid's and the regression's standard errors are white-noise ones, sigma^2 (X^T X)^-1: under 1/f
noise a probe's noise wanders at the record's own periods, a wander each offset takes almost one to one,
and the offsets were off by 30 times their stated errors, the matrix's named parameters by 3 to 7 times
(tests/numerics/test_stderr.py). Here each parameter is written as a weighted sum of each raw axis's noise,

    delta o_j = sum_n sum_a W[n, j, a] eps[n, a],

and the wander is carried in with the power-law spectrum of the probe's noise (engine/coloured.py's law,
fitted above 16 cycles per record): Var = sum_a integral |W_ja(f)|^2 S(f) df. Below the band the law was
fitted on it is carried on as flicker noise (the knee; the drift's errors instead keep a steeper law there:
a law of -2.5 measured on a hand-turned board, whose residual follows the hand's slow turning, claimed
offset errors of 1,100-2,400 nT where its halves' fits disagree by 220-340 nT). The noise's own mean over
the record is a constant the record cannot tell from the offset, and under 1/f noise it has no finite
variance: the error stated is that of the offset over this record (the weights less their mean enter, and
the integral ends at f = 0 by itself), and how far the offset wanders beyond the record is said apart, per
decade of time.

- Ellipsoid ([TwoFluxgate] eq. 5-9 in centred, scaled u): the noise moves the design, and at the fitted quadric
  delta theta = -(Phi^T Phi)^-1 sum_n phi_n g_n^T eps_n, g_n = (2 A' u_n + b') / s the gradient of the
  quadric in r; then delta o = J_o delta theta, and the matrix's terms through their Jacobian likewise.
  The term (d phi_n / d r)^T times the equation's residual is left out: second order where the model fits,
  not where a reduced order (axes, sphere) leaves a real misfit.
- Regression onto the reference probe ([TwoFluxgate] eq. 13-16): ref = A r + c + e, o = -A^-1 c, and
  delta o = -A^-1 sum_n h_n e_n with h_n = [o, 1]^T (X^T X)^-1 x_n, e the regression's residual per axis
  (the difference channel), whose own spectrum is fitted; row i of A moves by the first three of
  (X^T X)^-1 sum_n x_n e_ni.

A constant added to the noise moves the offsets by that constant (the ellipsoid's weights sum to the
identity; the regression's, on its residual, to -A^-1) and the matrix not at all (its weights sum to zero).
Only the power-law part is integrated here: the white part is the white-noise error already stated, and
the two add in variance.

Numerics only.
"""

from __future__ import annotations

import numpy as np

from ..engine.coloured import binned_fft, power_law_spectrum
from .model import triangular_params
from .order import EXPANSIONS
from .quadric import normalise, quadric_design, quadric_to_calibration, unit_volume_total


def ellipsoid_weights(raw: np.ndarray, offset: np.ndarray, matrix: np.ndarray, order: str = "full",
                      total_nT: np.ndarray | float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(W_o (N, 3, 3), W_m (N, 15, 3)): the weights on raw axis a's noise at sample n of the offsets, and of
    the matrix's nine elements (row by row) then its named parameters (nonorth_deg phi, theta, psi; scale c_x,
    c_y, c_z: model.triangular_params of Q's triangular factor), for the ellipsoid |M (r - o)| = F of model
    order `order` fitted to raw (N, 3) (ellipsoid.solve_quadric: centred, scaled u; the delta column when the
    reference total_nT (N,) varies by more than 1 nT rms; None: the field unknown, F the unit-volume one).
    The quadric's coefficients are rebuilt from (o, M); a rotation of M (alignment) is held fixed."""
    raw = np.asarray(raw, float)
    center, scale = normalise(raw)
    known = total_nT is not None
    f2 = (float(np.mean(np.square(total_nT))) if known else
          float(np.mean(np.sum(((raw - offset) @ matrix.T) ** 2, axis=1))))
    q = matrix.T @ matrix
    o_u = (np.asarray(offset, float) - center) / scale
    a = q * scale ** 2 / (f2 - scale ** 2 * o_u @ q @ o_u)           # A' = Q s^2 / kappa: right side 1
    theta9 = np.array([a[0, 0], a[1, 1], a[2, 2], a[0, 1], a[0, 2], a[1, 2], *(-2.0 * a @ o_u)])
    t = EXPANSIONS[order]
    u = (raw - center) / scale
    phi = quadric_design(u) @ t
    if np.ndim(total_nT) == 1 and float(np.std(total_nT)) > 1.0:
        f2s = np.asarray(total_nT, float) ** 2
        phi = np.column_stack([phi, -(f2s - f2s.mean()) / scale ** 2])
    g = phi.T @ phi
    col = np.sqrt(np.diag(g))
    col[col == 0] = 1.0
    ginv = (np.linalg.pinv(g / np.outer(col, col)) / np.outer(col, col))[:t.shape[1]]
    grad = (2.0 * u @ _sym(theta9) + theta9[6:9]) / scale            # the quadric's gradient in r

    def shape(th: np.ndarray) -> np.ndarray:
        f2th = f2 if known else unit_volume_total(th, scale, center) ** 2
        tri = quadric_to_calibration(th, scale, f2th, center)[1]
        angles, scales = triangular_params(tri)
        return np.concatenate([(rot @ tri).ravel(), angles, scales])

    tri0 = quadric_to_calibration(theta9, scale, f2 if known else unit_volume_total(theta9, scale, center) ** 2,
                                  center)[1]
    rot = matrix @ np.linalg.inv(tri0)
    jac = np.empty((15, 9))
    for i in range(9):
        h = 1e-6 * max(abs(theta9[i]), 1e-3 * np.max(np.abs(theta9)))
        tp, tm = theta9.copy(), theta9.copy()
        tp[i] += h
        tm[i] -= h
        jac[:, i] = (shape(tp) - shape(tm)) / (2 * h)
    jac = np.vstack([_offset_jacobian(theta9, scale), jac])          # (18, 9)
    h = phi @ (-(jac @ t) @ ginv).T                                  # (N, 18)
    w = h[:, :, None] * grad[:, None, :]
    return w[:, :3], w[:, 3:]


def _sym(theta9: np.ndarray) -> np.ndarray:
    return np.array([[theta9[0], theta9[3], theta9[4]],
                     [theta9[3], theta9[1], theta9[5]],
                     [theta9[4], theta9[5], theta9[2]]])


def _offset_jacobian(theta9: np.ndarray, scale: float) -> np.ndarray:
    """d offset / d theta (3, 9): o = c + s o_u, o_u = -A'^-1 b' / 2, so d o_u = -A'^-1 (dA' o_u + db' / 2)."""
    a = _sym(theta9)
    ainv = np.linalg.inv(a)
    o_u = -0.5 * ainv @ theta9[6:9]
    jac = np.empty((3, 9))
    for i, (r, c) in enumerate([(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]):
        da = np.zeros((3, 3))
        da[r, c] = da[c, r] = 1.0
        jac[:, i] = -ainv @ da @ o_u
    jac[:, 6:9] = -0.5 * ainv
    return scale * jac


def regression_weights(raw: np.ndarray, a: np.ndarray, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(W_o (N, 3, 3), W_m (N, 9, 3)): the weights on the regression residual's axis i at sample n of the
    offsets and of A's nine elements (row by row), for the regression ref = A r + c + e of raw (N, 3) with
    o = -A^-1 c: row i of [A | c] moves by (X^T X)^-1 sum_n x_n e_ni."""
    x = np.column_stack([np.asarray(raw, float), np.ones(np.shape(raw)[0])])
    xtx = x.T @ x
    col = np.sqrt(np.diag(xtx))
    col[col == 0] = 1.0
    hx = x @ (np.linalg.pinv(xtx / np.outer(col, col)) / np.outer(col, col))      # (N, 4): rows of (X^T X)^-1 x_n
    h = hx @ np.append(offset, 1.0)                                                 # (N,), sums to one
    w_o = -h[:, None, None] * np.linalg.inv(a)[None, :, :]
    w_m = np.zeros((x.shape[0], 9, 3))
    for i in range(3):
        w_m[:, 3 * i:3 * i + 3, i] = hx[:, :3]
    return w_o, w_m


def record_se(weights: np.ndarray, grid: np.ndarray, dt: float, laws: list[tuple[float, float, float] | None],
              knee: tuple[float, float] | None = None) -> np.ndarray:
    """(J,) the standard error each parameter (an offset, a matrix element) gains from the power-law part
    a f^alpha of its noise sources' spectra: Var_j = sum_a integral |W_ja(f)|^2 S_a(f) df (the sources
    independent), on engine.coloured.binned_fft of the weights (N, J, A) placed at `grid` (N,) on a uniform
    grid of step dt. laws: one (w, a, alpha) per source (the weights' last axis; None: no power law); below
    knee = (f_k, beta) the law carries on at slope beta. To be added in variance to the white-noise error,
    whose residual variance holds the law's power within the band as well: that part is counted twice, on the
    safe side, by at most the white-noise error itself. An offset's error is that over this record: of the
    static offset plus the noise's mean over the record (a constant the record cannot tell from the offset),
    so the weights enter less their mean, which sum to zero and end the integral at f = 0 by themselves (a
    matrix's sum to zero already: a constant moves only the offset)."""
    centred = weights - weights.mean(axis=0)
    var = np.zeros(weights.shape[1])
    for a, law in enumerate(laws):
        cols = np.flatnonzero(np.any(centred[:, :, a] != 0, axis=0))         # structural zeros: none
        if law is None or not cols.size:
            continue
        f, x, norm = binned_fft(centred[:, cols, a], grid, dt)
        var[cols] += power_law_spectrum(f, law, knee) @ np.abs(x) ** 2 / norm
    return np.sqrt(var)


def wander_per_decade(law: tuple[float, float, float], duration_s: float,
                      knee: tuple[float, float] | None = None) -> float:
    """nT: how far the noise's mean over a record moves between records a decade of time apart and more, from
    the power law's part a f^alpha between one tenth of a cycle and one cycle per record (below knee = (f_k,
    beta) the law carried on at slope beta, as record_se): what an offset fitted to this record cannot
    know of the offset at a later time."""
    _, a, alpha = law
    f0 = 1.0 / duration_s
    if knee is not None and f0 < knee[0]:
        a, alpha = a * knee[0] ** (alpha - knee[1]), knee[1]
    if abs(alpha + 1.0) < 1e-9:
        return float(np.sqrt(a * np.log(10.0)))
    return float(np.sqrt(a * (f0 ** (alpha + 1) - (f0 / 10) ** (alpha + 1)) / (alpha + 1)))
