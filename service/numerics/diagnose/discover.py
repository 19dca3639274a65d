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
4. The set chosen on all blocks (a lag's time constant then refined between its grid neighbours, a loop's window
   and width chosen and its sign taken again from the reading less its steps) fitted by the engine beside the
   model (all rows, Gauss-Newton, 1/f-aware standard errors); a group stays only where its parameters stand beyond
   their errors (jointly, or one alone) at P_SIGNIFICANT over the number of groups tried, and an offset and scale
   whose scale factors are within their errors is taken as its offset alone; read back as physics with standard
   errors (reading.py).

Numerics only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluxcal.drivers.errors import FluxcalError
from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.engine import FitResult, Problem, residual_hints
from fluxcal.service.numerics.jsonsafe import finite_or_none as _num
from fluxcal.service.numerics.jsonsafe import json_safe as _plain

from .fits import Heldout, _beyond_errors, _compare, _fit_beside, heldout
from .forms import choose_forms
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
from .reading import FoundGroup, covariance, read_group, read_law_group, scale_parts
from .result import GAIN_SIGMAS, MIN_GAIN, P_SIGNIFICANT
from .selection import (
    SHORTLIST,
    blocks_of,
    crossval,
    fit_all,
    held_by,
    marginals,
    nested_in,
    normals,
    prune,
    rss_of,
    select,
    shortlist,
)


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
    #: the groups as the selection chose them, before a shape's form replaced its splines (forms.py)
    chosen: list[Group] = field(default_factory=list, repr=False)
    #: per claimed shape, the forms tried and the one kept (forms.choose_forms)
    forms: list[dict[str, Any]] = field(default_factory=list)
    #: the residual's lines that a logged column's motion makes (line Hz -> (column, how)): its shapes take them
    harmonics: dict[float, tuple[str, str]] = field(default_factory=dict)

    @property
    def terms(self) -> list[str]:
        return [g.term for g in self.groups]

    def sentence(self) -> str:
        """The finding in one sentence (for the verdict), or why nothing is claimed."""
        if not self.claimed:
            return f"discovery tried {self.tried} groups beyond the catalogue and claims none: {self.reason}"
        # a law not singled out says so in its own reading; a part of a catalogue term says whose
        found = "; ".join(" ".join(filter(None, (g.reading, catalogue_part(g.group)))) for g in self.groups)
        return (f"discovered beyond the catalogue: {found}; with {'it' if len(self.groups) == 1 else 'them'} the "
                f"held-out error falls from {self.base_heldout_rms_nT:.3f} to {self.heldout_rms_nT:.3f} nT against a "
                f"{self.floor_nT:.3f} nT floor (the search itself, every choice made without the block it predicts, "
                f"takes {100 * self.cv_gain:.0f} % of the held-out sum of squares); write it as an effect of your own "
                f"(docs/effects.md)")

    def as_dict(self) -> dict[str, Any]:
        return {"tried": self.tried, "tried_params": self.tried_params, "claimed": self.claimed,
                "groups": [g.as_dict() for g in self.groups], "base_rms_nT": _num(self.base_rms_nT),
                "base_heldout_rms_nT": _num(self.base_heldout_rms_nT), "floor_nT": _num(self.floor_nT),
                "rms_nT": _num(self.rms_nT), "heldout_rms_nT": _num(self.heldout_rms_nT), "gain": _num(self.gain),
                "cv_gain": _num(self.cv_gain), "cv_log_ratio": _num(self.cv_log_ratio),
                "cv_log_ratio_se": _num(self.cv_log_ratio_se), "reason": self.reason, "taus_s": list(self.taus_s),
                "lines_hz": list(self.lines_hz), "borrowed": dict(self.borrowed), "forms": _plain(self.forms),
                "harmonics": [{"line_hz": hz, "column": col, "how": how} for hz, (col, how) in self.harmonics.items()],
                "sentence": self.sentence()}


