"""The library of candidate terms that discovery tries beyond the catalogue, generated from what the data carry.

Features: time series the data carry or imply, each centred on its mean over the data (a reference the
parameters are defined against, kept with the written effect):

- each observable: each probe's temperature, every logged column, time, the total field of a varying scalar
  reference, the angular rate |w|; the slow ones (temperatures, columns) also low-passed by a first-order lag
  (time constants on a grid of ratio 3: the selection chooses among them inside its training blocks);
- the phase of a logged speed or frequency column (2 pi times its time integral, in Hz, rpm or rad/s as its
  name says, else tried as Hz and rpm where the residual has power in that band), cosine and sine;
- the spectral lines of the residual (spectra.py: peaks standing above their neighbourhood), cosine and sine;
- the smooth sign of each axis' rate of change, tanh(rate / s) (a core's loop: an offset that depends on
  whether the field along the axis rises or falls).

Groups of a few parameters in physical units. Per probe, in its raw frame (subtracted before its matrix):

    offset   x e_a                          nT per unit of x, per axis
    scale    x e_a, 1e-6 x u_a e_a          nT and ppm per unit: the offset and the scale factors follow x, the
                                            catalogue's temperature term for any observable (a supply or a heater
                                            that moves a probe's gain moves its offset too, and a gain that acts on
                                            the raw output, or about any centre, is a scale about the fitted centre
                                            and an offset)
    matrix   1e-6 x u_j e_i, u = raw - o     ppm per unit: the probe's matrix follows x, read back as scale
                                            (diagonal), non-orthogonality (symmetric) and rotation (antisymmetric)
    wave     cos(phi) e_a, sin(phi) e_a     nT: a field at a phase
    loop     tanh(rate_a / s_a) e_a         nT: the offset follows the sign of the axis' rate

(a raw-frame term with free per-axis amplitudes spans the same as the corrected-frame one: the matrix is
constant). For arrays, common to all probes in the aligned (corrected) frame, one set for the array: a field
following x or at a phase, which shows in the scalar channels and cancels in the differences (the channel
families: an effect of one probe shows in its scalar channel and its differences, a common one in the scalar
channels only).

Numerics only.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import AXES, EffectData, EffectTerm, ProbeView, axis_columns
from fluxcal.service.numerics.effects.column import column_values, usable_columns
from fluxcal.service.numerics.effects.temperature import borrowed_from
from fluxcal.service.numerics.effects.thermal import low_pass

from .harmonics import column_lines, harmonic_lines, harmonic_source
from .shapes import SHAPE_ORDERS, shape_recipes
from .spectra import excess_spectra, set_spectra, spectral_lines

#: the groups that follow a smooth function of an observable (shapes.py): a probe's, in its raw frame, and one common
#: to all probes of an array, in the aligned frame
SHAPE_KINDS = ("shape", "common shape")

#: low-pass time constants: from a quarter of the record down by factors of 3, at most this many
N_TAUS = 4
TAU_RATIO = 3.0
#: the smallest time constant tried, in sample intervals (shorter is the value itself)
MIN_TAU_SAMPLES = 20
#: the phase of an unnamed positive column is tried where its band holds this share of some channel's excess power
BAND_SHARE = 0.2
#: the smooth sign of a rate: tanh(rate / (LOOP_SCALE std(rate)))
LOOP_SCALES = (0.05, 0.3)
#: a column's unit by its name: cycles per unit of the column
PHASE_HINTS = (("rpm", 1.0 / 60.0), ("rad_s", 1.0 / (2 * np.pi)), ("rads", 1.0 / (2 * np.pi)), ("rps", 1.0),
               ("hz", 1.0), ("freq", 1.0))
SPEED_WORDS = ("speed", "tach", "fan", "pump", "motor", "rotor", "prop", "wheel", "rev")
UNIT_OF_SCALE = {1.0: "Hz", 1.0 / 60.0: "rpm", 1.0 / (2 * np.pi): "rad/s"}


@dataclass
class Feature:
    """A time series a group follows. values: (N,) centred on `centre`, or (N, 2) cos and sin of a phase, or
    (N, 3) per axis (the loop). recipe: how the written effect makes it again (JSON-ready)."""

    name: str                        # "s2_temp", "heater_A low-passed 60 s", "fan_hz phase", "line at 1.51 Hz"
    observable: str                  # what the data carry: "s2_temp", "heater_A", "time", "residual", "rate of s1"
    unit: str                        # the unit per which a coefficient is given: "degC", "heater_A", "h", ""
    how: str                         # "value", "low-passed", "phase", "line", "sign of rate"
    recipe: dict[str, Any]
    values: np.ndarray = field(repr=False)
    per_sample: bool = True
    borrowed: str | None = None      # a probe's temperature taken from others: from which

    @property
    def per(self) -> str:
        """' per heater_A', '/degC', '/h' (after a unit in a parameter name)."""
        if self.unit in ("degC", "h", "nT", "deg/s"):
            return f"/{self.unit}"
        return f" per {self.unit}" if self.unit else ""


@dataclass
class Group:
    """A few parameters that follow one feature: kind offset, scale, matrix, wave, loop (per probe, raw frame) or
    common offset, common wave (all probes, corrected frame)."""

    kind: str
    probe: int | None                # None: common to all probes
    probe_name: str
    feature: Feature

    @property
    def common(self) -> bool:
        return self.probe is None

    @property
    def frame(self) -> str:
        return "corrected" if self.common else "raw"

    @property
    def per_sample(self) -> bool:
        return self.feature.per_sample

    @property
    def key(self) -> str:
        return f"{self.probe_name} {self.kind} {self.feature.name}"

    @property
    def size(self) -> int:
        if self.kind in SHAPE_KINDS:
            return 3 * self.feature.values.shape[1]
        return {"offset": 3, "scale": 6, "matrix": 9, "wave": 6, "loop": 3, "common offset": 3,
                "common wave": 6}[self.kind]

    @property
    def holds(self) -> tuple[str, int | None, str] | None:
        """(kind, probe, feature name) of the next smaller group this one holds, or None: a scale group its offset (the
        offset and scale factors following x hold the offset alone), a spline of x the smaller spline of x, the
        smallest spline of x the offset that follows x itself (a cubic spline reproduces x)."""
        r = self.feature.recipe
        if self.kind == "scale":
            return "offset", self.probe, self.feature.name
        if self.kind in SHAPE_KINDS and r.get("basis") == "spline":
            smaller = [m for m in SHAPE_ORDERS if m < r["functions"]]
            if smaller:
                return self.kind, self.probe, self.feature.name.replace(f"({r['functions']})", f"({smaller[-1]})")
            return ("common offset" if self.common else "offset"), self.probe, r["of"]
        if self.kind in SHAPE_KINDS and r["harmonics"] > 1:
            return self.kind, self.probe, self.feature.name.replace(f"({r['harmonics']})", f"({r['harmonics'] - 1})")
        return None

    @property
    def slow(self) -> bool:
        return self.feature.how in ("value", "low-passed") and self.feature.observable != "angular rate"

    def param_names(self) -> list[str]:
        p, f = self.probe_name, self.feature
        if self.kind in ("offset", "common offset"):
            return [f"{p}.{f.name} {a} nT{f.per}" for a in AXES]
        if self.kind == "scale":
            return [f"{p}.{f.name} {a} nT{f.per}" for a in AXES] + [f"{p}.{f.name} {a} ppm{f.per}" for a in AXES]
        if self.kind == "matrix":
            return [f"{p}.{f.name} [{a}{b}] ppm{f.per}" for a in AXES for b in AXES]
        if self.kind in ("wave", "common wave"):
            return [f"{p}.{f.name} {part} {a} nT" for part in ("cos", "sin") for a in AXES]
        if self.kind in SHAPE_KINDS:
            return [f"{p}.{f.name} b{j + 1} {a} nT" for a in AXES for j in range(f.values.shape[1])]
        return [f"{p}.{f.name} {a} nT" for a in AXES]                       # loop

    def columns(self, data: EffectData, offset_nT: np.ndarray, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        """(n, 3, size) regressors at `rows`: raw frame for a probe's group (u = raw - offset_nT[probe]), corrected
        frame for a common one."""
        v = self.feature.values[rows]
        n = v.shape[0]
        if self.kind in ("offset", "common offset"):
            return axis_columns(np.repeat(v[:, None], 3, axis=1))
        if self.kind == "loop":
            return axis_columns(v)
        if self.kind in SHAPE_KINDS:                                        # column a m + j: function j on axis a
            m = v.shape[1]
            out = np.zeros((n, 3, 3 * m))
            for a in range(3):
                out[:, a, a * m:(a + 1) * m] = v
            return out
        if self.kind in ("wave", "common wave"):
            out = np.zeros((n, 3, 6))
            idx = np.arange(3)
            out[:, idx, idx] = v[:, :1]
            out[:, idx, 3 + idx] = v[:, 1:2]
            return out
        u = data.raw_nT[rows, self.probe, :] - offset_nT[self.probe]
        if self.kind == "scale":
            out = np.zeros((n, 3, 6))
            idx = np.arange(3)
            out[:, idx, idx] = v[:, None]
            out[:, idx, 3 + idx] = 1e-6 * v[:, None] * u
            return out
        out = np.zeros((n, 3, 9))
        for i in range(3):
            out[:, i, 3 * i:3 * i + 3] = 1e-6 * v[:, None] * u
        return out


# --- features -------------------------------------------------------------------------------------------

def tau_grid(data: EffectData) -> list[float]:
    """Low-pass time constants: a quarter of the record, then down by TAU_RATIO, at least MIN_TAU_SAMPLES
    sample intervals; at most N_TAUS, rounded to two significant figures (written into the effect)."""
    out, tau = [], data.duration_s / 4.0
    while tau >= MIN_TAU_SAMPLES * data.dt_s and len(out) < N_TAUS:
        out.append(float(f"{tau:.2g}"))
        tau /= TAU_RATIO
    return out


def _centred(x: np.ndarray) -> tuple[np.ndarray, float]:
    c = float(np.mean(x))
    return x - c, c


def angular_rate_deg_s(data: EffectData) -> np.ndarray:
    """(N,) |w| of probe 1's field direction, deg/s: |b x db/dt| / |b|^2 (as where.py measures it)."""
    s, r = data.smooth(0), data.rate(0)
    return np.degrees(np.linalg.norm(np.cross(s, r), axis=1) / np.sum(s * s, axis=1))


