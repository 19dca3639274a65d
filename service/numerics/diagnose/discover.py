"""Discovery: the missing term found in a library of candidate groups (library.py), judged like the catalogue.

1. Screening: per time block, the normal equations of the model's parameters and of each group of the library
   beside them (not of the groups with each other: linear in the library's size), linearised at the model's fit, on
   at most SCREEN_ROWS rows spread evenly over each block (the residual, the model's Jacobian and each group's
   response: a probe's group in its scalar channel and its differences, a common one in the scalar channels). For
   each fold (the blocks less one) and for all blocks, the SHORTLIST groups whose F-test beside the model, on those
   blocks alone, is strongest and below P_SIGNIFICANT over the number of groups tried. The lines and bands a fold
   may follow are those its training blocks show (fold_waves).
2. Grouped forward selection among a fold's shortlist, every choice made inside its training blocks (the dense
   normal equations of the shortlists' union): the group whose F-test is strongest is added while its p-value is
   below that level and, leaving each training block out in turn, its held-out gain is at least MIN_GAIN and
   GAIN_SIGMAS standard errors (block to block) above zero; at most MAX_GROUPS. The F-test alone passes a real
   residual's structure (on a real hand-turned sphere it chose four groups in every fold, three of them noise),
   and prefers a larger group there: one that holds a smaller (an offset and scale, its offset) is taken only
   where it predicts the training blocks better than the smaller. The low-pass time constant, the speed's unit and
   the frequency are which group of the library is chosen, so they are chosen there too.
3. The procedure judged on held-out blocks: for each block, the selection run on the others and the block
   predicted by what it chose and fitted there. Discovery claims a set of groups only where that held-out gain
   is at least MIN_GAIN and GAIN_SIGMAS standard errors above zero (exact for the linearised problem).
4. The set chosen on all blocks (a lag's time constant then refined between its grid neighbours, a loop's sign
   taken again from the reading less its steps) fitted by the
   engine beside the model (all rows, Gauss-Newton, 1/f-aware standard errors); a group stays only where its
   parameters stand beyond their errors (jointly, or one alone) at P_SIGNIFICANT over the number of groups tried;
   read back as physics with standard errors.

Numerics only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from drivers.errors import FluxcalError
from service.numerics.effects.base import AXES, EffectData
from service.numerics.engine import FitResult, Parameter, Problem, residual_hints
from service.numerics.jsonsafe import finite_or_none as _num
from service.numerics.jsonsafe import json_safe as _plain

from .fits import Heldout, _beyond_errors, _compare, _fit_beside, heldout
from .library import (
    LOOP_SCALES,
    TAU_RATIO,
    Group,
    GroupTerm,
    Library,
    build_library,
    loop_feature,
    loop_label,
    relagged,
    wave_features,
    wave_groups,
)
from .result import GAIN_SIGMAS, MIN_GAIN, P_SIGNIFICANT
from .selection import SHORTLIST, blocks_of, crossval, fit_all, marginals, normals, rss_of, select, shortlist


@dataclass
class FoundGroup:
    """A discovered group read back as physics: its parameters with standard errors and what they say."""

    group: Group
    term: str                                   # the engine's name for it in the fit
    parameters: list[Parameter]
    reading: str                                # one sentence of physics
    parts: dict[str, Any] = field(default_factory=dict)

    @property
    def observable(self) -> str:
        return self.group.feature.observable

    def as_dict(self) -> dict[str, Any]:
        g, f = self.group, self.group.feature
        return {"probe": None if g.common else g.probe_name, "kind": g.kind, "feature": f.name,
                "observable": f.observable, "how": f.how, "frame": g.frame, "per_sample": g.per_sample,
                "borrowed": f.borrowed, "reading": self.reading, "parts": _plain(self.parts),
                "parameters": [{"name": p.name, "value": _num(p.value), "stderr": _num(p.stderr)}
                               for p in self.parameters]}


@dataclass
class Discovery:
    """What discovery tried and found (or why it claims nothing)."""

    tried: int                                  # groups in the library
    tried_params: int
    claimed: bool
    groups: list[FoundGroup]
    base_rms_nT: float
    base_heldout_rms_nT: float
    floor_nT: float
    rms_nT: float | None = None                 # in-sample, with the groups (engine fit, all rows)
    heldout_rms_nT: float | None = None         # held-out, with the groups chosen on all blocks
    gain: float | None = None                   # that held-out gain (the engine's blocks)
    cv_gain: float = 0.0                        # the selection judged on held-out blocks (choices inside training)
    cv_log_ratio: float = 0.0
    cv_log_ratio_se: float = 0.0
    reason: str | None = None                   # why nothing is claimed
    taus_s: list[float] = field(default_factory=list)
    lines_hz: list[float] = field(default_factory=list)
    borrowed: dict[str, str] = field(default_factory=dict)
    fit: FitResult | None = field(default=None, repr=False)

    @property
    def terms(self) -> list[str]:
        return [g.term for g in self.groups]

    def sentence(self) -> str:
        """The finding in one sentence (for the verdict), or why nothing is claimed."""
        if not self.claimed:
            return f"discovery tried {self.tried} groups beyond the catalogue and claims none: {self.reason}"
        found = "; ".join(g.reading for g in self.groups)
        return (f"discovered beyond the catalogue: {found}; with {'it' if len(self.groups) == 1 else 'them'} the "
                f"held-out error falls from {self.base_heldout_rms_nT:.3f} to {self.heldout_rms_nT:.3f} nT against a "
                f"{self.floor_nT:.3f} nT floor (chosen inside training blocks, judged on held-out ones: gain "
                f"{100 * self.cv_gain:.0f} %); write it as an effect of your own (docs/effects.md)")

    def as_dict(self) -> dict[str, Any]:
        return {"tried": self.tried, "tried_params": self.tried_params, "claimed": self.claimed,
                "groups": [g.as_dict() for g in self.groups], "base_rms_nT": _num(self.base_rms_nT),
                "base_heldout_rms_nT": _num(self.base_heldout_rms_nT), "floor_nT": _num(self.floor_nT),
                "rms_nT": _num(self.rms_nT), "heldout_rms_nT": _num(self.heldout_rms_nT), "gain": _num(self.gain),
                "cv_gain": _num(self.cv_gain), "cv_log_ratio": _num(self.cv_log_ratio),
                "cv_log_ratio_se": _num(self.cv_log_ratio_se), "reason": self.reason, "taus_s": list(self.taus_s),
                "lines_hz": list(self.lines_hz), "borrowed": dict(self.borrowed), "sentence": self.sentence()}


# --- discovery ------------------------------------------------------------------------------------------

def discover(data: EffectData, base: FitResult, base_ho: Heldout, reference: np.ndarray, weights: np.ndarray,
             n_blocks: int, floor_nT: float, *, library: Library | None = None,
             progress: Callable[[str], None] | None = None) -> Discovery:
    """Find the groups of the library that the model `base` misses (the module doc). reference, weights,
    n_blocks: as base was fitted."""
    def tell(msg: str) -> None:
        if progress is not None:
            progress(msg)

    lib = library or build_library(data, base, 1.0 / weights)
    groups = list(lib.groups)
    out = Discovery(tried=len(groups), tried_params=lib.n_params, claimed=False, groups=[],
                    base_rms_nT=base.rms_nT, base_heldout_rms_nT=base_ho.rms_nT, floor_nT=floor_nT,
                    taus_s=lib.taus_s, lines_hz=lib.lines_hz, borrowed=lib.borrowed)
    if not groups:
        out.reason = "the data carry nothing to build a group from"
        return out
    p_level = P_SIGNIFICANT / len(groups)
    n_lib = len(groups)
    # the lines and bands each fold's selection may follow: those its own training blocks show
    extra, owner, hidden = fold_waves(data, base, 1.0 / weights, groups, blocks_of(base))
    groups += extra
    tell(f"screening {len(groups)} groups")
    mg = marginals(data, base, groups)
    k = mg.sse.size
    lists = [shortlist(mg, [j for j in range(k) if j != b], p_level, SHORTLIST,
                       [i for i in range(len(groups)) if (i < n_lib and i not in hidden[b])
                        or (i >= n_lib and owner[i - n_lib] == b)]) for b in range(k)]
    lists.append(shortlist(mg, list(range(k)), p_level, SHORTLIST, list(range(n_lib))))
    union = sorted(set().union(*lists))
    # the offset group each scale group holds, which the selection takes instead where the scale adds nothing
    held = {(g.probe, g.feature.name): i for i, g in enumerate(groups) if g.kind == "offset"}
    union = sorted(set(union) | {held[(groups[i].probe, groups[i].feature.name)] for i in union
                                 if groups[i].kind == "scale" and (groups[i].probe, groups[i].feature.name) in held})
    if not union:
        out.reason = (f"no group's F-test beside the model reaches p < {p_level:.2g} (P_SIGNIFICANT over the "
                      f"{n_lib} groups tried)")
        return out
    tell(f"selection inside training blocks among {len(union)} groups")
    nm = normals(data, base, [groups[i] for i in union])
    where = {g: j for j, g in enumerate(union)}
    allowed = [np.isin(np.arange(len(union)), [where[i] for i in lst]) for lst in lists]
    cv = crossval(nm, p_level, allowed=allowed[:k])
    ok, out.cv_gain, out.cv_log_ratio, out.cv_log_ratio_se = cv.verdict
    chosen = [union[j] for j in select(nm, list(range(k)), p_level, allowed=allowed[k])]
    if not chosen:
        out.reason = (f"no group passes the selection on all blocks (F-test at p < {p_level:.2g}, held-out gain at "
                      f"least {100 * MIN_GAIN:g} % and {GAIN_SIGMAS:g} standard errors above zero)")
        return out
    if not ok:
        sigmas = out.cv_log_ratio / out.cv_log_ratio_se if out.cv_log_ratio_se > 0 else 0.0
        out.reason = (f"chosen inside training blocks, the groups do not predict the held-out ones (gain "
                      f"{100 * out.cv_gain:.1f} %, {sigmas:.1f} "
                      f"standard errors; needs {100 * MIN_GAIN:g} % and {GAIN_SIGMAS:g})")
        return out
    tell("fitting the groups found")
    kept = refine_loops(data, base, refine_lags(data, base, [groups[i] for i in chosen]))
    return conclude(out, data, base, base_ho, kept, reference, weights, n_blocks, p_level)


#: a line that a fold's training blocks show is the whole residual's where their frequencies differ by at most this
#: many cycles per record (a phase error of a few degrees over the record)
SAME_LINE_CYCLES = 0.1


def fold_waves(data: EffectData, base: FitResult, noise: np.ndarray, groups: list[Group],
               edges: list[tuple[int, int]]) -> tuple[list[Group], list[int], list[set[int]]]:
    """The residual chooses the lines and the bands (a column's phase tried where its band holds excess power) that
    the library follows; seen on the whole residual, a held-out block's own noise would have helped choose them. So
    each fold looks at its training blocks alone: a wave of the library its training blocks do not show is hidden
    from its selection, and one they show that the library lacks is added for it alone. Returns (the groups added,
    the fold each belongs to, per fold the indices in `groups` hidden from it)."""
    full = {id(g.feature): g.feature for g in groups if g.kind in ("wave", "common wave")}
    extra: list[Group] = []
    owner: list[int] = []
    hidden: list[set[int]] = []
    for b, span in enumerate(edges):
        seen, new = set(), []
        for f in wave_features(data, base, noise, exclude=span):
            same = next((m for m in full.values() if _same_wave(f, m, data.duration_s)), None)
            if same is None:
                new.append(f)
            else:
                seen.add(id(same))
        hidden.append({i for i, g in enumerate(groups) if id(g.feature) in full and id(g.feature) not in seen})
        added = wave_groups(data, new)
        extra += added
        owner += [b] * len(added)
    return extra, owner, hidden


def _same_wave(f: Any, g: Any, duration_s: float) -> bool:
    if f.how != g.how:
        return False
    if f.how == "phase":
        return f.recipe["column"] == g.recipe["column"] and f.recipe["cycles_per_unit"] == g.recipe["cycles_per_unit"]
    return abs(f.recipe["hz"] - g.recipe["hz"]) * duration_s <= SAME_LINE_CYCLES


def conclude(out: Discovery, data: EffectData, base: FitResult, base_ho: Heldout, kept: list[Group],
             reference: np.ndarray, weights: np.ndarray, n_blocks: int, p_level: float) -> Discovery:
    """The groups fitted by the engine beside `base`; those whose parameters are within their errors dropped (and the
    rest fitted again); read back as physics. `out` filled in and returned."""
    hints = residual_hints(base)
    for _ in range(len(kept)):
        try:
            fit, ho = _fit_groups(data, base, kept, reference, weights, n_blocks, hints)
        except (FluxcalError, np.linalg.LinAlgError, ValueError) as e:
            out.claimed, out.reason = False, f"the fit of the groups found failed: {e}"
            return out
        params = {t.name: [p for p in fit.parameters() if p.term == t.name] for t in fit.problem.terms
                  if isinstance(t, GroupTerm)}
        weak = [t.group for t in fit.problem.terms if isinstance(t, GroupTerm)
                and _beyond_errors(params[t.name], p_level) is not None]
        if not weak:
            break
        kept = [g for g in kept if g not in weak]
        if not kept:
            out.claimed = False
            out.reason = (f"the groups chosen ({', '.join(g.key for g in weak)}) have parameters within their "
                          f"(1/f-aware) errors of zero at p < {p_level:.2g}: the held-out gain follows the noise's "
                          f"slow wander")
            return out
    cmp = _compare(base, base_ho, fit, ho)
    out.claimed, out.reason = True, None
    out.fit = fit
    out.base_rms_nT, out.base_heldout_rms_nT = base.rms_nT, base_ho.rms_nT
    out.rms_nT, out.heldout_rms_nT, out.gain = fit.rms_nT, ho.rms_nT, cmp["gain"]
    out.groups = [read_group(t.group, t.name, params[t.name], fit) for t in fit.problem.terms
                  if isinstance(t, GroupTerm)]
    return out


def beside(found: Discovery, data: EffectData, base: FitResult, base_ho: Heldout, reference: np.ndarray,
           weights: np.ndarray, n_blocks: int) -> Discovery:
    """The groups `found` fitted beside another model (the model without the catalogue's effect it was found
    beside): a new Discovery with the same selection figures."""
    from dataclasses import replace

    again = replace(found, groups=[], fit=None)
    return conclude(again, data, base, base_ho, [g.group for g in found.groups], reference, weights, n_blocks,
                    P_SIGNIFICANT / max(found.tried, 1))


#: a chosen low-pass time constant is refined on all the data over this many steps within a grid step of it
REFINE_STEPS = 9


def refine_lags(data: EffectData, base: FitResult, groups: list[Group]) -> list[Group]:
    """The time constant of each low-passed group chosen, refined on all the data between its grid neighbours
    (the claim was decided on the grid, inside training blocks; this only makes the figure finer)."""
    out = list(groups)
    for i, g in enumerate(groups):
        if g.feature.how != "low-passed":
            continue
        tau0 = float(g.feature.recipe["low_pass_s"])
        best, best_rss = g, np.inf
        for tau in tau0 * TAU_RATIO ** np.linspace(-0.5, 0.5, REFINE_STEPS):
            tau = float(f"{tau:.2g}")
            cand = Group(g.kind, g.probe, g.probe_name, relagged(data, g.feature, tau))
            trial = out[:i] + [cand] + out[i + 1:]
            nm = normals(data, base, trial)
            rss, _ = rss_of(nm.a.sum(0), nm.g.sum(0), float(nm.sse.sum()), np.arange(nm.a.shape[1]))
            if rss < best_rss:
                best, best_rss = cand, rss
        out[i] = best
    return out


#: a chosen loop is refined at most this many times (its steps fitted beside the groups chosen, its sign taken again
#: from the reading less them: library.loop_feature) while the sum of squares falls
LOOP_REFINE = 4
#: a chosen loop's rate window: the data's own (smooth_window_s) times each of these, then refined to the sample
#: between the best one's neighbours, on all the data (as a lag's time constant)
LOOP_WINDOWS = tuple(2.0 ** (np.arange(-2, 5) / 2))


def refine_loops(data: EffectData, base: FitResult, groups: list[Group]) -> list[Group]:
    """Each loop chosen: the window its rate is taken over, and its sign taken again from the reading less its fitted
    steps (the claim was decided on the reading's own rate, inside training blocks; this only makes the figure finer).
    Where the field's rate turns depends on the window: on a real hand-turned board with a loop added that follows
    its field's rate over 0.25 s, the rate over the board's own 0.1 s left the held-out error 1.13 times the
    untouched board's; over 0.2, 0.25, 0.3 and 0.4 s: 1.08, 1.01, 1.05, 1.13."""
    out = list(groups)
    for i, g in enumerate(groups):
        if g.kind != "loop":
            continue
        nm = normals(data, base, out)
        d, best_rss = fit_all(nm)
        raw = data.raw_nT[:, g.probe, :]
        tried: dict[tuple[float, int], tuple[float, list[Group], np.ndarray]] = {}

        def at(width: float, n: int, less: np.ndarray) -> tuple[float, list[Group], np.ndarray]:
            window = n * data.dt_s                                  # n samples (odd): data.samples_for gives n back
            f = loop_feature(data, g.probe, loop_label(width), width * np.std(data.derivative(raw, window), axis=0),
                             less, window)
            trial = out[:i] + [Group(g.kind, g.probe, g.probe_name, f)] + out[i + 1:]
            nm_t = normals(data, base, trial)
            d_t, rss = fit_all(nm_t)
            return rss, trial, d_t[nm_t.spans[i]]

        def rss_at(width: float, n: int) -> float:
            if (width, n) not in tried:
                tried[(width, n)] = at(width, n, d[nm.spans[i]])
            return tried[(width, n)][0]

        grid = sorted({data.samples_for(data.smooth_window_s * r) for r in LOOP_WINDOWS})
        for width in LOOP_SCALES:                                   # the sign's width: each of the library's
            j = int(np.argmin([rss_at(width, n) for n in grid]))
            lo, hi = grid[max(j - 1, 0)], grid[min(j + 1, len(grid) - 1)]
            while hi - lo > 8:                                      # the window to the sample between them
                m1, m2 = lo + 2 * ((hi - lo) // 6), hi - 2 * ((hi - lo) // 6)
                lo, hi = (lo, m2) if rss_at(width, m1) <= rss_at(width, m2) else (m1, hi)
            for n in range(lo, hi + 1, 2):
                rss_at(width, n)
        width, n = min(tried, key=lambda key: tried[key][0])
        rss, trial, steps = tried[(width, n)]
        if not rss < best_rss:
            continue
        out, best_rss = trial, rss
        for _ in range(LOOP_REFINE - 1):
            rss, trial, d_i = at(width, n, steps)
            if not rss < best_rss:
                break
            out, best_rss, steps = trial, rss, d_i
    return out


def _fit_groups(data: EffectData, base: FitResult, groups: list[Group], reference: np.ndarray,
                weights: np.ndarray, n_blocks: int, hints: Any) -> tuple[FitResult, Heldout]:
    model = base.model
    for i, g in enumerate(groups):
        model = model + GroupTerm(g, i)
    pr = Problem(data, model, base.state.linear, reference, weights=weights, n_blocks=n_blocks, hints=hints,
                 refs=[v.cache for v in base.problem.views])
    fit = _fit_beside(pr, base)
    return fit, heldout(fit)


# --- reading a group back as physics --------------------------------------------------------------------

def _wald(values: np.ndarray, cov: np.ndarray) -> float:
    lam, vec = np.linalg.eigh(cov)
    keep = lam > 1e-12 * max(float(lam[-1]), 1e-300)
    z = vec[:, keep].T @ values
    return float(np.sum(z * z / lam[keep]))


def _covariance(fit: FitResult, term: str) -> tuple[np.ndarray, np.ndarray]:
    """(values, covariance) of a term's parameters: the normal matrix's inverse, scaled as the robust (1/f-aware)
    standard errors are to the white-noise ones."""
    pr = fit.problem
    idx = np.concatenate([np.arange(s.start, s.stop) for s in pr.slots if s.term is not None and s.term.name == term])
    a = fit.a_blocks.sum(0)
    d = np.sqrt(np.clip(np.diag(a), 1e-300, None))
    lam, vec = np.linalg.eigh(a / np.outer(d, d))
    keep = lam > 1e-7 * lam[-1]
    inv = (vec[:, keep] / lam[keep]) @ vec[:, keep].T / np.outer(d, d)
    s2 = fit.rss_w / max(fit.n_rows - fit.rank, 1)
    cov = inv[np.ix_(idx, idx)] * s2
    white = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    robust = fit.robust_stderr[idx]
    scale = float(np.median(robust / white))
    return fit.values[idx], cov * max(scale, 1.0) ** 2


#: a matrix that follows x, split into its physical parts: scale and non-orthogonality in the probe's frame (its
#: own axes), rotation in the aligned (platform) frame (its alignment to the others)
MATRIX_PARTS = ("rotation", "scale", "non-orthogonality")
#: a part is named beside the largest only where it is at least this share of it (a probe's own non-orthogonality
#: turns a pure rotation of the platform frame into small scale and non-orthogonality parts in its own)
PART_SHARE = 0.2


def matrix_parts(values: np.ndarray, cov: np.ndarray, m: np.ndarray) -> dict[str, Any]:
    """A raw-frame matrix K (9 values, ppm per unit: raw_corrected = raw - 1e-6 x K u) in parts with standard errors
    and their joint Wald statistic: scale (diagonal) and non-orthogonality (symmetric off-diagonal, xy xz yz) of K
    in the probe's frame; rotation (about x y z) of K' = M K M^-1, the same matrix in the aligned frame."""
    k = values.reshape(3, 3)
    jac = np.kron(m, np.linalg.inv(m).T)                        # vec(M K M^-1) = (M kron M^-T) vec(K), row-major
    kc = m @ k @ np.linalg.inv(m)
    out: dict[str, Any] = {"matrix_probe_frame": k.tolist(), "matrix_platform_frame": kc.tolist()}
    for part in MATRIX_PARTS:
        t = np.zeros((3, 9))
        if part == "scale":
            for r in range(3):
                t[r, 4 * r] = 1.0
        elif part == "non-orthogonality":
            for r, (i, j) in enumerate(((0, 1), (0, 2), (1, 2))):
                t[r, 3 * i + j] = t[r, 3 * j + i] = 0.5
        else:
            for r, (i, j) in enumerate(((2, 1), (0, 2), (1, 0))):     # [theta]x: theta_x = A_zy, ...
                t[r, 3 * i + j], t[r, 3 * j + i] = 0.5, -0.5
            t = t @ jac
        v, c = t @ values, t @ cov @ t.T
        wald = _wald(v, c)
        out[part] = {"values": v.tolist(), "stderr": np.sqrt(np.clip(np.diag(c), 0.0, None)).tolist(), "wald": wald,
                     "significant": bool(wald >= stats.chi2.isf(P_SIGNIFICANT, 3)),
                     "frame": "platform" if part == "rotation" else "probe"}
    return out


def scale_parts(values: np.ndarray, cov: np.ndarray) -> dict[str, Any]:
    """A scale group's 6 values (offset nT, scale ppm per unit, per axis of the probe) in its two parts with standard
    errors and their joint Wald statistic."""
    out: dict[str, Any] = {}
    for part, sl in (("offset", slice(0, 3)), ("scale", slice(3, 6))):
        v, c = values[sl], cov[sl, sl]
        wald = _wald(v, c)
        out[part] = {"values": v.tolist(), "stderr": np.sqrt(np.clip(np.diag(c), 0.0, None)).tolist(), "wald": wald,
                     "significant": bool(wald >= stats.chi2.isf(P_SIGNIFICANT, 3)), "frame": "probe"}
    return out


def read_group(g: Group, term: str, params: list[Parameter], fit: FitResult) -> FoundGroup:
    """A group's parameters as physics, in the probe's and the aligned (platform) frame, with standard errors."""
    values, cov = _covariance(fit, term)
    f = g.feature
    who = "a field common to all probes" if g.common else g.probe_name
    src = _source(f)
    parts: dict[str, Any] = {}
    if g.kind in ("offset", "common offset"):
        se = np.sqrt(np.diag(cov))
        vec = values if g.common else fit.state.linear.matrix[g.probe] @ values
        parts["vector"] = {"probe_frame" if not g.common else "platform_frame": values.tolist(),
                           "stderr": se.tolist(), "platform_frame": vec.tolist()}
        unit = f"nT{f.per}"
        head = (f"{who}'s offset follows {src}" if not g.common else
                f"{who} follows {src} (it shows in the scalar channels and cancels in the differences)")
        reading = (f"{head}: ({', '.join(f'{v:.3g}' for v in values)}) +- ({', '.join(f'{s:.2g}' for s in se)}) "
                   f"{unit} on the {'platform' if g.common else 'probe'}'s x, y, z axes")
    elif g.kind == "scale":
        parts.update(scale_parts(values, cov))
        off, sc = parts["offset"], parts["scale"]
        if sc["significant"] or (not off["significant"] and sc["wald"] >= off["wald"]):
            v, se = np.asarray(sc["values"]), np.asarray(sc["stderr"])
            i = int(np.argmax(np.abs(v)))
            reading = (f"{g.probe_name}'s scale factors follow {src}: scale {v[i]:.3g} +- {se[i]:.2g} ppm{f.per} of "
                       f"the probe's {AXES[i]} ({', '.join(f'{x:.3g}' for x in v)} ppm{f.per} on x, y, z), its offset "
                       f"({', '.join(f'{x:.3g}' for x in off['values'])}) +- "
                       f"({', '.join(f'{x:.2g}' for x in off['stderr'])}) nT{f.per}")
        else:
            reading = (f"{g.probe_name}'s offset follows {src} (its scale factors within their errors): "
                       f"({', '.join(f'{x:.3g}' for x in off['values'])}) +- "
                       f"({', '.join(f'{x:.2g}' for x in off['stderr'])}) nT{f.per} on the probe's x, y, z axes")
    elif g.kind == "matrix":
        parts.update(matrix_parts(values, cov, fit.state.linear.matrix[g.probe]))
        named = {p: parts[p] for p in MATRIX_PARTS}
        big = max(float(np.max(np.abs(named[p]["values"]))) for p in MATRIX_PARTS)
        sig = [p for p in sorted(MATRIX_PARTS, key=lambda p: -named[p]["wald"]) if named[p]["significant"]
               and float(np.max(np.abs(named[p]["values"]))) >= PART_SHARE * big] or \
            [max(named, key=lambda p: named[p]["wald"])]
        bits = []
        for p in sig:
            v, se = np.asarray(named[p]["values"]), np.asarray(named[p]["stderr"])
            u, frame = ("µrad", "platform") if p == "rotation" else ("ppm", "probe")
            about = {"rotation": "about", "scale": "of", "non-orthogonality": "between"}[p]
            labels = ("xy", "xz", "yz") if p == "non-orthogonality" else AXES
            i = int(np.argmax(np.abs(v)))
            bits.append(f"{p} {v[i]:.3g} +- {se[i]:.2g} {u}{f.per} {about} the {frame}'s {labels[i]} "
                        f"({', '.join(f'{x:.3g}' for x in v)} {u}{f.per} on {', '.join(labels)})")
        what = ("alignment to the others" if sig[0] == "rotation" and fit.problem.P > 1 else
                "scale factors" if sig == ["scale"] else "matrix")
        reading = f"{g.probe_name}'s {what} follow{'s' if what != 'scale factors' else ''} {src}: " + "; ".join(bits)
    elif g.kind in ("wave", "common wave"):
        c, s = values[:3], values[3:]
        if not g.common:
            m = fit.state.linear.matrix[g.probe]
            c, s = m @ c, m @ s
        amp = np.sqrt(c ** 2 + s ** 2)
        parts["amplitude_platform_frame_nT"] = amp.tolist()
        se = np.sqrt(np.diag(cov))
        parts["stderr_nT"] = se.tolist()
        at = (f"at the phase of {f.observable} ({f.recipe.get('unit')}, its time integral)" if f.how == "phase"
              else f"periodic at {f.recipe['hz']:.4g} Hz (a line of the residual; no logged column follows it)")
        head = f"a field {at} on {who}" if not g.common else f"a field common to all probes {at}"
        reading = (f"{head}: amplitudes ({', '.join(f'{x:.3g}' for x in amp)}) nT on the platform's x, y, z axes "
                   f"(+- {float(np.median(se)):.2g} nT each cosine and sine part)"
                   + (" (it shows in the scalar channels and cancels in the differences)" if g.common else ""))
    else:                                                              # loop
        se = np.sqrt(np.diag(cov))
        parts["step_nT"] = values.tolist()
        parts["stderr_nT"] = se.tolist()
        window = f.recipe.get("window_s")
        parts["rate_window_s"] = window if window is not None else None
        over = f"; the rate over {window:.2g} s" if window is not None else ""
        reading = (f"{g.probe_name}'s offset follows the sign of each axis' rate of change (a core's loop, "
                   f"hysteresis{over}): +-({', '.join(f'{v:.3g}' for v in values)}) +- "
                   f"({', '.join(f'{s:.2g}' for s in se)}) nT on the probe's x, y, z axes as the field along it rises or falls")
    return FoundGroup(g, term, params, reading, parts)


def _source(f: Any) -> str:
    """What a feature is, in words: 's2_temp', 'heater_A through a first-order lag of 60 s', 'the time'."""
    base = {"time": "time", "ref_total": "the total field (ref_total)",
            "angular rate": "the angular rate"}.get(f.observable, f.observable)
    if f.borrowed:
        base = f"{base} (borrowed: {f.name.split('(', 1)[-1].rstrip(')')})"
    if f.how == "low-passed":
        return f"{base} through a first-order lag of {f.recipe['low_pass_s']:g} s (low-passed)"
    return base
