"""The form of a claimed shape (discover.py step 4, laws.py): once the library's splines of an observable are claimed,
the per-axis function they found is tried as one direction per probe times one function the probes share (a free
spline, then each law), every form fitted by the engine beside the model and the other groups found and judged on the
held-out blocks; the smallest whose held-out error no other form beats by the held-out rule is kept. Numerics only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fluxcal.drivers.errors import FluxcalError
from fluxcal.service.numerics.engine import FitResult, Problem, fit_problem

from .fits import Heldout, heldout
from .laws import LAWS, LawTerm, context, start_law
from .library import SHAPE_KINDS, Group, GroupTerm
from .selection import _passes
from .shape_reading import curve, observable_values
from .shapes import basis_of, unit_of

#: iterations of the engine for a form (non-linear: a law's parameters move from their start)
FORM_ITERATIONS = 12
#: the forms are compared on at most this many rows spread evenly over the record (each a fit of the whole model); the
#: one kept is fitted again on all of them
FORM_ROWS = 20000
#: a law whose start misfits the shape by more than this share of its variance is not fitted
START_MISFIT = 0.5


@dataclass
class Form:
    """One form of a claimed shape fitted beside the rest: its law (None with a term: a free spline; no term: the
    per-axis groups as claimed), the fit, its held-out residual and its number of parameters."""

    label: str
    term: LawTerm | None
    fit: FitResult
    ho: Heldout
    n_params: int


def observable_key(g: Group) -> tuple:
    r = g.feature.recipe
    return r["source"], r.get("column"), r.get("probe")


def shape_sets(kept: list[Group]) -> dict[tuple, list[Group]]:
    """The claimed spline groups (not an angle's turns: a field that turns is no one direction) by observable."""
    out: dict[tuple, list[Group]] = {}
    for g in kept:
        if g.kind in SHAPE_KINDS and g.feature.recipe.get("basis") == "spline":
            out.setdefault(observable_key(g), []).append(g)
    return out


def _groupterms(groups: list[Group], kept: list[Group]) -> list[GroupTerm]:
    return [GroupTerm(g, kept.index(g)) for g in groups]


def _curves(fit: FitResult, groups: list[Group], kept: list[Group], x: np.ndarray) -> tuple[list[int], np.ndarray]:
    """(the probes the shape acts on, (N, 3 P') each one's fitted shape in the platform frame at the samples)."""
    params = fit.values
    probes: list[int] = []
    cols = []
    for g in groups:
        term = f"discovered-{kept.index(g) + 1}"
        idx = np.concatenate([np.arange(s.start, s.stop) for s in fit.problem.slots
                              if s.term is not None and s.term.name == term])
        zero = np.zeros((idx.size, idx.size))
        if g.common:
            v, _ = curve(g.feature.recipe, x, params[idx], zero, None)
            for k in range(fit.problem.P):
                if k not in probes:
                    probes.append(k)
                    cols.append(v)
        else:
            v, _ = curve(g.feature.recipe, x, params[idx], zero, fit.state.linear.matrix[g.probe])
            if g.probe in probes:
                cols[probes.index(g.probe)] = cols[probes.index(g.probe)] + v
            else:
                probes.append(g.probe)
                cols.append(v)
    return probes, np.concatenate(cols, axis=1)


def _starts(groups: list[Group], x: np.ndarray, stacked: np.ndarray, n_probes: int, ctx: dict,
            unit: str, index: int) -> list[tuple[str, LawTerm]]:
    """The rank-one forms to try, each a LawTerm at its start: a free spline on the largest basis claimed, then each
    law whose start takes the shape within START_MISFIT."""
    y0 = stacked - stacked.mean(axis=0)
    u, s, vt = np.linalg.svd(y0, full_matrices=False)
    y, w = u[:, 0] * s[0], vt[0]
    big = max(groups, key=lambda g: g.feature.values.shape[1])
    recipe = big.feature.recipe
    phi = basis_of(recipe, x)
    c, *_ = np.linalg.lstsq(phi - phi.mean(0), y, rcond=None)
    fixed = int(np.argmax(np.abs(c)))
    free = np.delete(c, fixed) / c[fixed]
    out = [("shape", LawTerm(None, recipe, ctx, [], index, np.concatenate([c[fixed] * w, free]), unit, fixed))]
    for law in LAWS:
        got = start_law(law, x, y, ctx)
        if got is None or got[2] > START_MISFIT:
            continue
        p, amp, _ = got
        out.append((law.name, LawTerm(law, recipe, ctx, [], index, np.concatenate([amp * w, p]), unit)))
    return out


def _fit_form(data, base: FitResult, kept: list[Group], others: list[Group], terms: list[LawTerm], reference,
              weights, n_blocks: int, hints, previous: Any, rows: np.ndarray | None = None) -> tuple[FitResult,
                                                                                                     Heldout] | None:
    """The model, the groups `others` and the law terms fitted by the engine from `previous` (the groups' values by
    name, each law from its start), on `rows` (all the base's where None); None where the fit fails or diverges."""
    model = base.model
    for t in _groupterms(others, kept) + terms:
        model = model + t
    pr = Problem(data, model, base.state.linear, reference, weights=weights, n_blocks=n_blocks, hints=hints,
                 refs=[v.cache for v in base.problem.views], rows=base.problem.rows if rows is None else rows)
    try:
        # a law's trial step may go far out (a power of a distance near its pole): its residual is then infinite,
        # and the fit's line search takes a shorter step
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            fit = fit_problem(pr, pr.start_state(previous.linear, previous), max_iter=FORM_ITERATIONS)
    except (FluxcalError, np.linalg.LinAlgError, ValueError, FloatingPointError):
        return None
    if not np.isfinite(fit.rss_w):
        return None
    return fit, heldout(fit)


def choose_forms(data: Any, base: FitResult, kept: list[Group], fit: FitResult, ho: Heldout, reference: np.ndarray,
                 weights: np.ndarray, n_blocks: int, hints: Any) -> tuple[FitResult, Heldout, list[Group],
                                                                         list[LawTerm], list[dict[str, Any]]]:
    """For each observable whose splines were claimed, the form kept (the module doc): (the final fit, its held-out
    residual, the groups kept as they are, the law terms that replace the others, what was tried for each: label,
    parameters, held-out RMS)."""
    laws: list[LawTerm] = []
    tried: list[dict[str, Any]] = []
    groups = list(kept)
    for i, (key, shape) in enumerate(shape_sets(kept).items()):
        others = [g for g in groups if g not in shape]
        x = observable_values(data, shape[0].feature.recipe)
        ctx = context(x)
        probes, stacked = _curves(fit, shape, kept, x)
        rows = base.problem.rows
        thin = None if rows.size <= FORM_ROWS else rows[::-(-rows.size // FORM_ROWS)]
        per_axis = (fit, ho) if thin is None else _fit_form(data, base, kept, groups, laws, reference, weights,
                                                            n_blocks, hints, fit.state, thin)
        forms = [Form("per axis", None, *per_axis, sum(g.size for g in shape))]
        for label, term in _starts(shape, x, stacked, len(probes), ctx, unit_of(shape[0].feature.recipe), i):
            term.probes = probes
            got = _fit_form(data, base, kept, others, laws + [term], reference, weights, n_blocks, hints, fit.state,
                            thin)
            if got is not None:
                forms.append(Form(label, term, got[0], got[1], term.start.size))
        best_sse = min(forms, key=lambda f: f.ho.sse_w.sum())
        chosen = next(f for f in sorted(forms, key=lambda f: (f.n_params, f.ho.sse_w.sum()))
                      if f is best_sse or not _passes(f.ho.sse_w, best_sse.ho.sse_w, f.ho.n)[0])
        # the other laws the held-out blocks do not tell from the best (the free forms are no rival: a law they do
        # not beat has caught the shape): the chosen law's parameters are then its own, not a law the data single out
        law = chosen.term is not None and chosen.label != "shape"
        alike = [f.label for f in forms if law and f is not chosen and f.term is not None and f.label != "shape"
                 and (f is best_sse or not _passes(f.ho.sse_w, best_sse.ho.sse_w, f.ho.n)[0])]
        tried.append({"observable": shape[0].feature.observable, "chosen": chosen.label, "alike": alike,
                      "forms": [{"form": f.label, "parameters": f.n_params, "heldout_rms_nT": f.ho.rms_nT}
                                for f in forms]})
        if chosen.term is not None:
            chosen.term.alike = list(alike)
            if thin is not None:                        # chosen on a share of the rows: fitted on all from there
                chosen.term.start = chosen.fit.state.shared[chosen.term.name].copy()
                got = _fit_form(data, base, kept, others, laws + [chosen.term], reference, weights, n_blocks, hints,
                                fit.state)
                if got is None:
                    continue
                chosen.fit, chosen.ho = got
            laws.append(chosen.term)
            groups = others
            fit, ho = chosen.fit, chosen.ho
    return fit, ho, groups, laws, tried