def catalogue_part(g: Group) -> str:
    """Words for a group that is part of a catalogue term (a probe's offset, or offset and scale, following its own
    temperature: the temperature term's; following it low-passed: thermal's), else "". Found beside the catalogue,
    whose candidates were tried first, such a part stands where the whole term (every probe's offset and scale) did
    not: its reading said that the catalogue holds it, beside "temperature: within its errors of zero"."""
    if g.kind not in ("offset", "scale"):
        return ""
    f = g.feature
    if f.recipe.get("source") != "temperature" or f.recipe.get("probe") != g.probe or f.borrowed:
        return ""
    term = {"value": "temperature", "low-passed": "thermal"}.get(f.how)
    if term is None:
        return ""
    part = "offset" if g.kind == "offset" else "offset and scale"
    return (f"(the {part} part of the catalogue's {term} term, for {g.probe_name} alone: the whole term, every "
            f"probe's offset and scale, is judged in the candidates above)")


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
                    taus_s=lib.taus_s, lines_hz=lib.lines_hz, borrowed=lib.borrowed, harmonics=lib.harmonics)
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
    # the smaller groups each holds (a scale group its offset, a spline the smaller spline and the value), which the
    # selection takes instead where the larger adds nothing
    nested = nested_in(groups)
    union = sorted(set(union) | {j for i in union for j in held_by(nested, i)})
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
    if len(kept) > 1:                               # refined, each still passes beside the others, or goes
        kept = [kept[i] for i in prune(normals(data, base, kept))]
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
    """The groups fitted by the engine beside `base`; those whose parameters are within their errors dropped, and an
    offset and scale whose scale factors are within theirs taken as its offset alone (the rest fitted again each
    time); read back as physics. `out` filled in and returned."""
    hints = residual_hints(base)
    for _ in range(2 * len(kept) + 1):              # each round drops or narrows a group, or ends
        try:
            fit, ho = _fit_groups(data, base, kept, reference, weights, n_blocks, hints)
        except (FluxcalError, np.linalg.LinAlgError, ValueError) as e:
            out.claimed, out.reason = False, f"the fit of the groups found failed: {e}"
            return out
        params = {t.name: [p for p in fit.parameters() if p.term == t.name] for t in fit.problem.terms
                  if isinstance(t, GroupTerm)}
        weak = [t.group for t in fit.problem.terms if isinstance(t, GroupTerm)
                and _beyond_errors(params[t.name], p_level) is not None and not jointly_beyond(fit, t.name, p_level)]
        if weak:
            kept = [g for g in kept if g not in weak]
            if not kept:
                out.claimed = False
                out.reason = (f"the groups chosen ({', '.join(g.key for g in weak)}) have parameters within their "
                              f"(1/f-aware) errors of zero at p < {p_level:.2g}: the held-out gain follows the "
                              f"noise's slow wander")
                return out
            continue
        plain = offset_alone(fit)
        if not plain:
            break
        kept = [Group("offset", g.probe, g.probe_name, g.feature) if g in plain else g for g in kept]
    out.chosen = list(kept)
    # a claimed shape in its form: one direction per probe times a function they share, a law where one takes it
    fit, ho, _, laws, out.forms = choose_forms(data, base, kept, fit, ho, reference, weights, n_blocks, hints)
    params = {t.name: [p for p in fit.parameters() if p.term == t.name] for t in fit.problem.terms
              if isinstance(t, GroupTerm)}
    cmp = _compare(base, base_ho, fit, ho)
    out.claimed, out.reason = True, None
    out.fit = fit
    out.base_rms_nT, out.base_heldout_rms_nT = base.rms_nT, base_ho.rms_nT
    out.rms_nT, out.heldout_rms_nT, out.gain = fit.rms_nT, ho.rms_nT, cmp["gain"]
    out.groups = ([read_group(t.group, t.name, params[t.name], fit) for t in fit.problem.terms
                   if isinstance(t, GroupTerm)] + [read_law_group(t, fit) for t in laws])
    return out


