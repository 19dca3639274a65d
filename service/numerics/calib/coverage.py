"""Which field directions a probe has seen, how well they determine a fit, and what motion is missing.

What users of ArduPilot/PX4/MotionCal calibrators ask for most: a map of the directions still missing
(not only a percentage), the conditioning of the fit those samples give, and a refusal that says why
and which turn would fill the gap.

- Directions: the samples' field direction in the probe frame (relative to `centre_nT`, default
  zero: fluxgate offsets are small next to the Earth's field), binned on 26 sphere directions: the
  cube's 6 faces, 12 edges and 8 corners ("+z", "+x+z", "+x-y+z"), each sample to the nearest. A bin
  counts as seen once it holds `min_count` samples.
- Missing regions: neighbouring missing bins (≤ 60° apart) grouped, each named by the bin nearest the
  region's mean direction.
- The motion that fills a region around direction d: a turn about axis e keeps every direction's
  angle to e, so it carries a seen direction s to d only if s·e = d·e. An axis qualifies when some
  seen direction lies on d's circle about it (|s·e − d·e| < 0.3, ~17°) and d is not within 30° of
  it; those perpendicular to d (great circles through d) come first, at most two are named.
- Conditioning: the condition number of the nine-term ellipsoid design (ellipsoid.py) after column
  scaling, the number the batch fit refuses above (ellipsoid.MAX_CONDITION).
- Refusal (`usable` False, `reason` says why and what to do): fewer than 10 samples, samples in one
  plane (a single-axis turn: the design has rank 5), condition above the limit, or less than
  `min_fraction` of the bins seen. A usable set with gaps gets the advice in `reason` too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluxcal.drivers.errors import CalibrationRefused

from .excitation import PLANARITY_MIN, planarity
from .quadric import MAX_CONDITION, MIN_SAMPLES, gram_condition, normalise, quadric_design

_DIRS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)],
                 dtype=float)
#: (26, 3) unit bin centres: cube faces, edges, corners
BIN_CENTRES = _DIRS / np.linalg.norm(_DIRS, axis=1, keepdims=True)


def _label(v: np.ndarray) -> str:
    return "".join(f"{'+' if c > 0 else '-'}{a}" for a, c in zip("xyz", v) if c != 0)


#: names of the bins, e.g. "+z", "+x-y", "-x+y+z"
BIN_LABELS = [_label(v) for v in _DIRS]
_AXIS_NAMES = ("x", "y", "z")
_BIN_OF = {tuple(int(v) for v in d): b for b, d in enumerate(_DIRS)}      # (i, j, k) -> bin
_NEIGHBOUR_COS = np.cos(np.radians(61.0))
#: default share of bins that must be seen
MIN_FRACTION = 0.3
#: samples a coverage looks at, at most (evenly spaced beyond): the map of 26 bins needs no more
MAX_SAMPLES = 5000


@dataclass(frozen=True)
class MissingRegion:
    """Neighbouring direction bins without samples."""

    label: str                   # the bin nearest the region's mean direction, e.g. "+z"
    centre: np.ndarray           # (3,) unit mean direction
    bins: list[str]              # every bin of the region
    axes: list[str]              # turn about these axes (best first) to sweep it


@dataclass(frozen=True)
class Coverage:
    """Coverage of the field directions in one probe's samples; see the module docstring."""

    fraction: float              # share of the 26 direction bins seen
    counts: np.ndarray           # (26,) samples per bin (BIN_CENTRES, BIN_LABELS)
    missing_centres: np.ndarray  # (K, 3) unit centres of the bins not seen
    regions: list[MissingRegion]  # the missing bins grouped, largest first
    condition: float             # of the column-scaled nine-term ellipsoid design
    planarity: float             # out-of-plane spread / in-plane spread (0 = one plane, a single-axis turn)
    usable: bool                 # the data can determine an ellipsoid fit
    reason: str                  # why not, and what to do; for usable data with gaps, the advice; "" if complete
    text_map: str                # the 26 bins as three cube layers: '#' seen, 'o' thinly, '.' missing
    sky_map: str                 # elevation bands by azimuth sectors, finer
    n_samples: int = 0
    min_count: int = 1           # samples a bin needs to count as seen

    @property
    def missing(self) -> list[str]:
        """Labels of the missing regions (e.g. ["-z", "+x"])."""
        return [r.label for r in self.regions]

    @property
    def missing_bins(self) -> list[str]:
        return [BIN_LABELS[i] for i in range(26) if self.counts[i] < self.min_count]

    def advice(self) -> str:
        """What is missing and the turn that would fill it ("" when nothing is)."""
        if not self.regions:
            return ""
        parts = [f"{r.label} ({len(r.bins)} bin{'s' if len(r.bins) > 1 else ''}): turn about "
                 f"{' or '.join(r.axes) if r.axes else 'any axis that brings the field there'}" for r in self.regions]
        return "directions not covered: " + "; ".join(parts)


