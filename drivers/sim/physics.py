"""The physical effects of the simulated probes, each acting at one place of the forward chain (sampling
instant, field at the probe, transfer, offset); each is off while its parameters are zero.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from .config import SimConfig


@dataclass
class EffectContext:
    """What effects may look at, for N instants and P probes."""

    t_s: np.ndarray                # (N, P) the instants the probes were sampled
    temp_C: np.ndarray             # (N, P) probe temperatures
    dsensor_dt_nT_s: np.ndarray    # (N, P, 3) dB_sensor/dt from rotation, drift and gradient


class Effect:
    """One physical term of the forward model, with per-probe parameters in physical units.

    Override only the hooks the effect acts at; the world calls them in this order:
    sample_time (instant), sensor_field (field at the probe, sensor frame), transfer (u = C A B_sensor),
    offset. `active` is False while every parameter is zero."""

    name: ClassVar[str] = ""

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "Effect":
        raise NotImplementedError

    def active(self) -> bool:
        return False

    def params(self, k: int) -> dict[str, Any]:
        """Probe k's parameters for the truth file."""
        return {}

    def sample_time(self, t_s: np.ndarray) -> np.ndarray:
        return t_s

    def sensor_field(self, ctx: EffectContext, b_nT: np.ndarray) -> np.ndarray:
        return b_nT

    def transfer(self, ctx: EffectContext, u_nT: np.ndarray) -> np.ndarray:
        return u_nT

    def offset(self, ctx: EffectContext, offset_nT: np.ndarray) -> np.ndarray:
        return offset_nT


def _stack(cfg: SimConfig, attr: str) -> np.ndarray:
    return np.array([getattr(p, attr) for p in cfg.probes], dtype=np.float64)


class LagEffect(Effect):
    """A probe sampled lag_s after the unit's instant: it sees the attitude (and field) of t + lag_s."""

    name = "lag"

    def __init__(self, lag_s: np.ndarray) -> None:
        self.lag_s = np.asarray(lag_s, dtype=np.float64)          # (P,)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "LagEffect":
        return cls(_stack(cfg, "lag_s"))

    def active(self) -> bool:
        return bool(np.any(self.lag_s))

    def params(self, k: int) -> dict[str, Any]:
        return {"lag_s": float(self.lag_s[k])}

    def sample_time(self, t_s: np.ndarray) -> np.ndarray:
        return t_s + self.lag_s                                   # t_k = t + lag_k


class EddyEffect(Effect):
    """Fields induced by changing flux: B_sensor += E dB_sensor/dt, E (3x3, s) per probe."""

    name = "eddy"

    def __init__(self, matrix_s: np.ndarray) -> None:
        self.matrix_s = np.asarray(matrix_s, dtype=np.float64)    # (P, 3, 3)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "EddyEffect":
        return cls(_stack(cfg, "eddy_s"))

    def active(self) -> bool:
        return bool(np.any(self.matrix_s))

    def params(self, k: int) -> dict[str, Any]:
        return {"matrix_s": self.matrix_s[k].tolist()}

    def sensor_field(self, ctx: EffectContext, b_nT: np.ndarray) -> np.ndarray:
        return b_nT + np.einsum("pij,npj->npi", self.matrix_s, ctx.dsensor_dt_nT_s)


class TemperatureEffect(Effect):
    """Scale and offset follow the probe temperature: u (1 + ppm 1e-6 ΔT), offset + k ΔT, ΔT = T - reference."""

    name = "temperature"

    def __init__(self, offset_nT_per_C: np.ndarray, scale_ppm_per_C: np.ndarray, reference_C: float) -> None:
        self.offset_nT_per_C = np.asarray(offset_nT_per_C, dtype=np.float64)   # (P, 3)
        self.scale_ppm_per_C = np.asarray(scale_ppm_per_C, dtype=np.float64)   # (P, 3)
        self.reference_C = reference_C

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "TemperatureEffect":
        return cls(_stack(cfg, "temp_offset_nT_per_C"), _stack(cfg, "temp_scale_ppm_per_C"),
                   cfg.temperature.reference_C)

    def active(self) -> bool:
        return bool(np.any(self.offset_nT_per_C) or np.any(self.scale_ppm_per_C))

    def params(self, k: int) -> dict[str, Any]:
        return {"offset_nT_per_C": self.offset_nT_per_C[k].tolist(),
                "scale_ppm_per_C": self.scale_ppm_per_C[k].tolist(), "reference_C": self.reference_C}

    def transfer(self, ctx: EffectContext, u_nT: np.ndarray) -> np.ndarray:
        dt = (ctx.temp_C - self.reference_C)[..., None]
        return u_nT * (1.0 + 1e-6 * self.scale_ppm_per_C * dt)

    def offset(self, ctx: EffectContext, offset_nT: np.ndarray) -> np.ndarray:
        return offset_nT + self.offset_nT_per_C * (ctx.temp_C - self.reference_C)[..., None]


class NonlinearityEffect(Effect):
    """Per-axis transfer non-linearity: out = u + q u^2 + c u^3 on the field term u = C A B_sensor (nT)."""

    name = "nonlinearity"

    def __init__(self, quadratic_per_nT: np.ndarray, cubic_per_nT2: np.ndarray) -> None:
        self.quadratic_per_nT = np.asarray(quadratic_per_nT, dtype=np.float64)   # (P, 3)
        self.cubic_per_nT2 = np.asarray(cubic_per_nT2, dtype=np.float64)         # (P, 3)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "NonlinearityEffect":
        return cls(_stack(cfg, "nonlin_quadratic_per_nT"), _stack(cfg, "nonlin_cubic_per_nT2"))

    def active(self) -> bool:
        return bool(np.any(self.quadratic_per_nT) or np.any(self.cubic_per_nT2))

    def params(self, k: int) -> dict[str, Any]:
        return {"quadratic_per_nT": self.quadratic_per_nT[k].tolist(),
                "cubic_per_nT2": self.cubic_per_nT2[k].tolist()}

    def transfer(self, ctx: EffectContext, u_nT: np.ndarray) -> np.ndarray:
        return u_nT + self.quadratic_per_nT * u_nT ** 2 + self.cubic_per_nT2 * u_nT ** 3


class OffsetDriftEffect(Effect):
    """Slow offset drift per probe and axis: offset + d t / 3600 (the ambient drift is in the field)."""

    name = "drift"

    def __init__(self, offset_nT_per_h: np.ndarray) -> None:
        self.offset_nT_per_h = np.asarray(offset_nT_per_h, dtype=np.float64)     # (P, 3)

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "OffsetDriftEffect":
        return cls(_stack(cfg, "drift_offset_nT_per_h"))

    def active(self) -> bool:
        return bool(np.any(self.offset_nT_per_h))

    def params(self, k: int) -> dict[str, Any]:
        return {"offset_nT_per_h": self.offset_nT_per_h[k].tolist()}

    def offset(self, ctx: EffectContext, offset_nT: np.ndarray) -> np.ndarray:
        return offset_nT + self.offset_nT_per_h * (ctx.t_s / 3600.0)[..., None]


#: the catalogue, in the order the world applies them; adding an effect is adding a class here
EFFECTS: tuple[type[Effect], ...] = (LagEffect, EddyEffect, TemperatureEffect, NonlinearityEffect, OffsetDriftEffect)
