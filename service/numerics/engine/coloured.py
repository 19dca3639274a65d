"""Standard errors of the effects' parameters under coloured noise, from a power-law model of the spectrum.

A drift (a polynomial in time) and the noise's own wander at periods as long as the record look alike, and so
do a step, a heater switched every 40 s or a thermal lag of 90 s and the wander at their periods. The block
jackknife (solve.FitResult.robust_stderr) sees the wander only between its blocks, and under 1/f noise these
parameters' errors were 2 to 2.5 times the stated ones. Here a parameter's variance is computed from the
spectrum the noise has at those periods:

- per channel, S(f) = w + a f^alpha (one-sided, nT^2/Hz), fitted to the Welch spectrum of the residual:
  alpha on a grid in [-2.5, 0], w and a >= 0 by least squares relative to the spectrum;
- the parameter's weights u (its row of the weighted least-squares solution: delta theta = sum u eps, an
  (N, C) array) placed on the uniform sample grid (gaps hold no weight), and

      Var = sum_c  integral |U_c(f)|^2 S_c(f) df

  the white part exactly (S = 2 sigma^2 dt gives back sigma^2 sum u^2: the usual formula), the power law's on
  a zero-padded FFT of u summed into at most WEIGHT_BINS bins of time.

The model extends the power law below the band it was fitted on (MIN_CYCLES per record and up: lower, the fitted
slow terms took the power) as flicker noise (1/f): a law flatter than flicker is made flicker once the noise is
coloured, and a steeper one is carried on below the band at flicker's slope (the knee, as fit's offsets take it:
calib/offset_noise.py) where the residual's own power at 1-2 cycles per record refutes the steep law
(low_frequency_knee), else steeply. That assumption, standard for rates under flicker noise (Williams 2003, J.
Geodesy 76: 483-494), is what the figure rests on; a noise whose spectrum steepens below what the record shows is
understated. A steeper law carried on steeply claims what the data deny: on a real hand-turned board (106 s) the
residual's law above the band is f^-2.5 (the hand's turning, about 10 s a turn) and its own power at 1-2 cycles
per record is 260 times below that law's; an offset that follows a logged heater got 2,700 nT/A where its spread
over 60 random heater histories is 281 (the knee: 319). Under a random walk the residual keeps the steep power
there, and the knee taken regardless made a drift that is not there significant (its errors 2-4 times too
small). The
channels are not independent (one probe's noise is in its scalar channel and in every difference with it,
and a probe's axes mix under its matrix): their cross-spectra are taken as rho (sqrt(w_c w_c') +
sqrt(p_c p_c')), p the power law, rho the correlation of the channels' slow parts (their means over
contiguous blocks).

Numerics only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.timebase import MAX_GRID_FILL, sample_grid

from .jacobian import _chunks

#: the spectral index grid of the power law
ALPHAS = np.round(np.arange(-2.5, 0.001, 0.05), 3)
#: a coloured noise is extrapolated below the fitted band at least as steeply as flicker noise (1/f), the
#: fluxgate's own low-frequency noise: one record fixes alpha only to a few tenths (fits of 1/f noise gave
#: -0.7 to -1.15), and a flatter law understates the wander at the record's own period
FLICKER = -1.0
#: the power law is fitted above this many cycles per record: below, the residual has lost the power that the
#: fitted slow terms took (a quadratic drift takes the wander at the record's own periods)
MIN_CYCLES = 16.0
#: the noise is coloured when its power law is above the white level at this many cycles per record (four
#: times the lowest fitted frequency)
COLOURED_CYCLES = 4 * MIN_CYCLES


def power_law(y: np.ndarray, dt: float, alphas: np.ndarray = ALPHAS,
              spectrum: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[float, float, float] | None:
    """(w, a, alpha) of S(f) = w + a f^alpha (one-sided, alpha the best of `alphas`) fitted to y's Welch
    spectrum above MIN_CYCLES per record (`spectrum`, when already taken), or None when y is too short."""
    got = probe_power_laws(np.asarray(y, float)[:, None], dt, np.ones((1, 1)), alphas,
                           spectra=None if spectrum is None else [spectrum])
    return None if got is None else (float(got[0][0]), float(got[1][0]), got[2])


def _welch_bins(y: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray] | None:
    n = y.size
    if n < 512 or not dt > 0:
        return None
    from scipy.signal import welch                      # here, not at import (a command's start)

    f, p = welch(y - y.mean(), fs=1.0 / dt, nperseg=int(2 ** np.floor(np.log2(n / 4))))
    return f[1:], p[1:]


def welch_spectra(values: np.ndarray, dt: float) -> list:
    """Each channel's Welch spectrum (frequencies, power) without its zero bin; None for a channel too short."""
    return [_welch_bins(values[:, c], dt) for c in range(values.shape[1])]


