"""The groups and laws discovery found, written as an effect module of the user's own (docs/effects.md): the Python
source of one EffectTerm class that holds everything the discovered figure rests on: a probe's groups in its raw
frame (per-probe parameters), groups common to all probes and laws in the aligned frame (shared parameters, a law's
acting non-linearly: each probe's field in nT, then the law's own parameters in the observable's unit), and in
`beside` the catalogue's effects it was found beside, which `--effects FILE.py:Discovered` brings with it. Named
parameters in physical units, `frame`, and `per_sample` where each sample's correction needs that sample alone. Fitted
on the same data it gives the discovered error (the same regressors and laws, computed the same way:
tests/numerics/test_discover.py).

Only text: the caller writes it where the user asked. Numerics only.
"""

from __future__ import annotations

import keyword
import re
from typing import Any, Sequence

from .effect_code import HEADER, LAW_PARTS, SHARED_VIEW
from .laws import LAW_CODE
from .library import Group

def _ident(text: str) -> str:
    s = re.sub(r"\W+", "_", text).strip("_").lower() or "x"
    if s[0].isdigit() or keyword.iskeyword(s):
        s = "f_" + s
    return s


def _observable_code(r: dict[str, Any], data: str) -> str:
    """The expression of the observable a recipe follows, its values before any centring, in terms of `data`."""
    src = r["source"]
    if src == "temperature":
        probe = r.get("probe_name")
        index = f"{data}.probe_names.index({probe!r})" if probe else repr(int(r["probe"]))
        return f"{data}.temperature({index})"
    if src == "column" or (src == "phase" and "column" in r):
        return f"column({data}, {r['column']!r})"
    if src == "time":
        return f"{data}.t_s / 3600.0"
    if src == "ref_total":
        return f"{data}.ref_total_nT"
    if src == "angular rate":
        return f"angular_rate_deg_s({data})"
    raise ValueError(f"recipe: {r!r} is not one the writer knows")


def _basis_code(r: dict[str, Any], raw: str) -> str:
    """A shape's basis (shapes.py) as the written module makes it."""
    if r["basis"] == "spline":
        return f"spline_basis({raw}, {[float(k) for k in r['knots']]!r}, {int(r['degree'])}, {list(r['centre'])!r})"
    return (f"turn_basis({raw}, {float(r['radians_per_unit'])!r}, {int(r['harmonics'])}, "
            f"{list(r['centre'])!r})")


def _feature_code(g: Group) -> tuple[str, list[str]]:
    """(the expression of the group's feature in terms of `view`, the lines before it)."""
    f, r = g.feature, g.feature.recipe
    key = f"discovered:{f.name}"
    src = r["source"]
    lines: list[str] = []
    if src == "temperature" and not r.get("probe_name"):
        r = {**r, "probe_name": f.observable.rsplit("_temp", 1)[0]}
    if "basis" in r:
        raw = _observable_code(r, "view.data")
        if "low_pass_s" in r:
            lines.append(f"x = low_pass(view.data.t_s, {raw}, {r['low_pass_s']!r})       # a first-order lag, s")
            raw = "x"
        return _basis_code(r, raw), lines
    if src == "line":
        return f"2 * np.pi * {r['hz']!r} * view.data.t_s", lines
    if src == "sign of rate":
        k = g.probe
        lines.append(f"scale = np.array({[float(x) for x in r['scale']]!r})       # nT/s: the sign's width per axis")
        window = r.get("window_samples")
        if window is None:
            lines.append(f"sign = np.tanh(view.data.rate({k}) / scale)")
        else:
            lines.append(f"window = {int(window)!r}       # samples: the rate's window (odd)")
            lines.append(f"sign = np.tanh(view.data.derivative(view.data.raw_nT[:, {k}, :], window) / scale)")
        if "less_nT" in r:
            # the core follows the field's rate: the sign taken again from the reading less the steps found
            lines.append(f"steps = np.array({[float(x) for x in r['less_nT']]!r})       # nT per axis")
            lines.append(f"for _ in range({int(r['passes'])}):")
            lines.append(f"    less = view.data.raw_nT[:, {k}, :] - steps * sign")
            over = "" if window is None else ", window"
            lines.append(f"    sign = np.tanh(view.data.derivative(less{over}) / scale)")
        return "sign", lines
    raw = _observable_code(r, "view.data")
    if src == "phase":
        return f"phase_of(view.data.t_s, {raw}, {r['cycles_per_unit']!r})       # {r.get('unit', '')}", lines
    if "low_pass_s" in r:
        lines.append(f"x = low_pass(view.data.t_s, {raw}, {r['low_pass_s']!r})       # a first-order lag, s")
        raw = "x"
    return f"centred(view, {key!r}, {raw})", lines


