"""Hysteresis: perming, the offset jumps a fluxgate core keeps after a strong field or a shock.

    raw_corrected_a = raw_a - sum_j s_ja H(t - t_j)        H the unit step

The step instants t_j are found in the current model's scalar residual of each probe: in windows
of W samples before and after each instant the local offset change delta is estimated by least
squares on the residual's sensitivity to an offset, g = n^T M (so a rotating probe shows its jump
at every heading), and

    chi2(t) = (delta_R - delta_L)^T [sigma^2 (G_L^-1 + G_R^-1)]^-1 (delta_R - delta_L),  G = sum g g^T

must exceed `threshold` (chi-square with 3 degrees of freedom; the default is far beyond what noise
reaches). sigma^2 / W is the variance of a window mean only for white noise: a residual that wanders
(1/f noise, a smooth offset change that no term follows) makes the difference of two window means
vary far more, and every wander would pass for a step. So chi2 is first divided by its own typical
size along the record, median(chi2) / median(chi-square_3) when that exceeds 1: a step must stand out
of the wander of this very residual, not only of its white noise. Parameters: the jump per step and
axis, in nT.
"""

from __future__ import annotations

import numpy as np

from fluxcal.service.numerics.noise import robust_noise

from .base import AXES, EffectTerm, ProbeView

CHI2_3_MEDIAN = 2.366         # median of a chi-square with 3 degrees of freedom
#: a step's chi-square (3 degrees of freedom, wander-normalised) must exceed this (a single chi-square_3 passes it
#: 1.4e-6 of the time; the highest of the windows' values along 18 probe-records of white and 1/f noise without
#: a step were 10 to 23); what it proposes, the held-out cross-fit judges (diagnose/fits.py)
THRESHOLD = 30.0
#: a step must beat a linear change of the offset, and a jump a bend, over the same stretch by this many noise
#: variances (the RSS drops' differences). Measured: true 7.8 nT steps beat the line by 33-2,192 (white noise, ten
#: worlds) and 5-137 (1/f noise of 0.3 nT/sqrt(Hz), nine), the bend by 12-1,266 and 0.7-81; warm-ups (25 nT,
#: 6-30 s) lost to the line by 6-40; a ramp's corners beat the line (39, 176) and lost to the bend (-55, -1).
#: Zero: each must simply fit better
STEP_OVER_RAMP = 0.0
#: peaks looked at per step allowed: a smooth change rejected (_steplike) keeps chi2 high over its whole length,
#: and must not use up the search before a true step elsewhere
MAX_PASSES = 4
#: the single step the calibration's share is refitted beside is looked for at most at this many instants
SCAN_POINTS = 20_000
#: a view's cache key for a stretch (t_lo, t_hi) the steps are searched around, not across (diagnose's
#: held-out block; diagnose/fits.py crossfit_heldout)
BARRIER = "ref:hysteresis_barrier"
#: a step undone by the next: their jumps' sum at most this share of the first's size, or within the errors
#: (chi-square below RETURNED_CHI2, 3 degrees of freedom, p = 0.01, the two errors taken as independent) (rules_out)
RETURNED = 0.25
RETURNED_CHI2 = 11.34
#: a step that stays counts as perming when its jump's chi-square (3 degrees of freedom) is at least this (p ~ 0.001)
STAYS_CHI2 = 16.27
#: a view's cache key for the instants where the residual changed beyond the noise but smoothly (not a step)
SMOOTH = "ref:hysteresis_smooth"


