"""What motion the samples lack: whether they lie in one plane (a single-axis turn), which probe axes no
field direction came near, and which turn would fill them. Used by refusals and advice."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

#: out-of-plane spread / in-plane spread below which samples count as one plane (a single-axis turn)
PLANARITY_MIN = 0.02

#: half-width (deg) of the band of polar angles about one axis within which the field directions seen (about
#: the fitted centre) count as one turn: in a turn about an axis the field traces one cone about it, and the
#: offset along the axis rests on the wobble. Measured (direction_band) on real hand-turned boards
#: (../shared/real-data): their single-axis turns read 4-8°, thin plane cuts of full spheres 6-10°; a ±17° band
#: 17-18°, hemispheres 33-39°, a 40° cap 16°.
BAND_MIN_DEG = 12.0
#: ... and such a turn is refused when the model's misfit, levered onto the axial offset (residual RMS over the
#: directions' spread along the axis), exceeds this share of the field: a misfit the ellipsoid cannot follow
#: (the boards' 180-220 nT, 0.4 % of the field) then moves that offset by thousands of nT (the boards' turns were
#: fitted 1,500-12,800 nT from their full-sphere fit, 4-35 times the stated error; their levers read 6-25 % of the
#: field), while a fluxgate's white noise (0.6 nT) on the same motion levers 0.05 % and its fit is right.
LEVER_MAX = 0.01

_AXES = {"+x": (1.0, 0, 0), "-x": (-1.0, 0, 0), "+y": (0, 1.0, 0), "-y": (0, -1.0, 0),
         "+z": (0, 0, 1.0), "-z": (0, 0, -1.0)}


def planarity(raw: np.ndarray) -> tuple[float, np.ndarray]:
    """sqrt(smallest / largest eigenvalue) of the sample covariance, and the plane's normal."""
    w, v = np.linalg.eigh(np.cov(raw.T))
    return (float(np.sqrt(max(w[0], 0.0) / w[2])) if w[2] > 0 else 0.0), v[:, 0]


def direction_band(directions: np.ndarray) -> tuple[float, np.ndarray]:
    """Half-width (deg) of the band of polar angles that holds the unit field directions (N, 3) about the
    axis they vary least along, and that axis: √3 × the standard deviation of the angle to it (a uniform
    band of ±w reads w). A single-axis turn traces one cone about its axis and reads its wobble; a full
    sphere reads about 67°, a hemisphere 37°, a 60° cap 25°. Independent of origin and unit when the
    directions are taken about the fitted centre in the calibrated frame."""
    d = np.asarray(directions, float)
    if d.shape[0] < 3:
        return 0.0, np.array([0.0, 0.0, 1.0])
    axis = np.linalg.eigh(np.cov(d.T))[1][:, 0]
    polar = np.degrees(np.arccos(np.clip(d @ axis, -1.0, 1.0)))
    return float(np.sqrt(3.0) * np.std(polar)), axis


@dataclass(frozen=True)
class Cone:
    """The cone the field directions (about a fitted centre, in the calibrated frame) lie in, and what the model's
    misfit does to the offset along its axis: band_deg (direction_band), the axis, the directions' spread along it,
    the misfit (residual RMS, nT), its lever on the axial offset (misfit / spread, nT) and the field; `problem` says
    why the offset along the axis is not determined ("" where it is: a band wider than BAND_MIN_DEG, or a lever
    within LEVER_MAX of the field)."""

    band_deg: float
    axis: tuple[float, float, float]
    axis_name: str
    spread: float
    misfit_nT: float
    lever_nT: float
    field_nT: float
    problem: str = ""

    def as_dict(self) -> dict:
        return {"band_deg": self.band_deg, "axis": list(self.axis), "axis_name": self.axis_name,
                "spread": self.spread, "misfit_nT": self.misfit_nT, "lever_nT": self.lever_nT,
                "field_nT": self.field_nT, "lever_share": self.lever_nT / self.field_nT if self.field_nT else None}


