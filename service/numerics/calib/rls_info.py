"""The information form of the online ellipsoid RLS, P probes at once: Λ = Σ w φφᵀ, η = Σ w φ y, Σ w y²
and Σ w in coordinates fixed by each probe's first samples, a block at a time, with forgetting that
follows the motion; and the anchor that floors it. rls.py has the estimator that solves it, and the
equations."""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from drivers.errors import DataError

from .ellipsoid import N_GEOMETRY, quadric_design, quadric_to_calibration


class Information:
    """What the online estimator knows, per probe: Λ, η, Σ w y², Σ w, the samples taken, the scale s
    (u = r / s) and F₀² fixed by the first samples, the total field assumed when none is given, and
    the last field direction (for the swept angle). See RlsEllipsoid for the settings."""

    def __init__(self, n_probes: int, n_params: int, *, forgetting: float, forget_deg: float | None,
                 varying_total: bool, total_nT: float | None) -> None:
        p, k = n_probes, n_params
        self.forgetting, self.forget_deg = forgetting, forget_deg
        self.varying_total, self.total_nT = varying_total, total_nT
        self.info = np.zeros((p, k, k))           # Λ
        self.eta = np.zeros((p, k))               # η
        self.y2 = np.zeros(p)                     # Σ w y², for the residual variance
        self.weight = np.zeros(p)                 # Σ w, the effective number of samples
        self.n = np.zeros(p, dtype=np.int64)
        self.scale = np.full(p, np.nan)           # s, nT: u = r / s, fixed by the first samples
        self.f2_ref = np.full(p, np.nan)          # F₀², nT²
        self.assumed_total = np.full(p, np.nan)   # total field assumed when none is given
        self.last_dir = np.full((p, 3), np.nan)

    def totals(self, total_nT, raw: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """F per sample and probe, (N, P)."""
        n, p = raw.shape[:2]
        t = total_nT if total_nT is not None else self.total_nT
        if t is None:
            # unknown total field: each probe's first mean raw magnitude fixes the (conventional) scale
            fresh = np.isnan(self.assumed_total) & ok.any(axis=0)
            if fresh.any():
                mag = np.linalg.norm(np.where(ok[..., None], raw, 0.0), axis=2)
                self.assumed_total[fresh] = (mag.sum(axis=0) / np.maximum(ok.sum(axis=0), 1))[fresh]
            return np.broadcast_to(self.assumed_total[None, :], (n, p))
        t = np.asarray(t, dtype=float)
        if t.ndim == 0:
            return np.full((n, p), float(t))
        if t.shape == (n,):
            return np.broadcast_to(t[:, None], (n, p))
        if t.shape == (n, p):
            return t
        raise DataError(f"total_nT: expected a number, {n} values or ({n}, {p}), got shape {t.shape}")

    def add(self, raw: np.ndarray, total_nT) -> bool:
        """Take a block (N, P, 3) of raw samples; total_nT as RlsEllipsoid.partial_fit. Returns, per probe,
        whether it saw a sample (its estimate needs solving again)."""
        n = raw.shape[0]
        ok = np.isfinite(raw).all(axis=2)
        f = self.totals(total_nT, raw, ok)
        ok &= np.isfinite(f)
        all_ok = bool(ok.all())
        if not all_ok:
            raw = np.where(ok[..., None], raw, 0.0)
            f = np.where(ok, f, 0.0)
        if np.isnan(self.scale).any():
            self.first_samples(raw, f, ok)
        live = ~np.isnan(self.scale)                 # probes that have seen a sample
        s = np.where(live, self.scale, 1.0)
        # probe-major (P, N, ·) so every probe's Φᵀ W Φ is one contiguous BLAS product
        u = raw.transpose(1, 0, 2) / s[:, None, None]
        delta = None
        if self.varying_total:
            delta = (f.T * f.T - np.where(live, self.f2_ref, 0.0)[:, None]) / (s * s)[:, None]
        phi = quadric_design(u, delta)                       # (P, N, k)
        lam = self.forgetting
        m = np.full(raw.shape[1], float(n)) if self.forget_deg is None else \
            np.minimum(n, self.swept_deg(raw, ok, all_ok) / self.forget_deg)
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
        self.info = decay[:, None, None] * self.info + np.matmul(pwt, phi)
        self.eta = decay[:, None] * self.eta + np.matmul(pwt, np.ones(n))
        wsum = w.sum(axis=1)
        self.y2 = decay * self.y2 + wsum
        self.weight = decay * self.weight + wsum
        self.n += ok.sum(axis=0)
        return ok.any(axis=0)


    def first_samples(self, raw: np.ndarray, f: np.ndarray, ok: np.ndarray) -> None:
        """Fix s (median raw magnitude) and F₀² (mean F²) of probes seeing their first samples."""
        fresh = np.isnan(self.scale) & ok.any(axis=0)
        for j in np.flatnonzero(fresh):
            rows = ok[:, j]
            self.scale[j] = float(np.median(np.linalg.norm(raw[rows, j], axis=1)))
            self.f2_ref[j] = float(np.mean(f[rows, j] ** 2))

    def swept_deg(self, raw: np.ndarray, ok: np.ndarray, all_ok: bool) -> np.ndarray:
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
        prev = np.where(np.isnan(self.last_dir), first, self.last_dir)
        self.last_dir = np.where(np.isnan(seg[-1]), self.last_dir, seg[-1])
        a = np.concatenate([prev[None], seg[:-1]])                             # (S, P, 3)
        b = seg
        # atan2(|a × b|, a · b): accurate for small angles, scale-free (sums serve as directions)
        cx = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
        cy = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
        cz = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
        ang = np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), (a * b).sum(axis=-1))
        return np.degrees(np.where(np.isnan(ang), 0.0, ang)).sum(axis=0)

    def ridged(self, j: int, ridge: np.ndarray) -> np.ndarray:
        """Λ of probe j with the ridge on γ (scaled by the samples in memory)."""
        return self.info[j] + np.diag(ridge * max(self.weight[j], 1.0))

    def rss(self, j: int, theta: np.ndarray) -> float:
        """Weighted residual sum of squares at θ: Σw y² − 2θᵀη + θᵀΛθ."""
        return max(self.y2[j] - 2 * theta @ self.eta[j] + theta @ self.info[j] @ theta, 0.0)


