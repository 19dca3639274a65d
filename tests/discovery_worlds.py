"""Worlds with an effect outside the catalogue, and effect-free controls, for discovery (issue 30): the simulated
unit (fluxcal.drivers.sim) with a term added to its probes' outputs from what the world knows (the field in the platform
frame, each probe's transfer matrix, its temperature, the field's rate), and logged columns beside it.

KINDS (each one physical effect the catalogue has no term for), with what the verdict must name:

    temperature rotation   s2's mounting turns about the platform's z axis with s2's temperature, 40 µrad/degC
                           (its alignment to s1 follows s2_temp: the differences only, |B| is unchanged)
    fan phase              a field of 3 nT turning with a fan whose variable speed is logged (fan_hz), on s2
    core loop              s3's offset steps with the sign of each axis' rate of change (a core's loop), 3-4 nT
    lagged heater          s2's offset follows a logged heater current through a first-order lag of 60 s, 8 nT/A
    supply scale           s3's scale factors follow a logged supply voltage (vbus_V), 300 ppm/V: seen in the
                           scalar channel only through the field's direction
    common line            a 6 nT field at 1.37 Hz common to all probes, fixed in the platform frame (a pump far from
                           the array): the scalar channels only, nothing logged follows it

Every world carries the same decoy columns (a heater, a fan, a supply), coupled or not, so that the library is
as large in the controls as in the worlds with an effect.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.effects.thermal import low_pass

ROOT = Path(__file__).resolve().parents[1]
F_TOTAL = 51500.0
KINDS = ("temperature rotation", "fan phase", "core loop", "lagged heater", "supply scale", "common line")
#: what the discovered groups must name, per kind: (observable, kinds of group, words of the reading); a scale that
#: follows the supply is a `scale` group (its offset and scale factors) or the scale part of a `matrix`
TRUTH = {
    "temperature rotation": ("s2_temp", ("matrix",), ("s2_temp", "rotation")),
    "fan phase": ("fan_hz", ("wave",), ("fan_hz", "phase")),
    "core loop": ("rate of s3", ("loop",), ("s3", "sign of each axis' rate")),
    "lagged heater": ("heater_A", ("offset",), ("heater_A", "lag")),
    "supply scale": ("vbus_V", ("scale", "matrix"), ("vbus_V", "scale")),
    "common line": ("residual", ("common wave",), ("1.37 Hz", "common to all probes")),
}
TUMBLE = {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 6.0}


def _probe(k: int, pink: float) -> dict[str, Any]:
    rng = np.random.default_rng(100 + k)
    return {"position_m": [0.25 * np.cos(k * np.pi / 2), 0.25 * np.sin(k * np.pi / 2), 0.0],
            "scale": (1 + 0.02 * rng.standard_normal(3)).tolist(), "nonorth_deg": rng.uniform(-2, 2, 3).tolist(),
            "misalign_deg": rng.uniform(-3, 3, 3).tolist(), "offset_nT": rng.uniform(-400, 400, 3).tolist(),
            "noise_nT": float(rng.uniform(0.5, 1.2)), "pink_nT_rtHz": pink}


def _columns(t: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The logged decoys: a heater switched at random (0 / 1.5 A), a fan of variable speed (Hz), a supply that
    wanders and steps (V); each logged with a little noise of its own."""
    n = t.size
    switches = np.cumsum(rng.uniform(20.0, 80.0, 64))
    heater = 1.5 * (np.searchsorted(switches, t - t[0]) % 2)
    fan = 1.9 + 0.5 * np.sin(2 * np.pi * (t - t[0]) / 97.0 + rng.uniform(0, 6.3)) + 0.1 * np.sin(
        2 * np.pi * (t - t[0]) / 23.0)
    walk = np.cumsum(rng.standard_normal(n)) * 0.004
    steps = 0.3 * (np.searchsorted(np.cumsum(rng.uniform(60.0, 150.0, 32)), t - t[0]) % 3 - 1)
    vbus = 12.0 + walk - np.linspace(walk[0], walk[-1], n) + steps
    return {"heater_A": heater, "fan_hz": fan, "vbus_V": vbus,
            "_noise": rng.standard_normal((3, n))}


def tumbling(seed: int, pink: float, n: int, rate: float, n_probes: int) -> tuple:
    """The platform every world here tumbles: (probe tables, the simulated Unit, its block with the three columns
    logged (each with its reading noise), the world's truth, the columns' true values)."""
    probes = [_probe(k, pink) for k in range(n_probes)]
    cfg = load_sim_config({
        "seed": seed, "rate_hz": rate, "duration_s": n / rate,
        "field": {"total_nT": F_TOTAL, "inclination_deg": 62.0, "declination_deg": -5.0},
        "reference": {"enabled": True, "noise_nT": 0.05}, "motion": TUMBLE,
        "temperature": {"start_C": 21.0, "ramp_C_per_h": 10.0, "amplitude_C": 4.0, "period_s": n / rate / 2.3},
        "probes": probes})
    unit = Unit(cfg)
    s = unit.digitise(0, n)
    block = s.to_block()
    cols = _columns(block.t_s, np.random.default_rng(seed + 7919))
    noise = cols.pop("_noise")
    for i, (name, v) in enumerate(cols.items()):
        block.extras[name] = v + {"heater_A": 0.01, "fan_hz": 0.001, "vbus_V": 0.002}[name] * noise[i]
    return probes, unit, block, s.world, cols


