"""The Gauss-Newton solve: steps on the column-scaled normal equations, standard errors, warm starts.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import Model

from .jacobian import _Jac
from .problem import Problem
from .residuals import Channels, _Eval
from .state import State, floor_vector

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


def solve_normal(a: np.ndarray, g: np.ndarray, damping: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
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


@dataclass
class Parameter:
    """One fitted parameter in physical units; stderr None when the data do not determine it."""

    name: str
    value: float
    stderr: float | None
    term: str
    probe: str | None = None          # the probe it belongs to (None: shared, or the baseline's)
    key: tuple = ()                   # what it is, as its term's param_keys say: the term reads this, never the name
    at_floor: str | None = None       # held at the lowest value its physics allows: why (EffectTerm.floors)

    @property
    def unit(self) -> str:
        """The unit written at the end of the name ("s1.x nT/degC" -> "nT/degC"), or "" if none.

        >>> Parameter("s1.eddy[xy] s", 0.0, None, "eddy").unit, Parameter("s1.platform induced[xy]", 0.0, None, "p").unit
        ('s', '')
        """
        last = self.name.rsplit(" ", 1)[-1]
        return last if (" " in self.name and (last == "s" or "nT" in last or "/" in last)) else ""

    def as_dict(self) -> dict[str, Any]:
        out = {"name": self.name, "value": self.value, "stderr": self.stderr, "unit": self.unit}
        return out | ({"at_floor": self.at_floor} if self.at_floor else {})


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
    _deltas: Any = field(repr=False, default=None, compare=False)
    at_floor: Any = None              # (p,) bool: held at its floor, out of the normal equations (None: none)

    @property
    def model(self) -> Model:
        return self.problem.model

    @property
    def n_rows(self) -> int:
        return int(self.channels.values.size)

    @property
    def rms_nT(self) -> float:
        return self.channels.total_rms_nT

    def block_deltas(self) -> np.ndarray:
        """(K, p) the parameters fitted without each time block, less the full fit's (one Gauss-Newton step
        from the full fit, exact for the linearised problem): the held-out predictions and the block
        jackknife share them."""
        if self._deltas is None and self.values.size == 0:
            self._deltas = np.zeros((len(self.a_blocks), 0))
        if self._deltas is None:
            a_all, g_all = self.a_blocks.sum(0), self.g_blocks.sum(0)
            self._deltas = np.array([solve_normal(a_all - a_b, g_all - g_b)[0]
                                     for a_b, g_b in zip(self.a_blocks, self.g_blocks)]).reshape(-1, self.values.size)
        return self._deltas

    @cached_property
    def robust_stderr(self) -> np.ndarray:
        """Standard errors that hold on coloured noise. Noise correlated in time (1/f, a wander no term
        follows) moves whole blocks together, which the white-noise figure (normal equations and residual
        variance) does not see; the delete-a-block jackknife over the K contiguous time blocks,
        sqrt((K - 1) / K sum_b (d_b - mean d)^2), does. With K = 8 one jackknife figure is itself uncertain
        (about 50 %), so per term (the offsets, the matrices, each effect) the white-noise errors are scaled
        by the median over its parameters of jackknife / white when that exceeds 1: white noise keeps its
        white-noise errors, 1/f noise gets the jackknife's (temperature coefficients were understated
        9-fold under 1/f noise; now within 0.9, tests/numerics/test_stderr.py). The jackknife sees the wander only
        between its blocks: every effect's parameters also get coloured_stderr's power-law figure where that
        is larger (a drift, a step, a heater switched every 40 s, a 90-s thermal lag)."""
        d = self.block_deltas()
        k = d.shape[0]
        if k < 3 or d.shape[1] == 0:
            return self.stderr
        jack = np.sqrt((k - 1) / k * np.sum((d - d.mean(0)) ** 2, axis=0))
        out = self.stderr.copy()
        groups: dict[str, list[int]] = {}
        for sl in self.problem.slots:
            key = sl.kind if sl.term is None else sl.term.name
            groups.setdefault(key, []).extend(range(sl.start, sl.stop))
        for idx in groups.values():
            i = np.array([j for j in idx if not self.undetermined[j] and self.stderr[j] > 0], dtype=int)
            if i.size:
                ratio = float(np.median(jack[i] / self.stderr[i]))
                out[idx] = self.stderr[idx] * max(1.0, ratio)
        # every effect's parameters: the noise's wander at the record's own periods, from a power law of its
        # spectrum (a drift, a step, a heater switched every 40 s, a thermal lag of 90 s: under 1/f noise the
        # jackknife alone left their errors 2 to 2.5 times too small)
        terms = np.array([j for sl in self.problem.slots if sl.term is not None
                          for j in range(sl.start, sl.stop) if not self.undetermined[j]], dtype=int)
        try:
            spectral = self.coloured_stderr(terms) if terms.size else None
        except (np.linalg.LinAlgError, ValueError, RuntimeError):
            spectral = None                               # the jackknife's errors stand
        if spectral is not None:
            out[terms] = np.maximum(out[terms], spectral)
        return out

    def coloured_stderr(self, idx: np.ndarray) -> np.ndarray | None:
        """Standard errors of parameters idx under a power-law model of the noise spectrum (coloured.coloured_stderr);
        None when the noise is not coloured at the record's own period."""
        from .coloured import coloured_stderr

        return coloured_stderr(self, idx, RANK_TOL)

    def parameters(self, *, effects_only: bool = True) -> list[Parameter]:
        out = []
        robust = self.robust_stderr
        for s in self.problem.slots:
            if effects_only and s.kind in ("offset", "matrix"):
                continue
            if s.kind == "matrix":
                continue                       # perturbations are zero at convergence; see state.linear
            for j, name in enumerate(s.names):
                i = s.start + j
                val = self.values[i]
                se = None if self.undetermined[i] else float(robust[i])
                held = self.at_floor is not None and self.at_floor[i]
                out.append(Parameter(name, float(val), se, s.term.name if s.term is not None else "baseline",
                                     None if s.k is None else self.problem.data.probe_names[s.k],
                                     s.keys[j] if s.keys else (j,), s.term.floors[j][1] if held else None))
        return out

    def heldout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per block: weighted SSE, unweighted SSE (nT^2) and value count of the held-out residual, and per block and
        channel its unweighted SSE (K, C), each block predicted by the fit to the other blocks (one Gauss-Newton step
        from the full fit, exact for the linearised problem)."""
        pr = self.problem
        r = self.channels.values
        w = pr.weights
        nb = len(pr.blocks)
        sse_w, sse, cnt = np.zeros(nb), np.zeros(nb), np.zeros(nb)
        per_channel = np.zeros((nb, r.shape[1]))
        deltas = self.block_deltas() if pr.n_params else None
        for b, sl in enumerate(pr.blocks):
            rb = r[sl]
            if deltas is not None:
                rb = rb + pr.apply(self.jac, self.ev, deltas[b], sl)
            per_channel[b] = np.einsum("nc,nc->c", rb, rb)
            sse_w[b] = float(per_channel[b] @ w ** 2)
            sse[b] = float(per_channel[b].sum())
            cnt[b] = rb.size
        return sse_w, sse, cnt, per_channel


@dataclass
class Warm:
    """Normal equations already assembled at the start point for some parameters (a model's, when a
    candidate is added to it): `known` marks them; only the others' rows are assembled."""

    a_blocks: np.ndarray
    g_blocks: np.ndarray
    known: np.ndarray


