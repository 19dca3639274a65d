"""Effect terms: the physical corrections fluxcal adds to a linear calibration, and how they compose.

An effect term is one small class with named parameters in physical units. Given the data of one
probe it returns regressor columns for a correction in the probe's raw frame,

    raw_corrected = raw - offset - sum_j theta_j phi_j(data)         (frame = "raw")
    corrected     = matrix @ raw_corrected                           (the linear calibration)

or, for effects that live outside the probe (platform fields, site gradient), in the corrected
frame: corrected -= sum_j theta_j psi_j(data)                        (frame = "corrected").
Terms compose with `+` in the manner of PySINDy feature libraries and lmfit models:

>>> from fluxcal.service.numerics.effects import Baseline, Temperature, Eddy
>>> model = Baseline() + Temperature() + Eddy()
>>> str(model), model.effects
('Baseline + Temperature + Eddy', ['temperature', 'eddy'])

Numerics only: no file or network I/O here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Iterable, Sequence

import numpy as np

from fluxcal.drivers.block import SampleBlock, Timed
from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.numerics.channels import AXES  # noqa: F401 - the effect terms take the axes from here
from fluxcal.service.numerics.usable import usable_samples

from .attitude import quat_to_matrix, rx, ry, rz
from .timebase import TimeBase

#: extra columns that carry the platform attitude, R = Rz(azimuth) Ry(pitch) Rx(heel), platform -> NED
ATTITUDE_EULER = ("heel_deg", "pitch_deg", "azimuth_deg")
ATTITUDE_QUATERNION = ("q_w", "q_x", "q_y", "q_z")
#: extra columns that are bookkeeping, not observables
#: extra columns of a reference vector: the field at the platform origin in the platform frame, nT
REF_VECTOR = ("ref_x", "ref_y", "ref_z")
#: the model's field along a track, NED (fluxcal.service.numerics.calib.track): bookkeeping of the reference, not a logged value
REF_DIRECTION = ("ref_north_nT", "ref_east_nT", "ref_down_nT")
NOT_OBSERVABLES = frozenset({"ref_total", "seq", "flags", *ATTITUDE_EULER, *ATTITUDE_QUATERNION, *REF_VECTOR,
                             *REF_DIRECTION})


# --- the data every term looks at -------------------------------------------------------------------


def savgol_filter(*args: Any, **kwargs: Any) -> np.ndarray:
    """scipy.signal's, imported when first asked: not at every `fluxcal` command's start (half of it)."""
    from scipy.signal import savgol_filter as savgol
    return savgol(*args, **kwargs)


@dataclass
class EffectData(Timed):
    """N samples of P probes prepared for effect fitting: raw field, time, temperature, references.

    t_s           (N,)      s, strictly increasing
    raw_nT        (N, P, 3) probe outputs in nT (no NaN: rows with a NaN are dropped by `from_block`)
    temp_C        (N, P)    probe temperatures, NaN where unknown
    ref_total_nT  (N,)      scalar reference of the total field, or None
    total_nT      float     the total field from the configuration, or None (then estimated)
    positions_m   (P, 3)    probe positions in the platform frame, or None
    extras        dict of (N,) arrays: other observables (attitude columns among them)
    smooth_window_s         Savitzky-Golay window for smoothing and dB/dt
    """

    PROBE_ARRAY = "raw_nT"

    t_s: np.ndarray
    raw_nT: np.ndarray
    temp_C: np.ndarray
    probe_names: list[str]
    ref_total_nT: np.ndarray | None = None
    total_nT: float | None = None
    positions_m: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    smooth_window_s: float = 0.1
    dropped_rows: int = 0
    #: what was left out and why, per probe (fluxcal.service.numerics.usable), for the notes
    dropped_notes: list[str] = field(default_factory=list)
    _cache: dict[Any, Any] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        n = self.t_s.shape[0]
        if self.raw_nT.ndim != 3 or self.raw_nT.shape[0] != n or self.raw_nT.shape[2] != 3:
            raise DataError(f"raw_nT: expected shape (N={n}, P, 3), got {self.raw_nT.shape}")
        if self.temp_C.shape != self.raw_nT.shape[:2]:
            raise DataError(f"temp_C: expected shape {self.raw_nT.shape[:2]}, got {self.temp_C.shape}")
        if len(self.probe_names) != self.n_probes:
            raise DataError(f"probe_names: expected {self.n_probes} names, got {len(self.probe_names)}")
        if self.positions_m is not None:
            self.positions_m = np.asarray(self.positions_m, dtype=np.float64)
            if self.positions_m.shape != (self.n_probes, 3):
                raise DataError(f"positions_m: expected shape ({self.n_probes}, 3), got {self.positions_m.shape}")
        if n < 30:
            raise DataError(f"{n} usable samples: too few to fit or diagnose anything (need at least 30)")
        if np.any(np.diff(self.t_s) <= 0):
            raise DataError("t: time must be strictly increasing")

    # -- construction --------------------------------------------------------------------------------
    @classmethod
    def from_block(cls, block: SampleBlock, probe_names: Sequence[str] | None = None, *,
                   total_nT: float | None = None, positions_m: np.ndarray | None = None,
                   smooth_window_s: float = 0.1) -> "EffectData":
        """From a SampleBlock; samples where any probe axis is NaN (saturated) are dropped and counted."""
        names = list(probe_names) if probe_names is not None else [f"s{k + 1}" for k in range(block.n_probes)]
        usable = usable_samples(block, names) if len(names) == block.n_probes else None
        good = np.all(np.isfinite(block.field_nT), axis=(1, 2)) & np.isfinite(block.t_s)
        ref = block.extras.get("ref_total")
        if ref is not None:
            good &= np.isfinite(ref)
        extras = {k: np.asarray(v, dtype=np.float64)[good] for k, v in block.extras.items()
                  if k != "ref_total"}
        return cls(t_s=np.asarray(block.t_s, dtype=np.float64)[good],
                   raw_nT=np.asarray(block.field_nT, dtype=np.float64)[good],
                   temp_C=np.asarray(block.temp_C, dtype=np.float64)[good], probe_names=names,
                   ref_total_nT=None if ref is None else np.asarray(ref, dtype=np.float64)[good],
                   total_nT=total_nT, positions_m=positions_m, extras=extras,
                   smooth_window_s=smooth_window_s, dropped_rows=int(np.count_nonzero(~good)),
                   dropped_notes=usable.notes if usable is not None else [])

    # -- shapes --------------------------------------------------------------------------------------

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def dt_s(self) -> float:
        """Median sample interval."""
        return float(np.median(np.diff(self.t_s)))

    @property
    def window_samples(self) -> int:                 # about smooth_window_s long
        return self.odd_window(self.smooth_window_s / self.dt_s)

    def odd_window(self, n: float) -> int:
        """A Savitzky-Golay window of about n samples: odd, at least 5, at most a quarter of the run."""
        return int(min(max(int(round(n)) | 1, 5), max(5, (self.n_samples // 4) | 1)))

    @property
    def edge_samples(self) -> int:
        """Samples at each end (and around gaps) where derivatives and time shifts are unreliable."""
        return self.window_samples

    @property
    def time_base(self) -> TimeBase:
        """Steady or bursty, its gaps (gap_s: a hole of a few samples in a steady one is bridged, a bursty board's
        pauses are its rhythm), and the samples' slots on a uniform grid (effects.timebase)."""
        if "time base" not in self._cache:
            self._cache["time base"] = TimeBase.of(self.t_s)
        return self._cache["time base"]

    def valid_rows(self) -> np.ndarray:
        """Rows used for fitting: away from the ends and from gaps in time (gap_s)."""
        key = "valid"
        if key not in self._cache:
            n, e = self.n_samples, self.edge_samples
            ok = np.ones(n, bool)
            ok[:e] = False
            ok[n - e:] = False
            gaps = np.flatnonzero(np.diff(self.t_s) > self.time_base.gap_s)
            for g in gaps:                                   # a loop over gaps, not samples
                ok[max(0, g - e + 1):g + e + 1] = False
            self._cache[key] = np.flatnonzero(ok)
        return self._cache[key]

    # -- cached features -----------------------------------------------------------------------------
    def _uniform(self) -> bool:
        d = np.diff(self.t_s)
        return bool(np.max(np.abs(d - self.dt_s)) <= 0.05 * self.dt_s)

    def smooth(self, k: int) -> np.ndarray:
        """(N, 3) probe k's raw output smoothed by a quadratic Savitzky-Golay filter (noise removed,
        motion kept: the window is short against a turn)."""
        key = ("smooth", k)
        if key not in self._cache:                # samples missing from a steady grid: on the grid (as derivative)
            self._cache[key] = self.time_base.filtered(self.raw_nT[:, k, :], self.window_samples)
        return self._cache[key]

    def rate(self, k: int) -> np.ndarray:
        """(N, 3) d raw/dt of probe k in nT/s: Savitzky-Golay derivative (vectorised over the run)."""
        key = ("rate", k)
        if key not in self._cache:
            self._cache[key] = self.derivative(self.raw_nT[:, k, :])
        return self._cache[key]

    def derivative(self, x: np.ndarray, window: int | None = None) -> np.ndarray:
        """d x/dt of a series x (N, ...) over `window` samples (odd; None: window_samples), as rate() takes a probe's:
        the Savitzky-Golay derivative on a uniform time base, else the gradient of the smoothed series."""
        w = self.window_samples if window is None else int(window)
        if self.time_base.holes:      # samples missing from a steady grid: on the grid, the holes interpolated
            return self.time_base.filtered(x, w, deriv=1)
        if self._uniform():
            return savgol_filter(x, w, 2, deriv=1, delta=self.dt_s, axis=0, mode="interp")
        return np.gradient(savgol_filter(x, w, 2, axis=0, mode="interp"), self.t_s, axis=0)

    def temperature(self, k: int) -> np.ndarray | None:
        """(N,) probe k's temperature, gaps (NaN) filled by interpolation in time; the mean of the
        other probes if this one has none; None if no probe has a temperature."""
        key = ("temp", k)
        if key not in self._cache:
            t = self.temp_C[:, k]
            ok = np.isfinite(t)
            if ok.sum() < 2:
                others = [j for j in range(self.n_probes) if np.isfinite(self.temp_C[:, j]).sum() >= 2]
                self._cache[key] = (np.mean([self.temperature(j) for j in others], axis=0) if others
                                    else None)
            elif ok.all():
                self._cache[key] = t.copy()
            else:
                self._cache[key] = np.interp(self.t_s, self.t_s[ok], t[ok])
        return self._cache[key]

    def has_temperature(self) -> bool:
        return self.temperature(0) is not None

    def attitude(self) -> np.ndarray | None:
        """(N, 3, 3) platform -> NED attitude from extra columns (heel/pitch/azimuth in degrees, or a
        quaternion q_w..q_z), or None when the data carry none."""
        key = "attitude"
        if key not in self._cache:
            ex = self.extras
            att = None
            if all(c in ex for c in ATTITUDE_EULER):
                h, p, a = (np.radians(ex[c]) for c in ATTITUDE_EULER)
                att = rz(a) @ ry(p) @ rx(h)
            elif all(c in ex for c in ATTITUDE_QUATERNION):
                att = quat_to_matrix(*(ex[c] for c in ATTITUDE_QUATERNION))
            self._cache[key] = att
        return self._cache[key]

    @property
    def ref_vector_nT(self) -> np.ndarray | None:
        """(N, 3) the reference vector (extra columns ref_x, ref_y, ref_z: the field at the platform origin in
        the platform frame, from a reference vector magnetometer), or None."""
        if all(c in self.extras for c in REF_VECTOR):
            return np.stack([self.extras[c] for c in REF_VECTOR], axis=1)
        return None

    def observables(self) -> dict[str, np.ndarray]:
        """Extra columns that are observables (not bookkeeping such as seq, flags, attitude)."""
        return {k: v for k, v in self.extras.items() if k not in NOT_OBSERVABLES}

    def subset(self, rows: np.ndarray) -> "EffectData":
        """The same data restricted to some rows (for benchmarks and sub-studies); caches are dropped."""
        return EffectData(t_s=self.t_s[rows], raw_nT=self.raw_nT[rows], temp_C=self.temp_C[rows],
                          probe_names=list(self.probe_names),
                          ref_total_nT=None if self.ref_total_nT is None else self.ref_total_nT[rows],
                          total_nT=self.total_nT, positions_m=self.positions_m,
                          extras={k: v[rows] for k, v in self.extras.items()},
                          smooth_window_s=self.smooth_window_s)