def probe_power_laws(values: np.ndarray, dt: float, gain: np.ndarray, alphas: np.ndarray = ALPHAS,
                     spectra: list | None = None) -> tuple[np.ndarray, np.ndarray, float] | None:
    """(w (P,), a (P,), alpha): each probe's noise per axis, S_k(f) = w_k + a_k f^alpha (one-sided, the same
    on its three axes, one alpha for all, the best of `alphas`), fitted to the Welch spectra of the residual
    channels `values` (N, C) above MIN_CYCLES per record, channel c carrying gain[c, k] times probe k's axis
    noise power (the sum over the axes of its squared sensitivity to them). The noise lives in the probes,
    not in the channels: a probe's wander is in its scalar channel and in every difference with it. spectra:
    the channels' `welch_spectra`, when already taken."""
    if spectra is None:
        spectra = welch_spectra(values, dt)
    if any(sp is None for sp in spectra):
        return None
    f = spectra[0][0]
    pc = np.array([sp[1] for sp in spectra])                  # (C, F)
    ok = np.all(pc > 0, axis=0) & (f >= MIN_CYCLES / (values.shape[0] * dt))
    f, pc = f[ok], pc[:, ok]
    if f.size < 8:
        return None
    p_n = gain.shape[1]
    wt = np.sqrt(1.0 / f / np.sum(1.0 / f))                   # as many per decade low as high
    # rows (c, f): [gain_ck, gain_ck f^alpha] h_cf, h = wt / S, target wt: the least squares of these rows
    # through their normal equations, whose sums over f are taken for every alpha at once
    h = wt[None, :] / pc
    fa = f[:, None] ** np.asarray(alphas, float)[None, :]      # (F, A)
    h2, hw = h * h, h * wt[None, :]
    s0, s1, s2 = h2.sum(axis=1), h2 @ fa, h2 @ (fa * fa)     # (C,), (C, A), (C, A)
    t0, t1 = hw.sum(axis=1), hw @ fa
    coefs = _nnls_normals(*_law_normals(gain, s0, s1, s2, t0, t1))
    best, best_score = None, np.inf
    for i, alpha in enumerate(alphas):
        coef = coefs[i]
        if alpha == 0.0:                 # f^0 = 1: the two columns are one; all of it is white (as nnls on the rows)
            coef = np.concatenate([coef[:p_n] + coef[p_n:], np.zeros(p_n)])
        model = np.einsum("ck,kf->cf", gain, coef[:p_n, None] + coef[p_n:, None] * fa[None, :, i])
        if not np.all(model > 0):
            continue
        score = float(np.sum(np.log(pc / model) ** 2 / f[None, :]))
        if score < best_score:
            best, best_score = (coef[:p_n].copy(), coef[p_n:].copy(), float(alpha)), score
    return best


