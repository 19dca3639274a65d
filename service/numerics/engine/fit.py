"""Fitting a linear calibration plus effect terms to the residual channels, by Gauss-Newton.

Residual channels (CONTRACTS.md §3), for probes k = 1..P with y_k = raw_k - o_k - sum theta phi:

    v_k        = M_k y_k - sum (corrected-frame corrections)          the corrected field
    s<k>.scalar: |v_k| - F(t)                                          F: ref_total, configured or estimated
    s<k>-s1.a  : (v_k - v_1)_a, a = x, y, z                            arrays only, aligned differences

Each iteration linearises around the current estimate and solves one weighted linear least
squares (weights 1/noise per channel):

    J = [d r / d(o, M, theta)],  d s_k = n_k^T dv_k,  dv_k/do = -M,  dv_k/dX_ij = e_i (M y)_j,
    dv_k/dtheta = -M phi        (raw-frame terms),  -psi (corrected-frame terms)

with M_k <- (I + X_k) M_k, X symmetric for probe 1 (the common frame's rotation is free) and
general for the others (their rotation to probe 1 is the alignment). The normal equations are
accumulated per contiguous time block, so held-out fits of K-1 blocks cost one small solve each.
Standard errors come from the final normal matrix. Numerics only, no I/O.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from drivers.block import SampleBlock
from drivers.errors import CalibrationRefused, DataError

from service.numerics.effects.base import AXES, REF_PREFIX, Baseline, EffectData, EffectTerm, Model, ProbeView
from service.numerics.effects.hysteresis import robust_noise

#: eigenvalues of the column-scaled normal matrix below this fraction of the largest are a null space: a
#: direction in which the columns are collinear to R^2 > 1 - 1e-7. Measured: directions the data cannot
#: determine (lag against an isotropic eddy, a gradient under a single-axis turn) sit at 1e-10..1e-8,
#: lifted off zero by noise and by the curvature of |B|; weak but real ones (a lag's second-order
#: signature at a fast turn) at 4e-7 and above. Kept in the fit, the former promise large gains that
#: the linearisation cannot deliver.
RANK_TOL = 1e-7
#: a step is final when the actual RSS matches the linearised prediction so closely that the
#: parameters are within this many standard errors of the minimum
LINEARITY_SE = 0.1
#: an iteration lowering the weighted RSS by less than this many s^2 ends the fit (flat directions only)
RSS_TOL = 0.01
#: floor of the per-channel noise used as weight, nT (the ADC step of the unit)
NOISE_FLOOR_NT = 1e-3


# --- the linear part ---------------------------------------------------------------------------------

@dataclass
class LinearCalibration:
    """Per probe: corrected = matrix (raw - offset_nT), in the common frame (probe 1's)."""

    offset_nT: np.ndarray      # (P, 3)
    matrix: np.ndarray         # (P, 3, 3)

    def copy(self) -> "LinearCalibration":
        return LinearCalibration(self.offset_nT.copy(), self.matrix.copy())

    @classmethod
    def from_any(cls, cal: Any, n_probes: int) -> "LinearCalibration":
        """From an ArrayCalibration (service.numerics.calib.model), a list of ProbeCalibration, a CONTRACTS §3
        `fit --json` dict (sensors: offset_nT, matrix), or a LinearCalibration."""
        if isinstance(cal, LinearCalibration):
            return cal.copy()
        probes = None
        if isinstance(cal, dict):
            probes = cal.get("sensors") or cal.get("probes")
        else:
            for attr in ("probes", "sensors", "calibrations"):
                if hasattr(cal, attr):
                    probes = getattr(cal, attr)
                    break
            if probes is None and isinstance(cal, (list, tuple)):
                probes = cal
        if probes is None:
            raise DataError(f"calibration: cannot read offsets and matrices from a {type(cal).__name__}")
        probes = list(probes)
        if len(probes) != n_probes:
            raise DataError(f"calibration: it has {len(probes)} probes, the data have {n_probes}")
        off, mat = [], []
        for p in probes:
            get = p.get if isinstance(p, dict) else (lambda k, _p=p: getattr(_p, k, None))
            o, m = get("offset_nT"), get("matrix")
            if o is None or m is None:
                raise DataError("calibration: a probe entry lacks offset_nT or matrix")
            off.append(np.asarray(o, dtype=np.float64).reshape(3))
            mat.append(np.asarray(m, dtype=np.float64).reshape(3, 3))
        return cls(np.array(off), np.array(mat))


def _algebraic_ellipsoid(raw: np.ndarray, total_nT: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Offset and symmetric matrix from a least-squares quadric through the points (a start only).

    x^T Q x + b^T x = 1 (scaled coordinates); o = -Q^-1 b / 2; M = F sqrtm(Q / (1 + o^T Q o))."""
    scale = float(np.median(np.linalg.norm(raw - raw.mean(0), axis=1))) or 1.0
    c = raw.mean(0)
    x = (raw - c) / scale
    design = np.column_stack([x[:, 0] ** 2, x[:, 1] ** 2, x[:, 2] ** 2, 2 * x[:, 0] * x[:, 1],
                              2 * x[:, 0] * x[:, 2], 2 * x[:, 1] * x[:, 2], x])
    sol, *_ = np.linalg.lstsq(design, np.ones(x.shape[0]), rcond=None)
    q = np.array([[sol[0], sol[3], sol[4]], [sol[3], sol[1], sol[5]], [sol[4], sol[5], sol[2]]])
    ok = bool(np.all(np.linalg.eigvalsh(q) > 0))
    if ok:
        o = -0.5 * np.linalg.solve(q, sol[6:9])
        q = q / (1.0 + o @ q @ o)
        w, v = np.linalg.eigh(q)
        ok = bool(np.all(w > 0))
    if not ok:
        # turns about one axis (or too few directions): a plain centre and unit shape as the start
        o = np.zeros(3)
        m = np.eye(3)
    else:
        m = (v * np.sqrt(w)) @ v.T
    offset = c + scale * o
    mags = np.linalg.norm((raw - offset) @ m.T, axis=1)
    target = total_nT if total_nT is not None else float(np.median(np.linalg.norm(raw - offset, axis=1)))
    return offset, m * (target / float(np.median(mags)))


def initial_linear(data: EffectData, reference_nT: np.ndarray | float | None) -> LinearCalibration:
    """A starting linear calibration: an ellipsoid per probe (service.numerics.calib when present), then each
    probe regressed onto probe 1 (paper 000 eq. 10-16) for the alignment. Gauss-Newton refines it."""
    f_total = None if reference_nT is None else float(np.median(reference_nT))
    offs, mats = [], []
    try:
        from service.numerics.calib.ellipsoid import fit_ellipsoid      # the calibration core, when it exists
    except Exception:                                          # noqa: BLE001 - optional collaborator
        fit_ellipsoid = None
    for k in range(data.n_probes):
        raw = data.raw_nT[:, k, :]
        o = m = None
        if fit_ellipsoid is not None and reference_nT is not None:
            try:
                # refuses planar data (a single-axis turn): then our own start, which GN refines
                with warnings.catch_warnings(), np.errstate(all="ignore"):
                    warnings.simplefilter("ignore")
                    res = fit_ellipsoid(raw, reference_nT, name=data.probe_names[k])
                cal = getattr(res, "calibration", res)
                o = np.asarray(cal.offset_nT, dtype=np.float64).reshape(3)
                m = np.asarray(cal.matrix, dtype=np.float64).reshape(3, 3)
            except Exception:                                  # noqa: BLE001 - fall back to our own start
                o = m = None
        if o is None or not np.all(np.isfinite(m)):
            o, m = _algebraic_ellipsoid(raw, f_total)
        offs.append(o)
        mats.append(m)
    cal = LinearCalibration(np.array(offs), np.array(mats))
    vref = data.ref_vector_nT
    if data.n_probes > 1 or vref is not None:
        # align to the reference vector when there is one, else to probe 1
        v1 = vref if vref is not None else (data.raw_nT[:, 0, :] - cal.offset_nT[0]) @ cal.matrix[0].T
        for k in range(0 if vref is not None else 1, data.n_probes):
            vk = (data.raw_nT[:, k, :] - cal.offset_nT[k]) @ cal.matrix[k].T
            design = np.column_stack([vk, np.ones(vk.shape[0])])
            # v1 = A vk + b: regression of probe k onto probe 1
            sol, *_ = np.linalg.lstsq(design, v1, rcond=None)
            a = sol[:3].T
            cal.matrix[k] = a @ cal.matrix[k]
            # fold b into the offset: A M (raw - o) + b = A M (raw - o + (A M)^-1 b)
            cal.offset_nT[k] = cal.offset_nT[k] - np.linalg.solve(cal.matrix[k], sol[3])
    return cal


# --- state and layout -----------------------------------------------------------------------------------

@dataclass
class State:
    """Everything being fitted: the linear part and the effect parameters."""

    linear: LinearCalibration
    theta: dict[str, list[np.ndarray]]       # term name -> per-probe parameter vectors
    shared: dict[str, np.ndarray]            # term name -> shared parameter vector

    def copy(self) -> "State":
        return State(self.linear.copy(), {k: [a.copy() for a in v] for k, v in self.theta.items()},
                     {k: v.copy() for k, v in self.shared.items()})


@dataclass
class _Slot:
    kind: str                        # "offset", "matrix", "term", "shared"
    k: int | None                    # probe, None for shared
    term: EffectTerm | None
    names: list[str]
    start: int = 0

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def stop(self) -> int:
        return self.start + self.size


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


@dataclass
class Channels:
    """Residual channels of a model on the fitted rows: names, values (rows, C) in nT, time."""

    names: list[str]
    values: np.ndarray
    t_s: np.ndarray
    rows: np.ndarray

    @property
    def rms_nT(self) -> np.ndarray:
        return np.sqrt(np.mean(self.values ** 2, axis=0))

    @property
    def total_rms_nT(self) -> float:
        """RMS over all channels (CONTRACTS §3 rms_nT)."""
        return float(np.sqrt(np.mean(self.values ** 2)))

    def as_dict(self) -> dict[str, np.ndarray]:
        return {n: self.values[:, i] for i, n in enumerate(self.names)}


def channel_names(probe_names: Sequence[str], vector: bool = False) -> list[str]:
    """['s1.scalar', ..., 's2-s1.x', 's2-s1.y', 's2-s1.z', ...] and, with a reference vector, 's1-ref.x', ...

    >>> channel_names(["s1", "s2"])
    ['s1.scalar', 's2.scalar', 's2-s1.x', 's2-s1.y', 's2-s1.z']
    >>> channel_names(["s1"], vector=True)
    ['s1.scalar', 's1-ref.x', 's1-ref.y', 's1-ref.z']
    """
    names = [f"{p}.scalar" for p in probe_names]
    for p in probe_names[1:]:
        names += [f"{p}-{probe_names[0]}.{a}" for a in AXES]
    if vector:
        for p in probe_names:
            names += [f"{p}-ref.{a}" for a in AXES]
    return names


@dataclass
class _Eval:
    v0: list[np.ndarray]           # full length (N, 3) per probe, before corrected-frame corrections
    v: list[np.ndarray]            # rows (M, 3)
    nhat: list[np.ndarray]         # rows (M, 3)
    scalar: np.ndarray             # (M, P)
    diff: np.ndarray               # (M, P-1, 3)
    vec: np.ndarray | None = None  # (M, P, 3) corrected minus the reference vector
    _matrix: np.ndarray | None = field(default=None, repr=False)

    def channel_matrix(self) -> np.ndarray:
        """(M, C) every residual channel (built once; treat as read-only)."""
        if self._matrix is None:
            m = self.scalar.shape[0]
            parts = [self.scalar, self.diff.reshape(m, -1)]
            if self.vec is not None:
                parts.append(self.vec.reshape(m, -1))
            self._matrix = np.concatenate(parts, axis=1)
        return self._matrix


#: bytes of one chunk of Jacobian rows (3 rows per sample, 8 bytes per column): well under glibc's 32 MiB
#: mmap threshold, so the allocator reuses memory instead of faulting fresh pages in every time, and
#: large enough that per-chunk Python work stays small
CHUNK_BYTES = 12 * 2 ** 20
CHUNK_SAMPLES = 4096


def _chunks(block: slice, n_params: int = 0) -> list[slice]:
    """A time block cut into chunks of at most ~CHUNK_BYTES of Jacobian (CHUNK_SAMPLES if n_params is 0)."""
    size = CHUNK_SAMPLES if n_params <= 0 else int(np.clip(CHUNK_BYTES // (24 * n_params), 1024, 65536))
    return [slice(a, min(a + size, block.stop)) for a in range(block.start, block.stop, size)]


@dataclass
class _Jac:
    """The Jacobian's sources at one state (built block by block by Problem._block)."""

    state: "State"
    ev: _Eval
    sources: list[Any]


def _solve(a: np.ndarray, g: np.ndarray, damping: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """delta = -(A + damping diag A)^+ g on the column-scaled system (Levenberg-Marquardt when damping > 0),
    the diagonal of A^+, the undetermined mask and the rank."""
    p = a.shape[0]
    if p == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, bool), 0
    d = np.sqrt(np.clip(np.diag(a), 0.0, None))
    zero = d <= 0
    d[zero] = 1.0
    a_s = a / np.outer(d, d)
    lam, vec = np.linalg.eigh(a_s)
    top = lam[-1] if lam[-1] > 0 else 1.0
    keep = lam > RANK_TOL * top
    vk = vec[:, keep]
    delta = -(vk @ ((vk.T @ (g / d)) / (lam[keep] + damping))) / d
    cov_diag = (vk ** 2 / lam[keep]).sum(axis=1) / d ** 2
    null = (vec[:, ~keep] ** 2).sum(axis=1)
    undetermined = zero | (null > 0.01)
    return delta, cov_diag, undetermined, int(keep.sum())


class Problem:
    """Data, model and weights: residual channels, Jacobian and block normal equations."""

    def __init__(self, data: EffectData, model: Model, bind: LinearCalibration, reference_nT: np.ndarray, *,
                 weights: np.ndarray | None = None, n_blocks: int = 8,
                 hints: tuple[list[np.ndarray], list[np.ndarray]] | None = None,
                 rows: np.ndarray | None = None) -> None:
        self.data = data
        self.model = model
        self.fit_linear = model.has_baseline
        self.terms = model.effect_terms
        self.P = data.n_probes
        self.rows = data.valid_rows() if rows is None else np.asarray(rows)
        self.M = int(self.rows.size)
        if self.M < 20:
            raise DataError(f"only {self.M} samples left away from the ends and gaps: too few to fit")
        self.reference = np.broadcast_to(np.asarray(reference_nT, dtype=np.float64), (data.n_samples,))[self.rows]
        self.views = [ProbeView(data, k, bind.offset_nT[k].copy(), bind.matrix[k].copy(),
                                None if hints is None else hints[0][k], None if hints is None else hints[1][k])
                      for k in range(self.P)]
        edges = np.linspace(0, self.M, n_blocks + 1).round().astype(int)
        self.blocks = [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        vref = data.ref_vector_nT
        self.vref = None if vref is None else vref[self.rows]
        self.channel_names = channel_names(data.probe_names, vector=self.vref is not None)
        self.C = len(self.channel_names)
        self.vec0 = self.P + 3 * (self.P - 1)              # first vector-reference channel
        self.weights = np.ones(self.C) if weights is None else np.asarray(weights, dtype=np.float64)
        self.slots = self._layout()
        self.n_params = self.slots[-1].stop if self.slots else 0

    # -- layout --------------------------------------------------------------------------------------
    def _layout(self) -> list[_Slot]:
        slots: list[_Slot] = []
        for k in range(self.P):
            name = self.data.probe_names[k]
            if self.fit_linear:
                slots.append(_Slot("offset", k, None, [f"{name}.offset {a} nT" for a in AXES]))
                if k == 0 and self.data.ref_vector_nT is None:
                    # without a reference vector the common frame's rotation is free: symmetric X only
                    slots.append(_Slot("matrix", k, None, [f"{name}.matrix sym[{AXES[i]}{AXES[j]}]" for i, j in _SYM]))
                else:
                    slots.append(_Slot("matrix", k, None, [f"{name}.matrix d[{a}{b}]" for a in AXES for b in AXES]))
            for term in self.terms:
                names = term.param_names(self.views[k])
                if names:
                    slots.append(_Slot("term", k, term, names))
        for term in self.terms:
            names = term.shared_names(self.data)
            if names:
                slots.append(_Slot("shared", None, term, names))
        start = 0
        for s in slots:
            s.start = start
            start += s.size
        return slots

    def param_names(self) -> list[str]:
        return [n for s in self.slots for n in s.names]

    def term_size(self, term_name: str) -> int:
        return sum(s.size for s in self.slots if s.term is not None and s.term.name == term_name)

    def start_state(self, linear: LinearCalibration, previous: State | None = None) -> State:
        theta = {t.name: [np.zeros(len(t.param_names(v))) for v in self.views] for t in self.terms}
        shared = {t.name: np.zeros(len(t.shared_names(self.data))) for t in self.terms}
        if previous is not None:
            for name, vals in previous.theta.items():
                if name in theta and all(a.shape == b.shape for a, b in zip(vals, theta[name])):
                    theta[name] = [a.copy() for a in vals]
            for name, val in previous.shared.items():
                if name in shared and val.shape == shared[name].shape:
                    shared[name] = val.copy()
        return State(linear.copy(), theta, shared)

    # -- residuals -----------------------------------------------------------------------------------
    def evaluate(self, st: State) -> _Eval:
        rows = self.rows
        v0s, vs, nhats = [], [], []
        for k, view in enumerate(self.views):
            y = view.raw_nT - st.linear.offset_nT[k]
            for t in self.terms:
                if t.frame == "raw":
                    y = y - t.correction(view, st.theta[t.name][k])
            v0 = y @ st.linear.matrix[k].T
            v = v0.copy()
            for t in self.terms:
                if t.frame == "corrected":
                    if st.theta[t.name][k].size:
                        v -= t.correction(view, st.theta[t.name][k], v0)
                    cols = t.shared_vcolumns(self.data, k)
                    if cols is not None:
                        v -= cols @ st.shared[t.name]
            v0s.append(v0)
            vr = v[rows]
            vs.append(vr)
            nhats.append(vr / np.linalg.norm(vr, axis=1, keepdims=True))
        ref = self.reference.copy()
        for t in self.terms:
            sc = t.shared_scolumns(self.data)
            if sc is not None:
                ref = ref + sc[rows] @ st.shared[t.name]
        scalar = np.stack([np.linalg.norm(v, axis=1) - ref for v in vs], axis=1)
        diff = (np.stack([vs[k] - vs[0] for k in range(1, self.P)], axis=1) if self.P > 1
                else np.zeros((self.M, 0, 3)))
        vec = None if self.vref is None else np.stack([v - self.vref for v in vs], axis=1)
        return _Eval(v0s, vs, nhats, scalar, diff, vec)

    def channel_probe(self, c: int) -> tuple[str, int]:
        """What channel c is: ("scalar", k), ("diff", k) (probe k minus probe 1) or ("vec", k)."""
        if c < self.P:
            return "scalar", c
        if c < self.vec0:
            return "diff", 1 + (c - self.P) // 3
        return "vec", (c - self.vec0) // 3

    def _cols(self, kind: str, k: int) -> slice:
        return slice(self.P + 3 * (k - 1), self.P + 3 * k) if kind == "diff" else slice(self.vec0 + 3 * k,
                                                                                          self.vec0 + 3 * k + 3)

    # -- Jacobian ------------------------------------------------------------------------------------
    # The Jacobian is never held for all rows at once: `jacobian` gathers its full-length sources once
    # per iteration, `_block` builds it for one time block. Block-sized temporaries are reused by the
    # allocator; run-sized ones cost a page fault per 4 KiB every time, which dominated the run time.

    def jacobian(self, st: State, ev: _Eval) -> "_Jac":
        """The sources of the Jacobian at st: per slot a full-length (N, 3, m) array or a recipe."""
        src: list[Any] = []
        for s in self.slots:
            if s.kind in ("offset", "matrix"):
                src.append(None)
            elif s.kind == "term":
                view, theta = self.views[s.k], st.theta[s.term.name][s.k]
                if s.term.frame == "raw":
                    src.append(s.term.jacobian(view, theta))                            # phi (N, 3, m)
                else:
                    src.append(s.term.jacobian(view, theta, ev.v0[s.k]))               # psi (N, 3, m)
            else:
                src.append(({k: c for k in range(self.P)
                             if (c := s.term.shared_vcolumns(self.data, k)) is not None},
                            s.term.shared_scolumns(self.data)))
        return _Jac(st, ev, src)

    def _block(self, jac: "_Jac", sl: slice) -> list[tuple[_Slot, dict[int, np.ndarray], np.ndarray | None]]:
        """Per slot, for rows sl: v-space blocks {probe: (m_b, 3, m)} and a scalar-only block (m_b, m)."""
        rows = self.rows[sl]
        nb = rows.size
        st, ev = jac.state, jac.ev
        out = []
        for s, src in zip(self.slots, jac.sources):
            vb: dict[int, np.ndarray] = {}
            sb = None
            if s.kind == "offset":
                vb[s.k] = np.broadcast_to(-st.linear.matrix[s.k], (nb, 3, 3))           # dv/do = -M
            elif s.kind == "matrix":
                v0 = ev.v0[s.k][rows]
                if s.size == 6:                                                         # symmetric X
                    cols = np.zeros((nb, 3, 6))
                    for c, (i, j) in enumerate(_SYM):
                        cols[:, i, c] += v0[:, j]
                        if i != j:
                            cols[:, j, c] += v0[:, i]
                else:                                                                   # general X
                    cols = np.zeros((nb, 3, 9))
                    for i in range(3):
                        cols[:, i, 3 * i:3 * i + 3] = v0                                # e_i v0_j
                vb[s.k] = cols
            elif s.kind == "term":
                if s.term.frame == "raw":
                    vb[s.k] = -np.matmul(st.linear.matrix[s.k], src[rows])              # dv/dtheta = -M phi
                else:
                    vb[s.k] = -src[rows]                                                # -psi
            else:                                                                       # shared
                vcols, scols = src
                for k, c in vcols.items():
                    vb[k] = -c[rows]
                if scols is not None:
                    sb = -scols[rows]                                                   # dF adds to F
            out.append((s, vb, sb))
        return out

    def _local(self, blk, nhat_k: np.ndarray | None, k: int, kind: str,
               weight: np.ndarray | float = 1.0) -> tuple[np.ndarray, np.ndarray] | None:
        """Weighted local Jacobian of probe k's scalar channel (m_b, m), or of its difference to probe 1
        ("diff") or to the reference vector ("vec"), the three components interleaved sample by sample
        (3 m_b, m); and the global parameter indices. Built in one preallocated array (every copy of a
        chunk of Jacobian costs as much as the arithmetic)."""
        use = []
        for s, vb, sb in blk:
            if kind == "vec":
                on = k in vb
            elif kind == "diff":
                on = k in vb or 0 in vb
            else:
                on = k in vb or sb is not None
            if on:
                use.append((s, vb, sb))
        if not use:
            return None
        m = sum(s.size for s, _, _ in use)
        nb = blk[0][1][next(iter(blk[0][1]))].shape[0] if blk[0][1] else blk[0][2].shape[0]
        idx = np.concatenate([np.arange(s.start, s.stop) for s, _, _ in use])
        if kind == "scalar":
            jl = np.empty((nb, m))
            c = 0
            for s, vb, sb in use:
                out = jl[:, c:c + s.size]
                if k in vb:
                    np.einsum("na,nam->nm", nhat_k, vb[k], out=out)
                    if sb is not None:
                        out += sb
                else:
                    out[...] = sb
                c += s.size
            jl *= weight
            return jl, idx
        jl = np.empty((nb, 3, m))
        c = 0
        for s, vb, sb in use:
            out = jl[:, :, c:c + s.size]
            if kind == "vec":
                out[...] = vb[k]
            elif k in vb and 0 in vb:
                np.subtract(vb[k], vb[0], out=out)
            elif k in vb:
                out[...] = vb[k]
            else:
                np.negative(vb[0], out=out)
            c += s.size
        jl *= np.asarray(weight)[None, :, None]
        return jl.reshape(nb * 3, m), idx                   # rows n*3 + a, sample by sample

    def assemble(self, jac: "_Jac", ev: _Eval | None = None, residual: np.ndarray | None = None,
                 only: np.ndarray | None = None):
        """Weighted normal equations per time block: A_b (K, p, p) and g_b = J_b^T W r_b (K, p).

        only (bool, p): compute just the rows and columns of these parameters (the rest stays zero), for
        a candidate added to a model whose normal equations are already known."""
        ev = jac.ev if ev is None else ev
        p, nbk = self.n_params, len(self.blocks)
        r_all = ev.channel_matrix() if residual is None else residual
        a_b = np.zeros((nbk, p, p))
        g_b = np.zeros((nbk, p))
        if p == 0:
            return a_b, g_b
        for b, block in enumerate(self.blocks):
            for sl in _chunks(block, p):          # chunks: temporaries the allocator reuses
                blk = self._block(jac, sl)
                r_blk = r_all[sl]
                for k in range(self.P):
                    for kind in ("scalar", "diff", "vec"):
                        if (kind == "diff" and k == 0) or (kind == "vec" and self.vref is None):
                            continue
                        if kind != "scalar":
                            cols = self._cols(kind, k)
                            w = self.weights[cols]
                            rl = (r_blk[:, cols] * w).reshape(-1)                # rows n*3 + a
                        else:
                            w = self.weights[k]
                            rl = r_blk[:, k] * w
                        local = self._local(blk, ev.nhat[k][sl] if kind == "scalar" else None, k, kind, w)
                        if local is None:
                            continue
                        jl, idx = local
                        if only is None:
                            a_b[b][np.ix_(idx, idx)] += jl.T @ jl
                            g_b[b, idx] += jl.T @ rl
                        else:
                            sel = only[idx]
                            if sel.any():
                                jc = jl[:, sel]
                                a_b[b][np.ix_(idx[sel], idx)] += jc.T @ jl      # rows of `only`, all columns
                                g_b[b, idx[sel]] += jc.T @ rl
        if only is not None:
            a_b[:, :, only] = np.swapaxes(a_b[:, only, :], 1, 2)             # symmetric: columns = rows^T
        return a_b, g_b

    def apply(self, jac: "_Jac", ev: _Eval | None, delta: np.ndarray, sl: slice = slice(None)) -> np.ndarray:
        """J delta on the rows of block slice sl (or all rows), unweighted: (rows, C) change of every channel."""
        ev = jac.ev if ev is None else ev
        if sl == slice(None):
            return np.concatenate([self.apply(jac, ev, delta, c) for b in self.blocks
                                   for c in _chunks(b, self.n_params)])
        chunks = _chunks(sl, self.n_params)
        if len(chunks) > 1:
            return np.concatenate([self.apply(jac, ev, delta, c) for c in chunks])
        blk = self._block(jac, sl)
        dv: list[Any] = [None] * self.P
        ds = None
        for s, vb, sb in blk:
            d = delta[s.start:s.stop]
            if not np.any(d):
                continue
            for k, part in vb.items():
                inc = part @ d
                dv[k] = inc if dv[k] is None else dv[k] + inc
            if sb is not None:
                inc = sb @ d
                ds = inc if ds is None else ds + inc
        n = self.rows[sl].size
        out = np.zeros((n, self.C))
        for k in range(self.P):
            if dv[k] is not None:
                out[:, k] = np.einsum("na,na->n", ev.nhat[k][sl], dv[k])
            if ds is not None:
                out[:, k] += ds
        for k in range(1, self.P):
            dk = dv[k] if dv[k] is not None else 0.0
            d0 = dv[0] if dv[0] is not None else 0.0
            out[:, self.P + 3 * (k - 1):self.P + 3 * k] = dk - d0
        if self.vref is not None:
            for k in range(self.P):
                if dv[k] is not None:
                    out[:, self._cols("vec", k)] = dv[k]
        return out

    # -- updates -------------------------------------------------------------------------------------
    def update(self, st: State, delta: np.ndarray) -> State:
        new = st.copy()
        for s in self.slots:
            d = delta[s.start:s.stop]
            if s.kind == "offset":
                new.linear.offset_nT[s.k] += d
            elif s.kind == "matrix":
                x = np.zeros((3, 3))
                if s.size == 6:
                    for c, (i, j) in enumerate(_SYM):
                        x[i, j] += d[c]
                        if i != j:
                            x[j, i] += d[c]
                else:
                    x = d.reshape(3, 3)
                new.linear.matrix[s.k] = (np.eye(3) + x) @ st.linear.matrix[s.k]     # M <- (I + X) M
            elif s.kind == "term":
                new.theta[s.term.name][s.k] = st.theta[s.term.name][s.k] + d
            else:
                new.shared[s.term.name] = st.shared[s.term.name] + d
        return new

    def weighted_rss(self, ev: _Eval) -> float:
        r = ev.channel_matrix()
        return float(np.einsum("nc,nc->c", r, r) @ self.weights ** 2)


# --- the fit ------------------------------------------------------------------------------------------------

@dataclass
class Parameter:
    """One fitted parameter in physical units; stderr None when the data do not determine it."""

    name: str
    value: float
    stderr: float | None
    term: str

    @property
    def unit(self) -> str:
        """The unit written at the end of the name ("s1.x nT/degC" -> "nT/degC"), or "" if none.

        >>> Parameter("s1.eddy[xy] s", 0.0, None, "eddy").unit, Parameter("s1.platform induced[xy]", 0.0, None, "p").unit
        ('s', '')
        """
        last = self.name.rsplit(" ", 1)[-1]
        return last if (" " in self.name and (last == "s" or "nT" in last or "/" in last)) else ""

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "stderr": self.stderr, "unit": self.unit}


@dataclass
class FitResult:
    """A fitted model: its state, parameters with standard errors, residual channels and what the
    held-out (blocked) evaluation needs."""

    problem: Problem
    state: State
    channels: Channels
    values: np.ndarray
    stderr: np.ndarray
    undetermined: np.ndarray
    rank: int
    rss_w: float
    iterations: int
    converged: bool
    a_blocks: np.ndarray
    g_blocks: np.ndarray
    jac: Any = field(repr=False, default=None)
    ev: Any = field(repr=False, default=None)

    @property
    def model(self) -> Model:
        return self.problem.model

    @property
    def n_rows(self) -> int:
        return int(self.channels.values.size)

    @property
    def rms_nT(self) -> float:
        return self.channels.total_rms_nT

    def parameters(self, *, effects_only: bool = True) -> list[Parameter]:
        out = []
        for s in self.problem.slots:
            if effects_only and s.kind in ("offset", "matrix"):
                continue
            if s.kind == "matrix":
                continue                       # perturbations are zero at convergence; see state.linear
            for j, name in enumerate(s.names):
                i = s.start + j
                val = self.values[i]
                se = None if self.undetermined[i] else float(self.stderr[i])
                out.append(Parameter(name, float(val), se, s.term.name if s.term is not None else "baseline"))
        return out

    def heldout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per block: weighted SSE, unweighted SSE (nT^2) and row count of the held-out residual,
        each block predicted by the fit to the other blocks (one Gauss-Newton step from the full fit,
        exact for the linearised problem)."""
        pr = self.problem
        a_all, g_all = self.a_blocks.sum(0), self.g_blocks.sum(0)
        r = self.channels.values
        w = pr.weights
        nb = len(pr.blocks)
        sse_w, sse, cnt = np.zeros(nb), np.zeros(nb), np.zeros(nb)
        for b, sl in enumerate(pr.blocks):
            rb = r[sl]
            if pr.n_params:
                delta, *_ = _solve(a_all - self.a_blocks[b], g_all - self.g_blocks[b])
                rb = rb + pr.apply(self.jac, self.ev, delta, sl)
            sse_w[b] = float(np.sum((rb * w) ** 2))
            sse[b] = float(np.sum(rb ** 2))
            cnt[b] = rb.size
        return sse_w, sse, cnt


@dataclass
class Warm:
    """Normal equations already assembled at the start point for some parameters (a model's, when a
    candidate is added to it): `known` marks them; only the others' rows are assembled."""

    a_blocks: np.ndarray
    g_blocks: np.ndarray
    known: np.ndarray


def warm_from(base: "FitResult", pr: Problem) -> Warm | None:
    """The base fit's block normal equations placed into problem pr's layout (which must contain every
    base parameter, under the same name, with the same rows, blocks and weights)."""
    names = pr.param_names()
    where = {n: i for i, n in enumerate(names)}
    base_names = base.problem.param_names()
    if (not all(n in where for n in base_names) or base.problem.M != pr.M
            or len(base.problem.blocks) != len(pr.blocks) or not np.array_equal(base.problem.weights, pr.weights)):
        return None
    m = np.array([where[n] for n in base_names], dtype=int)
    nb, p = len(pr.blocks), pr.n_params
    a = np.zeros((nb, p, p))
    g = np.zeros((nb, p))
    if m.size:
        a[:, m[:, None], m[None, :]] = base.a_blocks
        g[:, m] = base.g_blocks
    known = np.zeros(p, bool)
    known[m] = True
    return Warm(a, g, known)


def fit_problem(pr: Problem, start: State, *, max_iter: int = 8, tol_se: float = 0.01,
                progress: Callable[[str], None] | None = None, warm: Warm | None = None,
                ev0: _Eval | None = None, jac0: "_Jac | None" = None) -> FitResult:
    """Gauss-Newton from `start` until every step is below tol_se standard errors. With `warm`, the first
    linearisation assembles only the rows of the parameters warm does not know. ev0, jac0: the residuals
    and Jacobian at `start` when the caller has them already."""
    st = start
    ev = pr.evaluate(st) if ev0 is None else ev0
    rss = pr.weighted_rss(ev)
    n_rows = pr.M * pr.C
    converged = pr.n_params == 0
    it = 0
    jac = a_b = g_b = None
    delta = np.zeros(pr.n_params)
    cov = np.zeros(pr.n_params)
    undet = np.zeros(pr.n_params, bool)
    rank = 0
    while True:
        jac = jac0 if (it == 0 and jac0 is not None) else pr.jacobian(st, ev)
        if warm is not None and it == 0:
            a_b, g_b = pr.assemble(jac, ev, only=~warm.known)
            keep = warm.known
            a_b[:, keep[:, None] & keep[None, :]] = warm.a_blocks[:, keep[:, None] & keep[None, :]]
            g_b[:, keep] = warm.g_blocks[:, keep]
        else:
            a_b, g_b = pr.assemble(jac, ev)
        if pr.n_params == 0:
            converged = True
            break
        delta, cov, undet, rank = _solve(a_b.sum(0), g_b.sum(0))
        s2 = max(rss / max(n_rows - rank, 1), 1e-300)
        se = np.sqrt(np.clip(cov * s2, 0, None))
        small = not np.any(np.abs(delta)[~undet] > tol_se * se[~undet])
        if small or it >= max_iter:
            converged = small
            if small and np.any(delta):
                # the last step is tiny: take it without re-linearising, and move the block gradients
                # with it (g_b + A_b delta), so the held-out solves start from the final point
                trial = pr.update(st, delta)
                ev_t = pr.evaluate(trial)
                rss_t = pr.weighted_rss(ev_t)
                if np.isfinite(rss_t) and rss_t <= rss * (1 + 1e-9):
                    st, ev, rss = trial, ev_t, rss_t
                    g_b = g_b + np.einsum("bij,j->bi", a_b, delta)
            break
        it += 1
        damping = 0.0
        for _ in range(10):
            # Levenberg-Marquardt: a step that does not lower the RSS (a badly determined direction
            # taken too far) is retried shorter and turned towards the gradient
            if damping > 0:
                delta, *_ = _solve(a_b.sum(0), g_b.sum(0), damping)
            trial = pr.update(st, delta)
            ev_t = pr.evaluate(trial)
            rss_t = pr.weighted_rss(ev_t)
            if np.isfinite(rss_t) and rss_t <= rss * (1 + 1e-12) + 1e-12:
                break
            damping = 1e-6 if damping == 0 else damping * 10.0
        else:
            converged = True                                  # no descent left: at the minimum
            break
        step = 1.0 if damping == 0 else 0.0
        predicted = rss + float(g_b.sum(0) @ delta)           # rss - g^T A^+ g of the linearised problem
        # the excess of the actual over the predicted RSS bounds how far the step is from the minimum:
        # excess = d^T A d for a parameter error d, i.e. sqrt(excess / s2) standard errors
        linear_enough = step == 1.0 and abs(rss_t - predicted) <= LINEARITY_SE ** 2 * s2
        # an iteration that lowers the RSS by less than RSS_TOL s^2 only creeps along flat directions
        flat = rss - rss_t < RSS_TOL * s2
        st, ev, rss = trial, ev_t, rss_t
        if linear_enough or flat:
            # the step did what the linearisation promised: a second linearisation would move the
            # parameters by a negligible amount, so keep this one and move the block gradients with it
            g_b = g_b + np.einsum("bij,j->bi", a_b, delta)
            converged = True
            break
        if progress is not None:
            progress(f"iteration {it}")
    s2 = rss / max(n_rows - rank, 1)
    values = _flatten(pr, st)
    chans = Channels(pr.channel_names, ev.channel_matrix(), pr.data.t_s[pr.rows], pr.rows)
    return FitResult(problem=pr, state=st, channels=chans, values=values,
                     stderr=np.sqrt(np.clip(cov * s2, 0, None)), undetermined=undet, rank=rank, rss_w=rss,
                     iterations=it, converged=converged, a_blocks=a_b, g_blocks=g_b, jac=jac, ev=ev)


def _flatten(pr: Problem, st: State) -> np.ndarray:
    out = np.zeros(pr.n_params)
    for s in pr.slots:
        if s.kind == "offset":
            out[s.start:s.stop] = st.linear.offset_nT[s.k]
        elif s.kind == "term":
            out[s.start:s.stop] = st.theta[s.term.name][s.k]
        elif s.kind == "shared":
            out[s.start:s.stop] = st.shared[s.term.name]
    return out


# --- public API ---------------------------------------------------------------------------------------------

def reference_total(data: EffectData, linear: LinearCalibration | None = None) -> tuple[np.ndarray, str]:
    """The total field each scalar channel is compared with: ref_total, the configured total, or the
    median |corrected| of probe 1 (estimated); and which of the three it is."""
    if data.ref_total_nT is not None:
        return data.ref_total_nT, "ref_total"
    if data.total_nT is not None:
        return np.full(data.n_samples, float(data.total_nT)), "config"
    if linear is None:
        raise CalibrationRefused("no total field: give ref_total in the data, a total in --config, or a start")
    v = (data.raw_nT[:, 0, :] - linear.offset_nT[0]) @ linear.matrix[0].T
    return np.full(data.n_samples, float(np.median(np.linalg.norm(v, axis=1)))), "estimated"


def channel_noise(values: np.ndarray) -> np.ndarray:
    """Noise floor per channel (columns of values): std of second differences / sqrt(6), robust."""
    return np.array([robust_noise(values[:, c]) for c in range(values.shape[1])])


def as_effect_data(data: Any, *, total_nT: float | None = None, positions_m: np.ndarray | None = None,
                   probe_names: Sequence[str] | None = None) -> EffectData:
    """EffectData from EffectData, a LabData (service.io.recordings.labdata) or a SampleBlock."""
    if isinstance(data, EffectData):
        if total_nT is not None:
            data.total_nT = total_nT
        if positions_m is not None:
            data.positions_m = np.asarray(positions_m, dtype=np.float64)
        return data
    block = getattr(data, "block", data)
    if not isinstance(block, SampleBlock):
        raise DataError(f"data: expected a SampleBlock, LabData or EffectData, got {type(data).__name__}")
    names = probe_names if probe_names is not None else getattr(data, "probe_names", None)
    return EffectData.from_block(block, names, total_nT=total_nT, positions_m=positions_m)


@dataclass
class EffectsFit:
    """A calibration with effect terms: the linear part (CONTRACTS §3: corrected = matrix (raw - offset)
    before any effect term) plus every effect parameter with its standard error."""

    probe_names: list[str]
    effects: list[str]
    offset_nT: np.ndarray               # (P, 3)
    matrix: np.ndarray                  # (P, 3, 3)
    parameters: list[Parameter]
    offset_stderr_nT: np.ndarray        # (P, 3), NaN where undetermined
    rms_nT: float
    channel_rms_nT: dict[str, float]
    reference: str
    result: FitResult = field(repr=False)
    base_method: str = "ellipsoid"
    base_align: str | None = None
    total_nT: float | None = None

    def calibration(self) -> Any:
        """A service.numerics.calib.model.ArrayCalibration: the linear part with offset standard errors, the
        effect names and `effect_params` {effect: {name: {"value", "se", "unit"}}}, plus the fit's
        RMS in `diagnostics`. (The plain LinearCalibration if the calibration core is missing.)"""
        try:
            from service.numerics.calib.model import ArrayCalibration, ProbeCalibration
        except Exception:                                     # noqa: BLE001 - optional collaborator
            return LinearCalibration(self.offset_nT.copy(), self.matrix.copy())
        probes = [ProbeCalibration(n, self.offset_nT[k].copy(), self.matrix[k].copy(), self.offset_stderr_nT[k].copy())
                  for k, n in enumerate(self.probe_names)]
        effect_params: dict[str, Any] = {}
        for p in self.parameters:
            effect_params.setdefault(p.term, {})[p.name] = {"value": p.value, "se": p.stderr, "unit": p.unit}
        for term, name, value, unit in self.constants():
            effect_params.setdefault(term, {})[name] = {"value": value, "se": None, "unit": unit,
                                                        "note": "reference the parameters are defined against"}
        data = self.result.problem.data
        return ArrayCalibration(method=self.base_method, align=self.base_align, probes=probes, total_nT=self.total_nT,
                                effects=list(self.effects), effect_params=effect_params,
                                diagnostics={"rms_nT": self.rms_nT, "channel_rms_nT": dict(self.channel_rms_nT),
                                             "reference": self.reference},
                                span=(float(data.t_s[0]), float(data.t_s[-1]), int(data.n_samples)))

    def constants(self) -> list[tuple[str, str, float, str]]:
        """(effect, name, value, unit) of the references the effect parameters are defined against."""
        pr = self.result.problem
        out = []
        for t in pr.terms:
            for view in pr.views:
                for name, (value, unit) in t.constants(view).items():
                    out.append((t.name, name, float(value), unit))
        return out

    def effect_parameters(self) -> dict[str, dict[str, float | None]]:
        """{"temperature": {"s1.x nT/degC": value, ...}, ...} and the same with standard errors."""
        out: dict[str, dict[str, float | None]] = {}
        for p in self.parameters:
            out.setdefault(p.term, {})[p.name] = p.value
        return out

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: the sensors in CONTRACTS §3 form plus `effect_parameters` with errors."""
        sensors = [{"name": n, "offset_nT": self.offset_nT[k].tolist(), "matrix": self.matrix[k].tolist(),
                    "scalar_rms_nT": self.channel_rms_nT.get(f"{n}.scalar")}
                   for k, n in enumerate(self.probe_names)]
        return {"effects": list(self.effects), "sensors": sensors, "rms_nT": self.rms_nT,
                "reference": self.reference,
                "effect_parameters": [p.as_dict() | {"effect": p.term} for p in self.parameters],
                "effect_constants": [{"effect": e, "name": n, "value": v, "unit": u}
                                     for e, n, v, u in self.constants()]}

    def correct(self, data: Any) -> np.ndarray:
        """(N, P, 3) corrected field of other data with this calibration and its effects."""
        ed = as_effect_data(data, probe_names=self.probe_names)
        lin = LinearCalibration(self.offset_nT, self.matrix)
        pr = Problem(ed, Model(self.result.model.effect_terms), lin, np.zeros(ed.n_samples), n_blocks=1,
                     rows=np.arange(ed.n_samples))
        for old, new in zip(self.result.problem.views, pr.views):
            # the references of the fit (temperature, time origin, step instants): keep them
            new.cache.update({k: v for k, v in old.cache.items() if k.startswith(REF_PREFIX)})
        pr.slots = pr._layout()
        pr.n_params = pr.slots[-1].stop if pr.slots else 0
        st = pr.start_state(lin, self.result.state)
        ev = pr.evaluate(st)
        return np.stack(ev.v, axis=1)


def fit_with_effects(data: Any, effects: Sequence[str] | Model, base_calibration: Any = None, *,
                     total_nT: float | None = None, positions_m: np.ndarray | None = None,
                     fix_linear: bool = False, n_blocks: int = 8,
                     progress: Callable[[str], None] | None = None) -> tuple[EffectsFit, Channels]:
    """Fit the linear calibration (unless fix_linear) and the named effects; return the calibration with
    effect parameters and standard errors, and the residual channels.

    data: EffectData, LabData or SampleBlock. effects: catalogue names or a Model. base_calibration: the
    starting linear calibration (ArrayCalibration, LinearCalibration, `fit --json` dict) or None to start
    from an ellipsoid per probe aligned to probe 1."""
    from service.numerics.effects import make_model

    ed = as_effect_data(data, total_nT=total_nT, positions_m=positions_m)
    if isinstance(effects, Model):
        model = effects if (effects.has_baseline or fix_linear) else Model([Baseline()]) + effects
        if fix_linear:
            model = model.without_baseline()
    else:
        model = make_model(list(effects), baseline=not fix_linear)
    for t in model.effect_terms:
        why = t.why_unavailable(ed)
        if why:
            raise CalibrationRefused(f"effect {t.name!r} cannot be fitted to these data: {why}")
    if base_calibration is None:
        ref0 = ed.ref_total_nT if ed.ref_total_nT is not None else ed.total_nT
        linear = initial_linear(ed, ref0)
    else:
        linear = LinearCalibration.from_any(base_calibration, ed.n_probes)
    reference, kind = reference_total(ed, linear)
    weights = start_weights(ed, linear, reference)
    res = fit_model(ed, model, linear, reference, weights, n_blocks=n_blocks, progress=progress)
    out = effects_fit_from(res, kind)
    out.base_method = getattr(base_calibration, "method", None) or "ellipsoid"
    out.base_align = getattr(base_calibration, "align", None)
    out.total_nT = ed.total_nT if kind != "ref_total" else float(np.median(reference))
    return out, res.channels


def residual_hints(fit: FitResult) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Full-length scalar residual and offset sensitivity n^T M per probe (NaN off the fitted rows): what
    terms with `needs_residual` look for their regressors in."""
    pr = fit.problem
    n = pr.data.n_samples
    res, gain = [], []
    for k in range(pr.P):
        r = np.full(n, np.nan)
        r[pr.rows] = fit.channels.values[:, k]
        g = np.full((n, 3), np.nan)
        g[pr.rows] = fit.ev.nhat[k] @ fit.state.linear.matrix[k]
        res.append(r)
        gain.append(g)
    return res, gain


def fit_model(data: EffectData, model: Model, linear: LinearCalibration, reference: np.ndarray,
              weights: np.ndarray, *, n_blocks: int = 8, progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit a model from a linear start. Terms that find their regressors in a residual (perming steps)
    get the residual of the model without them: two stages."""
    hints = None
    if any(t.needs_residual for t in model.effect_terms):
        first = Model([t for t in model if not t.needs_residual])
        pr0 = Problem(data, first, linear, reference, weights=weights, n_blocks=n_blocks)
        fit0 = fit_problem(pr0, pr0.start_state(linear), progress=progress)
        hints = residual_hints(fit0)
        pr = Problem(data, model, fit0.state.linear, reference, weights=weights, n_blocks=n_blocks, hints=hints)
        return fit_problem(pr, pr.start_state(fit0.state.linear, fit0.state), progress=progress)
    pr = Problem(data, model, linear, reference, weights=weights, n_blocks=n_blocks)
    return fit_problem(pr, pr.start_state(linear), progress=progress)


def start_weights(data: EffectData, linear: LinearCalibration, reference: np.ndarray) -> np.ndarray:
    """1 / noise per residual channel, the noise estimated at the start (model-independent)."""
    pr = Problem(data, Model([]), linear, reference, n_blocks=1)
    ev = pr.evaluate(pr.start_state(linear))
    noise = channel_noise(ev.channel_matrix())
    noise = np.where(np.isfinite(noise), np.maximum(noise, NOISE_FLOOR_NT), 1.0)
    return 1.0 / noise


def effects_fit_from(res: FitResult, reference_kind: str) -> EffectsFit:
    pr = res.problem
    off_se = np.full((pr.P, 3), np.nan)
    for s in pr.slots:
        if s.kind == "offset":
            se = res.stderr[s.start:s.stop].copy()
            se[res.undetermined[s.start:s.stop]] = np.nan
            off_se[s.k] = se
    rms = res.channels.rms_nT
    return EffectsFit(probe_names=list(pr.data.probe_names), effects=pr.model.effects,
                      offset_nT=res.state.linear.offset_nT.copy(), matrix=res.state.linear.matrix.copy(),
                      parameters=res.parameters(), offset_stderr_nT=off_se, rms_nT=res.rms_nT,
                      channel_rms_nT={n: float(rms[i]) for i, n in enumerate(res.channels.names)},
                      reference=reference_kind, result=res)