def _unit_directions(field_nT: np.ndarray, centre_nT: np.ndarray | None) -> np.ndarray:
    f = np.asarray(field_nT, float)
    d = f - (0.0 if centre_nT is None else np.asarray(centre_nT, float))
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(n > 0, n, 1.0)


def samples_condition(field_nT: np.ndarray) -> float:
    """Condition number of the column-scaled nine-term ellipsoid design of these samples (large = poorly
    determined); the same number `fit_ellipsoid` reports and refuses above MAX_CONDITION."""
    f = np.asarray(field_nT, float)
    if f.shape[0] < 9:
        return float("inf")
    center, s = normalise(f)
    phi = quadric_design((f - center) / s)
    return gram_condition(phi.T @ phi) if f.shape[0] >= phi.shape[1] else float("inf")


def turn_axes(direction: np.ndarray, seen_dirs: np.ndarray, tol: float = 0.3, most: int = 2) -> list[str]:
    """Coordinate axes a turn about which carries some seen direction onto `direction`, best first
    (a turn about e keeps s·e: it reaches d from s only if s·e = d·e; an axis within 30° of d sweeps
    only a small circle around itself and is not offered; axes ⟂ d sweep great circles through d)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    scored = []
    for a, e in enumerate(np.eye(3)):
        if abs(float(d @ e)) > np.cos(np.radians(30.0)):
            continue
        gap = float(np.min(np.abs(seen_dirs @ e - d @ e))) if seen_dirs.size else 0.0
        if gap < tol:
            scored.append((abs(float(d @ e)) + gap, _AXIS_NAMES[a]))
    return [name for _, name in sorted(scored)][:most]


def _regions(missing: np.ndarray, seen_dirs: np.ndarray) -> list[MissingRegion]:
    """Connected components of the missing bins (neighbours ≤ 60° apart), largest first."""
    idx = list(np.flatnonzero(missing))
    out = []
    while idx:
        comp = [idx.pop(0)]
        frontier = list(comp)
        while frontier:
            b = frontier.pop()
            near = [i for i in idx if BIN_CENTRES[i] @ BIN_CENTRES[b] > _NEIGHBOUR_COS]
            for i in near:
                idx.remove(i)
            comp += near
            frontier += near
        mean = BIN_CENTRES[comp].sum(axis=0)
        if np.linalg.norm(mean) < 1e-9:                 # a symmetric ring: name it by its first bin
            mean = BIN_CENTRES[comp[0]]
        mean = mean / np.linalg.norm(mean)
        label = BIN_LABELS[int(np.argmax(BIN_CENTRES @ mean))]
        out.append(MissingRegion(label, mean, [BIN_LABELS[i] for i in sorted(comp)], turn_axes(mean, seen_dirs)))
    return sorted(out, key=lambda r: -len(r.bins))


def coverage(field_nT: np.ndarray, *, centre_nT: np.ndarray | None = None, min_count: int | None = None,
             min_fraction: float = MIN_FRACTION, max_condition: float = MAX_CONDITION,
             max_samples: int = MAX_SAMPLES, maps: bool = True) -> Coverage:
    """Coverage of the field directions in (N, 3) probe samples (rows with NaN are ignored); beyond
    `max_samples`, of evenly spaced ones (directions change slowly next to the sample rate). maps=False:
    without the text maps, and without the missing regions unless the samples are not usable (the online
    gate asks every few seconds, shows no map and says only why a candidate is refused)."""
    f = np.asarray(field_nT, float)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"field_nT: expected shape (N, 3), got {f.shape}")
    f = f[np.isfinite(f).all(axis=1)]
    if f.shape[0] > max_samples:
        f = f[::-(-f.shape[0] // max_samples)]
    n = f.shape[0]
    if n == 0:
        counts = np.zeros(26, int)
        return Coverage(0.0, counts, BIN_CENTRES.copy(), [], float("inf"), 0.0, False,
                        "no samples: rotate the probe about at least two axes", _cube_map(counts, 1), "", 0)
    dirs = _unit_directions(f, centre_nT)
    idx = np.argmax(dirs @ BIN_CENTRES.T, axis=1)
    counts = np.bincount(idx, minlength=26)
    need = min_count if min_count is not None else max(1, n // 1000)
    seen = counts >= need
    flatness, normal = planarity(f) if n > 3 else (0.0, np.array([0.0, 0.0, 1.0]))
    cond = samples_condition(f)
    fraction = float(seen.mean())
    problem = _problem(n, flatness, normal, cond, max_condition, fraction, min_fraction)
    # the missing regions and the advice they give: always with the maps, else only to say why not usable
    regions = _regions(~seen, BIN_CENTRES[seen]) if maps or problem else []
    cov = Coverage(fraction, counts, BIN_CENTRES[~seen].copy(), regions, cond, flatness, True, "",
                   _cube_map(counts, need) if maps else "", _sky_map(dirs) if maps else "", n, need)
    advice = cov.advice()
    if problem:
        reason = problem + (f"; {advice}" if advice else "")
        return _replace(cov, usable=False, reason=reason)
    return _replace(cov, reason=advice)


def _problem(n: int, flatness: float, normal: np.ndarray, cond: float, max_condition: float, fraction: float,
             min_fraction: float) -> str:
    """Why samples with these figures cannot determine an ellipsoid fit ("" if they can)."""
    problem = ""
    if n < MIN_SAMPLES:
        problem = f"{n} samples; a fit needs at least {MIN_SAMPLES} spread over turns about at least two axes"
    elif flatness < PLANARITY_MIN:
        axis = _AXIS_NAMES[int(np.argmax(np.abs(normal)))]
        others = [a for a in _AXIS_NAMES if a != axis]
        problem = (f"the samples lie in one plane (a single-axis turn about {axis}): a plane section does not fix "
                   f"an ellipsoid; turn about the {others[0]} or {others[1]} axis too")
    elif not np.isfinite(cond) or cond > max_condition:
        problem = f"the samples do not determine an ellipsoid (condition number {cond:.3g} > {max_condition:.3g})"
    elif fraction < min_fraction:
        problem = f"only {fraction:.0%} of the directions seen (at least {min_fraction:.0%} needed)"
    return problem


def _replace(cov: Coverage, **kw) -> Coverage:
    from dataclasses import replace

    return replace(cov, **kw)


def check_fit_data(field_nT: np.ndarray, *, name: str = "s1", **kw) -> None:
    """None if the samples can determine an ellipsoid fit; else CalibrationRefused saying why, which
    directions are missing and which turn would fill them."""
    cov = coverage(field_nT, **kw)
    if not cov.usable:
        raise CalibrationRefused(f"{name}: {cov.reason}")


def check_excitation(field_nT: np.ndarray, *, name: str = "s1") -> None:
    """Refuse samples that lie in one plane (a single-axis rotation determines no ellipsoid)."""
    f = np.asarray(field_nT, float)
    if f.shape[0] <= 3:
        return
    if planarity(f)[0] < PLANARITY_MIN:
        raise CalibrationRefused(f"{name}: {coverage(f).reason}")


def _cube_map(counts: np.ndarray, need: int) -> str:
    """The 26 bins as the cube's three z layers, x down the rows (+x on top), y across (−y left)."""
    def cell(i: int, j: int, k: int) -> str:
        if (i, j, k) == (0, 0, 0):
            return " "
        c = counts[_BIN_OF[(i, j, k)]]
        return "." if c < need else "o" if c < 4 * need else "#"

    head = "    z+ (top)       z 0            z- (bottom)"
    cols = "    -y  0 +y       -y  0 +y       -y  0 +y"
    rows = []
    for i, lab in ((1, "+x"), (0, " 0"), (-1, "-x")):
        layers = ["  ".join(cell(i, j, k) for j in (-1, 0, 1)) for k in (1, 0, -1)]
        rows.append(f"{lab}  " + "      ".join(layers))
    return "\n".join([head, cols, *rows, "    # seen   o thinly   . missing"])


def _sky_map(dirs: np.ndarray, rows: int = 6, cols: int = 12) -> str:
    """Elevation bands (top: +z) by azimuth sectors (−180..180° from +x towards +y); '#' seen, '.' not."""
    el = np.arcsin(np.clip(dirs[:, 2], -1, 1))
    az = np.arctan2(dirs[:, 1], dirs[:, 0])
    r = np.clip(((np.pi / 2 - el) / np.pi * rows).astype(int), 0, rows - 1)
    c = np.clip(((az + np.pi) / (2 * np.pi) * cols).astype(int), 0, cols - 1)
    grid = np.zeros((rows, cols), bool)
    grid[r, c] = True
    lines = ["+z " + "".join("#" if g else "." for g in grid[0])]
    lines += ["   " + "".join("#" if g else "." for g in row) for row in grid[1:-1]]
    lines.append("-z " + "".join("#" if g else "." for g in grid[-1]))
    return "\n".join(lines) + "\n   azimuth -180..180 deg"
