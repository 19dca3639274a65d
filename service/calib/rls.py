"""Online recursive least squares of the ellipsoid, in information form, updated a block at a time.

Same quadric, scaling and right side as the batch fit (ellipsoid.py: uᵀA'u + b'ᵀu − γδ = 1), so
the two agree. The δ column (reference field variation) is used only when asked for
(`varying_total=True`, e.g. a survey with a proton magnetometer over a changing field): with a
nearly steady F it is nearly constant, and a constant column brings back the null direction the
nine-term form avoids. With a
forgetting factor λ per sample, a block of n samples updates

    Λ ← λⁿ Λ + Φᵀ W Φ,   η ← λⁿ η + Φᵀ W y,   W = diag(λ^(n−1−i)),

which equals n single-sample updates exactly (in exact arithmetic) at the cost of one matrix
product. θ solves Λ θ = η (Cholesky, never an inverse). Effective memory ≈ 1 / (1 − λ) samples.

No excitation (a platform at rest) makes Λ lose information in every direction but the one being
seen; plain RLS then winds up. Two guards:
- forgetting follows motion: a block forgets λ^m with m = min(n, swept angle / `forget_deg`), so a
  platform at rest forgets nothing and its samples only add information where they are;
- the solve is anchored to the last well-conditioned estimate θ_a with a small share μ of the
  information it had:  (Λ + μ Λ_a) θ = η + μ Λ_a θ_a, so no solve can go singular or NaN.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from drivers.errors import CalibrationRefused, NotCalibratedError

from .ellipsoid import N_GEOMETRY, N_PARAMS, quadric_design, quadric_to_calibration
from .model import ProbeCalibration


class RlsEllipsoid:
    """Online ellipsoid estimator for one probe.

    forgetting: λ per sample (1.0 = growing memory, equal to the batch fit).
    anchor: μ, the share of the last good information that holds unobserved directions.
    max_condition: a solve is accepted as the new anchor only below this condition number.
    """

    def __init__(self, *, forgetting: float = 0.9995, anchor: float = 1e-3, max_condition: float = 200.0,
                 total_nT: float | None = None, varying_total: bool = False,
                 forget_deg: float | None = 0.05) -> None:
        self.forgetting = forgetting
        self.forget_deg = forget_deg
        self.varying_total = varying_total
        self.n_params = N_PARAMS if varying_total else N_GEOMETRY
        self.anchor = anchor
        self.max_condition = max_condition
        self.total_nT = total_nT
        self.reset()

    def reset(self) -> None:
        self.scale_: float | None = None
        self.info_ = np.zeros((self.n_params, self.n_params))
        self.eta_ = np.zeros(self.n_params)
        self.y2_ = 0.0                 # Σ w y², for the residual variance
        self.f2_ref_: float | None = None   # F₀², fixed at the first block
        self.weight_ = 0.0             # Σ w, the effective number of samples
        self.n_samples_ = 0
        self._theta: np.ndarray | None = None
        self._condition = float("inf")
        self._dirty = False
        self._anchor_theta: np.ndarray | None = None
        self._anchor_info: np.ndarray | None = None
        self._last_dir: np.ndarray | None = None

    def fit(self, field_nT: np.ndarray, total_nT=None) -> "RlsEllipsoid":
        self.reset()
        return self.partial_fit(field_nT, total_nT)

    def partial_fit(self, field_nT: np.ndarray, total_nT=None) -> "RlsEllipsoid":
        """Update with a block of (n, 3) raw samples (rows with NaN are skipped)."""
        raw = np.asarray(field_nT, dtype=float)
        if raw.ndim != 2 or raw.shape[1] != 3:
            raise ValueError(f"field_nT: expected shape (n, 3), got {raw.shape}")
        ok = np.isfinite(raw).all(axis=1)
        f = self._total(total_nT, raw)
        ok &= np.isfinite(f)
        if not ok.all():
            raw, f = raw[ok], f[ok]
        n = raw.shape[0]
        if n == 0:
            return self
        if self.scale_ is None:
            self.scale_ = float(np.median(np.linalg.norm(raw, axis=1)))
            self.f2_ref_ = float(np.mean(f * f))
            # a ridge on γ (the δ column) of ~1e-9 of the information of one sample's geometry
            self._ridge = np.zeros(self.n_params)
            if self.varying_total:
                self._ridge[-1] = 1e-9
        s = self.scale_
        phi = quadric_design(raw / s, (f * f - self.f2_ref_) / s ** 2 if self.varying_total else None)
        y = np.ones(n)
        lam = self.forgetting
        m = n if self.forget_deg is None else min(n, self._swept_deg(raw) / self.forget_deg)
        decay = lam ** m
        # within the block, sample i is m/n sample-steps older per step than the next
        w = lam ** (np.arange(n - 1, -1, -1, dtype=float) * (m / n)) if lam < 1.0 else np.ones(n)
        pw = phi * w[:, None]
        # Λ ← λⁿ Λ + Φᵀ W Φ ;  η ← λⁿ η + Φᵀ W y
        self.info_ = decay * self.info_ + pw.T @ phi
        self.eta_ = decay * self.eta_ + pw.T @ y
        self.y2_ = decay * self.y2_ + float(w @ (y * y))
        self.weight_ = decay * self.weight_ + float(w.sum())
        self.n_samples_ += n
        self._dirty = True             # solved lazily, when an estimate is asked for
        return self

    def _swept_deg(self, raw: np.ndarray) -> float:
        """Angle the field direction swept over this block (and since the last one), in degrees;
        averaged over tenths of the block so noise at rest reads as nearly zero."""
        k = max(1, raw.shape[0] // 10)
        first = raw[:k].mean(axis=0)
        last = raw[-k:].mean(axis=0)
        prev = self._last_dir if self._last_dir is not None else first
        self._last_dir = last

        def angle(a: np.ndarray, b: np.ndarray) -> float:
            c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
            return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

        return angle(prev, first) + angle(first, last)

    @property
    def theta_(self) -> np.ndarray | None:
        if self._dirty:
            self._dirty = False
            self._solve()
        return self._theta

    @property
    def condition_(self) -> float:
        self.theta_
        return self._condition

    def _total(self, total_nT, raw: np.ndarray) -> np.ndarray:
        t = total_nT if total_nT is not None else self.total_nT
        if t is None:
            # unknown total field: the mean raw magnitude fixes the (conventional) scale
            if not hasattr(self, "_assumed_total"):
                self._assumed_total = float(np.mean(np.linalg.norm(raw[np.isfinite(raw).all(axis=1)], axis=1)))
            t = self._assumed_total
        t = np.asarray(t, dtype=float)
        return np.full(raw.shape[0], float(t)) if t.ndim == 0 else t

    def _solve(self) -> None:
        g = self.info_[:N_GEOMETRY, :N_GEOMETRY]            # the geometry block decides conditioning
        d = np.sqrt(np.maximum(np.diag(g), 1e-300))
        info_n = g / np.outer(d, d)
        ev = np.linalg.eigvalsh(info_n)
        cond = float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")
        self._condition = float(np.sqrt(cond)) if np.isfinite(cond) else cond   # of Φ, like the batch fit
        lhs, rhs = self.info_ + np.diag(self._ridge * max(self.weight_, 1.0)), self.eta_
        if self._anchor_info is not None:
            # (Λ + μ Λa) θ = η + μ Λa θa
            lhs = lhs + self.anchor * self._anchor_info
            rhs = rhs + self.anchor * self._anchor_info @ self._anchor_theta
        elif self._condition > self.max_condition:
            return
        try:
            theta = cho_solve(cho_factor(lhs), rhs)
        except np.linalg.LinAlgError:
            return
        if not np.all(np.isfinite(theta)):
            return
        try:
            quadric_to_calibration(theta, self.scale_, self._f2_mean())
        except np.linalg.LinAlgError:
            return                      # not an ellipsoid (yet): keep the last estimate
        self._theta = theta
        if self._condition <= self.max_condition:
            self._anchor_theta = theta.copy()
            self._anchor_info = self.info_.copy()

    def _f2_mean(self) -> float:
        return self.f2_ref_ if self.f2_ref_ is not None else 1.0

    @property
    def theta_cov_(self) -> np.ndarray:
        """cov(θ) = σ² Λ⁻¹ with σ² from the weighted residual sum of squares."""
        if self.theta_ is None:
            raise NotCalibratedError("RlsEllipsoid: no estimate yet")
        th = self.theta_
        rss = max(self.y2_ - 2 * th @ self.eta_ + th @ self.info_ @ th, 0.0)
        dof = max(self.weight_ - self.n_params, 1.0)
        try:
            inv = cho_solve(cho_factor(self.info_ + np.diag(self._ridge * max(self.weight_, 1.0))), np.eye(self.n_params))
        except np.linalg.LinAlgError:
            return np.full((self.n_params, self.n_params), np.nan)
        return rss / dof * inv

    @property
    def offset_(self) -> np.ndarray:
        return self.snapshot().offset_nT

    @property
    def matrix_(self) -> np.ndarray:
        return self.snapshot().matrix

    def snapshot(self, name: str = "s1") -> ProbeCalibration:
        """The current estimate as a ProbeCalibration with standard errors."""
        if self.theta_ is None:
            raise CalibrationRefused(f"{name}: the online estimate is not determined yet "
                                     f"({self.n_samples_} samples; keep rotating about several axes)")
        from .ellipsoid import _propagate

        f2m = self._f2_mean()
        offset, matrix = quadric_to_calibration(self.theta_, self.scale_, f2m)
        cov = self.theta_cov_
        o_se, m_se = _propagate(self.theta_, cov, self.scale_, f2m) if np.all(np.isfinite(cov)) else \
            (np.full(3, np.nan), np.full((3, 3), np.nan))
        params = {"offset_nT": {"value": offset.tolist(), "se": o_se.tolist(), "unit": "nT"},
                  "samples": {"value": self.n_samples_, "se": None, "unit": ""}}
        return ProbeCalibration(name, offset, matrix, o_se, m_se, params)