BUILDERS = {"offset": "offset_columns({x})", "common offset": "offset_columns({x})",
            "scale": "scale_columns({x}, view.centred_nT)", "matrix": "matrix_columns({x}, view.centred_nT)",
            "wave": "wave_columns({x})", "common wave": "wave_columns({x})", "loop": "loop_columns({x})",
            "shape": "shape_columns({x})", "common shape": "shape_columns({x})"}


def _group_block(g: Group, indent: str) -> list[str]:
    expr, pre = _feature_code(g)
    borrowed = f" (borrowed: {g.feature.borrowed})" if g.feature.borrowed else ""
    out = [f"{indent}# {g.kind}: {g.feature.name}{borrowed}"]
    out += [indent + ln for ln in pre]
    out.append(f"{indent}parts.append({BUILDERS[g.kind].format(x=expr)})")
    return out


def _why_unavailable(groups: Sequence[Group]) -> list[str]:
    """The written class's why_unavailable: the columns, temperatures or reference its groups and laws follow, said
    missing where other data lack them (a KeyError deep in the fit before)."""
    columns = sorted({g.feature.recipe["column"] for g in groups if "column" in g.feature.recipe})
    temperature = any(g.feature.recipe["source"] == "temperature" for g in groups)
    reference = any(g.feature.recipe["source"] == "ref_total" for g in groups)
    probes = sorted({p for g in groups if g.kind == "law" for p in g.feature.recipe["probes"]})
    if not (columns or temperature or reference or probes):
        return []
    out = ["    def why_unavailable(self, data):",
           "        \"\"\"What these data lack that the groups follow (None: nothing).\"\"\""]
    if columns:
        out += [f"        missing = [c for c in {columns!r} if c not in data.extras]",
                "        if missing:",
                "            return (f\"the data carry no {', '.join(missing)} column (this effect follows it; \"",
                "                    f\"columns carried: {', '.join(sorted(data.extras)) or 'none'})\")"]
    if temperature:
        out += ["        if not data.has_temperature():",
                "            return \"the data carry no probe temperature (this effect follows it)\""]
    if reference:
        out += ["        if data.ref_total_nT is None:",
                "            return \"the data carry no reference total field, ref_total (this effect follows it)\""]
    if probes:
        out += [f"        gone = [p for p in {probes!r} if p not in data.probe_names]",
                "        if gone:",
                "            return f\"the data carry no probe {', '.join(gone)} (this effect's law acts on it)\""]
    return out + ["        return None", ""]


def _law_code(g: Group, i: int) -> list[str]:
    """A law's function (laws.LAW_CODE, or a free spline), named law_<i>, and what it follows, at module level."""
    r = g.feature.recipe
    if r["law"] is not None:
        code = LAW_CODE[r["law"]].replace("def law(", f"def law_{i}(", 1)
    else:
        free = "[j for j in range(phi.shape[1]) if j != fixed]"
        code = (f"def law_{i}(x, p, ref, span):\n"
                f"    \"\"\"One smooth function of x that none of the laws takes: B-splines of x, the "
                f"{int(r['fixed']) + 1}th held at one.\"\"\"\n"
                f"    phi = {_basis_code(r, 'x')}\n"
                f"    fixed = {int(r['fixed'])}\n"
                f"    free = {free}\n"
                f"    return phi[:, fixed] + phi[:, free] @ p, phi[:, free]\n")
    ctx = r["reference"]
    return (["", ""] + code.rstrip("\n").split("\n") + ["", "",
            f"def x_law_{i}(data):", f"    return {_lagged(r, _observable_code(r, 'data'))}", "", "",
            f"LAW_{i} = {{\"probes\": {list(r['probes'])!r}, \"ref\": {float(ctx['ref'])!r}, "
            f"\"span\": {max(float(ctx['hi']) - float(ctx['lo']), 1e-12)!r}, \"start\": {list(r['values'])!r}}}"])