def _law_normals(gain: np.ndarray, s0: np.ndarray, s1: np.ndarray, s2: np.ndarray, t0: np.ndarray,
                 t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """probe_power_laws' normal equations for every alpha: g (A, 2P, 2P) = [[G0, G1], [G1, G2]], G_j = gain' (s_j
    gain), and b (A, 2P) = [gain' t0, gain' t1]; the parts that do not depend on alpha formed once."""
    p_n, n_a = gain.shape[1], s1.shape[1]
    g, b = np.empty((n_a, 2 * p_n, 2 * p_n)), np.empty((n_a, 2 * p_n))
    g[:, :p_n, :p_n] = gain.T @ (s0[:, None] * gain)
    b[:, :p_n] = gain.T @ t0
    for i in range(n_a):
        g[i, :p_n, p_n:] = g[i, p_n:, :p_n] = gain.T @ (s1[:, i, None] * gain)
        g[i, p_n:, p_n:] = gain.T @ (s2[:, i, None] * gain)
        b[i, p_n:] = gain.T @ t1[:, i]
    return g, b


def _nnls_normals(g: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin over c >= 0 of c' g c - 2 b' c (the least squares whose normal equations are g c = b) for a stack of
    problems g (A, m, m), b (A, m): nnls on a square root of each g, column-scaled, without its null space; the
    eigen-decompositions taken at once (numpy's stacked eigh solves each matrix as it solves it alone)."""
    from scipy.optimize import nnls                     # here, not at import (a command's start)

    d = np.sqrt(np.clip(np.einsum("aii->ai", g), 0.0, None))
    d[d <= 0] = 1.0
    lams, vecs = np.linalg.eigh(g / (d[:, :, None] * d[:, None, :]))
    out = np.empty(b.shape)
    for i, (lam, vec) in enumerate(zip(lams, vecs)):
        keep = lam > 1e-13 * max(lam[-1], 1e-300)
        root = np.sqrt(lam[keep])
        a = (vec[:, keep] * root).T                               # a' a = g scaled
        y = (vec[:, keep].T @ (b[i] / d[i])) / root
        out[i] = nnls(a, y)[0] / d[i]
    return out


def looks_white(spectra: list, duration_s: float, margin: float = 1.2) -> bool:
    """A cheap test before any power law is fitted (welch_spectra of the residual channels): no channel's mean
    power between MIN_CYCLES and COLOURED_CYCLES per record stands `margin` times above its median power beyond
    four times that. A law is coloured only where it stands above the white level at COLOURED_CYCLES
    (is_coloured), which puts that band's power at twice the white level or more; white residuals skip the
    fits (a third of diagnose's time on a white world of 36,000 x 3 probes)."""
    for sp in spectra:
        if sp is None:
            return False
        f, p = sp
        band = (f >= MIN_CYCLES / duration_s) & (f <= COLOURED_CYCLES / duration_s)
        beyond = f >= 4 * COLOURED_CYCLES / duration_s
        if band.sum() < 2 or beyond.sum() < 8 or np.mean(p[band]) >= margin * np.median(p[beyond]):
            return False
    return True


def is_coloured(model: tuple[float, float, float] | None, duration_s: float) -> bool:
    """Whether the power law stands above the white level over the low end of the band it was fitted on, up
    to COLOURED_CYCLES per record: seen in the data, not only extrapolated (a steep law of tiny amplitude
    fits a chance excess of white noise in the lowest bins, and would claim a wander hundreds of times the
    white level at the record's own period)."""
    if model is None or duration_s <= 0:
        return False
    w, a, alpha = model
    return alpha < -0.3 and a * (COLOURED_CYCLES / duration_s) ** alpha >= max(w, 1e-300)


#: the weights are summed into at most this many bins of time before the power law's integral (their spectrum
#: at the record's own periods is what it needs; the white part is summed exactly)
WEIGHT_BINS = 1 << 15


def spectral_variance(u: np.ndarray, grid: np.ndarray, models: list[tuple[float, float, float] | None],
                      dt: float, rho: np.ndarray | None = None, pad: int = 4, f_min: float = 0.0,
                      bins: int = WEIGHT_BINS, knee: tuple[float, float] | None = None) -> float:
    """Var(sum u eps) for weights u (N, C) at positions `grid` (N,) of a uniform grid of step dt, the noise
    of channel c having the one-sided spectrum models[c] = (w, a, alpha) and the channels the correlation rho
    (C, C; None: independent). A channel without a model (too short for a spectrum) is taken as white at the
    mean of the others' white levels.

    The white part is exact, sum_cc' rho_cc' sqrt(w_c w_c') / (2 dt) u_c . u_c' (Parseval); the power law's,
    sum_cc' rho_cc' integral U_c* U_c' sqrt(p_c p_c') df with p = a f^alpha, on a zero-padded FFT of the
    weights summed into at most `bins` bins of time (the cross-spectrum of two channels taken as the sum of
    their white and power-law parts' geometric means).

    Weights that sum to zero for every noise source (a parameter fitted beside offsets) give a finite integral
    down to f = 0; weights that do not (no offset fitted) would grow with the padding under 1/f noise, and
    f_min (one cycle per record) then ends the integral where the record itself ends. knee = (f_k, beta): below
    f_k a law steeper than beta carries on at slope beta (power_law_spectrum)."""
    return float(spectral_variances(np.asarray(u)[:, None, :], grid, models, dt, rho, pad, f_min, bins, knee)[0])


#: complex values of the weights' FFT held at once by spectral_variances (64 MB)
FFT_VALUES = 1 << 22


def spectral_variances(u: np.ndarray, grid: np.ndarray, models: list[tuple[float, float, float] | None],
                       dt: float, rho: np.ndarray | None = None, pad: int = 4, f_min: float = 0.0,
                       bins: int = WEIGHT_BINS, knee: tuple[float, float] | None = None) -> np.ndarray:
    """spectral_variance of K parameters at once, weights u (N, K, C): (K,)."""
    return row_variances(np.ascontiguousarray(np.moveaxis(u, 0, -1)), grid, models, dt, rho, pad, f_min, bins, knee)


def row_variances(rows: np.ndarray, grid: np.ndarray, models: list[tuple[float, float, float] | None],
                  dt: float, rho: np.ndarray | None = None, pad: int = 4, f_min: float = 0.0,
                  bins: int = WEIGHT_BINS, knee: tuple[float, float] | None = None) -> np.ndarray:
    """spectral_variances of weights laid out a row per parameter and channel, rows (K, C, N) contiguous (half the
    time of the FFT down columns): the power law taken once for all, and for independent channels (rho None) only
    each channel's own power formed."""
    k, c, n = rows.shape
    known = [mo for mo in models if mo is not None]
    white = float(np.mean([mo[0] for mo in known])) if known else 0.0
    used = [j for j in range(c) if np.any(rows[:, j])]
    if not used:
        return np.zeros(k)
    laws = np.array([models[j] if models[j] is not None else (white, 0.0, 0.0) for j in used])
    if len(used) < c:
        rows = rows[:, used]
    sw = np.sqrt(np.clip(laws[:, 0], 0.0, None))
    if rho is None:
        var = np.einsum("kcn,kcn->kc", rows, rows) @ (sw * sw)
    else:
        r = rho[np.ix_(used, used)]
        var = np.einsum("kcd,cd->k", np.matmul(rows, rows.transpose(0, 2, 1)), r * np.outer(sw, sw))
    var = var / (2.0 * dt)
    coloured = [j for j in range(len(used)) if laws[j, 1] > 0]
    if not coloured:
        return var
    cc = len(coloured)
    m = _fft_size(grid, bins, pad)[2]
    per = max(1, FFT_VALUES // (m * cc))                       # parameters per FFT call
    law = None
    for lo in range(0, k, per):
        part = rows[lo:lo + per] if cc == len(used) else rows[lo:lo + per][:, coloured]      # (K', Cc, N)
        f, x, norm = _binned_rows(part.reshape(-1, n), grid, dt, bins, pad)
        keep = slice(int(np.searchsorted(f, f_min)), None)       # f increases
        if law is None:
            law = np.array([power_law_spectrum(f[keep], tuple(laws[j]), knee if knee is not None
                                               and laws[j, 2] < knee[1] else None) for j in coloured])  # (Cc, F)
        x = x[:, keep].reshape(part.shape[0], cc, -1)
        if rho is None:
            re = x.view(np.float64)                          # real and imaginary parts side by side
            pw = np.einsum("kcf,kcf,cf->k", re, re, np.repeat(law, 2, axis=1))
        else:
            g = x * np.sqrt(law)[None]
            cross = np.matmul(g, g.conj().transpose(0, 2, 1)).real                        # (K', Cc, Cc)
            pw = np.einsum("kcd,cd->k", cross, r[np.ix_(coloured, coloured)])
        var[lo:lo + per] += pw / norm
    return var


def _fft_size(grid: np.ndarray, bins: int, pad: int) -> tuple[int, int, int]:
    """(step, bins used, FFT length) of binned_fft for positions `grid` (the last one the largest)."""
    from scipy.fft import next_fast_len                 # here, not at import (a command's start)

    step = max(1, -(-(int(np.max(grid)) + 1) // bins))
    length = int(np.max(grid)) // step + 1
    return step, length, next_fast_len(pad * length)


def _binned_rows(u: np.ndarray, grid: np.ndarray, dt: float, bins: int, pad: int
                 ) -> tuple[np.ndarray, np.ndarray, float]:
    """binned_fft of weights laid out a row each, u (J, N): X is (J, F). Where every sample has its own bin (no
    gap, no binning) the bins are the weights themselves (+ 0.0: as bincount's sums into zeros, -0.0 made 0.0)."""
    step, length, m = _fft_size(grid, bins, pad)
    x = np.zeros((u.shape[0], m))                              # zero-padded to the FFT's length
    if step == 1 and length == u.shape[1] and np.all(np.diff(grid) == 1):
        np.add(u, 0.0, out=x[:, :length])
    else:
        where = np.asarray(grid) // step
        for j in range(u.shape[0]):
            x[j, :length] = np.bincount(where, weights=u[j], minlength=length)
    from scipy.fft import rfft, rfftfreq

    return rfftfreq(m, dt * step)[1:], rfft(x, axis=1)[:, 1:], m * dt * step


def binned_fft(u: np.ndarray, grid: np.ndarray, dt: float, bins: int = WEIGHT_BINS,
               pad: int = 4) -> tuple[np.ndarray, np.ndarray, float]:
    """(f, X, norm): the zero-padded FFT X (F, J) of weights u (N, J) at positions `grid` (N,) of a uniform
    grid of step dt, summed into at most `bins` bins of time, at frequencies f > 0; sum_f |X_j|^2 S(f) / norm is
    integral |U_j(f)|^2 S(f) df for a one-sided spectrum S."""
    f, x, norm = _binned_rows(np.ascontiguousarray(np.asarray(u).T), grid, dt, bins, pad)
    return f, x.T, norm


#: the knee is taken where each coloured channel's own power at 1-2 cycles per record is this many times below its
#: steep law carried on there: the data refute the steep law below its band (a hand-turned board: 260 times below);
#: a random walk's residual keeps its steep power there (a drift fitted beside it included) and keeps the steep law
KNEE_EVIDENCE = 10.0


def low_frequency_knee(values: np.ndarray, dt: float, spectra: list,
                       laws: list | None = None) -> tuple[float, float] | None:
    """(f_k, FLICKER): carry laws steeper than flicker on below their band (MIN_CYCLES per record) at flicker's
    slope, where the residual `values` (N, C, the samples in order at step dt; `spectra` their welch_spectra) show
    it: at 1-2 cycles per record, each channel whose law is coloured and steeper than flicker holds KNEE_EVIDENCE
    times less power than that law carried on steeply. None: the steep law stands (it is not refuted, or no law
    is steeper than flicker). laws: each channel's power_law on its spectrum, when already fitted."""
    from scipy.signal import periodogram

    n = values.shape[0]
    duration = n * dt
    f, power = periodogram(values, fs=1.0 / dt, detrend="constant", axis=0)
    low = slice(1, 3)                                     # 1 and 2 cycles per record
    steep = False
    for c in range(values.shape[1]):
        if laws is not None:
            law = laws[c]
        else:
            law = power_law(values[:, c], dt, spectrum=spectra[c]) if spectra[c] is not None else None
        if law is None or not is_coloured(law, duration) or law[2] >= FLICKER:
            continue
        steep = True
        if KNEE_EVIDENCE * float(np.mean(power[low, c])) > float(np.mean(power_law_spectrum(f[low], law))):
            return None
    return (MIN_CYCLES / duration, FLICKER) if steep else None


def power_law_spectrum(f: np.ndarray, law: tuple[float, float, float],
                       knee: tuple[float, float] | None = None) -> np.ndarray:
    """The part a f^alpha of the law (w, a, alpha) at frequencies f > 0; below knee = (f_k, beta), the law
    carried on at slope beta: a f_k^alpha (f / f_k)^beta."""
    _, a, alpha = law
    s = a * f ** alpha
    if knee is not None:
        low = f < knee[0]
        s[low] = a * knee[0] ** alpha * (f[low] / knee[0]) ** knee[1]
    return s


def low_frequency_correlation(values: np.ndarray, blocks: int = 32) -> np.ndarray:
    """(C, C) correlation of the channels' slow parts: of their means over `blocks` contiguous blocks (at
    least four per channel), where a wander shared by channels (one probe's noise in several) shows."""
    n, c = values.shape
    nb = min(max(blocks, 4 * c), n // 4)
    if nb < c + 2:
        return np.eye(c)
    means = np.array([b.mean(0) for b in np.array_split(values, nb)])
    sd = means.std(0)
    sd[sd <= 0] = 1.0
    z = (means - means.mean(0)) / sd
    return z.T @ z / nb


def pinv_columns(a: np.ndarray, idx: np.ndarray, rank_tol: float) -> np.ndarray:
    """Columns idx of the pseudo-inverse of a symmetric normal matrix, on its column-scaled form (as the
    solve itself: eigenvalues below rank_tol of the largest are a null space)."""
    d = np.sqrt(np.clip(np.diag(a), 0.0, None))
    d[d <= 0] = 1.0
    lam, vec = np.linalg.eigh(a / np.outer(d, d))
    keep = lam > rank_tol * (lam[-1] if lam[-1] > 0 else 1.0)
    vk = vec[:, keep]
    return (vk @ (vk[idx].T / lam[keep][:, None])) / d[:, None] / d[idx][None, :]


#: coloured_stderr maps parameter directions to the channels in passes of at most this many values (float64:
#: directions x channels x rows; 160 MB)
APPLY_VALUES = 20_000_000


def coloured_stderr(fit: Any, idx: np.ndarray, rank_tol: float) -> np.ndarray | None:
    """Standard errors of parameters idx of a fit (solve.FitResult) under a power-law model of the noise spectrum;
    None when the noise is not coloured at the record's own period. With the offsets fitted, the model is per probe
    axis (the channels' sensitivity to a probe's noise is minus their sensitivity to its offset); otherwise per
    channel, with the channels' slow parts' correlation. The knee below the band (low_frequency_knee) is looked for
    only where a law steeper than flicker is used: it changes no other."""
    ch, pr = fit.channels, fit.problem
    if ch.values.shape[0] < 512 or fit.jac is None:
        return None
    grid, dt = sample_grid(ch.t_s)
    if grid[-1] + 1 > MAX_GRID_FILL * grid.size:
        return None                                   # mostly gaps: the jackknife's errors stand
    spectra = welch_spectra(ch.values, dt)
    if looks_white(spectra, ch.values.shape[0] * dt):     # the length the spectra are taken over (gaps closed)
        return None
    cols = pinv_columns(fit.a_blocks.sum(0), idx, rank_tol)
    offsets = [(sl.k, j) for sl in pr.slots if sl.kind == "offset" for j in range(sl.start, sl.stop)]
    if len(offsets) == 3 * pr.P:
        return _per_probe_axis(fit, cols, offsets, grid, dt, spectra)
    return _per_channel(fit, cols, grid, dt, spectra)


def _per_probe_axis(fit: Any, cols: np.ndarray, offsets: list[tuple[int, int]], grid: np.ndarray, dt: float,
                    spectra: list) -> np.ndarray | None:
    ch, pr = fit.channels, fit.problem
    duration = ch.values.shape[0] * dt
    units = np.zeros((pr.n_params, len(offsets)))
    units[[j for _, j in offsets], np.arange(len(offsets))] = 1.0
    sens = pr.apply(fit.jac, fit.ev, units)                                 # (N, C, 3P): per probe axis
    gain = np.mean(sens ** 2, axis=0).reshape(ch.values.shape[1], pr.P, 3).sum(axis=2)
    law = probe_power_laws(ch.values, dt, gain, spectra=spectra)
    if law is None or not any(is_coloured((float(w), float(a), law[2]), duration) for w, a in zip(*law[:2])):
        return None
    if law[2] > FLICKER:
        law = probe_power_laws(ch.values, dt, gain, alphas=np.array([FLICKER]), spectra=spectra) or law
    w, a, alpha = law
    knee = low_frequency_knee(ch.values, dt, spectra) if alpha < FLICKER else None     # below the band
    models = [(float(w[k]), float(a[k]), alpha) for k, _ in offsets]
    return np.sqrt(np.concatenate([row_variances(rows, grid, models, dt, knee=knee)
                                   for rows in _weight_rows(fit, cols, sens)]))


def _per_channel(fit: Any, cols: np.ndarray, grid: np.ndarray, dt: float, spectra: list) -> np.ndarray | None:
    values = fit.channels.values
    duration = values.shape[0] * dt
    laws = [power_law(values[:, c], dt, spectrum=spectra[c]) for c in range(values.shape[1])]
    if not any(is_coloured(m, duration) for m in laws):
        return None
    models = [power_law(values[:, c], dt, np.array([FLICKER]), spectrum=spectra[c]) or m
              if m is not None and is_coloured(m, duration) and m[2] > FLICKER else m
              for c, m in enumerate(laws)]
    steep = any(m is not None and m[2] < FLICKER for m in models)
    knee = low_frequency_knee(values, dt, spectra, laws) if steep else None            # below the band
    rho = low_frequency_correlation(values)
    return np.sqrt(np.concatenate([row_variances(rows, grid, models, dt, rho, f_min=1.0 / duration, knee=knee)
                                   for rows in _weight_rows(fit, cols)]))


def _weight_rows(fit: Any, cols: np.ndarray, sens: np.ndarray | None = None):
    """The weighted channel weights of parameter directions cols (n_params, J), a row per direction and channel
    (J', C, N) as row_variances takes them, or per direction and probe axis through the channels' sensitivities
    to them, sens (N, C, 3P): (J', 3P, N). As many directions a pass as APPLY_VALUES allows, each pass built a
    chunk of samples at a time into its layout (no copy of the whole pass in another)."""
    pr = fit.problem
    n, c = fit.channels.values.shape
    width = c if sens is None else sens.shape[2]
    per = max(1, APPLY_VALUES // (n * max(c, width)))
    w2 = pr.weights ** 2
    for lo in range(0, cols.shape[1], per):
        d = cols[:, lo:lo + per]
        rows = np.empty((d.shape[1], width, n))
        at = 0
        for sl in [c for b in pr.blocks for c in _chunks(b, pr.n_params)]:
            u = pr.apply(fit.jac, fit.ev, d, sl)                                 # (m, C, J')
            u *= w2[None, :, None]
            m = u.shape[0]
            rows[:, :, at:at + m] = (u.transpose(2, 1, 0) if sens is None
                                     else np.matmul(u.transpose(0, 2, 1), sens[at:at + m]).transpose(1, 2, 0))
            at += m
        yield rows