def warm_from(base: FitResult, pr: Problem) -> Warm | None:
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
    if base.at_floor is not None:
        known[m[base.at_floor]] = False           # held out of the base's equations: assembled again
    return Warm(a, g, known)


def fit_problem(pr: Problem, start: State, *, max_iter: int = 8, tol_se: float = 0.01,
                progress: Callable[[str], None] | None = None, warm: Warm | None = None,
                ev0: _Eval | None = None, jac0: _Jac | None = None) -> FitResult:
    """Gauss-Newton from `start` until every step is below tol_se standard errors. With `warm`, the first
    linearisation assembles only the rows of the parameters warm does not know. ev0, jac0: the residuals
    and Jacobian at `start` when the caller has them already."""
    st = start
    lo = floor_vector(pr.slots)
    lo = lo if np.isfinite(lo).any() else None        # a parameter the physics bounds below: held at its floor
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
        a_b, g_b = _assemble(pr, jac, ev, warm if it == 0 else None)
        if pr.n_params == 0:
            converged = True
            break
        a_s, g_s = a_b.sum(0), g_b.sum(0)
        delta, cov, undet, rank = solve_normal(a_s, g_s)
        room = None if lo is None else lo - _flatten(pr, st)
        if room is not None:
            a_s, g_s, delta = _held_at_floors(a_s, g_s, delta, room)
        s2 = max(rss / max(n_rows - rank, 1), 1e-300)
        se = np.sqrt(np.clip(cov * s2, 0, None))
        small = not np.any(np.abs(delta)[~undet] > tol_se * se[~undet])
        if small or it >= max_iter:
            converged = small
            if small and np.any(delta):
                st, ev, rss, g_b = _take_last_step(pr, st, ev, rss, delta, a_b, g_b)
            break
        it += 1
        step = _descent_step(pr, st, rss, a_s, g_s, delta, room)
        if step is None:
            converged = True                                  # no descent left: at the minimum
            break
        delta, damping, trial, ev_t, rss_t = step
        # the RSS the linearised problem predicts for this step: rss - g^T A^+ g for the Gauss-Newton step itself, the
        # whole quadratic where a floor stopped it
        g_all = g_b.sum(0)
        predicted = rss + float(g_all @ delta if room is None else 2.0 * g_all @ delta + delta @ a_b.sum(0) @ delta)
        # the excess of the actual over the predicted RSS bounds how far the step is from the minimum:
        # excess = d^T A d for a parameter error d, i.e. sqrt(excess / s2) standard errors
        linear_enough = damping == 0 and abs(rss_t - predicted) <= LINEARITY_SE ** 2 * s2
        # an iteration that lowers the RSS by less than RSS_TOL s^2 only creeps along flat directions
        flat = rss - rss_t < RSS_TOL * s2
        st, ev, rss = trial, ev_t, rss_t
        # a non-linear parameter undetermined at the start (a time constant whose coefficient starts at zero)
        # can only be seen from the new point: linearise once more there before calling it converged
        revisit = it == 1 and bool(np.any(undet)) and any(not t.linear for t in pr.terms)
        if (linear_enough or flat) and not revisit:
            # the step did what the linearisation promised: a second linearisation would move the
            # parameters by a negligible amount, so keep this one and move the block gradients with it
            g_b = g_b + np.einsum("bij,j->bi", a_b, delta)
            converged = True
            break
        if progress is not None:
            progress(f"iteration {it}")
    values = _flatten(pr, st)
    held = None if lo is None else values <= lo + 1e-12 * np.maximum(1.0, np.abs(np.nan_to_num(lo, neginf=0.0)))
    held = held if held is not None and held.any() else None
    if held is not None:
        # at its floor with the data asking for less: out of the normal equations (its error is not a measurement)
        a_b, g_b = a_b.copy(), g_b.copy()
        a_b[:, held, :] = 0.0
        a_b[:, :, held] = 0.0
        g_b[:, held] = 0.0
        _, cov, undet, rank = solve_normal(a_b.sum(0), g_b.sum(0))
    s2 = rss / max(n_rows - rank, 1)
    chans = Channels(pr.channel_names, ev.channel_matrix(), pr.data.t_s[pr.rows], pr.rows)
    return FitResult(problem=pr, state=st, channels=chans, values=values,
                     stderr=np.sqrt(np.clip(cov * s2, 0, None)), undetermined=undet, rank=rank, rss_w=rss,
                     iterations=it, converged=converged, a_blocks=a_b, g_blocks=g_b, jac=jac, ev=ev, at_floor=held)


