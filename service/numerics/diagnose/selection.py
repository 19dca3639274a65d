"""Discovery's selection (discover.py steps 1-3): the normal equations of the model and of each candidate group, per
time block (screening), the grouped forward selection inside training blocks, and the held-out judgement of the
whole procedure. Numerics only."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.engine import RANK_TOL, FitResult, solve_normal
from fluxcal.service.numerics.engine.jacobian import block_jacobian, local_jacobian

from .library import Group
from .result import GAIN_SIGMAS, MIN_GAIN

#: rows of the normal equations of the library, spread evenly over each block
SCREEN_ROWS = 16384
#: rows per chunk of the assembly
CHUNK_ROWS = 1024
#: discovery's time blocks: each of the fit's (N_BLOCKS) cut in this many: the held-out test's standard error comes
#: from the spread of more blocks (a real hour-long recording with a lagged heater added: 8 blocks left its 13 %
#: gain at 1.2 standard errors, 16 at 2.6)
BLOCK_SPLIT = 2
#: the groups each selection chooses among: the strongest of those whose F-test beside the model alone, on its
#: training blocks, is below P_SIGNIFICANT over the number tried (the dense normal equations are for these only)
SHORTLIST = 16
#: groups a discovered set holds at most
MAX_GROUPS = 4


@dataclass
class _Span:
    start: int
    stop: int

    @property
    def size(self) -> int:
        return self.stop - self.start


@dataclass
class Normals:
    """Per block: A (K, p, p), g (K, p), the weighted sum of squares and the count of residual values; the first
    n_model parameters the model's, then each group's span."""

    a: np.ndarray
    g: np.ndarray
    sse: np.ndarray
    n: np.ndarray
    n_model: int
    spans: list[slice]
    nested: list[int | None] = field(default_factory=list)    # per group, a smaller group it holds (nested_in)
    #: heldout_sse's answers by (parameters, train blocks, test blocks): the selection asks a third of them again
    memo: dict = field(default_factory=dict, repr=False, compare=False)


def blocks_of(fit: FitResult, split: int = BLOCK_SPLIT) -> list[tuple[int, int]]:
    """Discovery's time blocks: (start, stop) positions in the fit's rows."""
    return _edges(fit, split)


def _edges(fit: FitResult, split: int) -> list[tuple[int, int]]:
    """Discovery's time blocks: each of the fit's cut into `split` contiguous ones (positions in the fit's rows)."""
    return [(int(a), int(b)) for blk in fit.problem.blocks
            for a, b in zip(np.linspace(blk.start, blk.stop, split + 1)[:-1].round(),
                            np.linspace(blk.start, blk.stop, split + 1)[1:].round()) if b > a]


def _channels(fit: FitResult):
    """(probe, kind) of every residual channel family the assembly visits."""
    pr = fit.problem
    for k in range(pr.P):
        for kind in ("scalar", "diff", "vec"):
            if (kind == "diff" and k == 0) or (kind == "vec" and pr.vref is None):
                continue
            yield k, kind


def _chunks_of(fit: FitResult, split: int, max_rows: int):
    """(block, positions) of the rows the normal equations use: at most max_rows spread evenly, CHUNK_ROWS at a time."""
    stride = max(1, -(-fit.problem.M // max_rows))
    for b, (lo_b, hi_b) in enumerate(_edges(fit, split)):
        pos = np.arange(lo_b, hi_b, stride)
        for lo in range(0, pos.size, CHUNK_ROWS):
            yield b, pos[lo:lo + CHUNK_ROWS]


def _response(g: Group, data: EffectData, fit: FitResult, rows: np.ndarray, start: int = 0) -> tuple:
    """A group's slot for local_jacobian at `rows`: its span and d v_k / d theta for the probes it moves."""
    lin = fit.state.linear
    cols = g.columns(data, lin.offset_nT, rows)
    vb = ({k: -cols for k in range(fit.problem.P)} if g.common else
          {g.probe: -np.matmul(lin.matrix[g.probe], cols)})
    return (_Span(start, start + g.size), vb, None)


def _weighted(fit: FitResult, r: np.ndarray, k: int, kind: str) -> tuple[Any, np.ndarray]:
    pr = fit.problem
    if kind == "scalar":
        return pr.weights[k], r[:, k] * pr.weights[k]
    cols = pr._cols(kind, k)
    return pr.weights[cols], (r[:, cols] * pr.weights[cols]).reshape(-1)


def normals(data: EffectData, fit: FitResult, groups: list[Group], max_rows: int = SCREEN_ROWS,
            split: int = BLOCK_SPLIT) -> Normals:
    """The normal equations of the model and the groups at fit's state, block by block (see the module doc): each of
    the fit's time blocks cut into `split` contiguous ones. Dense: for the groups a selection chooses among."""
    pr = fit.problem
    spans, start = [], pr.n_params
    for g in groups:
        spans.append(slice(start, start + g.size))
        start += g.size
    p, nb = start, len(_edges(fit, split))
    a, gv = np.zeros((nb, p, p)), np.zeros((nb, p))
    sse, cnt = np.zeros(nb), np.zeros(nb)
    for b, chunk in _chunks_of(fit, split, max_rows):
        rows = pr.rows[chunk]
        blk = block_jacobian(pr, fit.jac, chunk) if pr.n_params else []
        blk += [_response(g, data, fit, rows, sp.start) for g, sp in zip(groups, spans)]
        r = fit.channels.values[chunk]
        sse[b] += float(np.sum((r * pr.weights) ** 2))
        cnt[b] += r.size
        for k, kind in _channels(fit):
            w, rl = _weighted(fit, r, k, kind)
            local = local_jacobian(blk, fit.ev.nhat[k][chunk] if kind == "scalar" else None, k, kind, w)
            if local is None:
                continue
            jl, idx = local
            a[b][np.ix_(idx, idx)] += jl.T @ jl
            gv[b, idx] += jl.T @ rl
    return Normals(a, gv, sse, cnt, pr.n_params, spans, nested_in(groups))


def nested_in(groups: list[Group]) -> list[int | None]:
    """Per group, the index among `groups` of the next smaller group it holds (Group.holds), else None: a scale group
    (offset and scale factors following x) the offset group of the same probe and feature, a spline of x the smaller
    spline, the smallest spline the offset that follows x."""
    where = {(g.kind, g.probe, g.feature.name): i for i, g in enumerate(groups)}
    return [None if g.holds is None else where.get(g.holds) for g in groups]


def held_by(nested: list[int | None], i: int) -> list[int]:
    """Every group that group i holds, down its chain of nested groups (the next smaller first)."""
    out: list[int] = []
    j = nested[i] if nested else None
    while j is not None and j not in out:
        out.append(j)
        j = nested[j]
    return out


@dataclass
class Marginals:
    """Per block, the model's normal equations and, per group, its own block and its cross terms with the model only
    (not with the other groups): enough for each group's F-test beside the model on any set of blocks, at a cost and
    a memory linear in the library's size."""

    a_mm: np.ndarray                 # (K, pm, pm)
    g_m: np.ndarray                  # (K, pm)
    sse: np.ndarray
    n: np.ndarray
    a_gg: list[np.ndarray]           # per group (K, m, m)
    a_gm: list[np.ndarray]           # per group (K, m, pm)
    g_g: list[np.ndarray]            # per group (K, m)


def marginals(data: EffectData, fit: FitResult, groups: list[Group], max_rows: int = SCREEN_ROWS,
              split: int = BLOCK_SPLIT) -> Marginals:
    pr = fit.problem
    pm, nb = pr.n_params, len(_edges(fit, split))
    out = Marginals(np.zeros((nb, pm, pm)), np.zeros((nb, pm)), np.zeros(nb), np.zeros(nb),
                    [np.zeros((nb, g.size, g.size)) for g in groups], [np.zeros((nb, g.size, pm)) for g in groups],
                    [np.zeros((nb, g.size)) for g in groups])
    for b, chunk in _chunks_of(fit, split, max_rows):
        rows = pr.rows[chunk]
        blk = block_jacobian(pr, fit.jac, chunk) if pm else []
        r = fit.channels.values[chunk]
        out.sse[b] += float(np.sum((r * pr.weights) ** 2))
        out.n[b] += r.size
        model: dict[tuple[int, str], Any] = {}
        for k, kind in _channels(fit):
            w, rl = _weighted(fit, r, k, kind)
            nh = fit.ev.nhat[k][chunk] if kind == "scalar" else None
            local = local_jacobian(blk, nh, k, kind, w) if blk else None
            model[(k, kind)] = (w, rl, local)
            if local is not None:
                jm, idx = local
                out.a_mm[b][np.ix_(idx, idx)] += jm.T @ jm
                out.g_m[b, idx] += jm.T @ rl
        for i, g in enumerate(groups):
            slot = [_response(g, data, fit, rows)]
            for (k, kind), (w, rl, local) in model.items():
                if g.common and kind == "diff":
                    continue                                   # a common field cancels in the differences
                if not g.common and not (k == g.probe or (kind == "diff" and g.probe == 0)):
                    continue
                mine = local_jacobian(slot, fit.ev.nhat[k][chunk] if kind == "scalar" else None, k, kind, w)
                if mine is None:
                    continue
                jg = mine[0]
                out.a_gg[i][b] += jg.T @ jg
                out.g_g[i][b] += jg.T @ rl
                if local is not None:
                    jm, idx = local
                    out.a_gm[i][b][:, idx] += jg.T @ jm
    return out


def shortlist(mg: Marginals, train: list[int], p_level: float, size: int,
              candidates: list[int] | None = None) -> list[int]:
    """The groups whose F-test beside the model alone, on the train blocks, is below p_level: the `size` strongest
    (among `candidates`, where given)."""
    a_mm, g_m, sse = mg.a_mm[train].sum(0), mg.g_m[train].sum(0), float(mg.sse[train].sum())
    n_t = float(mg.n[train].sum())
    model = Nested.of(a_mm, g_m, sse)
    scored = []
    for i in range(len(mg.a_gg)) if candidates is None else candidates:
        rss1, rank1 = model.adding(mg.a_gg[i][train].sum(0), mg.a_gm[i][train].sum(0), mg.g_g[i][train].sum(0))
        dp = rank1 - model.rank
        if dp <= 0 or not rss1 < model.rss:
            continue
        dof = max(n_t - rank1, 1.0)
        logp = f_logsf(((model.rss - rss1) / dp) / (max(rss1, 1e-300) / dof), dp, dof)
        if logp <= np.log(p_level):
            scored.append((logp, -(model.rss - rss1), i))
    scored.sort()
    return [i for _, _, i in scored[:size]]


@dataclass
class Nested:
    """A least-squares problem in normal equations (A, g, the sum of squares at zero) solved once, so that each group
    added beside it is an F-test of its own size only: with the columns C of the group, the Schur complement
    S = A_CC - A_CB A_BB^+ A_BC and h = g_C - A_CB A_BB^+ g_B give rss = rss_B - h^T S^+ h and the rank rank_B +
    rank(S). The dense solve of the joint system cost the model's size cubed for every group and fold (27 of a
    diagnose's 70 s beside a catalogue term of 126 parameters). Ranks as solve_normal takes them, on the
    column-scaled system: a direction of S below RANK_TOL of its own columns' scale is in the span of B."""

    inv: np.ndarray                  # A_BB^+ (unscaled)
    g: np.ndarray
    rss: float
    rank: int

    @classmethod
    def of(cls, a: np.ndarray, g: np.ndarray, sse: float) -> "Nested":
        inv, rank = _pinv(a)
        return cls(inv, g, sse - float(g @ inv @ g), rank)

    def adding(self, a_cc: np.ndarray, a_cb: np.ndarray, g_c: np.ndarray) -> tuple[float, int]:
        """(the weighted sum of squares, the rank) with the columns C added: A_CC, A_CB, g_C."""
        x = a_cb @ self.inv
        s_c = a_cc - x @ a_cb.T
        h = g_c - x @ self.g
        s_inv, rank = _pinv(0.5 * (s_c + s_c.T), scale=np.diag(a_cc))
        return self.rss - float(h @ s_inv @ h), self.rank + rank


def _pinv(a: np.ndarray, scale: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """A^+ and its rank, on the system scaled by sqrt(diag(scale)) (A's own diagonal by default), eigenvalues below
    RANK_TOL of the largest (or of one, for a Schur complement scaled by its columns' own diagonal) dropped."""
    if a.shape[0] == 0:
        return np.zeros((0, 0)), 0
    d = np.sqrt(np.clip(np.diag(a) if scale is None else scale, 0.0, None))
    d[d <= 0] = 1.0
    lam, vec = np.linalg.eigh(a / np.outer(d, d))
    top = max(float(lam[-1]), 1e-300) if scale is None else max(float(lam[-1]), 1.0)
    keep = lam > RANK_TOL * top
    vk = vec[:, keep] / d[:, None]
    return (vk / lam[keep]) @ vk.T, int(keep.sum())


#: below this ln p scipy's tail is a denormal float (a few values left: ties again decided by sums of squares)
DENORMAL_LOG = -700.0


def f_logsf(f: float, d1: float, d2: float) -> float:
    """ln P(F > f) for F(d1, d2), also where the probability is below the smallest float: there scipy gives -inf,
    and the groups of a strong effect all tied at -inf were then ranked by their sum of squares alone, which the
    larger group always wins (an offset that follows a lagged heater lost to the 6 parameters of its offset and
    scale). The tail is I_x(d2/2, d1/2), x = d2 / (d2 + d1 f) (log_betainc)."""
    if not f > 0 or not np.isfinite(f):
        return 0.0 if not f > 0 else -np.inf
    from scipy import special                           # here, not at import (a command's start)

    with np.errstate(divide="ignore"):                   # scipy.stats.f.logsf's own figure, without its checks
        v = float(np.log(special.fdtrc(d1, d2, f)) if f > special.fdtri(d1, d2, 0.5)
                  else np.log1p(-special.fdtr(d1, d2, f)))
    x = d2 / (d2 + d1 * f)
    if (np.isfinite(v) and v > DENORMAL_LOG) or not x < (0.5 * d2 + 1.0) / (0.5 * (d1 + d2) + 2.0):
        return v
    return log_betainc(0.5 * d2, 0.5 * d1, x)       # where scipy's figure is denormal (a few values left) or -inf


def log_betainc(a: float, b: float, x: float) -> float:
    """ln I_x(a, b), the regularised incomplete beta function, for x below (a + 1) / (a + b + 2), by its continued
    fraction (modified Lentz, as Numerical Recipes' betacf), where it converges: x^a (1 - x)^b / (a B(a, b)) times
    the fraction, taken in logarithms so that it holds far below the smallest float."""
    from scipy import special

    tiny = 1e-300
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c, d = 1.0, 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 10000):
        m2 = 2 * m
        for aa in (m * (b - m) * x / ((qam + m2) * (a + m2)), -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-12:
            break
    return float(a * np.log(x) + b * np.log1p(-x) - np.log(a) - special.betaln(a, b) + np.log(h))


# --- the selection, inside training blocks ------------------------------------------------------------

def _idx(nm: Normals, chosen: list[int]) -> np.ndarray:
    return np.concatenate([np.arange(nm.n_model)] + [np.arange(nm.spans[i].start, nm.spans[i].stop) for i in chosen])


def _solve(a: np.ndarray, g: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, int]:
    """delta on idx (-A^+ g of the sub-system) and its rank."""
    if idx.size == 0:
        return np.zeros(0), 0
    d, _, _, rank = solve_normal(a[np.ix_(idx, idx)], g[idx])
    return d, rank


def rss_of(a: np.ndarray, g: np.ndarray, sse: float, idx: np.ndarray) -> tuple[float, int]:
    d, rank = _solve(a, g, idx)
    return sse + float(g[idx] @ d), rank


def fit_all(nm: Normals) -> tuple[np.ndarray, float]:
    """The linearised fit of the model and every group on all blocks: (delta, its weighted sum of squares)."""
    a, g = nm.a.sum(0), nm.g.sum(0)
    d, _ = _solve(a, g, np.arange(a.shape[0]))
    return d, float(nm.sse.sum()) + float(g @ d)


def heldout_sse(nm: Normals, idx: np.ndarray, train: list[int], test: list[int]) -> np.ndarray:
    """Weighted SSE of each test block predicted by the fit on the train blocks less that block (linearised); each
    answer worked out once per Normals."""
    key = (idx.tobytes(), tuple(train), tuple(test))
    if key not in nm.memo:
        nm.memo[key] = _heldout_sse(nm, idx, train, test)
    return nm.memo[key].copy()


def _heldout_sse(nm: Normals, idx: np.ndarray, train: list[int], test: list[int]) -> np.ndarray:
    out = np.zeros(len(test))
    if idx.size == 0:
        return nm.sse[test].astype(float)
    a_i, g_i = nm.a[np.ix_(np.arange(nm.a.shape[0]), idx, idx)], nm.g[:, idx]     # the sub-system alone
    a_t, g_t = a_i[train].sum(0), g_i[train].sum(0)
    for i, j in enumerate(test):
        a, g = (a_t - a_i[j], g_t - g_i[j]) if j in train else (a_t, g_t)
        d = solve_normal(a, g)[0]
        out[i] = nm.sse[j] + 2.0 * float(g_i[j] @ d) + float(d @ a_i[j] @ d)
    return out


def _passes(sse_base: np.ndarray, sse_with: np.ndarray, n: np.ndarray) -> tuple[bool, float, float, float]:
    """The catalogue's held-out rule: (passes, gain, mean log ratio, its standard error)."""
    gain = 1.0 - float(sse_with.sum() / sse_base.sum()) if sse_base.sum() > 0 else 0.0
    lr_b = np.log(np.maximum(sse_base / n, 1e-300) / np.maximum(sse_with / n, 1e-300))
    lr = float(lr_b.mean())
    se = float(lr_b.std(ddof=1) / np.sqrt(lr_b.size)) if lr_b.size > 1 else float("inf")
    return gain >= MIN_GAIN and lr > GAIN_SIGMAS * se, gain, lr, se


def select(nm: Normals, train: list[int], p_level: float, max_groups: int = MAX_GROUPS,
           allowed: np.ndarray | None = None) -> list[int]:
    """Grouped forward selection on the train blocks alone (the module doc, step 2): the groups chosen, in order.
    Where the strongest group holds a smaller one of the same feature (a scale group its offset), the smaller is
    taken unless the larger's held-out gain beside it passes the held-out rule: the smallest set that predicts (on
    a real residual, whose structure the F-test takes for signal, the 6 parameters of a heater's offset and scale
    outranked its offset alone and predicted the held-out blocks worse). The smaller is taken only where the fold
    allows it (`allowed`), and a larger chosen after its smaller replaces it."""
    a_t, g_t, sse_t = nm.a[train].sum(0), nm.g[train].sum(0), float(nm.sse[train].sum())
    n_t = float(nm.n[train].sum())
    log_level = np.log(p_level)
    chosen: list[int] = []
    while len(chosen) < max_groups:
        base = _idx(nm, chosen)
        fitted = Nested.of(a_t[np.ix_(base, base)], g_t[base], sse_t)
        rss0, rank0 = fitted.rss, fitted.rank
        best = None
        for gi, sp in enumerate(nm.spans):
            if gi in chosen or (allowed is not None and not allowed[gi]):
                continue
            cols = np.arange(sp.start, sp.stop)
            rss1, rank1 = fitted.adding(a_t[np.ix_(cols, cols)], a_t[np.ix_(cols, base)], g_t[cols])
            dp = rank1 - rank0
            if dp <= 0 or not rss1 < rss0:
                continue
            dof = max(n_t - rank1, 1.0)
            f = ((rss0 - rss1) / dp) / (max(rss1, 1e-300) / dof)
            logp = f_logsf(f, dp, dof)
            key = (logp, -(rss0 - rss1))
            if best is None or key < best[0]:
                best = (key, gi)
        if best is None or best[0][0] > log_level:
            break
        gi = _smallest(nm, chosen, best[1], train, allowed)
        with_g = _idx(nm, [c for c in chosen if c not in held_by(nm.nested, gi)] + [gi])
        s0 = heldout_sse(nm, base, train, train)
        s1 = heldout_sse(nm, with_g, train, train)
        if not _passes(s0, s1, nm.n[train])[0]:
            break
        # the larger holds them: one group, never its columns twice
        chosen = [c for c in chosen if c not in held_by(nm.nested, gi)] + [gi]
    return chosen


def _smallest(nm: Normals, chosen: list[int], gi: int, train: list[int], allowed: np.ndarray | None) -> int:
    """Down the chain of smaller groups that group gi holds (a spline of x: the smaller spline, then x itself), the
    first whose larger neighbour does not predict the training blocks better beside it by the held-out rule; where
    the fold does not allow the smaller, or it is chosen already, the larger stays."""
    while True:
        sub = nm.nested[gi] if nm.nested else None
        if sub is None or sub in chosen or (allowed is not None and not allowed[sub]):
            return gi
        if _passes(heldout_sse(nm, _idx(nm, chosen + [sub]), train, train),
                   heldout_sse(nm, _idx(nm, chosen + [gi]), train, train), nm.n[train])[0]:
            return gi
        gi = sub


def prune(nm: Normals) -> list[int]:
    """The groups of `nm` (all chosen, in order) that still pass the held-out rule beside the others, each block
    predicted by the rest (the last first; one stays at least). The choice was made with a lag's time constant on
    its grid: a second lag of the same column can pass there as the first's correction, and stay beside it once its
    time constant is refined (a simulated 3-s lag read as 2.9 s and 1.7 s of opposite signs, its errors no longer
    covering the truth; alone, (7.98, -5.98, 4) +- 0.02 for (8, -6, 4))."""
    keep = list(range(len(nm.spans)))
    every = list(range(nm.a.shape[0]))
    for i in reversed(range(len(nm.spans))):
        if len(keep) < 2:
            break
        others = [j for j in keep if j != i]
        if not _passes(heldout_sse(nm, _idx(nm, others), every, every), heldout_sse(nm, _idx(nm, keep), every, every),
                       nm.n)[0]:
            keep = others
    return keep


@dataclass
class Crossval:
    """The selection judged on held-out blocks: each block predicted by what the selection chose without it."""

    sse_base: np.ndarray
    sse_with: np.ndarray
    n: np.ndarray
    chosen: list[list[int]]

    @property
    def verdict(self) -> tuple[bool, float, float, float]:
        return _passes(self.sse_base, self.sse_with, self.n)


def crossval(nm: Normals, p_level: float, allowed: list[np.ndarray] | None = None) -> Crossval:
    """allowed: per block, the groups the selection without that block may choose (its shortlist)."""
    k = nm.a.shape[0]
    base, with_, chosen = np.zeros(k), np.zeros(k), []
    model = _idx(nm, [])
    for b in range(k):
        train = [j for j in range(k) if j != b]
        s = select(nm, train, p_level, allowed=None if allowed is None else allowed[b], )
        chosen.append(s)
        base[b] = heldout_sse(nm, model, train, [b])[0]
        with_[b] = heldout_sse(nm, _idx(nm, s), train, [b])[0] if s else base[b]
    return Crossval(base, with_, nm.n.copy(), chosen)


# --- the result -----------------------------------------------------------------------------------------