def cone_of(corrected: np.ndarray, residual_rms: float, field: float) -> Cone | None:
    """The Cone of calibrated samples (N, 3), given the fit's residual RMS and the field (same unit); None for fewer
    than three samples. The batch fit, diagnose, inspect and the online gate ask it alike (determinacy.judge)."""
    c = np.asarray(corrected, float)
    if c.shape[0] < 3:
        return None
    mag = np.linalg.norm(c, axis=1, keepdims=True)
    directions = c / np.where(mag > 0, mag, 1.0)
    band, normal = direction_band(directions)
    k = int(np.argmax(np.abs(normal)))
    normal = normal * (np.sign(normal[k]) or 1.0)
    axis = "xyz"[k] if abs(normal[k]) > 0.9 else "({:.2f}, {:.2f}, {:.2f})".format(*normal)
    spread = float(np.std(directions @ normal))
    lever = residual_rms / max(spread, 1e-12)
    cone = Cone(band, tuple(float(x) for x in normal), axis, spread, float(residual_rms), float(lever), float(field))
    if band >= BAND_MIN_DEG or not lever > LEVER_MAX * field:
        return cone
    others = sorted(a for _, a in sorted(zip(np.abs(normal), "xyz"))[:2])
    return replace(cone, problem=(
        f"the field directions stay within ±{band:.1f}° of one cone about {axis} (a turn about {axis}): the "
        f"offset along {axis} rests on that wobble, where the model's misfit ({residual_rms:.3g} nT RMS) moves it "
        f"by about {lever:,.0f} nT, {lever / field:.0%} of the field (accepted up to {LEVER_MAX:.0%}); turn about the "
        f"{others[0]} or {others[1]} axis too"))


def missing_directions(raw: np.ndarray, cone_deg: float = 45.0) -> list[str]:
    """Probe axes (±x, ±y, ±z) no sampled field direction came within `cone_deg` of.

    `raw` is taken about the centre it is given relative to (the caller subtracts the fitted offset,
    or the samples' mean before a fit): where the field pointed in the probe frame."""
    norm = np.linalg.norm(raw, axis=1, keepdims=True)
    u = raw / np.where(norm > 0, norm, 1.0)
    c = np.cos(np.radians(cone_deg))
    return [k for k, e in _AXES.items() if not np.any(u @ np.asarray(e) > c)]


def turn_axes_for(missing: list[str]) -> list[str]:
    """Axes to turn about so the field sweeps the missing directions: an axis sweeps the directions
    perpendicular to it; the axes sweeping most of them, best first."""
    score = {a: sum(1 for m in missing if m[1] != a) for a in "xyz"}
    best = max(score.values()) if score else 0
    return [a for a in "xyz" if score[a] == best and best > 0]


def excitation_problem(raw: np.ndarray) -> str:
    """Why these samples cannot fix an ellipsoid ("" if they can, as far as geometry goes)."""
    plan, normal = planarity(raw)
    if plan < PLANARITY_MIN:
        missing = missing_directions(raw - raw.mean(axis=0))       # only to say (three (N, 3) temporaries)
        axis = "xyz"[int(np.argmax(np.abs(normal)))]
        others = [a for a in "xyz" if a != axis]
        miss = f"; directions near {', '.join(missing)} not covered" if missing else ""
        return (f"the samples lie (nearly) in one plane (a single-axis turn about {axis}; the ten-term ellipsoid design "
                f"has rank 5 of 10 there, the points of one turn lie on one conic: a plane section does not fix "
                f"an ellipsoid){miss}: "
                f"turn about the {others[0]} or {others[1]} axis too")
    return ""


def coverage_hint(raw: np.ndarray, centre: np.ndarray | None = None) -> str:
    """Which directions about the centre (the fitted offset, else the samples' mean) were not seen."""
    missing = missing_directions(raw - (raw.mean(axis=0) if centre is None else np.asarray(centre, float)))
    if not missing:
        return "spread the samples over more attitudes (turn about at least two axes)"
    return (f"directions near {', '.join(missing)} not covered: turn about the "
            f"{' or '.join(turn_axes_for(missing))} axis")


#: samples (evenly spaced) on which turn_cone asks its question: the cone of directions and the misfit's lever
#: need a fair share of the record, not all of it (hours of data)
TURN_ROWS = 200_000


def turn_cone(raw: np.ndarray, offset_nT: np.ndarray, matrix: np.ndarray, total_nT=None, *,
              residual_rms: float | None = None, field: float | None = None) -> Cone | None:
    """cone_of a calibration (offset, matrix) over its raw samples (N, 3), on at most TURN_ROWS of them evenly
    spaced: the residual RMS and the field from |M (r − o)| against total_nT (a number or (N,); None: the mean
    magnitude), unless given (a fit's own). Rows holding NaN are left out; None where no row is left."""
    step = max(1, raw.shape[0] // TURN_ROWS)
    corr = (np.asarray(raw, float)[::step] - offset_nT) @ np.asarray(matrix, float).T
    mag = np.linalg.norm(corr, axis=1)
    t = np.asarray(total_nT, float) if total_nT is not None else np.asarray(np.nanmean(mag))
    f = t[::step] if t.ndim else np.full(mag.shape, float(t))
    ok = np.isfinite(mag) & np.isfinite(f)
    if not ok.any():
        return None
    rms = residual_rms if residual_rms is not None else float(np.sqrt(np.mean((mag[ok] - f[ok]) ** 2)))
    return cone_of(corr[ok], rms, field if field is not None else float(np.mean(f[ok])))
