"""Worlds whose missing term is a smooth, non-linear function of something the file logs (issue 36), for discovery
of shape: the simulated unit (fluxcal.drivers.sim) with a field added at its probes from a logged column or the temperature
through a law, and the decoy columns of tests/discovery_worlds.py beside it.

SHAPES (each a law the catalogue and the linear library do not take; `LAWS` holds each one's truth):

    flap magnet        a magnet on a flap whose angle (flap_deg, two slow swings) moves it towards s2: a field along
                       one platform direction as A (c / (c - angle))^n, c = 83.4 deg, n = 3; seen at s1 too, 0.15 as
                       strong (one source at two probes: the same direction and shape)
    temperature square s2's offset along one direction as the square of its temperature about 23 degC
    gimbal turn        a magnet on a gimbal that turns about the platform's z axis (gimbal_deg, all the way round,
                       at a varying speed): its field at s1 turns with the angle
    saturating coil    a coil beside s1 whose logged current (coil_A, switched and ramped 0-2 A) makes a field that
                       saturates: B_s tanh(I / I_s), I_s = 0.6 A, along one direction
    exponential supply s3's offset along one direction grows as exp(V / 0.35 V) of its logged supply (vbus_V)

Controls: the same worlds with no effect and `wander` logged columns beside the decoys (random walks and smooth
swings), the hardest case for a library that builds shapes of every column.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from discovery_worlds import tumbling

from fluxcal.service.numerics.effects.base import EffectData

SHAPES = ("flap magnet", "temperature square", "gimbal turn", "saturating coil", "exponential supply")
#: per shape: (the observable, the probes that carry it, the law that made it (None: no law of the set; a field that
#: turns with an angle), its parameters' truth by the name the reading gives them)
LAWS: dict[str, tuple[str, tuple[str, ...], str | None, dict[str, float]]] = {
    "flap magnet": ("flap_deg", ("s2", "s1"), "distance power", {"c": 83.4, "n": 3.0}),
    "temperature square": ("s2_temp", ("s2",), "polynomial", {"x0": 23.0}),
    "gimbal turn": ("gimbal_deg", ("s1",), None, {}),
    "saturating coil": ("coil_A", ("s1",), "saturation", {"s": 0.6}),
    "exponential supply": ("vbus_V", ("s3",), "exponential", {"s": 0.35}),
}
DIRECTION = np.array([0.61, -0.31, 0.73]) / np.linalg.norm([0.61, -0.31, 0.73])


def _flap(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A flap angle of two slow swings (deg, within +-30): the lines at f1 and f2 whose harmonics and sums a
    non-linear function of it puts in the residual."""
    s = t - t[0]
    f1, f2 = 0.0583, 0.1896
    return (18.0 * np.sin(2 * np.pi * f1 * s + rng.uniform(0, 6.3))
            + 11.0 * np.sin(2 * np.pi * f2 * s + rng.uniform(0, 6.3)))


def _gimbal(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A gimbal angle turning all the way round at a varying speed (deg, wrapped to 0-360 as a logger writes it)."""
    s = t - t[0]
    speed = 9.0 + 5.0 * np.sin(2 * np.pi * s / 137.0 + rng.uniform(0, 6.3))        # deg/s
    angle = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(s))]) + rng.uniform(0, 360)
    return np.mod(angle, 360.0)


def _coil(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A coil current switched between levels and ramped (A, 0-2)."""
    s = t - t[0]
    edges = np.cumsum(rng.uniform(8.0, 30.0, 400))
    levels = rng.uniform(0.0, 2.0, edges.size + 1)
    step = levels[np.searchsorted(edges, s)]
    ramp = np.clip(np.interp(s, edges, levels[:-1]), 0.0, 2.0)
    return np.where(np.searchsorted(edges, s) % 3 == 0, ramp, step)


def wandering(t: np.ndarray, n: int, seed: int) -> dict[str, np.ndarray]:
    """n logged columns that wander and follow nothing: random walks and smooth swings of random periods."""
    rng = np.random.default_rng(seed)
    out = {}
    s = t - t[0]
    for i in range(n):
        if i % 2:
            walk = np.cumsum(rng.standard_normal(t.size))
            out[f"aux{i:02d}"] = walk / max(float(np.std(walk)), 1e-9) + 0.01 * rng.standard_normal(t.size)
        else:
            period = rng.uniform(0.05, 0.6) * float(s[-1])
            out[f"aux{i:02d}"] = (np.sin(2 * np.pi * s / period + rng.uniform(0, 6.3))
                                  + 0.3 * np.sin(2 * np.pi * s / (period / 3.7)) + 0.01 * rng.standard_normal(t.size))
    return out


def shape_world(kind: str | None, seed: int, *, pink: float = 0.0, n: int = 12000, rate: float = 20.0,
                n_probes: int = 3, scale: float = 1.0, wander: int = 0) -> EffectData:
    """A world of shape `kind` (None: no effect), its seed and 1/f noise (nT/sqrt(Hz) per probe axis); scale
    multiplies the effect's size; wander: wandering columns logged beside the decoys."""
    probes, unit, block, w, cols = tumbling(seed, pink, n, rate, n_probes)
    t = block.t_s
    more = np.random.default_rng(seed + 104729)
    flap, gimbal, coil = _flap(t, more), _gimbal(t, more), _coil(t, more)
    block.extras.update(flap_deg=flap + 0.05 * more.standard_normal(n), gimbal_deg=gimbal,
                        coil_A=coil + 0.002 * more.standard_normal(n))
    block.extras.update(wandering(t, wander, seed + 31337))
    fwd = unit.world.probes.forward_matrix                              # (P, 3, 3): raw - offset = F B_platform
    add = np.zeros_like(block.field_nT)                                 # B_platform at each probe
    if kind == "flap magnet":
        f = (83.4 / (83.4 - flap)) ** 3.0
        add[:, 1] = 30.0 * np.outer(f - f.mean(), DIRECTION)
        add[:, 0] = 0.15 * add[:, 1]
    elif kind == "temperature square":
        temp = w.temp_C[:, 1]
        add[:, 1] = 1.5 * np.outer((temp - 23.0) ** 2 - np.mean((temp - 23.0) ** 2), DIRECTION)
    elif kind == "gimbal turn":
        a = np.radians(gimbal)
        b0 = np.array([9.0, 0.0, 4.0])                                  # nT on the gimbal, at angle 0
        add[:, 0] = np.column_stack([b0[0] * np.cos(a) - b0[1] * np.sin(a), b0[0] * np.sin(a) + b0[1] * np.cos(a),
                                     np.full(n, b0[2])]) - np.array([0.0, 0.0, b0[2]])
    elif kind == "saturating coil":
        f = np.tanh(coil / 0.6)
        add[:, 0] = 12.0 * np.outer(f - f.mean(), DIRECTION)
    elif kind == "exponential supply":
        v = cols["vbus_V"]
        f = np.exp((v - 12.0) / 0.35)
        add[:, 2] = 5.0 * np.outer(f - f.mean(), DIRECTION)
    elif kind is not None:
        raise ValueError(f"kind: {kind!r} is not one of {SHAPES}")
    block.field_nT[...] += scale * np.einsum("kij,nkj->nki", fwd, add)
    return EffectData.from_block(block, positions_m=np.array([p["position_m"] for p in probes]))


def truth(kind: str) -> tuple[str, tuple[str, ...], str | None, dict[str, Any]]:
    return LAWS[kind]
