"""The information form of the online ellipsoid RLS, P probes at once: Λ = Σ w φφᵀ, η = Σ w φ y, Σ w y²
and Σ w in coordinates fixed by each probe's first samples, a block at a time, with forgetting that
follows the motion; and the anchor that floors it. rls.py has the estimator that solves it, and the
equations."""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from fluxcal.drivers.errors import DataError

from .quadric import N_GEOMETRY, normalise, quadric_design, quadric_to_calibration, unit_volume_total


def finite_rows(field: np.ndarray) -> np.ndarray:
    """Where all three components of (..., 3) vectors are finite, (...): isfinite(field).all(axis=-1), without
    its slow reduction over three (a sixth of the time on a block)."""
    return np.isfinite(field[..., 0]) & np.isfinite(field[..., 1]) & np.isfinite(field[..., 2])


class Information:
    """What the online estimator knows, per probe: Λ, η, Σ w y², Σ w, the samples taken, the origin c and
    scale s (u = (r − c) / s) and F₀² fixed by the first samples, the total field assumed when none is
    given, and the last field direction (for the swept angle). See RlsEllipsoid for the settings."""

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
        self.origin = np.zeros((p, 3))            # c, nT: the first samples' mean (0 until they come)
        self.scale = np.full(p, np.nan)           # s, nT: u = (r − c) / s, fixed by the first samples
        self.f2_ref = np.full(p, np.nan)          # F₀², nT²
        self.assumed_total = np.full(p, np.nan)   # total field assumed when none is given
        self.total_known = np.ones(p, bool)       # False once a block came without a total field
        self.last_dir = np.full((p, 3), np.nan)
        # where field directions are taken about, nT: the origin, then the last good estimate's centre
        self.direction_centre = np.zeros((p, 3))

    #: the per-probe state (every array has the probe axis first)
    STATE = ("info", "eta", "y2", "weight", "n", "origin", "scale", "f2_ref", "assumed_total", "total_known",
             "last_dir", "direction_centre")

    def take(self, j: int) -> "Information":
        """A copy of probe j's state as an accumulator of one probe (`put` writes it back): updating it is
        exactly what a single-probe estimator would do, bit for bit."""
        one = Information.__new__(Information)
        one.forgetting, one.forget_deg = self.forgetting, self.forget_deg
        one.varying_total, one.total_nT = self.varying_total, self.total_nT
        for name in self.STATE:
            setattr(one, name, getattr(self, name)[j:j + 1].copy())
        return one

    def put(self, j: int, one: "Information") -> None:
        for name in self.STATE:
            getattr(self, name)[j] = getattr(one, name)[0]

    def totals(self, total_nT, raw: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """F per sample and probe, (N, P)."""
        n, p = raw.shape[:2]
        t = total_nT if total_nT is not None else self.total_nT
        if t is None:
            # unknown total field: each probe's first mean raw magnitude is F₀ for δ (unused without a
            # reference); the estimate's scale is set afterwards by unit_volume_total (Estimates.f2)
            self.total_known[:] = False
            fresh = np.isnan(self.assumed_total) & ok.any(axis=0)
            if fresh.any():
                mag = np.linalg.norm(np.where(ok[..., None], raw, 0.0), axis=2)
                # each probe's sum along a contiguous row, as for a single probe (bit for bit)
                self.assumed_total[fresh] = (np.ascontiguousarray(mag.T).sum(axis=1)
                                             / np.maximum(ok.sum(axis=0), 1))[fresh]
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
        """Take a block (N, P, 3) of raw samples; total_nT as RlsEllipsoid.partial_fit. Field directions
        (for the swept angle) are taken about `direction_centre`. Returns, per probe, whether it saw a
        sample (its estimate needs solving again)."""
        n = raw.shape[0]
        ok = finite_rows(raw)
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
        u = raw.transpose(1, 0, 2) - self.origin[:, None, :]
        u /= s[:, None, None]
        delta = None
        if self.varying_total:
            delta = (f.T * f.T - np.where(live, self.f2_ref, 0.0)[:, None]) / (s * s)[:, None]
        phi = quadric_design(u, delta)                       # (P, N, k)
        lam = self.forgetting
        m = np.full(raw.shape[1], float(n)) if self.forget_deg is None else \
            np.minimum(n, self.swept_deg(raw, ok, all_ok, self.direction_centre) / self.forget_deg)
        decay = lam ** m                              # λ^m per probe
        # sample i of n is (n − 1 − i) m/n sample-steps old at the block's end: W = diag(λ^((n−1−i) m/n))
        if lam < 1.0:
            w = lam ** ((m / n)[:, None] * np.arange(n - 1, -1, -1, dtype=float)[None, :])    # (P, N)
        else:
            w = np.ones((raw.shape[1], n))
        if lam < 1.0 and self.forget_deg is not None:
            # learning follows motion too: a block that barely moved counts as m samples, not n, so
            # a long rest neither forgets nor piles weight on one direction (Λ stays balanced)
            w *= (m / n)[:, None]
        if not all_ok:
            w *= ok.T
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
        """Fix c and s (ellipsoid.normalise of the first samples) and F₀² (mean F²) of probes seeing their
        first samples. Any c will do: the solve re-centres on the samples in memory (Estimates)."""
        fresh = np.isnan(self.scale) & ok.any(axis=0)
        for j in np.flatnonzero(fresh):
            rows = ok[:, j]
            self.origin[j], self.scale[j] = normalise(raw[rows, j])
            self.direction_centre[j] = self.origin[j]
            self.f2_ref[j] = float(np.mean(f[rows, j] ** 2))

    def swept_deg(self, raw: np.ndarray, ok: np.ndarray, all_ok: bool, centre: np.ndarray) -> np.ndarray:
        """Path angle (deg) the field direction swept in each probe's frame over this block (and since
        the last one): the directions about `centre` (P, 3) of ten consecutive segment means, so noise at
        rest reads ~zero and a full revolution within a block still counts. About the centre, not zero:
        a hard-iron offset larger than the field would hide the turns."""
        n = raw.shape[0]
        nseg = min(10, n)
        k = n // nseg
        seg = raw[:nseg * k].reshape(nseg, k, *raw.shape[1:]).sum(axis=1)       # (S, P, 3); NaN rows are 0
        if all_ok:
            seg -= k * centre[None]                                             # Σ (r − c) = Σ r − k c
        else:
            counts = ok[:nseg * k].reshape(nseg, k, -1).sum(axis=1)             # (S, P) rows taken
            seg -= counts[..., None] * centre[None]
            seg = np.where(counts[..., None] > 0, seg, np.nan)
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
        # summed probe by probe along a contiguous row: the same rounding for P probes at once as for one
        return np.ascontiguousarray(np.degrees(np.where(np.isnan(ang), 0.0, ang)).T).sum(axis=1)

    def mean(self, j: int) -> np.ndarray:
        """The weighted mean of probe j's samples in memory, u units (η's x, y, z entries over Σ w)."""
        return self.eta[j][6:9] / self.weight[j] if self.weight[j] > 0 else np.zeros(3)

    def centred(self, j: int, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Λ, η and Σ w y² of probe j about the point m (u units).

        With ψ = [φ, 1] the information is G = Σ w ψψᵀ = [[Λ, η], [ηᵀ, Σw y²]] (y = 1), and a move of
        the origin is linear in ψ: ψ(u − m) = T(−m) ψ(u), so G' = T G Tᵀ exactly. The solve then fixes
        the right side 1 about a point inside the ellipsoid (Estimates.centre), as the batch fit does
        about the samples' mean; about the first samples' mean (near the surface when they saw one
        direction) or about zero (outside the ellipsoid when the hard-iron offset exceeds the field) it
        would not be."""
        k = self.info.shape[-1]
        g = np.empty((k + 1, k + 1))
        g[:k, :k], g[:k, k], g[k, :k], g[k, k] = self.info[j], self.eta[j], self.eta[j], self.y2[j]
        t = translation(-m, k)
        gc = t @ g @ t.T
        return gc[:k, :k], gc[:k, k], float(gc[k, k])


def translation(m: np.ndarray, k: int) -> np.ndarray:
    """T (k+1, k+1) with ψ(v + m) = T ψ(v), ψ = [x², y², z², 2xy, 2xz, 2yz, x, y, z, (−δ), 1] (k = 9 or 10)."""
    t = np.eye(k + 1)
    for i in range(3):                        # (v + m)² = v² + 2 m v + m²;  v + m
        t[i, 6 + i], t[i, k], t[6 + i, k] = 2 * m[i], m[i] * m[i], m[i]
    for row, (a, b) in zip((3, 4, 5), ((0, 1), (0, 2), (1, 2))):
        t[row, 6 + a], t[row, 6 + b], t[row, k] = 2 * m[b], 2 * m[a], 2 * m[a] * m[b]
    return t


class Anchor:
    """The last well-conditioned estimate of each probe and the information behind it, kept in the
    accumulator's coordinates (homogeneous: the quadric h, G = Σ w ψψᵀ) and moved to the centre of each
    solve: no direction's information may fall below a share of the anchor's (rls.py's module docstring)."""

    def __init__(self, n_probes: int, n_params: int) -> None:
        k = n_params
        self.h = np.full((n_probes, k + 1), np.nan)          # [θ, −1] moved to the accumulator's origin
        self.g = np.zeros((n_probes, k + 1, k + 1))
        self.has = np.zeros(n_probes, bool)

    def set(self, j: int, theta: np.ndarray, m: np.ndarray, g_centred: np.ndarray) -> None:
        """θ and its information (k+1 square, about m) become the anchor."""
        k = theta.size
        t = translation(-m, k)                   # ψ(u − m) = T ψ(u): h_u = Tᵀ h_m, G_u = T⁻¹ G_m T⁻ᵀ
        self.h[j] = t.T @ np.append(theta, -1.0)
        back = translation(m, k)
        self.g[j] = back @ g_centred @ back.T
        self.has[j] = True

    def inside(self, j: int, m: np.ndarray) -> tuple[np.ndarray, float] | None:
        """The anchor ellipsoid's centre (u units) and the relative radius of m in it ((m − o)ᵀA(m − o)
        over its value on the surface: 0 at the centre, 1 on the surface); None without an anchor."""
        if not self.has[j]:
            return None
        h = self.h[j]
        a = np.array([[h[0], h[3], h[4]], [h[3], h[1], h[5]], [h[4], h[5], h[2]]])
        try:
            o = -0.5 * np.linalg.solve(a, h[6:9])
        except np.linalg.LinAlgError:
            return None
        surface = o @ a @ o - h[-1]
        return (o, float((m - o) @ a @ (m - o) / surface)) if surface != 0 else None

    def floor(self, j: int, info: np.ndarray, m: np.ndarray, share: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(Π, θ_a) about m for the information `info` (about m), None without an anchor or a deficit:
        Π = L V diag(max(0, f − g)) Vᵀ Lᵀ with Λ_a = L Lᵀ."""
        if not self.has[j]:
            return None
        k = info.shape[0]
        t = translation(-m, k)
        ga = t @ self.g[j] @ t.T
        h = translation(m, k).T @ self.h[j]
        if not abs(h[k]) > 0:
            return None
        try:
            lo = np.linalg.cholesky(ga[:k, :k])
        except np.linalg.LinAlgError:
            return None
        # C = L⁻¹ Λ L⁻ᵀ by two triangular solves
        c = solve_triangular(lo, solve_triangular(lo, info, lower=True).T, lower=True)
        g, v = np.linalg.eigh(0.5 * (c + c.T))
        deficit = np.maximum(share - g, 0.0)
        if not deficit.any():
            return None
        lv = lo @ v
        return (lv * deficit) @ lv.T, h[:k] / -h[k]


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
        self.center = np.zeros((p, 3))            # m, u units: the centre θ is taken about (Information.centred)
        self.anchor = Anchor(p, k)
        self.dirty = np.zeros(p, bool)

    #: the weighted mean of memory is the centre of the solve while it lies this deep inside the last good
    #: ellipsoid (relative radius²); nearer its surface (a long rest, one turn) the ellipsoid's own centre
    INSIDE = 0.25

    def centre(self, j: int) -> np.ndarray:
        """Where the solve fixes its right side 1 (u units): the weighted mean of the samples in memory,
        which makes the estimate without forgetting exactly the batch fit (taken about the samples' mean);
        the last good estimate's centre when that mean lies near its surface (memory of one direction)."""
        m = self.acc.mean(j)
        inside = self.anchor.inside(j, m)
        if inside is not None and not 0.0 <= inside[1] < self.INSIDE:
            return inside[0]
        return m

    def solve(self, j: int) -> None:
        self.dirty[j] = False
        m = self.centre(j)
        info, eta, y2 = self.acc.centred(j, m)
        g = info[:N_GEOMETRY, :N_GEOMETRY]            # the geometry block decides conditioning
        d = np.sqrt(np.maximum(np.diag(g), 1e-300))
        ev = np.linalg.eigvalsh(g / np.outer(d, d))
        cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
        self.condition[j] = float(np.sqrt(cond))    # of Φ column-scaled, like the batch fit
        lhs = info + np.diag(self.ridge * max(self.acc.weight[j], 1.0))
        rhs = eta
        floor = self.anchor.floor(j, lhs, m, self.share)
        if floor is not None:
            prior, theta_a = floor
            lhs, rhs = lhs + prior, rhs + prior @ theta_a                    # (Λ + Π) θ = η + Π θa
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
        self.theta[j], self.has_theta[j], self.center[j] = theta, True, m
        if self.condition[j] <= self.max_condition:
            self.acc.direction_centre[j] = self.acc.origin[j] + self._quadric_centre(theta, m) * self.acc.scale[j]
            k = theta.size
            gc = np.empty((k + 1, k + 1))
            gc[:k, :k], gc[:k, k], gc[k, :k], gc[k, k] = (info + np.diag(self.ridge * max(self.acc.weight[j], 1.0)),
                                                          eta, eta, y2)
            self.anchor.set(j, theta, m, gc)

    @staticmethod
    def _quadric_centre(theta: np.ndarray, m: np.ndarray) -> np.ndarray:
        """The centre of the quadric θ (about m), in the accumulator's u units."""
        a = np.array([[theta[0], theta[3], theta[4]], [theta[3], theta[1], theta[5]], [theta[4], theta[5], theta[2]]])
        return m - 0.5 * np.linalg.solve(a, theta[6:9])

    def solve_probe(self, j: int) -> None:
        """Solve probe j if it took samples since its last solve (the others wait until asked for:
        a solve moves the anchor, so each probe is solved exactly when a single-probe estimator would be)."""
        if self.dirty[j]:
            self.solve(j)

    def solve_dirty(self) -> None:
        for j in np.flatnonzero(self.dirty):
            self.solve(int(j))

    def f2(self, j: int) -> float:
        """F₀² of probe j's estimate: the given field's, or for an unknown field the one that gives the
        matrix determinant 1 (ellipsoid.unit_volume_total), as the batch fit assumes."""
        if self.acc.total_known[j]:
            return float(self.acc.f2_ref[j])
        return unit_volume_total(self.theta[j], float(self.acc.scale[j]), self.center_nT(j)) ** 2

    def center_nT(self, j: int) -> np.ndarray:
        """The point the estimate θ of probe j is taken about, nT: u = (r − this) / s."""
        return self.acc.origin[j] + self.center[j] * self.acc.scale[j]

    def theta_cov(self, j: int) -> np.ndarray:
        """cov(θ) = σ² (Λ + Π)⁻¹ with σ² = weighted RSS / (Σw − k), RSS = Σw y² − 2θᵀη + θᵀΛθ (about the
        centre of the solve): the information that actually holds the estimate (Π = 0 while the data
        determine it)."""
        k = self.acc.info.shape[-1]
        th = self.theta[j]
        m = self.center[j]
        info, eta, y2 = self.acc.centred(j, m)
        rss = max(y2 - 2 * th @ eta + th @ info @ th, 0.0)
        dof = max(self.acc.weight[j] - k, 1.0)
        lhs = info + np.diag(self.ridge * max(self.acc.weight[j], 1.0))
        floor = self.anchor.floor(j, lhs, m, self.share)
        if floor is not None:
            lhs = lhs + floor[0]
        try:
            # Λ⁻¹ is what the covariance is; through the Cholesky factor
            inv = cho_solve(cho_factor(lhs), np.eye(k))
        except np.linalg.LinAlgError:
            return np.full((k, k), np.nan)
        return rss / dof * inv
