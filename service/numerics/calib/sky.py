"""Field directions in a probe's own frame, for the calibration report: where the data went, which
directions they never visited, and the scalar residual mapped over direction.

- Direction of a sample: (raw − offset) / |raw − offset| in the sensor frame, as azimuth (from +x
  towards +y, −180..180°) and elevation (towards +z, −90..90°).
- Unvisited: of the 26 named directions of calib.coverage ("+z", "-x+y", "+x-y-z"), those with no
  sample within `radius_deg`. A corner or edge is named only when no face (axis) direction within
  55° of it is named already, so a missing −z cap reads as "-z", not as nine labels.
- Residual map: the samples binned on an equal-area grid (azimuth sectors by bands of equal
  sin(elevation)); per bin the count, mean and RMS of the scalar residual |B_cal| − F.
Numerics only: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .coverage import BIN_CENTRES, BIN_LABELS, turn_axes

#: a direction counts as visited when a sample lies within this angle of it
VISIT_RADIUS_DEG = 40.0
#: a corner or edge this close to a named face is part of that face's gap
_FACE_GROUP_DEG = 55.0
#: samples the maps keep for drawing, at most (evenly spaced)
MAX_DRAWN = 6000
_CHUNK = 50_000


def unit_directions(field_nT: np.ndarray, centre_nT: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) unit field directions of (N, 3) samples about `centre_nT` (zero when None)."""
    d = np.asarray(field_nT, float) - (0.0 if centre_nT is None else np.asarray(centre_nT, float))
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(n > 0, n, 1.0)