def _lagged(r: dict[str, Any], raw: str) -> str:
    """The observable through its first-order lag where the recipe has one."""
    return f"low_pass(data.t_s, {raw}, {r['low_pass_s']!r})" if "low_pass_s" in r else raw


def _param_names(g: Group, names: dict[int, list[str]]) -> list[str]:
    return names.get(id(g)) or g.param_names()


def _shared(common: list[Group], laws: list[Group], names: dict[int, list[str]]) -> list[str]:
    """The shared parameters of the class: the common groups (linear), then each law's (non-linear)."""
    n_common = sum(g.size for g in common)
    sizes = [len(g.feature.recipe["values"]) for g in laws]
    lines = ["    def shared_names(self, data):", "        names = []"]
    lines += [f"        names += {_param_names(g, names)!r}" for g in common + laws]
    lines += ["        return names", "",
              "    def shared_start_values(self, data):",
              f"        return np.array([0.0] * {n_common}" + "".join(f" + LAW_{i + 1}['start']"
                                                                for i in range(len(laws))) + ", dtype=float)", ""]
    if common:
        lines += ["    def _common(self, data):", "        key = \"discovered:common columns\"",
                  "        if key not in data._cache:", "            view = _Data(data)", "            parts = []"]
        for g in common:
            lines += _group_block(g, "            ")
        lines += ["            data._cache[key] = np.concatenate(parts, axis=2)", "        return data._cache[key]", ""]
    lines += ["    def _shared_parts(self, data, k, theta):",
              "        \"\"\"(the corrections, the Jacobians) of the shared parameters at probe k.\"\"\"",
              "        parts = []"]
    if common:
        lines += ["        cols = self._common(data)",
                  f"        parts.append((cols @ theta[:{n_common}], cols))"]
    at = n_common
    for i, size in enumerate(sizes):
        lines += [f"        law = LAW_{i + 1}",
                  f"        parts.append(law_parts(data, k, theta[{at}:{at + size}], law['probes'], law_{i + 1}, "
                  f"x_law_{i + 1}(data), law['ref'], law['span']))"]
        at += size
    lines += ["        return parts", "",
              "    def shared_vcorrection(self, data, k, theta):",
              "        return sum(c for c, _ in self._shared_parts(data, k, theta))", "",
              "    def shared_vjacobian(self, data, k, theta):",
              "        return np.concatenate([j for _, j in self._shared_parts(data, k, theta)], axis=2)"]
    return lines


