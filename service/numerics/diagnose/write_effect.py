"""The groups discovery found, written as an effect module of the user's own (docs/effects.md): the Python source
of one EffectTerm class per frame (a probe's groups in its raw frame; groups common to all probes in the aligned
frame, as shared parameters), with named parameters in physical units, `frame`, and `per_sample` where each sample's
correction needs that sample alone. `--effects FILE.py:Discovered` takes it back unchanged, and fitted on the same
data it gives the discovered error (the same regressors, computed the same way: tests/numerics/test_discover.py).

Only text: the caller writes it where the user asked. Numerics only.
"""

from __future__ import annotations

import keyword
import re
from typing import Any, Sequence

from .library import Group

HEADER = '''"""{doc}"""

import numpy as np

from service.numerics.effects import EffectTerm
{imports}

def offset_columns(x):
    """(N, 3, 3): x on each axis (nT per unit of x)."""
    out = np.zeros((x.size, 3, 3))
    idx = np.arange(3)
    out[:, idx, idx] = x[:, None]
    return out


def matrix_columns(x, u):
    """(N, 3, 9): 1e-6 x u_j on axis i (ppm per unit of x): the matrix follows x."""
    out = np.zeros((x.size, 3, 9))
    for i in range(3):
        out[:, i, 3 * i:3 * i + 3] = 1e-6 * x[:, None] * u
    return out


def scale_columns(x, u):
    """(N, 3, 6): x on each axis (nT per unit of x), then 1e-6 x u_i on axis i (ppm per unit of x): the offset and
    the scale factors follow x."""
    out = np.zeros((x.size, 3, 6))
    idx = np.arange(3)
    out[:, idx, idx] = x[:, None]
    out[:, idx, 3 + idx] = 1e-6 * x[:, None] * u
    return out


def wave_columns(phase):
    """(N, 3, 6): cos and sin of a phase on each axis (nT)."""
    out = np.zeros((phase.size, 3, 6))
    idx = np.arange(3)
    out[:, idx, idx] = np.cos(phase)[:, None]
    out[:, idx, 3 + idx] = np.sin(phase)[:, None]
    return out


def loop_columns(values):
    """(N, 3, 3): a per-axis value on its own axis (nT)."""
    out = np.zeros((values.shape[0], 3, 3))
    idx = np.arange(3)
    out[:, idx, idx] = values
    return out


def centred(view, key, x):
    """x less its mean over the data the effect was fitted to (kept with the calibration: a `ref:` key)."""
    key = "ref:" + key
    if key not in view.cache:
        view.cache[key] = float(np.mean(x))
    return x - view.cache[key]


def column(data, name):
    """A logged column, gaps (NaN) filled by interpolation in time."""
    x = np.asarray(data.extras[name], dtype=np.float64)
    ok = np.isfinite(x)
    return x if ok.all() else np.interp(data.t_s, data.t_s[ok], x[ok])


def phase_of(t_s, x, cycles_per_unit):
    """2 pi cycles_per_unit times the time integral of x from the first sample (trapezoids), rad."""
    inc = 0.5 * (x[1:] + x[:-1]) * np.diff(t_s)
    return 2 * np.pi * cycles_per_unit * np.concatenate([[0.0], np.cumsum(inc)])


def angular_rate_deg_s(data):
    """|w| of probe 1's field direction, deg/s."""
    s, r = data.smooth(0), data.rate(0)
    return np.degrees(np.linalg.norm(np.cross(s, r), axis=1) / np.sum(s * s, axis=1))
'''


def _ident(text: str) -> str:
    s = re.sub(r"\W+", "_", text).strip("_").lower() or "x"
    if s[0].isdigit() or keyword.iskeyword(s):
        s = "f_" + s
    return s


def _feature_code(g: Group) -> tuple[str, list[str]]:
    """(the expression of the group's feature in terms of `view`, the lines before it)."""
    f, r = g.feature, g.feature.recipe
    key = f"discovered:{f.name}"
    src = r["source"]
    lines: list[str] = []
    if src == "temperature":
        probe = g.feature.observable.rsplit("_temp", 1)[0]
        raw = f"view.data.temperature(view.data.probe_names.index({probe!r}))"
    elif src == "column" or (src == "phase" and "column" in r):
        raw = f"column(view.data, {r['column']!r})"
    elif src == "time":
        raw = "view.data.t_s / 3600.0"
    elif src == "ref_total":
        raw = "view.data.ref_total_nT"
    elif src == "angular rate":
        raw = "angular_rate_deg_s(view.data)"
    elif src == "line":
        return f"2 * np.pi * {r['hz']!r} * view.data.t_s", lines
    elif src == "sign of rate":
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
    else:
        raise ValueError(f"recipe: {r!r} is not one the writer knows")
    if src == "phase":
        return f"phase_of(view.data.t_s, {raw}, {r['cycles_per_unit']!r})       # {r.get('unit', '')}", lines
    if "low_pass_s" in r:
        lines.append(f"x = low_pass(view.data.t_s, {raw}, {r['low_pass_s']!r})       # a first-order lag, s")
        raw = "x"
    return f"centred(view, {key!r}, {raw})", lines


def _group_block(g: Group, indent: str) -> list[str]:
    expr, pre = _feature_code(g)
    borrowed = f" (borrowed: {g.feature.borrowed})" if g.feature.borrowed else ""
    out = [f"{indent}# {g.kind}: {g.feature.name}{borrowed}"]
    out += [indent + ln for ln in pre]
    builder = {"offset": "offset_columns({x})", "common offset": "offset_columns({x})",
               "scale": "scale_columns({x}, view.centred_nT)",
               "matrix": "matrix_columns({x}, view.centred_nT)", "wave": "wave_columns({x})",
               "common wave": "wave_columns({x})", "loop": "loop_columns({x})"}[g.kind]
    out.append(f"{indent}parts.append({builder.format(x=expr)})")
    return out


