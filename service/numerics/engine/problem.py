"""Fitting a linear calibration plus effect terms to the residual channels, by Gauss-Newton.

Residual channels (docs/contracts.md), for probes k = 1..P with y_k = raw_k - o_k - sum theta phi:

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

from typing import Any, Sequence

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import CalibrationRefused, DataError
from fluxcal.service.numerics.channels import channel_names
from fluxcal.service.numerics.effects.base import REF_PREFIX, EffectData, Model, ProbeView

from .jacobian import _chunks, _Jac, block_jacobian, local_jacobian
from .linear import LinearCalibration
from .residuals import _Eval
from .state import State, layout_slots, start_state, update_state


def make_views(data: EffectData, bind: LinearCalibration, hints: Any, refs: list[dict] | None) -> list[ProbeView]:
    """What each term sees of each probe; `refs`: references the terms were fitted with elsewhere (step
    instants, origins), kept rather than found again."""
    views = [ProbeView(data, k, bind.offset_nT[k].copy(), bind.matrix[k].copy(),
                       None if hints is None else hints[0][k], None if hints is None else hints[1][k])
             for k in range(data.n_probes)]
    for view, ref in zip(views, refs or []):
        view.cache.update({key: v for key, v in ref.items() if key.startswith(REF_PREFIX)})
    if hints is not None:
        for view in views:                       # every probe's residual, for terms that compare probes
            view.cache["residuals:all"] = hints[0]
    return views


class Problem:
    """Data, model and weights: residual channels, Jacobian and block normal equations."""

    def __init__(self, data: EffectData, model: Model, bind: LinearCalibration, reference_nT: np.ndarray, *,
                 weights: np.ndarray | None = None, n_blocks: int = 8,
                 hints: tuple[list[np.ndarray], list[np.ndarray]] | None = None,
                 rows: np.ndarray | None = None, refs: list[dict] | None = None) -> None:
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
        self.views = make_views(data, bind, hints, refs)
        edges = np.linspace(0, self.M, n_blocks + 1).round().astype(int)
        self.blocks = [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        vref = data.ref_vector_nT
        self.vref = None if vref is None else vref[self.rows]
        self.channel_names = channel_names(data.probe_names, vector=self.vref is not None)
        self.C = len(self.channel_names)
        self.vec0 = self.P + 3 * (self.P - 1)              # first vector-reference channel
        self.weights = np.ones(self.C) if weights is None else np.asarray(weights, dtype=np.float64)
        self.slots = layout_slots(data, self.terms, self.views, self.fit_linear)
        self.n_params = self.slots[-1].stop if self.slots else 0

    def start_state(self, linear: LinearCalibration, previous: State | None = None) -> State:
        return start_state(self.data, self.terms, self.views, linear, previous)

    def update(self, st: State, delta: np.ndarray) -> State:
        return update_state(self.slots, st, delta)
    def param_names(self) -> list[str]:
        return [n for s in self.slots for n in s.names]

    def term_size(self, term_name: str) -> int:
        return sum(s.size for s in self.slots if s.term is not None and s.term.name == term_name)

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
                if t.frame == "corrected" and st.theta[t.name][k].size:
                    v -= t.correction(view, st.theta[t.name][k], v0)
                if st.shared[t.name].size:                 # shared parameters act in the corrected frame
                    corr = t.shared_vcorrection(self.data, k, st.shared[t.name])
                    if corr is not None:
                        v -= corr
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
    # per iteration, `jacobian.block_jacobian` builds it for one time block. Block-sized temporaries are reused by the
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
                theta = st.shared[s.term.name]
                src.append(({k: c for k in range(self.P)
                             if (c := s.term.shared_vjacobian(self.data, k, theta)) is not None},
                            s.term.shared_scolumns(self.data)))
        return _Jac(st, ev, src)

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
                blk = block_jacobian(self, jac, sl)
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
                        local = local_jacobian(blk, ev.nhat[k][sl] if kind == "scalar" else None, k, kind, w)
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
        """J delta on the rows of block slice sl (or all rows), unweighted: (rows, C) change of every channel; for
        delta (n_params, K), K directions at once, (rows, C, K)."""
        ev = jac.ev if ev is None else ev
        if sl == slice(None):
            return np.concatenate([self.apply(jac, ev, delta, c) for b in self.blocks
                                   for c in _chunks(b, self.n_params)])
        chunks = _chunks(sl, self.n_params)
        if len(chunks) > 1:
            return np.concatenate([self.apply(jac, ev, delta, c) for c in chunks])
        blk = block_jacobian(self, jac, sl)
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
        out = np.zeros((n, self.C) + delta.shape[1:])
        for k in range(self.P):
            if dv[k] is not None:
                out[:, k] = np.einsum("na,na...->n...", ev.nhat[k][sl], dv[k])
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

    def weighted_rss(self, ev: _Eval) -> float:
        r = ev.channel_matrix()
        return float(np.einsum("nc,nc->c", r, r) @ self.weights ** 2)


def reference_total(data: EffectData, linear: LinearCalibration | None = None, *,
                    held: bool = False) -> tuple[np.ndarray, str]:
    """The total field each scalar channel is compared with: ref_total, the configured total, or one estimated from
    the data; and which of the three it is. Estimated, it is the field `fit` assumes (ellipsoid.assumed_total: the one
    at which probe 1's calibrated sphere has the volume of its raw ellipsoid), so that every command gives the same
    residual in nT for the same samples. With the linear part `held` fixed, the field it was made for (its
    assumed_total_nT: a calibration held keeps its own scale), else, as where the samples fit no ellipsoid, the median
    |corrected| of probe 1 by `linear`."""
    from fluxcal.service.numerics.calib.ellipsoid import assumed_total

    if data.ref_total_nT is not None:
        return data.ref_total_nT, "ref_total"
    if data.total_nT is not None:
        return np.full(data.n_samples, float(data.total_nT)), "config"
    if linear is None:
        raise CalibrationRefused("no total field: give ref_total in the data, a total in --config, or a start")
    estimated = linear.assumed_total_nT if held else assumed_total(data.raw_nT[:, 0, :])
    return np.full(data.n_samples, _size(data, linear) if estimated is None else estimated), "estimated"


def _size(data: EffectData, linear: LinearCalibration) -> float:
    """The median |corrected| of probe 1 by `linear`, nT."""
    v = (data.raw_nT[:, 0, :] - linear.offset_nT[0]) @ linear.matrix[0].T
    return float(np.nanmedian(np.linalg.norm(v, axis=1)))


def scaled_to(linear: LinearCalibration, data: EffectData, reference: np.ndarray) -> LinearCalibration:
    """The start `linear` with every probe's matrix scaled by one factor, so that probe 1's median |corrected| is the
    reference's median: the fit then starts where an estimated total field puts the scale (the probes' alignment
    kept)."""
    size = _size(data, linear)
    factor = float(np.median(reference)) / size if np.isfinite(size) and size > 0 else 1.0
    return LinearCalibration(linear.offset_nT.copy(), linear.matrix * factor)


def as_effect_data(data: Any, *, total_nT: float | None = None, positions_m: np.ndarray | None = None,
                   probe_names: Sequence[str] | None = None) -> EffectData:
    """EffectData from EffectData, a LabData (fluxcal.service.io.recordings.labdata) or a SampleBlock."""
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