#: ProbeView.cache keys that hold a term's references (temperature, time origin, step instants): they
#: travel with a fitted calibration to other data; every other cache entry belongs to one data set
REF_PREFIX = "ref:"


@dataclass
class ProbeView:
    """What a term sees of probe k: the data, and the linear calibration it is fitted around.

    offset_nT, matrix: the linear calibration at the time the term is bound (the model's current
    estimate); regressors that need "raw - offset" use this offset, so a linear term stays linear.
    model_residual, model_gain: the scalar residual of the current model (N,) and its gradient with
    respect to a raw-frame correction, n^T M (N, 3); NaN outside the fitted rows. Terms that look
    for features in the residual (perming steps) use them."""

    data: EffectData
    k: int
    offset_nT: np.ndarray
    matrix: np.ndarray
    model_residual: np.ndarray | None = None
    model_gain: np.ndarray | None = None
    cache: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.data.probe_names[self.k]

    @property
    def raw_nT(self) -> np.ndarray:
        return self.data.raw_nT[:, self.k, :]

    @property
    def centred_nT(self) -> np.ndarray:
        """(N, 3) raw - offset: the linear transfer output u that non-linear terms act on."""
        return self.raw_nT - self.offset_nT

    @property
    def corrected_nT(self) -> np.ndarray:
        """(N, 3) matrix (raw - offset): the linearly calibrated field."""
        return self.centred_nT @ self.matrix.T


