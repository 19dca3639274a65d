"""What the engine fits: the state (linear part and effect parameters) and its layout in parameter slots.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from fluxcal.service.numerics.effects.base import AXES, EffectData, EffectTerm, ProbeView

from .linear import LinearCalibration


@dataclass
class State:
    """Everything being fitted: the linear part and the effect parameters."""

    linear: LinearCalibration
    theta: dict[str, list[np.ndarray]]       # term name -> per-probe parameter vectors
    shared: dict[str, np.ndarray]            # term name -> shared parameter vector

    def copy(self) -> "State":
        return State(self.linear.copy(), {k: [a.copy() for a in v] for k, v in self.theta.items()},
                     {k: v.copy() for k, v in self.shared.items()})


@dataclass
class _Slot:
    kind: str                        # "offset", "matrix", "term", "shared"
    k: int | None                    # probe, None for shared
    term: EffectTerm | None
    names: list[str]
    start: int = 0
    keys: list[tuple] = field(default_factory=list)      # the term's param_keys, beside names

    @property
    def size(self) -> int:
        return len(self.names)

    @property
    def stop(self) -> int:
        return self.start + self.size


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def layout_slots(data: EffectData, terms: Sequence[EffectTerm], views: Sequence[ProbeView],
                 fit_linear: bool) -> list[_Slot]:
    """The parameter slots in order: per probe the offset and matrix (when the linear part is fitted) and
    each term's own parameters, then the terms' shared ones."""
    slots: list[_Slot] = []
    for k in range(len(views)):
        name = data.probe_names[k]
        if fit_linear:
            slots.append(_Slot("offset", k, None, [f"{name}.offset {a} nT" for a in AXES]))
            if k == 0 and data.ref_vector_nT is None:
                # without a reference vector the common frame's rotation is free: symmetric X only
                slots.append(_Slot("matrix", k, None, [f"{name}.matrix sym[{AXES[i]}{AXES[j]}]" for i, j in _SYM]))
            else:
                slots.append(_Slot("matrix", k, None, [f"{name}.matrix d[{a}{b}]" for a in AXES for b in AXES]))
        for term in terms:
            names = term.param_names(views[k])
            if names:
                keys = term.param_keys(views[k])
                if len(keys) != len(names):
                    raise ValueError(f"{term.name}: {len(keys)} param_keys for {len(names)} param_names")
                slots.append(_Slot("term", k, term, names, keys=keys))
    for term in terms:
        names = term.shared_names(data)
        if names:
            slots.append(_Slot("shared", None, term, names))
    start = 0
    for s in slots:
        s.start = start
        start += s.size
    return slots


def floor_vector(slots: Sequence[_Slot]) -> np.ndarray:
    """Per parameter the lowest value its term's physics allows (EffectTerm.floors), -inf where none."""
    lo = np.full(slots[-1].stop if slots else 0, -np.inf)
    for s in slots:
        if s.kind == "term":
            for j, (value, _why) in s.term.floors.items():
                if j < s.size:
                    lo[s.start + j] = value
    return lo


def start_state(data: EffectData, terms: Sequence[EffectTerm], views: Sequence[ProbeView], linear: LinearCalibration,
                previous: State | None = None) -> State:
    """Effect parameters at zero (or as `previous` has them, where the shapes agree) beside `linear`."""
    theta = {t.name: [np.asarray(t.start_values(v), dtype=np.float64).copy() for v in views] for t in terms}
    shared = {t.name: np.asarray(t.shared_start_values(data), dtype=np.float64).copy() for t in terms}
    if previous is not None:
        for name, vals in previous.theta.items():
            if name in theta and all(a.shape == b.shape for a, b in zip(vals, theta[name])):
                theta[name] = [a.copy() for a in vals]
        for name, val in previous.shared.items():
            if name in shared and val.shape == shared[name].shape:
                shared[name] = val.copy()
    return State(linear.copy(), theta, shared)


def update_state(slots: Sequence[_Slot], st: State, delta: np.ndarray) -> State:
    """The state after a step: offsets and effect parameters add, matrices multiply (M <- (I + X) M)."""
    new = st.copy()
    for s in slots:
        d = delta[s.start:s.stop]
        if s.kind == "offset":
            new.linear.offset_nT[s.k] += d
        elif s.kind == "matrix":
            x = np.zeros((3, 3))
            if s.size == 6:
                for c, (i, j) in enumerate(_SYM):
                    x[i, j] += d[c]
                    if i != j:
                        x[j, i] += d[c]
            else:
                x = d.reshape(3, 3)
            new.linear.matrix[s.k] = (np.eye(3) + x) @ st.linear.matrix[s.k]     # M <- (I + X) M
        elif s.kind == "term":
            new.theta[s.term.name][s.k] = st.theta[s.term.name][s.k] + d
        else:
            new.shared[s.term.name] = st.shared[s.term.name] + d
    return new