def world(kind: str | None, seed: int, *, pink: float = 0.0, n: int = 12000, rate: float = 20.0,
          n_probes: int = 3, scale: float = 1.0) -> EffectData:
    """A world of `kind` (None: no effect), its seed and 1/f noise (nT/sqrt(Hz) per probe axis); scale multiplies
    the effect's size."""
    probes, unit, block, w, cols = tumbling(seed, pink, n, rate, n_probes)
    t = block.t_s
    fwd = unit.world.probes.forward_matrix                              # (P, 3, 3): raw - offset = F B_platform
    bp = w.field_platform_nT
    add = np.zeros_like(block.field_nT)
    if kind == "temperature rotation":
        temp = w.temp_C[:, 1]
        eps = 40e-6 * (temp - temp.mean())
        turned = np.column_stack([-bp[:, 1, 1], bp[:, 1, 0], np.zeros(n)])          # e_z x B
        add[:, 1] = (eps[:, None] * turned) @ fwd[1].T
    elif kind == "fan phase":
        f = cols["fan_hz"]
        phi = 2 * np.pi * np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(t))]) + 0.7
        b = 3.0 * np.column_stack([np.cos(phi), np.sin(phi), 0.3 * np.cos(phi)])
        add[:, 1] = b @ fwd[1].T
    elif kind == "core loop":
        out = w.output_nT[:, 2]
        rate_ = np.gradient(out, t, axis=0)
        add[:, 2] = np.array([4.0, -3.0, 3.0]) * np.tanh(rate_ / (0.02 * rate_.std(0)))
    elif kind == "lagged heater":
        lag = low_pass(t, cols["heater_A"], 60.0)
        add[:, 1] = np.outer(lag - lag.mean(), [8.0, -6.0, 4.0])
    elif kind == "supply scale":
        v = cols["vbus_V"] - cols["vbus_V"].mean()
        u = w.output_nT[:, 2] - np.asarray(probes[2]["offset_nT"])
        add[:, 2] = 1e-6 * np.array([300.0, -200.0, 250.0]) * v[:, None] * u
    elif kind == "common line":
        e = np.array([0.6, -0.3, 0.74])
        b = 6.0 * np.outer(np.cos(2 * np.pi * 1.37 * t + 0.4), e / np.linalg.norm(e))
        for k in range(n_probes):
            add[:, k] = b @ fwd[k].T
    elif kind is not None:
        raise ValueError(f"kind: {kind!r} is not one of {KINDS}")
    block.field_nT[...] += scale * add
    return EffectData.from_block(block, positions_m=np.array([p["position_m"] for p in probes]))


def config_world(config: str, seed: int, *, pink: float, seconds: float | None = None,
                 decoys: bool = True) -> EffectData:
    """An effect-free world of the repository's configs/<config> with another seed and 1/f noise, with the decoy
    columns logged beside it (uncoupled)."""
    raw = tomllib.loads((ROOT / "configs" / config).read_text())["sim"]
    raw.update(seed=seed)
    if seconds is not None:
        raw["duration_s"] = seconds
    for p in raw["probes"]:
        p["pink_nT_rtHz"] = pink
    cfg = load_sim_config(raw)
    s = Unit(cfg).digitise(0, cfg.n_samples)
    block = s.to_block()
    if decoys:
        rng = np.random.default_rng(seed + 104729)
        cols = _columns(block.t_s, rng)
        noise = cols.pop("_noise")
        for i, (name, v) in enumerate(cols.items()):
            block.extras[name] = v + 0.01 * noise[i]
    return EffectData.from_block(block)


def named(d: Any, kind: str, probe: str | None = None) -> bool:
    """Whether diagnose's verdict names what the world of `kind` holds: a discovered group of the right kind on
    the right observable, and the verdict's advice says the observable and the word of its physics. probe: where the
    effect is, when not where the world of `kind` puts it (a real recording's s1)."""
    f = getattr(d, "discovery", None)
    if f is None or not f.claimed:
        return False
    obs, group_kinds, words = TRUTH[kind]
    if probe is not None:
        obs = obs.replace("s2", probe).replace("s3", probe)
        words = tuple(w.replace("s2", probe).replace("s3", probe) for w in words)
    advice = (d.verdict or {}).get("advice") or ""
    return any(g.observable == obs and g.group.kind in group_kinds and all(w in g.reading for w in words)
               for g in f.groups) and all(w in advice for w in words)
