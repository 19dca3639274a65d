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

from fluxcal.drivers.errors import CalibrationRefused, DataError, NotCalibratedError

from .model import ProbeCalibration, named
from .quadric import N_GEOMETRY, N_PARAMS, jacobian_se_many, quadric_to_calibration, quadric_to_calibration_many
from .rls_info import Estimates, Information


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
        self._acc = Information(p, k, forgetting=self.forgetting, forget_deg=self.forget_deg,
                                varying_total=self.varying_total, total_nT=self.total_nT)
        self._est = Estimates(self._acc, anchor=self.anchor, max_condition=self.max_condition)

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

    def partial_fit(self, field_nT: np.ndarray, total_nT=None) -> "RlsEllipsoid":
        """Update with a block of raw samples, (N, 3) or (N, P, 3); total_nT: None, a number, (N,) shared
        by the probes (one scalar reference) or (N, P). Rows holding NaN get zero weight."""
        raw = self._as_block(field_nT)
        if raw.shape[0]:
            self._est.dirty |= self._acc.add(raw, total_nT)   # solved lazily, when an estimate is asked for
        return self

    def probes(self) -> list["RlsProbe"]:
        """Each probe read, and updated alone, as an estimator of its own (RlsProbe)."""
        return [RlsProbe(self, j) for j in range(self._p)]

    # --- solve ------------------------------------------------------------------------------

    def _squeeze(self, a: np.ndarray):
        return a[0] if self.n_probes is None else a

    # --- fitted results ---------------------------------------------------------------------

    @property
    def info_(self) -> np.ndarray:
        """Λ, (k, k) or (P, k, k)."""
        return self._squeeze(self._acc.info)

    @property
    def eta_(self) -> np.ndarray:
        return self._squeeze(self._acc.eta)

    @property
    def weight_(self):
        """Σ w: the effective number of samples in memory."""
        return self._squeeze(self._acc.weight)

    @property
    def n_samples_(self):
        """Samples taken (NaN rows not counted), int or (P,)."""
        return int(self._acc.n[0]) if self.n_probes is None else self._acc.n.copy()

    @property
    def scale_(self):
        """s, nT (None / NaN before the first sample)."""
        if self.n_probes is None:
            return None if np.isnan(self._acc.scale[0]) else float(self._acc.scale[0])
        return self._acc.scale.copy()

    @property
    def origin_(self):
        """c, nT: the accumulator's origin (the first samples' mean); info_ and eta_ are about it."""
        return self._squeeze(self._acc.origin.copy())

    @property
    def center_(self) -> np.ndarray:
        """The point theta_ is taken about, nT (the weighted mean of the samples in memory at the solve)."""
        self._est.solve_dirty()
        return self._squeeze(np.stack([self._est.center_nT(j) for j in range(self._p)]))

    @property
    def theta_(self) -> np.ndarray | None:
        """θ of u = (r − center_) / scale_: uᵀA'u + b'ᵀu (− γδ) = 1."""
        self._est.solve_dirty()
        if self.n_probes is None:
            return self._est.theta[0].copy() if self._est.has_theta[0] else None
        return np.where(self._est.has_theta[:, None], self._est.theta, np.nan)

    @property
    def theta_cov_(self) -> np.ndarray:
        self._est.solve_dirty()
        if not self._est.has_theta.all():
            raise NotCalibratedError("RlsEllipsoid: no estimate yet")
        return self._squeeze(np.stack([self._est.theta_cov(j) for j in range(self._p)]))

    @property
    def condition_(self):
        """Condition number of the column-scaled design (inf before any sample), float or (P,)."""
        self._est.solve_dirty()
        return float(self._est.condition[0]) if self.n_probes is None else self._est.condition.copy()

    def _all(self, attr: str) -> np.ndarray:
        return self._squeeze(np.stack([getattr(self.snapshot(probe=j), attr) for j in range(self._p)]))

    def _linear_part(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(offset_nT, matrix) of probe j without the standard errors (cheap)."""
        self._est.solve_probe(j)
        if not self._est.has_theta[j]:
            self.snapshot(probe=j)                    # raises CalibrationRefused saying why
        return quadric_to_calibration(self._est.theta[j], float(self._acc.scale[j]), self._est.f2(j),
                                      self._est.center_nT(j))

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
        j = int(probe)
        self._est.solve_probe(j)
        name = name or f"s{j + 1}"
        if not self._est.has_theta[j]:
            raise CalibrationRefused(f"{name}: the online estimate is not determined yet ({int(self._acc.n[j])} samples, "
                                     f"condition {self._est.condition[j]:.3g}); keep rotating about several axes")
        return probe_calibration(name, self._est.theta[j], self._est.theta_cov(j), float(self._acc.scale[j]),
                                 self._est.f2(j), self._est.center_nT(j), {
                                     "samples": named(int(self._acc.n[j]), None, ""),
                                     "memory_samples": named(float(self._acc.weight[j]), None, "",
                                                             note="effective number of samples in memory "
                                                                  "(sum of weights)"),
                                     "condition": named(float(self._est.condition[j]), None, "")})

    def snapshots(self, names: list[str] | None = None) -> list[ProbeCalibration]:
        """Every probe's snapshot."""
        names = names or [f"s{j + 1}" for j in range(self._p)]
        return [self.snapshot(nm, probe=j) for j, nm in enumerate(names)]


class RlsProbe:
    """Probe j of an RlsEllipsoid of P probes as a single-probe estimator: each property solves this probe
    only (when it took samples since), and `partial_fit` updates it alone, so the estimates, anchors and
    every later update are those of P separate estimators, bit for bit (tests/numerics/test_rls_batched.py)."""

    def __init__(self, est: RlsEllipsoid, j: int) -> None:
        self.est, self.j = est, int(j)

    def partial_fit(self, field_nT: np.ndarray, total_nT=None) -> "RlsProbe":
        """Update this probe alone with (N, 3) samples: for blocks whose rows differ by probe (the
        pipeline drops a probe's NaN rows; a dropped row is not a zero-weight one: time stops for it)."""
        raw = np.asarray(field_nT, dtype=float)
        if raw.ndim != 2 or raw.shape[1] != 3:
            raise DataError(f"field_nT: expected shape (N, 3), got {raw.shape}")
        if raw.shape[0]:
            one = self.est._acc.take(self.j)
            self.est._est.dirty[self.j] |= bool(one.add(raw[:, None, :], total_nT)[0])
            self.est._acc.put(self.j, one)
        return self

    @property
    def n_samples_(self) -> int:
        return int(self.est._acc.n[self.j])

    def solve(self) -> None:
        """Solve this probe if it took samples since its last solve, as `snapshot` and every property do first (a
        solve moves the anchor: a caller that replays another's checks solves where they did)."""
        self.est._est.solve_probe(self.j)

    @property
    def condition_(self) -> float:
        self.solve()
        return float(self.est._est.condition[self.j])

    @property
    def offset_(self) -> np.ndarray:
        return self.est._linear_part(self.j)[0]

    @property
    def matrix_(self) -> np.ndarray:
        return self.est._linear_part(self.j)[1]

    @property
    def offset_se_(self) -> np.ndarray:
        return self.snapshot().offset_se_nT

    @property
    def matrix_se_(self) -> np.ndarray:
        return self.snapshot().matrix_se

    def snapshot(self, name: str | None = None) -> ProbeCalibration:
        return self.est.snapshot(name, probe=self.j)


def probe_calibration(name: str, theta: np.ndarray, cov: np.ndarray, scale: float, f2_ref: float,
                      center_nT: np.ndarray, params: dict) -> ProbeCalibration:
    """The calibration of an online estimate θ (about center_nT) with standard errors propagated from cov(θ)."""
    offset, matrix = quadric_to_calibration(theta, scale, f2_ref, center_nT)

    def flat(t: np.ndarray) -> np.ndarray:                # (M, k) -> (M, 12)
        o, mm = quadric_to_calibration_many(t, scale, f2_ref, center_nT)
        return np.concatenate([o, mm.reshape(-1, 9)], axis=1)

    se = jacobian_se_many(flat, theta, cov) if np.all(np.isfinite(cov)) else None
    o_se, m_se = (np.full(3, np.nan), np.full((3, 3), np.nan)) if se is None else (se[:3], se[3:].reshape(3, 3))
    return ProbeCalibration(name, offset, matrix, o_se, m_se, {"offset_nT": named(offset, o_se, "nT"), **params})