def azimuth_elevation_deg(dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth (from +x towards +y) and elevation (towards +z) of unit directions, degrees."""
    d = np.asarray(dirs, float)
    return np.degrees(np.arctan2(d[:, 1], d[:, 0])), np.degrees(np.arcsin(np.clip(d[:, 2], -1.0, 1.0)))


def nearest_angles_deg(dirs: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(K,) angle from each of (K, 3) unit targets to the nearest of (N, 3) unit directions, degrees."""
    best = np.full(targets.shape[0], -1.0)
    for a in range(0, dirs.shape[0], _CHUNK):                # bounded memory: N x 26 per chunk
        best = np.maximum(best, (dirs[a:a + _CHUNK] @ targets.T).max(axis=0))
    return np.degrees(np.arccos(np.clip(best, -1.0, 1.0)))


@dataclass(frozen=True)
class Unvisited:
    """A named direction with no sample within the radius."""

    label: str                      # "+z", "-x-y-z"
    direction: np.ndarray           # (3,) unit
    nearest_deg: float              # angle to the nearest sample
    radius_deg: float
    turn_about: list[str]           # coordinate axes a turn about which brings the field there
    outline_deg: np.ndarray         # (K, 2) azimuth, elevation of the circle of radius_deg around it

    def sentence(self) -> str:
        turn = f"; a turn about {' or '.join(self.turn_about)} sweeps it" if self.turn_about else ""
        return (f"no field within {self.radius_deg:.0f}° of {self.label} in the sensor frame (the nearest sample "
                f"is {self.nearest_deg:.0f}° away): tilt the unit so {self.label} points along the field{turn}")


def _circle_deg(centre: np.ndarray, radius_deg: float, k: int = 90) -> np.ndarray:
    """(k, 2) azimuth, elevation of the circle at angular radius `radius_deg` around unit `centre`."""
    a = np.eye(3)[int(np.argmin(np.abs(centre)))]
    u = np.cross(centre, a)
    u /= np.linalg.norm(u)
    v = np.cross(centre, u)
    t = np.linspace(0.0, 2.0 * np.pi, k)
    r = np.radians(radius_deg)
    pts = np.cos(r) * centre + np.sin(r) * (np.cos(t)[:, None] * u + np.sin(t)[:, None] * v)
    az, el = azimuth_elevation_deg(pts)
    return np.column_stack([az, el])


def unvisited_directions(dirs: np.ndarray, radius_deg: float = VISIT_RADIUS_DEG) -> list[Unvisited]:
    """The named directions with no sample within `radius_deg`, faces first, farthest first within each."""
    ang = nearest_angles_deg(dirs, BIN_CENTRES)
    missing = np.flatnonzero(ang > radius_deg)
    faces = [i for i in missing if np.count_nonzero(BIN_CENTRES[i]) == 1]
    group_cos = np.cos(np.radians(_FACE_GROUP_DEG))
    rest = [i for i in missing
            if i not in faces and not any(BIN_CENTRES[i] @ BIN_CENTRES[f] > group_cos for f in faces)]
    picked = sorted(faces, key=lambda i: -ang[i]) + sorted(rest, key=lambda i: -ang[i])
    seen = _thin(dirs, 2000)
    return [Unvisited(BIN_LABELS[i], BIN_CENTRES[i].copy(), float(ang[i]), float(radius_deg),
                      turn_axes(BIN_CENTRES[i], seen), _circle_deg(BIN_CENTRES[i], radius_deg))
            for i in picked]


def _thin(x: np.ndarray, most: int) -> np.ndarray:
    return x[::-(-x.shape[0] // most)] if x.shape[0] > most else x


@dataclass(frozen=True)
class ResidualMap:
    """The scalar residual binned over direction on an equal-area grid (rows: elevation bands, bottom
    first; columns: azimuth sectors from −180°)."""

    az_edges_deg: np.ndarray        # (A + 1,)
    el_edges_deg: np.ndarray        # (E + 1,) at equal steps of sin(elevation)
    count: np.ndarray               # (E, A)
    mean_nT: np.ndarray             # (E, A), NaN where empty
    rms_nT: np.ndarray              # (E, A), NaN where empty

    @property
    def colour_limit_nT(self) -> float:
        """The largest |mean| over the bins with samples (a symmetric colour scale), 1 nT if none."""
        m = np.abs(self.mean_nT[self.count > 0])
        return float(m.max()) if m.size and m.max() > 0 else 1.0

    def worst(self, min_count: int = 5) -> dict[str, Any] | None:
        """The bin whose mean residual is largest in size (with at least `min_count` samples): its
        centre, nearest named direction, mean, RMS, count and t (the mean in standard errors of a mean);
        None if no bin has enough."""
        ok = self.count >= min_count
        if not ok.any():
            return None
        m = np.where(ok, np.abs(self.mean_nT), -1.0)
        e, a = np.unravel_index(int(np.argmax(m)), m.shape)
        az = 0.5 * (self.az_edges_deg[a] + self.az_edges_deg[a + 1])
        el = float(np.degrees(np.arcsin(0.5 * (np.sin(np.radians(self.el_edges_deg[e]))
                                              + np.sin(np.radians(self.el_edges_deg[e + 1]))))))
        c = np.array([np.cos(np.radians(el)) * np.cos(np.radians(az)), np.cos(np.radians(el)) * np.sin(np.radians(az)),
                      np.sin(np.radians(el))])
        return {"azimuth_deg": float(az), "elevation_deg": el, "near": BIN_LABELS[int(np.argmax(BIN_CENTRES @ c))],
                "mean_nT": float(self.mean_nT[e, a]), "rms_nT": float(self.rms_nT[e, a]),
                "count": int(self.count[e, a]),
                # t = |mean| / (sd / sqrt(n)), sd² = rms² − mean²: is the bin's offset more than noise?
                "t": float(abs(self.mean_nT[e, a]) * np.sqrt(self.count[e, a]) /
                           max(np.sqrt(max(self.rms_nT[e, a] ** 2 - self.mean_nT[e, a] ** 2, 0.0)), 1e-12))}


def residual_by_direction(dirs: np.ndarray, residual_nT: np.ndarray, n_az: int = 24, n_el: int = 12) -> ResidualMap:
    """Bin (N,) residuals by the (N, 3) unit directions of their samples (NaN residuals left out)."""
    r = np.asarray(residual_nT, float)
    ok = np.isfinite(r)
    az, el = azimuth_elevation_deg(dirs[ok])
    r = r[ok]
    ia = np.clip(((az + 180.0) / 360.0 * n_az).astype(int), 0, n_az - 1)
    ie = np.clip(((np.sin(np.radians(el)) + 1.0) / 2.0 * n_el).astype(int), 0, n_el - 1)
    flat = ie * n_az + ia
    size = n_az * n_el
    count = np.bincount(flat, minlength=size).astype(float)
    total = np.bincount(flat, weights=r, minlength=size)
    square = np.bincount(flat, weights=r * r, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / count, np.nan)
        rms = np.where(count > 0, np.sqrt(square / count), np.nan)
    shape = (n_el, n_az)
    return ResidualMap(np.linspace(-180.0, 180.0, n_az + 1),
                       np.degrees(np.arcsin(np.linspace(-1.0, 1.0, n_el + 1))),
                       count.reshape(shape).astype(int), mean.reshape(shape), rms.reshape(shape))


@dataclass
class ProbeSky:
    """What the report draws of one probe: its samples' directions (thinned), what they missed, the
    coverage figure of the fit, and the residual over direction."""

    name: str
    azimuth_deg: np.ndarray         # (n,) drawn samples
    elevation_deg: np.ndarray
    unvisited: list[Unvisited]
    coverage_fraction: float        # calib.coverage: share of the 26 direction bins seen
    coverage_advice: str
    residual: ResidualMap
    residual_rms_nT: float
    n_samples: int
    notes: list[str] = field(default_factory=list)


def probe_sky(name: str, field_nT: np.ndarray, offset_nT: np.ndarray, residual_nT: np.ndarray, coverage: Any,
              radius_deg: float = VISIT_RADIUS_DEG) -> ProbeSky:
    """The sky of one probe from its (N, 3) raw samples, fitted offset, (N,) scalar residual and its
    calib.coverage.Coverage."""
    f = np.asarray(field_nT, float)
    keep = np.isfinite(f).all(axis=1)
    dirs = unit_directions(f[keep], offset_nT)
    res = np.asarray(residual_nT, float)[keep]
    shown = _thin(dirs, MAX_DRAWN)
    az, el = azimuth_elevation_deg(shown)
    finite = res[np.isfinite(res)]
    return ProbeSky(name, az, el, unvisited_directions(dirs, radius_deg), float(coverage.fraction), coverage.advice(),
                    residual_by_direction(dirs, res),
                    float(np.sqrt(np.mean(finite ** 2))) if finite.size else float("nan"), int(dirs.shape[0]))


@dataclass
class CalibrationSection:
    """Everything the calibration section of a report shows (fluxcal.service.io.report draws it)."""

    heading: str                    # what the calibration is: "ellipsoid fit", "the linear part diagnose refitted"
    description: str                # method, alignment, effects, total field source
    probes: list[ProbeSky]
    rows: list[Any]                 # calib.param_table.ParamRow: every probe's, then the effects'
    warnings: list[str]
    radius_deg: float = VISIT_RADIUS_DEG


__all__ = ["VISIT_RADIUS_DEG", "Unvisited", "ResidualMap", "ProbeSky", "CalibrationSection", "unit_directions",
           "azimuth_elevation_deg", "nearest_angles_deg", "unvisited_directions", "residual_by_direction", "probe_sky"]