def detect_steps(t_s: np.ndarray, residual: np.ndarray, gain: np.ndarray, *, window: int,
                 threshold: float = THRESHOLD, max_steps: int = 3, barrier: tuple[float, float] | None = None,
                 centred: np.ndarray | None = None, smooth: list | None = None) -> list[tuple[float, float]]:
    """Offset steps in a scalar residual: [(t_step_s, chi2), ...], strongest first.

    barrier (t_lo, t_hi): a stretch left out (a held-out block); the samples on either side are searched on
    their own, so no window spans it (a smooth change across it would otherwise look like a step at its edge).
    centred (N, 3): raw - offset; given, the residual is first cleaned of what the linear calibration took of
    a step (`without_calibration_share`). smooth: a list to which the peaks that stood out of the noise but were a
    smooth change, not a jump (`_steplike`), are added as (t_s, chi2)."""
    if barrier is not None:
        lo, hi = barrier
        found = []
        for side in (t_s < lo, t_s > hi):
            found += detect_steps(t_s, np.where(side, residual, np.nan), gain, window=window, threshold=threshold,
                                  max_steps=max_steps, centred=centred, smooth=smooth)
        return sorted(found, key=lambda tc: -tc[1])[:max_steps]
    ok = np.isfinite(residual) & np.all(np.isfinite(gain), axis=1)
    if centred is not None:
        ok &= np.all(np.isfinite(centred), axis=1)
    idx = np.flatnonzero(ok)
    n, w = idx.size, int(window)
    if w < 10 or n < 4 * w:
        return []
    r, g, t = residual[idx], gain[idx], t_s[idx]
    if centred is not None:
        r = without_calibration_share(r, g, centred[idx], margin=w)
    sigma = robust_noise(r)
    if not np.isfinite(sigma) or sigma <= 0:
        return []
    s_gg = np.concatenate([np.zeros((1, 3, 3)), np.cumsum(g[:, :, None] * g[:, None, :], axis=0)])
    s_gr = np.concatenate([np.zeros((1, 3)), np.cumsum(g * r[:, None], axis=0)])
    i = np.arange(w, n - w + 1)
    chi2 = _window_jump_chi2(s_gg, s_gr, i, w) / sigma ** 2
    # the residual's wander: how much larger chi2 typically is than white noise makes it (a few steps
    # move the median of thousands of window positions little)
    wander = float(np.median(chi2)) / CHI2_3_MEDIAN
    chi2 = chi2 / max(1.0, wander)
    steps: list[tuple[float, float]] = []
    chi2 = chi2.copy()
    for _ in range(MAX_PASSES * max_steps):        # a few peaks, not a loop over samples
        if len(steps) >= max_steps:
            break
        j = int(np.argmax(chi2))
        if chi2[j] < threshold:
            break
        # the sliding statistic has broad flanks and its peak can sit off the step when a window sees
        # few directions: place the step where one jump within [i_j - 2w, i_j + 2w) fits best
        lo, hi = max(0, int(i[j]) - 2 * w), min(n, int(i[j]) + 2 * w)
        at = _best_split(s_gg, s_gr, lo, hi, int(i[j]), w)
        # a step, not a smooth change: over the same stretch a jump must fit better than a bend at the same
        # instant; a warm-up's rise was taken for two steps (perming named, significant) where it is a change no
        # term of the catalogue follows
        if not _steplike(g[lo:hi], r[lo:hi], at - lo, sigma ** 2 * max(1.0, wander)):
            if smooth is not None:
                smooth.append((float(t[at]), float(chi2[j])))
            chi2[max(0, j - 2 * w):j + 2 * w] = 0.0     # the stretch judged; a rejection uses no step of max_steps
            continue
        steps.append((float(t[at]), float(chi2[j])))
        chi2[max(0, at - w - i[0]):max(0, at + w - i[0])] = 0.0
        chi2[max(0, j - w):j + w] = 0.0
    return steps