def _why_unavailable(groups: Sequence[Group]) -> list[str]:
    """The written class's why_unavailable: the columns, temperatures or reference its groups follow, said missing
    where other data lack them (a KeyError deep in the fit before)."""
    columns = sorted({g.feature.recipe["column"] for g in groups if "column" in g.feature.recipe})
    temperature = any(g.feature.recipe["source"] == "temperature" for g in groups)
    reference = any(g.feature.recipe["source"] == "ref_total" for g in groups)
    if not (columns or temperature or reference):
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
    return out + ["        return None", ""]


def _names_code(g: Group) -> str:
    return f"{g.param_names()!r}"


def _class(groups: Sequence[Group], class_name: str, name: str, readings: dict[int, str]) -> list[str]:
    common = groups[0].common
    per_sample = all(g.per_sample for g in groups)
    probes = sorted({g.probe_name for g in groups})
    physical = "; ".join(readings.get(id(g), g.key) for g in groups)
    doc = ("Groups common to all probes, in the aligned frame (shared parameters)." if common else
           f"Groups of {', '.join(probes)}, each in its probe's raw frame (subtracted before its matrix).")
    if len(physical) > 300:                                     # at a word, said as cut
        physical = physical[:300].rsplit(" ", 1)[0] + " ..."
    lines = ["", "", f"class {class_name}(EffectTerm):", f'    """{doc}"""', "",
             f"    name = {name!r}", f"    title = {class_name!r}       # what reports call it: rename it with the class",
             f"    physical = {physical!r}",
             f"    frame = {'corrected' if common else 'raw'!r}",
             f"    per_sample = {per_sample!r}" + ("" if per_sample else
                                                   "       # a lag, a phase or a rate needs the samples before"), ""]
    lines += _why_unavailable(groups)
    if common:
        lines += ["    def shared_names(self, data):", "        names = []"]
        lines += [f"        names += {_names_code(g)}" for g in groups]
        lines += ["        return names", "",
                  "    def shared_vcolumns(self, data, k):",
                  "        key = \"discovered:common columns\"",
                  "        if key not in data._cache:",
                  "            view = _Data(data)",
                  "            parts = []"]
        for g in groups:
            lines += _group_block(g, "            ")
        lines += ["            data._cache[key] = np.concatenate(parts, axis=2)", "        return data._cache[key]"]
        return lines
    lines += ["    def param_names(self, view):", "        names = []"]
    for p in probes:
        lines.append(f"        if view.name == {p!r}:")
        lines += [f"            names += {_names_code(g)}" for g in groups if g.probe_name == p]
    lines += ["        return names", "", "    def columns(self, view):", "        parts = []"]
    for p in probes:
        lines.append(f"        if view.name == {p!r}:")
        for g in groups:
            if g.probe_name == p:
                lines += _group_block(g, "            ")
    lines += ["        if not parts:", "            return np.zeros((view.data.n_samples, 3, 0))",
              "        return np.concatenate(parts, axis=2)"]
    return lines


SHARED_VIEW = '''

class _Data:
    """What the common groups look at: the data, and their references (the means of the data fitted), kept on
    the data under a `ref:` key, which travels with a fitted calibration to other data as a probe's do."""

    def __init__(self, data):
        self.data = data
        self.cache = data._cache.setdefault("ref:discovered", {})      # a `ref:` key: kept with the calibration
'''


def effect_classes(groups: Sequence[Group], class_name: str = "Discovered") -> list[str]:
    """The class names effect_source writes for these groups: one per frame present."""
    out = []
    if any(not g.common for g in groups):
        out.append(class_name)
    if any(g.common for g in groups):
        out.append(class_name + "Common" if out else class_name)
    return out


def effect_source(found: Any, class_name: str = "Discovered", name: str = "discovered", *,
                  data_name: str = "") -> str:
    """The Python source of an effect module holding the groups of `found` (a discover.Discovery, or a list of
    library Groups): one class per frame (effect_classes), named `class_name` (and `class_name`Common), its
    effect `name` (and `name`-common)."""
    if hasattr(found, "groups") and not isinstance(found, (list, tuple)):
        groups = [g.group for g in found.groups]
        readings = {id(g.group): g.reading for g in found.groups}
    else:
        groups, readings = list(found), {}
    if not groups:
        raise ValueError("effect_source: no group to write (discovery claimed nothing)")
    own = [g for g in groups if not g.common]
    common = [g for g in groups if g.common]
    names = effect_classes(groups, class_name)
    found_lines = "\n".join(f"  - {readings.get(id(g), g.key)}" for g in groups)
    use = ", ".join(f"FILE.py:{c}" for c in names)
    doc = ("An effect written by fluxcal diagnose from what discovery found beyond the catalogue"
           + (f" in {data_name}" if data_name else "") + f":\n\n{found_lines}\n\n"
           f"Give it back with --effects {use} (rename the class and `name` as you like; docs/effects.md).\n"
           f"The references the parameters are centred on (the means of the data fitted) are kept with the\n"
           f"calibration under `ref:` keys.")
    imports = ("from service.numerics.effects.thermal import low_pass\n"
               if any("low_pass_s" in g.feature.recipe for g in groups) else "")
    text = HEADER.format(doc=doc.replace('"""', "'''"), imports=imports)
    lines = [text.rstrip("\n")]
    if own:
        lines += _class(own, names[0], name, readings)
    if common:
        if own:
            lines += _class(common, names[1], f"{name}-common", readings)
        else:
            lines += _class(common, names[0], name, readings)
        lines += SHARED_VIEW.rstrip("\n").split("\n")
    return "\n".join(lines) + "\n"
