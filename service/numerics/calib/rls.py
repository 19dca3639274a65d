"""Online recursive least squares of the ellipsoid, in information form, a block at a time, P probes at once.

Same quadric, scaling and right side as the batch fit (ellipsoid.py: uᵀA'u + b'ᵀu − γδ = 1, u = r/s),
so the two agree: without forgetting, the online estimate after any blocking *is* the batch fit. The δ
column (reference field variation) is used only when asked for (`varying_total=True`, e.g. a survey
with a proton magnetometer over a changing field): with a nearly steady F it is nearly constant, and a
constant column brings back the null direction the nine-term form avoids.

With a forgetting factor λ per sample, a block of n samples φ_i (rows of Φ) updates

    Λ ← λⁿ Λ + Φᵀ W Φ,   η ← λⁿ η + Φᵀ W y,   W = diag(λ^(n−1−i)),  y = 1,

which equals n single-sample updates (Λ ← λΛ + φφᵀ) exactly, at the cost of one matrix product per
probe. θ solves Λ θ = η (Cholesky, never an inverse). Effective memory: 1 / (1 − λ) samples (the
weights sum to that).

No excitation (a platform at rest) makes plain RLS forget every direction but the one it still sees:
Λ decays towards singular and the estimate winds up. Two guards:
- forgetting and learning follow motion: a block forgets λ^m and its samples weigh m/n each, with
  m = min(n, swept angle / `forget_deg`) (the path angle the field direction swept in the probe
  frame, over ten segment means of the block). Time is counted in swept angle: a platform at rest
  forgets nothing and piles no weight on the one direction it sees (as ArduPilot's calibrator
  keeps only samples far enough from the others), a platform turning faster than `forget_deg` per
  sample is plain RLS; `forget_deg=None` is plain RLS always;
- an information floor: in no direction may the information fall below a share f (`anchor`) of
  Λ_a, the information of the last well-conditioned estimate θ_a; where it does, the anchor makes up
  the deficit. With the generalized eigenpairs Λ v = g Λ_a v (Λ_a = L Lᵀ, L⁻¹ Λ L⁻ᵀ = V diag(g) Vᵀ):
      Π = L V diag(max(0, f − g)) Vᵀ Lᵀ,   (Λ + Π) θ = η + Π θ_a.
  Well-excited data (g ≥ f everywhere) get Π = 0: the plain least-squares answer, no bias; a
  direction the data stopped informing keeps the last good value. No solve can go singular or NaN.
A probe whose samples are NaN in a block is updated with zero weight for them (time still passes).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from drivers.errors import CalibrationRefused, DataError, NotCalibratedError

from .ellipsoid import N_GEOMETRY, N_PARAMS, jacobian_se, quadric_to_calibration
from .model import ProbeCalibration, named


def _design(u: np.ndarray, delta: np.ndarray | None) -> np.ndarray:
    """(…, k) rows [x², y², z², 2xy, 2xz, 2yz, x, y, z] (and −δ) of scaled samples u (…, 3);
    the same columns as ellipsoid.quadric_design."""
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    cols = [x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z]
    if delta is not None:
        cols.append(-delta)
    return np.stack(cols, axis=-1)


class RlsEllipsoid:
    """Online ellipsoid estimator for one probe (inputs (N, 3)) or P probes at once (`n_probes=P`,
    inputs (N, P, 3), fitted results with a leading probe axis).

    forgetting: λ per sample (1.0 = growing memory, equal to the batch fit); memory 1/(1 − λ) samples.
    forget_deg: forget (and, with λ < 1, learn) only as the field direction sweeps, one sample-step
      per this many degrees (None: per sample, whatever the motion). With λ = 1 every sample counts,
      so the estimate stays the batch fit.
    anchor: f, the floor: the share of the last good information below which no direction may fall.
    max_condition: a solve becomes the new anchor only below this condition number (of the
      column-scaled design, as the batch fit reports it).
    total_nT: the total field when no reference comes with the samples (None: the first block's mean
      raw magnitude, so the scale of the matrix is a convention).
    varying_total: fit the δ column (reference field variation) too.

    >>> rng = np.random.default_rng(0)
    >>> d = rng.normal(size=(2000, 3)); d /= np.linalg.norm(d, axis=1, keepdims=True)
    >>> raw = 50000.0 * d @ np.diag([1.02, 0.98, 1.0]) + [300.0, -200.0, 100.0]
    >>> est = RlsEllipsoid(forgetting=1.0).fit(raw, 50000.0)
    >>> np.round(est.offset_, 6).tolist()
    [300.0, -200.0, 100.0]
    """

    def __init__(self, *, forgetting: float = 0.9995, anchor: float = 0.1, max_condition: float = 200.0,
                 total_nT: float | None = None, varying_total: bool = False,
                 forget_deg: float | None = 0.05, n_probes: int | None = None) -> None:
        self.forgetting = forgetting
        self.forget_deg = forget_deg
        self.varying_total = varying_total
        self.anchor = anchor
        self.max_condition = max_condition
        self.total_nT = total_nT
        self.n_probes = n_probes
        self.reset()

    # --- state ------------------------------------------------------------------------------

    @property
    def n_params(self) -> int:
        return N_PARAMS if self.varying_total else N_GEOMETRY

    @property
    def _p(self) -> int:
        return 1 if self.n_probes is None else int(self.n_probes)

    def reset(self) -> None:
        """Forget everything (fit = reset + partial_fit)."""
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"forgetting: expected 0 < λ <= 1, got {self.forgetting}")
        p, k = self._p, self.n_params
        self._info = np.zeros((p, k, k))           # Λ
        self._eta = np.zeros((p, k))               # η
        self._y2 = np.zeros(p)                     # Σ w y², for the residual variance
        self._weight = np.zeros(p)                 # Σ w, the effective number of samples
        self._n = np.zeros(p, dtype=np.int64)
        self._scale = np.full(p, np.nan)           # s, nT: u = r / s, fixed by the first samples
        self._f2_ref = np.full(p, np.nan)          # F₀², nT²
        self._assumed_total = np.full(p, np.nan)   # total field assumed when none is given
        self._last_dir = np.full((p, 3), np.nan)
        self._ridge = np.zeros(k)
        if self.varying_total:
            self._ridge[-1] = 1e-9                 # a ridge on γ of ~1e-9 of one sample's information
        self._theta = np.full((p, k), np.nan)
        self._has_theta = np.zeros(p, bool)
        self._condition = np.full(p, np.inf)
        self._anchor_theta = np.full((p, k), np.nan)
        self._anchor_chol = np.zeros((p, k, k))   # L: Λa = L Lᵀ
        self._has_anchor = np.zeros(p, bool)
        self._dirty = np.zeros(p, bool)

    def fit(self, field_nT: np.ndarray, total_nT=None) -> "RlsEllipsoid":
        self.reset()
        return self.partial_fit(field_nT, total_nT)

    # --- update -----------------------------------------------------------------------------

    def _as_block(self, field_nT: np.ndarray) -> np.ndarray:
        raw = np.asarray(field_nT, dtype=float)
        if self.n_probes is None:
            if raw.ndim != 2 or raw.shape[1] != 3:
                raise DataError(f"field_nT: expected shape (N, 3), got {raw.shape}")
            return raw[:, None, :]
        if raw.ndim != 3 or raw.shape[1:] != (self.n_probes, 3):
            raise DataError(f"field_nT: expected shape (N, {self.n_probes}, 3), got {raw.shape}")
        return raw

    def _totals(self, total_nT, raw: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """F per sample and probe, (N, P)."""
        n, p = raw.shape[:2]
        t = total_nT if total_nT is not None else self.total_nT
        if t is None:
            # unknown total field: each probe's first mean raw magnitude fixes the (conventional) scale
            fresh = np.isnan(self._assumed_total) & ok.any(axis=0)
            if fresh.any():
                mag = np.linalg.norm(np.where(ok[..., None], raw, 0.0), axis=2)
                self._assumed_total[fresh] = (mag.sum(axis=0) / np.maximum(ok.sum(axis=0), 1))[fresh]
            return np.broadcast_to(self._assumed_total[None, :], (n, p))
        t = np.asarray(t, dtype=float)
        if t.ndim == 0:
            return np.full((n, p), float(t))
        if t.shape == (n,):
            return np.broadcast_to(t[:, None], (n, p))
        if t.shape == (n, p):
            return t
        raise DataError(f"total_nT: expected a number, {n} values or ({n}, {p}), got shape {t.shape}")

    def partial_fit(self, field_nT: np.ndarray, total_nT=None) -> "RlsEllipsoid":
        """Update with a block of raw samples, (N, 3) or (N, P, 3); total_nT: None, a number, (N,) shared
        by the probes (one scalar reference) or (N, P). Rows holding NaN get zero weight."""
        raw = self._as_block(field_nT)
        n = raw.shape[0]
        if n == 0:
            return self
        ok = np.isfinite(raw).all(axis=2)
        f = self._totals(total_nT, raw, ok)
        ok &= np.isfinite(f)
        all_ok = bool(ok.all())
        if not all_ok:
            raw = np.where(ok[..., None], raw, 0.0)
            f = np.where(ok, f, 0.0)
        if np.isnan(self._scale).any():
            self._first_samples(raw, f, ok)
        live = ~np.isnan(self._scale)                 # probes that have seen a sample
        s = np.where(live, self._scale, 1.0)
        # probe-major (P, N, ·) so every probe's Φᵀ W Φ is one contiguous BLAS product
        u = raw.transpose(1, 0, 2) / s[:, None, None]
        delta = None
        if self.varying_total:
            delta = (f.T * f.T - np.where(live, self._f2_ref, 0.0)[:, None]) / (s * s)[:, None]
        phi = _design(u, delta)                       # (P, N, k)
        lam = self.forgetting
        m = np.full(raw.shape[1], float(n)) if self.forget_deg is None else \
            np.minimum(n, self._swept_deg(raw, ok, all_ok) / self.forget_deg)
        decay = lam ** m                              # λ^m per probe
        # sample i of n is (n − 1 − i) m/n sample-steps old at the block's end: W = diag(λ^((n−1−i) m/n))
        if lam < 1.0:
            w = lam ** ((m / n)[:, None] * np.arange(n - 1, -1, -1, dtype=float)[None, :])    # (P, N)
        else:
            w = np.ones((raw.shape[1], n))
        if lam < 1.0 and self.forget_deg is not None:
            # learning follows motion too: a block that barely moved counts as m samples, not n, so
            # a long rest neither forgets nor piles weight on one direction (Λ stays balanced)
            w = w * (m / n)[:, None]
        if not all_ok:
            w = w * ok.T
        pw = phi * w[..., None]
        pwt = pw.transpose(0, 2, 1)
        # Λ ← λ^m Λ + Φᵀ W Φ ;  η ← λ^m η + Φᵀ W y   (y = 1), every probe in one batched product
        self._info = decay[:, None, None] * self._info + np.matmul(pwt, phi)
        self._eta = decay[:, None] * self._eta + np.matmul(pwt, np.ones(n))
        wsum = w.sum(axis=1)
        self._y2 = decay * self._y2 + wsum
        self._weight = decay * self._weight + wsum
        self._n += ok.sum(axis=0)
        self._dirty |= ok.any(axis=0)                 # solved lazily, when an estimate is asked for
        return self

    def _first_samples(self, raw: np.ndarray, f: np.ndarray, ok: np.ndarray) -> None:
        """Fix s (median raw magnitude) and F₀² (mean F²) of probes seeing their first samples."""
        fresh = np.isnan(self._scale) & ok.any(axis=0)
        for j in np.flatnonzero(fresh):
            rows = ok[:, j]
            self._scale[j] = float(np.median(np.linalg.norm(raw[rows, j], axis=1)))
            self._f2_ref[j] = float(np.mean(f[rows, j] ** 2))

    def _swept_deg(self, raw: np.ndarray, ok: np.ndarray, all_ok: bool) -> np.ndarray:
        """Path angle (deg) the field direction swept in each probe's frame over this block (and since
        the last one): the directions of ten consecutive segment means, so noise at rest reads ~zero
        and a full revolution within a block still counts."""
        n = raw.shape[0]
        nseg = min(10, n)
        k = n // nseg
        seg = raw[:nseg * k].reshape(nseg, k, *raw.shape[1:]).sum(axis=1)       # (S, P, 3); NaN rows are 0
        if not all_ok:
            seen = ok[:nseg * k].reshape(nseg, k, -1).any(axis=1)
            seg = np.where(seen[..., None], seg, np.nan)
        first = seg[0]
        prev = np.where(np.isnan(self._last_dir), first, self._last_dir)
        self._last_dir = np.where(np.isnan(seg[-1]), self._last_dir, seg[-1])
        a = np.concatenate([prev[None], seg[:-1]])                             # (S, P, 3)
        b = seg
        # atan2(|a × b|, a · b): accurate for small angles, scale-free (sums serve as directions)
        cx = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
        cy = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
        cz = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        ang = np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), (a * b).sum(axis=-1))
        return np.degrees(np.where(np.isnan(ang), 0.0, ang)).sum(axis=0)

    # --- solve ------------------------------------------------------------------------------

    def _solve(self, j: int) -> None:
        self._dirty[j] = False
        info = self._info[j]
        g = info[:N_GEOMETRY, :N_GEOMETRY]            # the geometry block decides conditioning
        d = np.sqrt(np.maximum(np.diag(g), 1e-300))
        ev = np.linalg.eigvalsh(g / np.outer(d, d))
        cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
        self._condition[j] = float(np.sqrt(cond))    # of Φ column-scaled, like the batch fit
        lhs = info + np.diag(self._ridge * max(self._weight[j], 1.0))
        rhs = self._eta[j]
        prior = self._floor(j)
        if prior is not None:
            lhs, rhs = lhs + prior, rhs + prior @ self._anchor_theta[j]      # (Λ + Π) θ = η + Π θa
        elif self._condition[j] > self.max_condition:
            return
        try:
            theta = cho_solve(cho_factor(lhs), rhs)
        except np.linalg.LinAlgError:
            return
        if not np.all(np.isfinite(theta)):
            return
        try:
            quadric_to_calibration(theta, self._scale[j], self._f2_ref[j])
        except np.linalg.LinAlgError:
            return                                    # not an ellipsoid (yet): keep the last estimate
        self._theta[j], self._has_theta[j] = theta, True
        if self._condition[j] <= self.max_condition:
            self._anchor_theta[j] = theta
            try:
                self._anchor_chol[j] = np.linalg.cholesky(info + np.diag(self._ridge * max(self._weight[j], 1.0)))
                self._has_anchor[j] = True
            except np.linalg.LinAlgError:
                pass                                  # keep the previous anchor

    def _solve_dirty(self) -> None:
        for j in np.flatnonzero(self._dirty):
            self._solve(int(j))

    def _floor(self, j: int) -> np.ndarray | None:
        """Π = L V diag(max(0, f − g)) Vᵀ Lᵀ (see the module docstring), None without an anchor or a deficit."""
        if not self._has_anchor[j]:
            return None
        info = self._info[j] + np.diag(self._ridge * max(self._weight[j], 1.0))
        lo = self._anchor_chol[j]
        # C = L⁻¹ Λ L⁻ᵀ by two triangular solves
        c = solve_triangular(lo, solve_triangular(lo, info, lower=True).T, lower=True)
        g, v = np.linalg.eigh(0.5 * (c + c.T))
        deficit = np.maximum(self.anchor - g, 0.0)
        if not deficit.any():
            return None
        lv = lo @ v
        return (lv * deficit) @ lv.T

    def _theta_cov(self, j: int) -> np.ndarray:
        """cov(θ) = σ² (Λ + Π)⁻¹ with σ² = weighted RSS / (Σw − k), RSS = Σw y² − 2θᵀη + θᵀΛθ: the
        information that actually holds the estimate (Π = 0 while the data determine it)."""
        th = self._theta[j]
        info = self._info[j]
        rss = max(self._y2[j] - 2 * th @ self._eta[j] + th @ info @ th, 0.0)
        dof = max(self._weight[j] - self.n_params, 1.0)
        lhs = info + np.diag(self._ridge * max(self._weight[j], 1.0))
        prior = self._floor(j)
        if prior is not None:
            lhs = lhs + prior
        try:
            # Λ⁻¹ is what the covariance is; through the Cholesky factor
            inv = cho_solve(cho_factor(lhs), np.eye(self.n_params))
        except np.linalg.LinAlgError:
            return np.full((self.n_params, self.n_params), np.nan)
        return rss / dof * inv

    def _squeeze(self, a: np.ndarray):
        return a[0] if self.n_probes is None else a

    # --- fitted results ---------------------------------------------------------------------

    @property
    def info_(self) -> np.ndarray:
        """Λ, (k, k) or (P, k, k)."""
        return self._squeeze(self._info)

    @property
    def eta_(self) -> np.ndarray:
        return self._squeeze(self._eta)

    @property
    def weight_(self):
        """Σ w: the effective number of samples in memory."""
        return self._squeeze(self._weight)

    @property
    def n_samples_(self):
        """Samples taken (NaN rows not counted), int or (P,)."""
        return int(self._n[0]) if self.n_probes is None else self._n.copy()

    @property
    def scale_(self):
        """s, nT (None / NaN before the first sample)."""
        if self.n_probes is None:
            return None if np.isnan(self._scale[0]) else float(self._scale[0])
        return self._scale.copy()

    @property
    def theta_(self) -> np.ndarray | None:
        self._solve_dirty()
        if self.n_probes is None:
            return self._theta[0].copy() if self._has_theta[0] else None
        return np.where(self._has_theta[:, None], self._theta, np.nan)

    @property
    def theta_cov_(self) -> np.ndarray:
        self._solve_dirty()
        if not self._has_theta.all():
            raise NotCalibratedError("RlsEllipsoid: no estimate yet")
        return self._squeeze(np.stack([self._theta_cov(j) for j in range(self._p)]))

    @property
    def condition_(self):
        """Condition number of the column-scaled design (inf before any sample), float or (P,)."""
        self._solve_dirty()
        return float(self._condition[0]) if self.n_probes is None else self._condition.copy()

    def _all(self, attr: str) -> np.ndarray:
        return self._squeeze(np.stack([getattr(self.snapshot(probe=j), attr) for j in range(self._p)]))

    def _linear_part(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(offset_nT, matrix) of probe j without the standard errors (cheap)."""
        self._solve_dirty()
        if not self._has_theta[j]:
            self.snapshot(probe=j)                    # raises CalibrationRefused saying why
        return quadric_to_calibration(self._theta[j], float(self._scale[j]), float(self._f2_ref[j]))

    @property
    def offset_(self) -> np.ndarray:
        """corrected = matrix_ (raw − offset_), nT; (3,) or (P, 3)."""
        return self._squeeze(np.stack([self._linear_part(j)[0] for j in range(self._p)]))

    @property
    def matrix_(self) -> np.ndarray:
        return self._squeeze(np.stack([self._linear_part(j)[1] for j in range(self._p)]))

    @property
    def offset_se_(self) -> np.ndarray:
        return self._all("offset_se_nT")

    @property
    def matrix_se_(self) -> np.ndarray:
        return self._all("matrix_se")

    def snapshot(self, name: str | None = None, probe: int = 0) -> ProbeCalibration:
        """The current estimate of one probe as a ProbeCalibration with standard errors (raises
        CalibrationRefused while the data do not determine it: never NaN parameters)."""
        self._solve_dirty()
        j = int(probe)
        name = name or f"s{j + 1}"
        if not self._has_theta[j]:
            raise CalibrationRefused(f"{name}: the online estimate is not determined yet ({int(self._n[j])} samples, "
                                     f"condition {self._condition[j]:.3g}); keep rotating about several axes")
        theta, s, f2 = self._theta[j], float(self._scale[j]), float(self._f2_ref[j])
        offset, matrix = quadric_to_calibration(theta, s, f2)
        cov = self._theta_cov(j)

        def flat(t: np.ndarray) -> np.ndarray:
            o, mm = quadric_to_calibration(t, s, f2)
            return np.concatenate([o, mm.ravel()])

        se = jacobian_se(flat, theta, cov) if np.all(np.isfinite(cov)) else None
        o_se, m_se = (np.full(3, np.nan), np.full((3, 3), np.nan)) if se is None else (se[:3], se[3:].reshape(3, 3))
        params = {"offset_nT": named(offset, o_se, "nT"),
                  "samples": named(int(self._n[j]), None, ""),
                  "memory_samples": named(float(self._weight[j]), None, "",
                                          note="effective number of samples in memory (sum of weights)"),
                  "condition": named(float(self._condition[j]), None, "")}
        return ProbeCalibration(name, offset, matrix, o_se, m_se, params)

    def snapshots(self, names: list[str] | None = None) -> list[ProbeCalibration]:
        """Every probe's snapshot."""
        names = names or [f"s{j + 1}" for j in range(self._p)]
        return [self.snapshot(nm, probe=j) for j, nm in enumerate(names)]