def _class(groups: Sequence[Group], class_name: str, name: str, readings: dict[int, str],
           names: dict[int, list[str]], beside: Sequence[str]) -> list[str]:
    own = [g for g in groups if not g.common and g.kind != "law"]
    common = [g for g in groups if g.common and g.kind != "law"]
    laws = [g for g in groups if g.kind == "law"]
    per_sample = all(g.per_sample for g in groups)
    probes = sorted({g.probe_name for g in own})
    physical = "; ".join(readings.get(id(g), g.key) for g in groups)
    doc = "; ".join(
        ([f"groups of {', '.join(probes)}, each in its probe's raw frame (subtracted before its matrix)"] if own else [])
        + (["groups common to all probes, in the aligned frame (shared parameters)"] if common else [])
        + ([f"{len(laws)} law{'s' if len(laws) > 1 else ''} in the aligned frame (shared parameters, each probe's "
            f"field in nT then the law's own)"] if laws else []))
    if len(physical) > 300:                                     # at a word, said as cut
        physical = physical[:300].rsplit(" ", 1)[0] + " ..."
    lines = ["", "", f"class {class_name}(EffectTerm):", f'    """{doc[0].upper() + doc[1:]}."""', "",
             f"    name = {name!r}", f"    title = {class_name!r}       # what reports call it: rename it with the class",
             f"    physical = {physical!r}",
             "    frame = 'raw'",
             f"    per_sample = {per_sample!r}" + ("" if per_sample else
                                                   "       # a lag, a phase or a rate needs the samples before"),
             f"    #: the catalogue's effects it was found beside: --effects FILE.py:{class_name} brings them too",
             f"    beside = {tuple(beside)!r}", ""]
    lines += _why_unavailable(groups)
    if own:
        lines += ["    def param_names(self, view):", "        names = []"]
        for p in probes:
            lines.append(f"        if view.name == {p!r}:")
            lines += [f"            names += {_param_names(g, names)!r}" for g in own if g.probe_name == p]
        lines += ["        return names", "", "    def columns(self, view):", "        parts = []"]
        for p in probes:
            lines.append(f"        if view.name == {p!r}:")
            for g in own:
                if g.probe_name == p:
                    lines += _group_block(g, "            ")
        lines += ["        if not parts:", "            return np.zeros((view.data.n_samples, 3, 0))",
                  "        return np.concatenate(parts, axis=2)", ""]
    if common or laws:
        lines += _shared(common, laws, names)
    return lines


def effect_classes(groups: Sequence[Group], class_name: str = "Discovered") -> list[str]:
    """The class names effect_source writes for these groups: one, which holds them all."""
    return [class_name]


def effect_source(found: Any, class_name: str = "Discovered", name: str = "discovered", *,
                  data_name: str = "", beside: Sequence[str] | None = None) -> str:
    """The Python source of an effect module holding the groups and laws of `found` (a discover.Discovery, or a list
    of library Groups) in one class `class_name`, its effect `name`; `beside`: the catalogue's effects it was found
    beside (a Discovery's own model's, where not given)."""
    if hasattr(found, "groups") and not isinstance(found, (list, tuple)):
        groups = [g.group for g in found.groups]
        readings = {id(g.group): g.reading for g in found.groups}
        names = {id(g.group): [p.name for p in g.parameters] for g in found.groups if g.group.kind == "law"}
        if beside is None and getattr(found, "fit", None) is not None:
            beside = [e for e in found.fit.model.effects if not e.startswith("discovered-")]
    else:
        groups, readings, names = list(found), {}, {}
    if not groups:
        raise ValueError("effect_source: no group to write (discovery claimed nothing)")
    laws = [g for g in groups if g.kind == "law"]
    found_lines = "\n".join(f"  - {readings.get(id(g), g.key)}" for g in groups)
    also = f" (it brings {', '.join(beside)}, which it was found beside)" if beside else ""
    doc = ("An effect written by fluxcal diagnose from what discovery found beyond the catalogue"
           + (f" in {data_name}" if data_name else "") + f":\n\n{found_lines}\n\n"
           f"Give it back with --effects FILE.py:{class_name}{also}; rename the class and `name` as you\n"
           f"like, replace a shape by a law of your own (docs/effects.md). The references the parameters are\n"
           f"centred on (the means of the data fitted) are kept with the calibration under `ref:` keys.")
    imports = ("from fluxcal.effects import low_pass\n"
               if any("low_pass_s" in g.feature.recipe for g in groups) else "")
    text = HEADER.format(doc=doc.replace('"""', "'''"), imports=imports)
    lines = [text.rstrip("\n")]
    if laws:
        lines += LAW_PARTS.rstrip("\n").split("\n")
        for i, g in enumerate(laws):
            lines += _law_code(g, i + 1)
    lines += _class(groups, class_name, name, readings, names, beside or ())
    if any(g.common and g.kind != "law" for g in groups):
        lines += SHARED_VIEW.rstrip("\n").split("\n")
    return "\n".join(lines) + "\n"