class Anchor:
    """The last well-conditioned estimate of each probe, θ_a, and its information Λ_a = L Lᵀ: no direction's
    information may fall below a share of Λ_a (rls.py's module docstring)."""

    def __init__(self, n_probes: int, n_params: int) -> None:
        self.theta = np.full((n_probes, n_params), np.nan)
        self.chol = np.zeros((n_probes, n_params, n_params))   # L: Λa = L Lᵀ
        self.has = np.zeros(n_probes, bool)

    def set(self, j: int, theta: np.ndarray, info: np.ndarray) -> None:
        self.theta[j] = theta
        try:
            self.chol[j] = np.linalg.cholesky(info)
            self.has[j] = True
        except np.linalg.LinAlgError:
            pass                                  # keep the previous anchor

    def floor(self, j: int, info: np.ndarray, share: float) -> np.ndarray | None:
        """Π = L V diag(max(0, f − g)) Vᵀ Lᵀ for the information `info`, None without an anchor or a deficit."""
        if not self.has[j]:
            return None
        lo = self.chol[j]
        # C = L⁻¹ Λ L⁻ᵀ by two triangular solves
        c = solve_triangular(lo, solve_triangular(lo, info, lower=True).T, lower=True)
        g, v = np.linalg.eigh(0.5 * (c + c.T))
        deficit = np.maximum(share - g, 0.0)
        if not deficit.any():
            return None
        lv = lo @ v
        return (lv * deficit) @ lv.T


class Estimates:
    """Each probe's estimate θ, solved lazily from the information (when `dirty`), floored by the anchor;
    its condition number and covariance (rls.py's module docstring has the equations)."""

    def __init__(self, acc: Information, *, anchor: float, max_condition: float) -> None:
        p, k = acc.info.shape[:2]
        self.acc, self.share, self.max_condition = acc, anchor, max_condition
        self.ridge = np.zeros(k)
        if acc.varying_total:
            self.ridge[-1] = 1e-9                 # a ridge on γ of ~1e-9 of one sample's information
        self.theta = np.full((p, k), np.nan)
        self.has_theta = np.zeros(p, bool)
        self.condition = np.full(p, np.inf)
        self.anchor = Anchor(p, k)
        self.dirty = np.zeros(p, bool)

    def solve(self, j: int) -> None:
        self.dirty[j] = False
        info = self.acc.info[j]
        g = info[:N_GEOMETRY, :N_GEOMETRY]            # the geometry block decides conditioning
        d = np.sqrt(np.maximum(np.diag(g), 1e-300))
        ev = np.linalg.eigvalsh(g / np.outer(d, d))
        cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
        self.condition[j] = float(np.sqrt(cond))    # of Φ column-scaled, like the batch fit
        lhs = self.acc.ridged(j, self.ridge)
        rhs = self.acc.eta[j]
        prior = self.anchor.floor(j, lhs, self.share)
        if prior is not None:
            lhs, rhs = lhs + prior, rhs + prior @ self.anchor.theta[j]      # (Λ + Π) θ = η + Π θa
        elif self.condition[j] > self.max_condition:
            return
        try:
            theta = cho_solve(cho_factor(lhs), rhs)
        except np.linalg.LinAlgError:
            return
        if not np.all(np.isfinite(theta)):
            return
        try:
            quadric_to_calibration(theta, self.acc.scale[j], self.acc.f2_ref[j])
        except np.linalg.LinAlgError:
            return                                    # not an ellipsoid (yet): keep the last estimate
        self.theta[j], self.has_theta[j] = theta, True
        if self.condition[j] <= self.max_condition:
            self.anchor.set(j, theta, self.acc.ridged(j, self.ridge))

    def solve_dirty(self) -> None:
        for j in np.flatnonzero(self.dirty):
            self.solve(int(j))

    def theta_cov(self, j: int) -> np.ndarray:
        """cov(θ) = σ² (Λ + Π)⁻¹ with σ² = weighted RSS / (Σw − k), RSS = Σw y² − 2θᵀη + θᵀΛθ: the
        information that actually holds the estimate (Π = 0 while the data determine it)."""
        rss = self.acc.rss(j, self.theta[j])
        dof = max(self.acc.weight[j] - self.acc.info.shape[-1], 1.0)
        lhs = self.acc.ridged(j, self.ridge)
        prior = self.anchor.floor(j, lhs, self.share)
        if prior is not None:
            lhs = lhs + prior
        try:
            # Λ⁻¹ is what the covariance is; through the Cholesky factor
            inv = cho_solve(cho_factor(lhs), np.eye(self.acc.info.shape[-1]))
        except np.linalg.LinAlgError:
            return np.full((self.acc.info.shape[-1], self.acc.info.shape[-1]), np.nan)
        return rss / dof * inv