def _window_jump_chi2(s_gg: np.ndarray, s_gr: np.ndarray, i: np.ndarray, w: int) -> np.ndarray:
    """χ² σ² of the jump between the offsets fitted to the w samples before and the w after each instant i, from
    the cumulative sums s_gg of g gᵀ and s_gr of g r (each with a leading zero row)."""
    g_left, g_right = s_gg[i] - s_gg[i - w], s_gg[i + w] - s_gg[i]
    b_left, b_right = s_gr[i] - s_gr[i - w], s_gr[i + w] - s_gr[i]
    eye = np.eye(3)
    # a small ridge: a window of turns about one axis does not fix all three offset components
    ridge = 1e-6 * np.trace(g_left + g_right, axis1=1, axis2=2)[:, None, None] * eye
    d_left = np.linalg.solve(g_left + ridge, b_left[..., None])[..., 0]
    d_right = np.linalg.solve(g_right + ridge, b_right[..., None])[..., 0]
    jump = d_right - d_left
    # covariance of the jump / sigma^2 = G_L^-1 + G_R^-1 (3x3 per instant)
    cov = np.linalg.solve(g_left + ridge, np.broadcast_to(eye, g_left.shape)) + \
        np.linalg.solve(g_right + ridge, np.broadcast_to(eye, g_right.shape))
    return np.einsum("ni,ni->n", jump, np.linalg.solve(cov, jump[..., None])[..., 0])