def phase_of(t_s: np.ndarray, x: np.ndarray, cycles_per_unit: float) -> np.ndarray:
    """2 pi cycles_per_unit times the time integral of x from the first sample (trapezoids), rad."""
    inc = 0.5 * (x[1:] + x[:-1]) * np.diff(t_s)
    return 2 * np.pi * cycles_per_unit * np.concatenate([[0.0], np.cumsum(inc)])


def loop_label(width: float) -> str:
    """A loop feature's name: its sign's width as a share of the rate's spread, where the library tries several."""
    return "sign of rate" if len(LOOP_SCALES) == 1 else f"sign of rate ({width:g})"


def loop_values(rate: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(N, 3) the smooth sign of each axis' rate: tanh(rate / scale)."""
    return np.tanh(rate / scale)


#: a refined loop's sign is taken again this many times from the reading less its steps (loop_feature)
LOOP_PASSES = 2


def loop_feature(data: EffectData, k: int, label: str, scale: np.ndarray,
                 less_nT: np.ndarray | None = None, window: int | None = None) -> Feature:
    """The smooth sign of each axis' rate of probe k (a core's loop). The core follows the field's rate, not the
    reading's, and its own steps are in the reading: each step puts a spike of its own sign in the reading's rate
    where the field's turns, and on a noisy real board the sign chatters there (an offset stepping 250 nT with the
    sign of a 50-Hz board's rate, found from the reading's rate: held-out error 1.16 times the untouched board's;
    from the field's: 1.00). less_nT: the steps fitted (nT per axis); the sign is then taken again LOOP_PASSES times
    from the reading less the steps times the sign before. window: the samples the rate is taken over (odd; None:
    the data's own, window_samples); where the field's rate turns depends on it (discover.refine_loops chooses
    it). In samples: on a bursty time base a time would say little (77 samples 3.3 ms apart at the median span
    1.0 s on a hand-turned board)."""
    scale = np.asarray(scale, float)
    raw = data.raw_nT[:, k, :]
    values = loop_values(data.rate(k) if window is None else data.derivative(raw, window), scale)
    recipe: dict[str, Any] = {"source": "sign of rate", "scale": [float(x) for x in scale]}
    if window is not None:
        recipe["window_samples"] = int(window)
    if less_nT is not None:
        for _ in range(LOOP_PASSES):
            values = loop_values(data.derivative(raw - np.asarray(less_nT, float) * values, window), scale)
        recipe.update(less_nT=[float(x) for x in less_nT], passes=LOOP_PASSES)
    return Feature(label, f"rate of {data.probe_names[k]}", "", "sign of rate", recipe, values, per_sample=False)


def temperature_features(data: EffectData) -> list[tuple[int, Feature]]:
    """(probe, its temperature as a feature): its own, or the others' mean (borrowed, said)."""
    if not data.has_temperature():
        return []
    out = []
    for k, name in enumerate(data.probe_names):
        t = data.temperature(k)
        if t is None or float(np.ptp(t)) <= 1e-6:
            continue
        values, centre = _centred(t)
        borrowed = borrowed_from(data.temp_C, data.probe_names, k)
        fname = f"{name}_temp" if borrowed is None else f"{name}_temp (the mean of {borrowed}'s)"
        out.append((k, Feature(fname, f"{name}_temp", "degC", "value",
                               {"source": "temperature", "probe": k, "probe_name": name, "centre": centre}, values,
                               borrowed=borrowed)))
    return out


def _low_passed(data: EffectData, f: Feature, raw: np.ndarray, taus: list[float]) -> list[Feature]:
    out = []
    for tau in taus:
        values, centre = _centred(low_pass(data.t_s, raw, tau))
        out.append(Feature(f"{f.name} low-passed {tau:g} s", f.observable, f.unit, "low-passed",
                           {**f.recipe, "low_pass_s": tau, "centre": centre}, values, per_sample=False,
                           borrowed=f.borrowed))
    return out


def relagged(data: EffectData, f: Feature, tau_s: float) -> Feature:
    """A low-passed feature again at another time constant (from its recipe: a temperature or a column)."""
    r = f.recipe
    if r["source"] == "temperature":
        raw = data.temperature(r["probe"])
    else:
        raw = usable_columns(data)[r["column"]]
    base = f.name.rsplit(" low-passed", 1)[0]
    values, centre = _centred(low_pass(data.t_s, raw, tau_s))
    return Feature(f"{base} low-passed {tau_s:g} s", f.observable, f.unit, "low-passed",
                   {**r, "low_pass_s": tau_s, "centre": centre}, values, per_sample=False, borrowed=f.borrowed)


#: the shapes' basis values are held in single precision: they are most of the library's memory (304 of 369 MB on
#: 50,000 rows with 25 logged columns), and their rounding (6e-8 of a value between -1 and 1) is far below what any
#: residual they are fitted to can tell; every product with them is taken in double precision
SHAPE_DTYPE = np.float32


def shape_features(f: Feature, raw: np.ndarray) -> list[Feature]:
    """The shape features (shapes.py) of a value feature f whose values before centring are `raw`."""
    return [Feature(name, f.observable, "", how, {**recipe, "of": f.name}, values.astype(SHAPE_DTYPE),
                    per_sample=f.per_sample, borrowed=f.borrowed)
            for name, how, recipe, values in shape_recipes(f.name, raw, f.recipe)]


def _phase_scales(name: str) -> tuple[list[float], bool]:
    low = name.lower()
    for word, scale in PHASE_HINTS:
        if word in low:
            return [scale], True
    return [1.0, 1.0 / 60.0], any(w in low for w in SPEED_WORDS)


def phase_features(data: EffectData, spectra: list, columns: dict[str, np.ndarray]) -> list[Feature]:
    """The phase of each positive logged column that could be a speed or a frequency: named so (rpm, Hz,
    rad/s, speed ...), or with a share BAND_SHARE of some channel's excess power in the band it spans."""
    out = []
    nyquist = 0.5 / data.dt_s
    for name in columns:
        x = np.asarray(data.extras[name], dtype=np.float64)
        ok = np.isfinite(x)
        if ok.sum() < 2 or float(np.min(x[ok])) < 0 or float(np.max(x[ok])) <= 0:
            continue
        if not ok.all():
            x = np.interp(data.t_s, data.t_s[ok], x[ok])
        scales, named = _phase_scales(name)
        for scale in scales:
            lo, hi = float(np.min(x)) * scale, float(np.max(x)) * scale
            if hi >= nyquist or hi <= 2.0 / data.duration_s:
                continue
            if not named:
                band = [float(e[(f >= 0.9 * lo) & (f <= 1.1 * hi)].sum()) / max(float(e.sum()), 1e-300)
                        for f, e in spectra]
                if not band or max(band) < BAND_SHARE:
                    continue
            phi = phase_of(data.t_s, x, scale)
            unit = UNIT_OF_SCALE.get(scale, f"{scale:g} Hz per unit")
            label = f"{name} phase" if len(scales) == 1 else f"{name} phase (as {unit})"
            out.append(Feature(label, name, "", "phase", {"source": "phase", "column": name,
                                                          "cycles_per_unit": scale, "unit": unit},
                               np.column_stack([np.cos(phi), np.sin(phi)]), per_sample=False))
    return out


def line_features(data: EffectData, lines: list[float]) -> list[Feature]:
    out = []
    for hz in lines:
        w = 2 * np.pi * hz * data.t_s
        out.append(Feature(f"line at {hz:.4g} Hz", "residual", "", "line", {"source": "line", "hz": hz},
                           np.column_stack([np.cos(w), np.sin(w)])))
    return out


def wave_features(data: EffectData, fit: Any, noise: np.ndarray,
                  exclude: tuple[int, int] | None = None) -> list[Feature]:
    """The features the residual itself chooses: the phases of the columns whose band holds some of its excess
    power (phase_features) and its spectral lines. exclude: rows of the fit not looked at (a held-out block)."""
    spectra = set_spectra(fit, noise, exclude)
    sources = column_lines(data)
    # a line a logged column's own motion makes (a harmonic or a sum of its lines) is that column's shape, which the
    # library holds: never a wave of its own (harmonics.py)
    lines = line_features(data, [hz for hz in spectral_lines(fit, noise, exclude, spectra)
                                 if harmonic_source(hz, sources, data.duration_s) is None])
    return phase_features(data, excess_spectra(fit, noise, exclude, spectra), usable_columns(data)) + lines


def wave_groups(data: EffectData, waves: list[Feature]) -> list[Group]:
    """The groups of build_library that follow these wave features: each probe's, and the common one of an array."""
    out = [Group("wave", k, data.probe_names[k], f) for k in range(data.n_probes) for f in waves]
    if data.n_probes > 1:
        out += [Group("common wave", None, "common", f) for f in waves]
    return out


# --- the library -------------------------------------------------------------------------------------------

@dataclass
class Library:
    """The groups tried, and the features they follow (for the report: what was looked at)."""

    groups: list[Group]
    taus_s: list[float]
    lines_hz: list[float]
    borrowed: dict[str, str]          # probe -> whose temperature it takes
    #: the residual's lines a logged column's motion makes (line Hz -> (column, how)): its shapes take them
    harmonics: dict[float, tuple[str, str]] = field(default_factory=dict)

    @property
    def n_params(self) -> int:
        return sum(g.size for g in self.groups)


def build_library(data: EffectData, fit: Any, noise: np.ndarray) -> Library:
    """Every group the data allow, for the residual of `fit` (its spectral lines, the bands it has power in)."""
    names = data.probe_names
    taus = tau_grid(data)
    per_probe: dict[int, list[Feature]] = {k: [] for k in range(data.n_probes)}
    shared: list[Feature] = []          # features of the platform: every probe may follow them
    borrowed = {}
    shapes: dict[int, list[Feature]] = {k: [] for k in range(data.n_probes)}     # smooth functions (shapes.py)
    for k, f in temperature_features(data):
        raw = f.values + f.recipe["centre"]
        lagged = _low_passed(data, f, raw, taus)
        per_probe[k] += [f] + lagged
        shapes[k] += shape_features(f, raw) + [s for g in lagged for s in shape_features(g, g.values + g.recipe["centre"])]
        if f.borrowed:
            borrowed[names[k]] = f.borrowed
    cols = usable_columns(data)
    column_features, column_shapes, lag_shapes = [], [], []
    for c, v in cols.items():
        raw = column_values(data, c)
        f = Feature(c, c, c, "value", {"source": "column", "column": c, "centre": float(np.mean(raw))}, v)
        lagged = _low_passed(data, f, raw, taus)
        column_features += [f] + lagged
        column_shapes += shape_features(f, raw)
        lag_shapes += [s for g in lagged for s in shape_features(g, g.values + g.recipe["centre"])]
    shared += column_features
    t, tc = _centred((data.t_s - data.t_s[0]) / 3600.0)
    time_f = Feature("time", "time", "h", "value", {"source": "time", "centre": tc}, t)
    extra = []
    if data.ref_total_nT is not None and float(np.ptp(data.ref_total_nT)) > 1.0:
        b, bc = _centred(np.asarray(data.ref_total_nT, float))
        extra.append(Feature("total field", "ref_total", "nT", "value", {"source": "ref_total", "centre": bc}, b))
    w = angular_rate_deg_s(data)
    if float(np.ptp(w)) > 1e-6:
        wv, wc = _centred(w)
        extra.append(Feature("angular rate", "angular rate", "deg/s", "value",
                             {"source": "angular rate", "centre": wc}, wv, per_sample=False))
    extra_shapes = [g for f in extra for g in shape_features(f, f.values + f.recipe["centre"])]
    waves = wave_features(data, fit, noise)

    groups: list[Group] = []
    for k in range(data.n_probes):
        pname = names[k]
        for f in per_probe[k] + column_features + extra:
            groups += [Group(kind, k, pname, f) for kind in ("offset", "scale", "matrix")]
        groups += [Group("shape", k, pname, f) for f in shapes[k] + column_shapes + lag_shapes + extra_shapes]
        groups.append(Group("matrix", k, pname, time_f))
        groups += [Group("wave", k, pname, f) for f in waves]
        rate = data.rate(k)
        for s in LOOP_SCALES:
            scale = s * np.std(rate, axis=0)
            if np.all(scale > 0):
                groups.append(Group("loop", k, pname, loop_feature(data, k, loop_label(s), scale)))
    if data.n_probes > 1:
        groups += [Group("common offset", None, "common", f) for f in shared]
        groups += [Group("common shape", None, "common", f) for f in column_shapes]
        groups += [Group("common wave", None, "common", f) for f in waves]
    return Library(groups, taus, [f.recipe["hz"] for f in waves if f.how == "line"], borrowed,
                   harmonic_lines(data, fit, noise))


# --- a group as a term the engine fits ------------------------------------------------------------------

class GroupTerm(EffectTerm):
    """One library group as an effect term (the engine fits the groups discovery chose, with standard errors
    and held-out blocks, like any effect)."""

    linear = True
    title = "Discovered"
    physical = "a term the library of discovery found"

    def __init__(self, group: Group, index: int) -> None:
        self.group = group
        self.name = f"discovered-{index + 1}"                      # type: ignore[misc]
        self.frame = group.frame                                  # type: ignore[misc]
        self.per_sample = group.per_sample                        # type: ignore[misc]
        self.title = f"{group.probe_name} {group.kind} ~ {group.feature.name}"   # type: ignore[misc]

    def param_names(self, view: ProbeView) -> list[str]:
        return self.group.param_names() if view.k == self.group.probe else []

    def columns(self, view: ProbeView) -> np.ndarray:
        offsets = np.zeros((view.data.n_probes, 3))
        offsets[view.k] = view.offset_nT
        return self.group.columns(view.data, offsets)

    def shared_names(self, data: EffectData) -> list[str]:
        return self.group.param_names() if self.group.common else []

    def shared_vcolumns(self, data: EffectData, k: int) -> np.ndarray | None:
        if not self.group.common:
            return None
        key = ("discovered", self.group.key)
        if key not in data._cache:
            data._cache[key] = self.group.columns(data, np.zeros((data.n_probes, 3)))
        return data._cache[key]
