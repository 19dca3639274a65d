"""A discovered shape read back as physics (reading.py for the shape groups of library.py): the smooth function of the
observable that each axis follows, as a table over the observable's range with standard errors, in the platform
frame; how much of it lies along one fixed direction (rank one: one source of one direction whose size follows the
observable), and for an angle the axis about which the field turns. Numerics only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import AXES

from .shapes import basis_of, unit_of

#: points of the table a shape is read on, over the observable's range
TABLE_POINTS = 9


def observable_values(data: Any, recipe: dict[str, Any]) -> np.ndarray:
    """(N,) the observable a feature's recipe follows, as the library took it (gaps filled; through its first-order
    lag where the recipe has one)."""
    x = _raw_observable(data, recipe)
    if "low_pass_s" in recipe:
        from fluxcal.service.numerics.effects.thermal import low_pass

        x = low_pass(data.t_s, x, float(recipe["low_pass_s"]))
    return x


def _raw_observable(data: Any, recipe: dict[str, Any]) -> np.ndarray:
    from fluxcal.service.numerics.effects.column import column_values

    src = recipe["source"]
    if src == "temperature":
        return data.temperature(recipe["probe"])
    if src == "column":
        return column_values(data, recipe["column"])
    if src == "ref_total":
        return np.asarray(data.ref_total_nT, float)
    if src == "angular rate":
        from .library import angular_rate_deg_s

        return angular_rate_deg_s(data)
    raise ValueError(f"recipe: {src!r} is no observable a shape follows")


def curve(recipe: dict[str, Any], x: np.ndarray, coef: np.ndarray, cov: np.ndarray,
          matrix: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The shape at x (n,) per axis of the platform frame (n, 3) and its standard errors (n, 3): coef (3m) the
    group's parameters (function j on axis a at a m + j), cov their covariance; matrix: the probe's (raw frame), or
    None (a group common to all probes, in the aligned frame already)."""
    phi = basis_of(recipe, x)                                    # (n, m)
    m = phi.shape[1]
    lift = np.zeros((x.size, 3, 3 * m))
    for a in range(3):
        lift[:, a, a * m:(a + 1) * m] = phi
    if matrix is not None:
        lift = np.einsum("ij,njp->nip", matrix, lift)
    values = lift @ coef
    se = np.sqrt(np.clip(np.einsum("nap,pq,naq->na", lift, cov, lift), 0.0, None))
    return values, se


def direction_share(values: np.ndarray) -> tuple[np.ndarray, float]:
    """(the unit direction along which a shape (n, 3) varies most, the share of its variance along it)."""
    c = values - values.mean(axis=0)
    _, s, vt = np.linalg.svd(c, full_matrices=False)
    total = float(np.sum(s ** 2))
    u = vt[0] * np.sign(vt[0][np.argmax(np.abs(vt[0]))])
    return u, (float(s[0] ** 2) / total if total > 0 else 0.0)