def _best_split(s_gg: np.ndarray, s_gr: np.ndarray, lo: int, hi: int, centre: int, w: int) -> int:
    """The sample within w of `centre` (and w/2 inside lo..hi) where separate offsets before and after it fit
    the stretch lo..hi best (cumulative sums as in `_window_jump_chi2`)."""
    split = np.arange(max(lo + w // 2, centre - w), min(hi - w // 2, centre + w))
    gl, gr = s_gg[split] - s_gg[lo], s_gg[hi] - s_gg[split]
    bl, br = s_gr[split] - s_gr[lo], s_gr[hi] - s_gr[split]
    rdg = 1e-6 * np.trace(gl + gr, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    # RSS drop of fitting separate offsets left and right: b_L^T G_L^-1 b_L + b_R^T G_R^-1 b_R
    drop = (np.einsum("ni,ni->n", bl, np.linalg.solve(gl + rdg, bl[..., None])[..., 0])
            + np.einsum("ni,ni->n", br, np.linalg.solve(gr + rdg, br[..., None])[..., 0]))
    return int(split[int(np.argmax(drop))])


def _came_back(v0: np.ndarray, v1: np.ndarray) -> bool:
    """Whether step 1 undoes step 0: v = jump x, y, z and their standard errors."""
    total = v0[:3] + v1[:3]
    if np.linalg.norm(total) <= RETURNED * np.linalg.norm(v0[:3]):
        return True
    var = v0[3:] ** 2 + v1[3:] ** 2
    return bool(np.all(np.isfinite(var)) and np.all(var > 0) and float(np.sum(total ** 2 / var)) < RETURNED_CHI2)


def no_step_reason(views) -> str:
    """Why no perming step was fitted, for diagnose's table: nothing stood out of the noise, or what stood out
    changed smoothly (a ramp, a warm-up: not a step, and no catalogue term), said with where."""
    seen = {v.name: v.cache.get(SMOOTH, []) for v in views if v.cache.get(SMOOTH)}
    if not seen:
        return "no perming step stands out of the noise in the residual"
    where = "; ".join(f"{name} at {', '.join(f'{t:.1f}' for t in times)} s" for name, times in seen.items())
    return (f"no perming step: the residual changes beyond the noise ({where}) but smoothly, over seconds, "
            f"not in one jump (a ramp, a warm-up)")


def _steplike(g: np.ndarray, r: np.ndarray, at: int, noise2: float) -> bool:
    """Whether the stretch's residual r (sensitivity g) jumps at row `at`: two offsets, before and after, must fit
    it better than one moving linearly across it, and a line with a jump at `at` better than a line that bends
    there (each pair with as many parameters), by more than STEP_OVER_RAMP noise variances (noise2: sigma², wander
    included). A rise over seconds fails the first, the corner of a ramp the second; a perming step passes both."""
    tau = np.linspace(-0.5, 0.5, r.size)[:, None]
    after = (np.arange(r.size) >= at)[:, None]
    bent = np.where(after, tau - tau[min(at, r.size - 1)], 0.0)

    def gain(*cols: np.ndarray) -> float:
        x = np.concatenate([g * c for c in cols], axis=1)
        b = x.T @ r
        return float(b @ np.linalg.lstsq(x.T @ x, b, rcond=None)[0])

    one = np.ones_like(tau)
    margin = STEP_OVER_RAMP * noise2
    return (gain(one, after) - gain(one, tau) > margin
            and gain(one, tau, after) - gain(one, tau, bent) > margin)


def without_calibration_share(r: np.ndarray, g: np.ndarray, u: np.ndarray, margin: int) -> np.ndarray:
    """The scalar residual r less what a linear calibration fitted across a step left of it.

    A calibration fitted to data with an offset step takes part of the step into its offset and shape, and
    leaves a residual that follows the direction all along the record: in one world of ten (a 7.8 nT step,
    white noise) it made the windows' jumps peak 11 s off the step, and in two others it hid the step. So the
    calibration's share is refitted beside the likeliest single step (one: further steps are found by the
    windows in what is left): its columns X are the residual's sensitivity to the offsets (g) and to the shape
    (u_a u_b, six), the step's g H(t - t_k), and for every instant k (at most SCAN_POINTS of them, `margin`
    samples from either end) at once by suffix sums the drop of the residual sum of squares b_k^T C_k^-1 b_k, with
    b_k = S_k^T r - S_k^T X (X^T X)^-1 X^T r and C_k = S_k^T S_k - S_k^T X (X^T X)^-1 X^T S_k. The residual
    less X beta of the joint fit at the best instant keeps the step whole and loses the calibration's share;
    the windows' test then judges it (a wander stays a wander: the refit moves only the nine columns)."""
    quad = np.column_stack([u[:, 0] ** 2, u[:, 1] ** 2, u[:, 2] ** 2,
                            2 * u[:, 0] * u[:, 1], 2 * u[:, 0] * u[:, 2], 2 * u[:, 1] * u[:, 2]])
    scale = np.sqrt(np.mean(quad ** 2, axis=0))
    scale[scale == 0] = 1.0
    x = np.column_stack([g, quad / scale])
    xtx_inv = np.linalg.pinv(x.T @ x)
    proj = xtx_inv @ (x.T @ r)
    # the instants scanned: every `stride`-th sample (the windows place the step to the sample afterwards); the
    # sums per stretch between them, a chunk of rows at a time (a few hundred bytes per stretch, not per sample)
    n = r.size
    stride = max(1, n // SCAN_POINTS)
    starts = np.arange(0, n, stride)
    parts = [np.empty((starts.size, 3, 9)), np.empty((starts.size, 3, 3)), np.empty((starts.size, 3))]
    rows = stride * 4096
    for lo in range(0, n, rows):
        sl = slice(lo, min(n, lo + rows))
        at = starts[(starts >= lo) & (starts < sl.stop)] - lo
        seg = slice(lo // stride, lo // stride + at.size)
        gl = g[sl]
        parts[0][seg] = np.add.reduceat(gl[:, :, None] * x[sl][:, None, :], at, axis=0)
        parts[1][seg] = np.add.reduceat(gl[:, :, None] * gl[:, None, :], at, axis=0)
        parts[2][seg] = np.add.reduceat(gl * r[sl][:, None], at, axis=0)
    gx, gg, gr = (np.cumsum(a[::-1], axis=0)[::-1] for a in parts)          # S_k^T X, S_k^T S_k, S_k^T r
    inside = (starts >= margin) & (starts < n - margin)
    gx, gg, gr, instants = gx[inside], gg[inside], gr[inside], starts[inside]
    c = gg - np.einsum("nij,jk,nlk->nil", gx, xtx_inv, gx)
    b = gr - gx @ proj
    ridge = 1e-9 * np.trace(c, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    drop = np.einsum("ni,ni->n", b, np.linalg.solve(c + ridge, b[..., None])[..., 0])
    if not drop.size or not np.all(np.isfinite(drop)):
        return r
    best = int(instants[int(np.argmax(drop))])
    step = np.where(np.arange(n)[:, None] >= best, g, 0.0)
    coef, *_ = np.linalg.lstsq(np.column_stack([x, step]), r, rcond=None)
    return r - x @ coef[:x.shape[1]]


class Hysteresis(EffectTerm):
    """Offset steps (nT per axis) at instants found in the residual."""

    name = "hysteresis"
    title = "Hysteresis"
    needs_residual = True
    chooses_in_residual = True
    physical = "perming: offset steps after a strong field or a shock"
    separation = {
        "drift": "record longer: a drift changes smoothly, a perming step jumps once",
    }

    def __init__(self, *, threshold: float = THRESHOLD, max_steps: int = 3) -> None:
        self.threshold = threshold
        self.max_steps = max_steps

    def settings(self) -> dict:
        return {"threshold": self.threshold, "max_steps": self.max_steps}

    def steps(self, view: ProbeView) -> list[float]:
        """Step instants of probe view.k (found once per binding)."""
        key = "ref:hysteresis_steps"
        if key not in view.cache:
            if view.model_residual is None or view.model_gain is None:
                view.cache[key] = []
            else:
                data = view.data
                window = int(min(max(data.n_samples // 30, round(2.0 / data.dt_s), 50), data.n_samples // 5))
                smooth: list[tuple[float, float]] = []
                found = detect_steps(data.t_s, view.model_residual, view.model_gain, window=window,
                                     threshold=self.threshold, max_steps=self.max_steps,
                                     barrier=view.cache.get(BARRIER), centred=view.centred_nT, smooth=smooth)
                view.cache[key] = sorted(t for t, _ in found)
                view.cache[SMOOTH] = sorted(t for t, _ in smooth)
        return view.cache[key]

    def param_names(self, view: ProbeView) -> list[str]:
        return [f"{view.name}.{a} step@{t:.2f}s nT" for t in self.steps(view) for a in AXES]

    def param_keys(self, view: ProbeView) -> list[tuple]:
        return [("step", float(t), a) for t in self.steps(view) for a in range(3)]

    def rules_out(self, parameters) -> str | None:
        """Perming stays: without one step that stays and is determined (chi-square of its jump at least
        STAYS_CHI2), where the others come in pairs whose jumps cancel (the offset moved and came back, as under a
        magnet carried past the probe or a knock), the steps are a transient, not perming."""
        steps: dict[tuple[str, float], np.ndarray] = {}          # (probe, t) -> jump x, y, z and their errors
        for p in parameters:
            if p.term == self.name and p.key[:1] == ("step",):
                _, t, a = p.key
                v = steps.setdefault((p.probe, t), np.full(6, np.nan))
                v[a], v[3 + a] = p.value, np.nan if p.stderr is None else p.stderr
        by_probe: dict[str, list[tuple[float, np.ndarray]]] = {}
        for (probe, t), v in sorted(steps.items(), key=lambda kv: kv[0][1]):
            by_probe.setdefault(probe, []).append((t, v))
        pairs = []
        for probe, seq in by_probe.items():
            i = 0
            while i < len(seq):
                t0, v0 = seq[i]
                if i + 1 < len(seq) and _came_back(v0, seq[i + 1][1]):
                    size = float(np.linalg.norm(v0[:3]))
                    pairs.append(f"{probe} by {size:,.3g} nT over {t0:.1f}-{seq[i + 1][0]:.1f} s")
                    i += 2
                    continue
                if not np.all(np.isfinite(v0)) or float(np.sum((v0[:3] / v0[3:]) ** 2)) >= STAYS_CHI2:
                    return None                    # a step that stays (or one whose error is not known): perming
                i += 1
        if not pairs:
            return None
        return (f"the offset came back ({'; '.join(pairs)}) and no other step stays beyond its errors: a transient "
                f"(a magnet carried past the probe, a knock), not perming, which stays")

    def columns(self, view: ProbeView) -> np.ndarray:
        t = view.data.t_s
        steps = self.steps(view)
        cols = np.zeros((t.shape[0], 3, 3 * len(steps)))
        for j, ts in enumerate(steps):
            h = (t >= ts).astype(np.float64)
            for a in range(3):
                cols[:, a, 3 * j + a] = h
        return cols