def jointly_beyond(fit: FitResult, term: str, p_level: float) -> bool:
    """Whether a group's parameters stand beyond their errors jointly, with their correlations (reading.covariance):
    a spline of a column beside the catalogue's `column`, which holds the column's straight line, has each parameter
    within its error (the line can go to either) while the curve stands far beyond them (a saturating coil: claimed
    in 0 of 2 seeds where `column` was significant, by the parameters' errors alone)."""
    from scipy import stats                             # here, not at import (a command's start)

    values, cov = covariance(fit, term)
    lam, vec = np.linalg.eigh(cov)
    keep = lam > 1e-9 * max(float(lam[-1]), 1e-300)
    z = vec[:, keep].T @ values
    return bool(keep.any() and float(np.sum(z * z / lam[keep])) >= stats.chi2.isf(p_level, int(keep.sum())))


def offset_alone(fit: FitResult) -> list[Group]:
    """The offset and scale groups of `fit` whose scale factors are within their errors (scale_parts): their offset
    alone says what the data show. On a real hand-turned board with a lagged heater added to its offset, the
    selection took its offset and scale (it predicted the training blocks better), whose scale factors then stood
    within their errors: read as an offset, it was named as a scale group."""
    scales = [t for t in fit.problem.terms if isinstance(t, GroupTerm) and t.group.kind == "scale"]
    return [t.group for t in scales if not scale_parts(*covariance(fit, t.name))["scale"]["significant"]]


def beside(found: Discovery, data: EffectData, base: FitResult, base_ho: Heldout, reference: np.ndarray,
           weights: np.ndarray, n_blocks: int) -> Discovery:
    """The groups `found` fitted beside another model (the model without the catalogue's effect it was found
    beside): a new Discovery with the same selection figures."""
    from dataclasses import replace

    again = replace(found, groups=[], fit=None)
    return conclude(again, data, base, base_ho, list(found.chosen), reference, weights, n_blocks,
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
#: a chosen loop's rate window: the data's own (window_samples) times each of these, then refined to the sample
#: between the best one's neighbours, on all the data (as a lag's time constant)
LOOP_WINDOWS = tuple(2.0 ** (np.arange(-2, 5) / 2))


def refine_loops(data: EffectData, base: FitResult, groups: list[Group]) -> list[Group]:
    """Each loop chosen: the window its rate is taken over, and its sign taken again from the reading less its fitted
    steps (the claim was decided on the reading's own rate, inside training blocks; this only makes the figure finer).
    Where the field's rate turns depends on the window: on a real hand-turned board (bursty: 3.3 ms between samples
    at the median) with a loop added that follows its field's rate over 77 samples, the rate over the board's own
    31 left the held-out error 1.13 times the untouched board's; over 61, 77, 91 and 121: 1.08, 1.01, 1.05, 1.13."""
    out = list(groups)
    for i, g in enumerate(groups):
        if g.kind != "loop":
            continue
        nm = normals(data, base, out)
        d, best_rss = fit_all(nm)
        raw = data.raw_nT[:, g.probe, :]
        tried: dict[tuple[float, int], tuple[float, list[Group], np.ndarray]] = {}

        def at(width: float, n: int, less: np.ndarray) -> tuple[float, list[Group], np.ndarray]:
            f = loop_feature(data, g.probe, loop_label(width), width * np.std(data.derivative(raw, n), axis=0),
                             less, n)
            trial = out[:i] + [Group(g.kind, g.probe, g.probe_name, f)] + out[i + 1:]
            nm_t = normals(data, base, trial)
            d_t, rss = fit_all(nm_t)
            return rss, trial, d_t[nm_t.spans[i]]

        def rss_at(width: float, n: int) -> float:
            if (width, n) not in tried:
                tried[(width, n)] = at(width, n, d[nm.spans[i]])
            return tried[(width, n)][0]

        grid = sorted({data.odd_window(data.window_samples * r) for r in LOOP_WINDOWS})
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