def read_shape(g: Any, values: np.ndarray, cov: np.ndarray, fit: Any, source: str) -> tuple[str, dict[str, Any]]:
    """(one sentence, parts) of a shape group's parameters: its table over the observable's range, its range of
    values, and how much lies along one direction; for an angle, the axis the field turns about."""
    r = g.feature.recipe
    data = fit.problem.data
    x_all = observable_values(data, r)
    grid = np.linspace(float(np.min(x_all)), float(np.max(x_all)), TABLE_POINTS)
    matrix = None if g.common else fit.state.linear.matrix[g.probe]
    shape, se = curve(r, grid, values, cov, matrix)
    at_data, _ = curve(r, x_all, values, cov, matrix)
    u, share = direction_share(at_data)
    along = at_data @ u
    who = "a field common to all probes" if g.common else f"{g.probe_name}'s offset"
    parts: dict[str, Any] = {"observable": g.feature.observable, "grid": grid.tolist(),
                             "platform_frame_nT": shape.tolist(), "stderr_nT": se.tolist(),
                             "direction": u.tolist(), "direction_share": share,
                             "range_nT": [float(np.min(along)), float(np.max(along))]}
    unit = unit_of(r)
    if r["basis"] == "turn":
        cs = [values[a * 2 * r["harmonics"]:a * 2 * r["harmonics"] + 2] for a in range(3)]
        c, s = np.array([v[0] for v in cs]), np.array([v[1] for v in cs])
        if matrix is not None:
            c, s = matrix @ c, matrix @ s
        axis = np.cross(c, s)
        n = float(np.linalg.norm(axis))
        axis = axis / n if n > 0 else axis
        parts.update(turn_axis=axis.tolist(), amplitude_nT=[float(np.linalg.norm(c)), float(np.linalg.norm(s))])
        reading = (f"{who} turns with {source}: a field of {np.linalg.norm(c):.3g} and {np.linalg.norm(s):.3g} nT "
                   f"(cosine and sine parts) turning about the platform's "
                   f"({', '.join(f'{v:.2f}' for v in axis)}) axis as the angle turns (something on what turns "
                   f"carries a field)")
        return reading, parts
    lo, hi = float(grid[0]), float(grid[-1])
    reading = (f"{who} follows a smooth function of {source} (a spline of {r['functions']} functions): "
               f"{along.min():.3g} to {along.max():.3g} nT along the platform's "
               f"({', '.join(f'{v:.2f}' for v in u)}) ({100 * share:.0f} % of it along that one direction) over "
               f"{source} {lo:.3g} to {hi:.3g} {unit}; per axis in the table of --json (parts)")
    return reading, parts


def axis_table(parts: dict[str, Any]) -> list[str]:
    """The shape's table as text lines: the observable, then each platform axis with its standard error."""
    out = [f"      {parts['observable']:>12}  " + "  ".join(f"{a:>16}" for a in AXES)]
    for x, v, s in zip(parts["grid"], parts["platform_frame_nT"], parts["stderr_nT"]):
        out.append(f"      {x:12.4g}  " + "  ".join(f"{vi:8.3g} +- {si:5.2g}" for vi, si in zip(v, s)))
    return out


def _vector_text(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in v) + ")"