def _assemble(pr: Problem, jac: _Jac, ev: _Eval, warm: Warm | None) -> tuple[np.ndarray, np.ndarray]:
    """The per-block normal matrices and gradients of this linearisation; with `warm`, only the rows of the
    parameters warm does not know are assembled, the known ones taken from it."""
    if warm is None:
        return pr.assemble(jac, ev)
    a_b, g_b = pr.assemble(jac, ev, only=~warm.known)
    keep = warm.known
    a_b[:, keep[:, None] & keep[None, :]] = warm.a_blocks[:, keep[:, None] & keep[None, :]]
    g_b[:, keep] = warm.g_blocks[:, keep]
    return a_b, g_b


def _take_last_step(pr: Problem, st: State, ev: _Eval, rss: float, delta: np.ndarray, a_b: np.ndarray,
                    g_b: np.ndarray) -> tuple[State, _Eval, float, np.ndarray]:
    """The last, tiny step taken without re-linearising unless it raises the RSS: (state, residuals, RSS, block
    gradients), the gradients moved with it (g_b + A_b delta) so the held-out solves start from the final point."""
    trial = pr.update(st, delta)
    ev_t = pr.evaluate(trial)
    rss_t = pr.weighted_rss(ev_t)
    if np.isfinite(rss_t) and rss_t <= rss * (1 + 1e-9):
        return trial, ev_t, rss_t, g_b + np.einsum("bij,j->bi", a_b, delta)
    return st, ev, rss, g_b


def _held_at_floors(a: np.ndarray, g: np.ndarray, delta: np.ndarray,
                    room: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normal equations and step with the parameters at their floor that the step would take lower held
    there (out of the equations, the others solved without them), and every other step stopped at its floor:
    (a, g, delta). `room`: how far each parameter may go down (0 at its floor)."""
    held = (room >= 0.0) & (delta < room)
    if held.any():
        a, g = a.copy(), g.copy()
        a[held, :] = 0.0
        a[:, held] = 0.0
        g[held] = 0.0
        delta = solve_normal(a, g)[0]
    return a, g, np.maximum(delta, room)


def _descent_step(pr: Problem, st: State, rss: float, a: np.ndarray, g: np.ndarray, delta: np.ndarray,
                  room: np.ndarray | None = None) -> tuple[np.ndarray, float, State, _Eval, float] | None:
    """A step that does not raise the RSS: the Gauss-Newton `delta`, else (Levenberg-Marquardt) one retried
    shorter and turned towards the gradient, up to ten times; (step, damping, state, residuals, RSS) or None
    when none descends (the fit is at the minimum). a, g: the summed normal equations; `room`: how far each
    parameter may go down (its floor)."""
    damping = 0.0
    for _ in range(10):
        # a step that does not lower the RSS (a badly determined direction taken too far) is retried damped
        if damping > 0:
            delta, *_ = solve_normal(a, g, damping)
            delta = delta if room is None else np.maximum(delta, room)
        trial = pr.update(st, delta)
        ev_t = pr.evaluate(trial)
        rss_t = pr.weighted_rss(ev_t)
        if np.isfinite(rss_t) and rss_t <= rss * (1 + 1e-12) + 1e-12:
            return delta, damping, trial, ev_t, rss_t
        damping = 1e-6 if damping == 0 else damping * 10.0
    return None


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