# --- terms and their composition ----------------------------------------------------------------------

class EffectTerm:
    """One physical effect with named parameters in physical units (subclass per effect).

    Subclasses set `name` (the catalogue name, docs/effects.md), `title` (printed name), `physical`
    (one line), `frame` and `linear`, and implement `param_names` and `columns` (linear terms) or
    `correction` and `jacobian` (non-linear terms). Shared parameters (one set for all probes) use
    `shared_names` with `shared_vcolumns` (corrected frame, per probe) or `shared_scolumns` (added to
    the reference total field of every scalar channel); shared parameters that act non-linearly (a law whose
    exponent all probes share) give `shared_vcorrection` and `shared_vjacobian` instead of `shared_vcolumns`."""

    name: ClassVar[str] = ""
    title: ClassVar[str] = ""
    physical: ClassVar[str] = ""
    frame: ClassVar[str] = "raw"           # "raw": subtracted before the matrix; "corrected": after
    linear: ClassVar[bool] = True
    #: the term finds its regressors in the residual of the model without it (ProbeView.model_residual)
    needs_residual: ClassVar[bool] = False
    #: ... and chooses them there (perming step instants): diagnose then finds them again without each
    #: held-out block, so they are never chosen on the samples they are judged on (diagnose/fits.py)
    chooses_in_residual: ClassVar[bool] = False
    #: each sample's correction depends on that sample alone (and on references kept with the calibration):
    #: the running service can add it, and correcting block by block gives the same numbers however the input
    #: is cut (no derivatives, smoothing or time shifts across samples)
    per_sample: ClassVar[bool] = False
    #: other catalogue name -> what motion or data tells the two apart
    separation: ClassVar[dict[str, str]] = {}
    #: index in param_names -> (the lowest value the physics allows, why): the fit holds it there (engine/solve.py)
    floors: ClassVar[dict[int, tuple[float, str]]] = {}

    def why_unavailable(self, data: EffectData) -> str | None:
        """None if the term can be fitted to these data, else the reason (and what would help)."""
        return None

    def rules_out(self, parameters: Sequence[Any]) -> str | None:
        """None where the fitted parameters (read by `probe` and `key`) are a shape the physics allows, else why, as
        the verdict says it ("the offset came back: a transient"): diagnose then calls it not significant."""
        return None

    def rules_out_over(self, parameters: Sequence[Any], span: Any) -> str | None:
        """As rules_out, for a shape ruled out only over the readings the data hold (`span`, a span.ReadingSpan: each
        probe axis' lowest and highest reading about its offset): a transfer that folds back within them."""
        return None

    # per-probe parameters
    def param_names(self, view: ProbeView) -> list[str]:
        return []

    def param_keys(self, view: ProbeView) -> list[tuple]:
        """What each of param_names(view) is (default: its position), as its rules read it back from a fitted
        Parameter's `key` beside its `probe` (rules_out), never from names, which are for people."""
        return [(j,) for j in range(len(self.param_names(view)))]

    def columns(self, view: ProbeView) -> np.ndarray:
        """(N, 3, m) regressors phi_j of a linear term for probe view.k."""
        raise NotImplementedError

    def start_values(self, view: ProbeView) -> np.ndarray:
        """Where the fit starts probe view.k's parameters: zero (a non-linear term may start elsewhere, e.g. a
        time constant that zero would make undetermined)."""
        return np.zeros(len(self.param_names(view)))

    def constants(self, view: ProbeView) -> dict[str, tuple[float, str]]:
        """Fixed references the parameters are defined against (name -> (value, unit)), e.g. the temperature the
        coefficients are centred on: kept with the calibration and reused on other data; held, not fitted (outputs
        show them as fixed with their value, "fixed": true in effect_params, never as undetermined)."""
        return {}

    def cached_columns(self, view: ProbeView) -> np.ndarray:
        key = f"columns:{self.name}"
        if key not in view.cache:
            view.cache[key] = self.columns(view)
        return view.cache[key]

    def correction(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) the correction sum_j theta_j phi_j."""
        if theta.size == 0:
            return np.zeros((view.data.n_samples, 3))
        return self.cached_columns(view) @ theta

    def jacobian(self, view: ProbeView, theta: np.ndarray, v0: np.ndarray | None = None) -> np.ndarray:
        """(N, 3, m) d correction / d theta at theta."""
        return self.cached_columns(view)

    # shared parameters
    def shared_names(self, data: EffectData) -> list[str]:
        return []

    def shared_vcolumns(self, data: EffectData, k: int) -> np.ndarray | None:
        """(N, 3, m) corrected-frame regressors of the shared parameters for probe k."""
        return None

    def shared_scolumns(self, data: EffectData) -> np.ndarray | None:
        """(N, m) regressors added to the reference total field in every scalar channel."""
        return None

    def shared_vcorrection(self, data: EffectData, k: int, theta: np.ndarray) -> np.ndarray | None:
        """(N, 3) the corrected-frame correction of probe k by the shared parameters theta, or None where they do not
        act on it: shared_vcolumns @ theta for a linear term; a non-linear one (a law with a shared exponent) gives
        it with shared_vjacobian."""
        cols = self.shared_vcolumns(data, k)
        return None if cols is None else cols @ theta

    def shared_start_values(self, data: EffectData) -> np.ndarray:
        """Where the fit starts the shared parameters: zero (a non-linear one may start elsewhere: an exponent)."""
        return np.zeros(len(self.shared_names(data)))

    def shared_vjacobian(self, data: EffectData, k: int, theta: np.ndarray) -> np.ndarray | None:
        """(N, 3, m) d shared_vcorrection / d theta at theta (shared_vcolumns for a linear term)."""
        return self.shared_vcolumns(data, k)

    # composition and printing
    def settings(self) -> dict[str, Any]:
        return {}

    def __add__(self, other: "EffectTerm | Model") -> "Model":
        return Model([self]) + other

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.settings().items())
        return f"{type(self).__name__}({args})"

    def __str__(self) -> str:
        return self.title or type(self).__name__


class Baseline(EffectTerm):
    """The linear calibration itself: per probe an offset (nT) and a matrix, corrected = M (raw - o).

    The fitter handles it specially (a multiplicative update of M); as a term it marks that the
    linear part is fitted together with the effects. A model without Baseline holds it fixed."""

    name = "baseline"
    title = "Baseline"
    physical = "offset and linear transfer matrix of each probe"


class Model:
    """An ordered sum of terms: Baseline() + Temperature() + Eddy()."""

    def __init__(self, terms: Iterable[EffectTerm]) -> None:
        terms = list(terms)
        names = [t.name for t in terms]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"effects: {', '.join(dup)} given twice")
        self.terms: tuple[EffectTerm, ...] = tuple(terms)

    def __add__(self, other: "EffectTerm | Model") -> "Model":
        more = other.terms if isinstance(other, Model) else (other,)
        return Model(self.terms + tuple(more))

    def __radd__(self, other: "EffectTerm") -> "Model":
        return Model((other,) + self.terms)

    @property
    def has_baseline(self) -> bool:
        return any(isinstance(t, Baseline) for t in self.terms)

    @property
    def effect_terms(self) -> list[EffectTerm]:
        return [t for t in self.terms if not isinstance(t, Baseline)]

    @property
    def effects(self) -> list[str]:
        """Catalogue names of the effect terms (the `effects` of docs/contracts.md)."""
        return [t.name for t in self.effect_terms]

    def without_baseline(self) -> "Model":
        return Model(self.effect_terms)

    def __contains__(self, name: str) -> bool:
        return any(t.name == name for t in self.terms)

    def __iter__(self):
        return iter(self.terms)

    def __len__(self) -> int:
        return len(self.terms)

    def __str__(self) -> str:
        return " + ".join(str(t) for t in self.terms) if self.terms else "(nothing)"

    def __repr__(self) -> str:
        return " + ".join(repr(t) for t in self.terms) if self.terms else "Model([])"


def axis_columns(values: np.ndarray) -> np.ndarray:
    """(N, 3) per-axis values -> (N, 3, 3) regressors, column a acting on axis a only.

    >>> axis_columns(np.array([[1.0, 2.0, 3.0]]))[0].tolist()
    [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]]
    """
    n = values.shape[0]
    out = np.zeros((n, 3, 3))
    idx = np.arange(3)
    out[:, idx, idx] = values
    return out