def law_parameters(term: Any, fit: Any) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(values, standard errors (the robust, 1/f-aware ones; NaN where undetermined), names) of a law term's shared
    parameters in the fit."""
    ps = [p for p in fit.parameters() if p.term == term.name]
    return (np.array([p.value for p in ps]), np.array([np.nan if p.stderr is None else p.stderr for p in ps]),
            [p.name for p in ps])


def read_law(term: Any, fit: Any, source: str, cov: np.ndarray | None = None) -> tuple[str, dict[str, Any]]:
    """(one sentence, parts) of a law term (laws.LawTerm): the field's direction (platform frame) and how far it moves
    at each probe over the observable's range, whether the probes share the direction, and the law with its
    parameters and standard errors; a free spline as the shape that none of the laws takes, with its table."""
    values, se, names = law_parameters(term, fit)
    n_amp = 3 * len(term.probes)
    data = fit.problem.data
    x = observable_values(data, term.recipe)
    lo, hi = float(np.min(x)), float(np.max(x))
    grid = np.linspace(lo, hi, TABLE_POINTS)
    f, _ = term.function_at(grid, values[n_amp:])
    amps = values[:n_amp].reshape(-1, 3)
    sizes = np.linalg.norm(amps, axis=1)
    main = int(np.argmax(sizes))
    u = amps[main] / max(sizes[main], 1e-300)
    u = u * np.sign(u[np.argmax(np.abs(u))])
    probe_names = [data.probe_names[k] for k in term.probes]
    angles = [float(np.degrees(np.arccos(np.clip(abs(a @ u) / max(np.linalg.norm(a), 1e-300), -1, 1)))) for a in amps]
    # along u at each probe over the range: from its value at the low end to the high end (through its extreme
    # between them, where it turns), nT
    moves = [(float(f[0] * (a @ u)), float(f[-1] * (a @ u)), _turn(f * (a @ u))) for a in amps]
    parts: dict[str, Any] = {"law": term.law.name if term.law else "shape", "probes": probe_names,
                             "field_nT": amps.tolist(), "field_stderr_nT": se[:n_amp].reshape(-1, 3).tolist(),
                             "direction": u.tolist(), "angle_to_direction_deg": angles, "reference": term.ctx["ref"],
                             "range": [lo, hi], "grid": grid.tolist(), "function": f.tolist(),
                             "moves_nT": [[m[0], m[1]] for m in moves],
                             "parameters": {n: {"value": float(v), "stderr": None if not np.isfinite(e) else float(e)}
                                            for n, v, e in zip(names[n_amp:], values[n_amp:], se[n_amp:])}}
    if cov is not None:
        parts["partial"] = partial_residual(fit, term, values, cov)
    unit = term.unit

    def move(i: int) -> str:
        a, b, via = moves[i]
        own = f"{probe_names[i]} from {a:.3g}" + (f" through {via:.3g}" if via is not None else "") + f" to {b:.3g} nT"
        if i == main:
            return own
        return own + (f" ({sizes[i] / max(sizes[main], 1e-300):.2f} of {probe_names[main]}'s, "
                      f"{angles[i]:.0f} deg from its direction)")
    # a lagged observable is long to say: x in the law, said once
    x = "x" if " " in source else source
    head = (f"a field along the platform's {_vector_text(u)} that moves at {'; '.join(move(i) for i in range(len(moves)))} "
            f"as {source if x == source else f'x = {source},'} goes from {lo:.3g} to {hi:.3g} {unit}")
    if term.law is None:
        return (f"{head}, following one smooth function of {source} that none of the laws takes (a spline of "
                f"{term.n_law + 1} functions; its table in --json)"), parts
    p, e = values[n_amp:], se[n_amp:]

    def pm(i: int) -> str:
        return f"{p[i]:.4g} +- {e[i]:.2g}" if np.isfinite(e[i]) else f"{p[i]:.4g} (undetermined)"
    ref = term.ctx["ref"]
    name = term.law.name
    if name == "distance power":
        closes = "closes" if p[0] > hi else "opens"
        ratio = f"c / (c - {x})" if ref == 0 else f"(c - {ref:g}) / (c - {x})"
        law = (f"as a distance power, ({ratio})^n with c = {pm(0)} {unit} and n = {pm(1)}",
               f"a source whose distance {closes} as {x} rises, its field as the power {p[1]:.2g} of the distance")
    elif name == "polynomial":
        law = (f"as a polynomial of degree 2, ({x} - x0)^2 with x0 = {pm(0)} {unit}", f"a quadratic in {x} about x0")
    elif name == "cubic":
        law = (f"as a cubic, z + b2 z^2 + b3 z^3 with z = ({x} - {ref:g}) / {hi - lo:.3g} {unit}, b2 = {pm(0)} and "
               f"b3 = {pm(1)}", f"a polynomial of degree 3 in {x}")
    elif name == "exponential":
        law = (f"as an exponential, exp(({x} - {ref:g}) / s) with s = {pm(0)} {unit}", "")
    elif name == "saturation":
        law = (f"as a saturation, tanh({x} / s) with s = {pm(0)} {unit}", f"it saturates as {x} grows from zero")
    else:
        law = (f"as a shifted saturation, tanh(({x} - x0) / s) with x0 = {pm(0)} {unit} and s = {pm(1)} {unit}",
               "it saturates about x0")
    if term.alike:
        parts["alike"] = list(term.alike)
    return f"{head}, {as_form(*law, term.alike)}", parts


def as_form(formula: str, physics: str, alike: list[str]) -> str:
    """A law's clause as read: its formula with the fitted parameters, then what that law means (`physics`); where the
    held-out blocks tell no other law from it (`alike`), its parameters as the form's own and no physics read into
    them (one story with the forms' line and the verdict)."""
    if alike:
        return (f"{formula} (the held-out blocks do not tell it from {' or '.join(alike)}: these are the form's "
                f"parameters, not a law these data single out)")
    return f"{formula}: {physics}" if physics else formula


#: the partial residual is read in this many bins of the observable (quantiles)
PARTIAL_BINS = 24
#: ... on the samples where the law's direction stands at least this far along the field's (the cosine)
ALONG = 0.5


def _turn(along: np.ndarray) -> float | None:
    """The extreme of a law's field over the grid where it lies between the ends (the law turns there), else None."""
    i = int(np.argmax(np.abs(along - 0.5 * (along[0] + along[-1]))))
    return float(along[i]) if 0 < i < along.size - 1 and not min(along[0], along[-1]) <= along[i] <= max(
        along[0], along[-1]) else None


def partial_residual(fit: Any, term: Any, values: np.ndarray, cov: np.ndarray) -> list[dict[str, Any]]:
    """What the report and the dashboard draw of a law (laws.LawTerm), per probe it acts on: its scalar residual
    with the law's own field added back, seen along the law's direction u, (r + n.c) / (n.u) on the samples where
    |n.u| >= ALONG (n the field's direction), in PARTIAL_BINS bins of the observable (mean and standard error); and
    beside it the law's field along u over the observable's range, with a band of two standard errors (from the
    parameters' covariance `cov`: each probe's field, then the law's). JSON-ready."""
    pr = fit.problem
    data = pr.data
    n_amp = 3 * len(term.probes)
    x_all = observable_values(data, term.recipe)[pr.rows]
    f_all, _ = term.function(data, values[n_amp:])
    f_all = f_all[pr.rows]
    grid = np.linspace(float(np.min(x_all)), float(np.max(x_all)), 4 * TABLE_POINTS)
    fg, dfg = term.function_at(grid, values[n_amp:])
    out = []
    for i, k in enumerate(term.probes):
        a = values[3 * i:3 * i + 3]
        size = float(np.linalg.norm(a))
        if size <= 0:
            continue
        u = a / size
        n = fit.ev.nhat[k]
        along = n @ u
        ok = np.abs(along) >= ALONG
        if np.count_nonzero(ok) < 4 * PARTIAL_BINS:
            continue
        y = (fit.channels.values[ok, k] + along[ok] * size * f_all[ok]) / along[ok]
        x = x_all[ok]
        edges = np.unique(np.quantile(x, np.linspace(0.0, 1.0, PARTIAL_BINS + 1)))
        which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
        count = np.bincount(which, minlength=edges.size - 1)
        keep = count >= 3
        mean = np.bincount(which, weights=y, minlength=count.size)[keep] / count[keep]
        sq = np.bincount(which, weights=y * y, minlength=count.size)[keep] / count[keep]
        se = np.sqrt(np.clip(sq - mean ** 2, 0.0, None) / np.maximum(count[keep] - 1, 1))
        centre = np.bincount(which, weights=x, minlength=count.size)[keep] / count[keep]
        jac = np.column_stack([fg[:, None] * u[None, :], size * dfg])
        idx = np.concatenate([np.arange(3 * i, 3 * i + 3), np.arange(n_amp, values.size)])
        band = 2.0 * np.sqrt(np.clip(np.einsum("gp,pq,gq->g", jac, cov[np.ix_(idx, idx)], jac), 0.0, None))
        out.append({"probe": data.probe_names[k], "direction": u.tolist(), "x": centre.tolist(),
                    "mean_nT": mean.tolist(), "stderr_nT": se.tolist(), "samples": int(np.count_nonzero(ok)),
                    "grid": grid.tolist(), "law_nT": (size * fg).tolist(), "band_nT": band.tolist()})
    return out

