"""Which field directions a probe has seen, how well they determine a fit, and what motion is missing.

Users of today's calibrators ask for a map of the directions still missing (not only a percentage)
and a refusal that says what to do. Directions are binned on 26 sphere directions (cube faces,
edges and corners); a bin counts as seen once it holds at least `min_count` samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.errors import CalibrationRefused

_DIRS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)],
                 dtype=float)
BIN_CENTRES = _DIRS / np.linalg.norm(_DIRS, axis=1, keepdims=True)
_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
_AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True)
class Coverage:
    fraction: float              # share of the 26 direction bins seen
    counts: np.ndarray           # (26,) samples per bin
    missing: list[str]           # principal directions not seen, e.g. ["+z", "-z"]
    planarity: float             # out-of-plane spread / in-plane spread of the samples (0 = one plane)
    reason: str                  # "" when nothing is missing, else what is missing and what to do
    text_map: str                # a small map for a terminal: '#' seen, '.' missing

    @property
    def usable(self) -> bool:
        return not self.reason


def _directions(field_nT: np.ndarray) -> np.ndarray:
    f = np.asarray(field_nT, float)
    centre = f.mean(axis=0) if f.shape[0] > 20 else np.zeros(3)
    # centre on the mid-range, not the mean, so an uneven dwell does not pull it
    if f.shape[0] > 20:
        centre = 0.5 * (f.min(axis=0) + f.max(axis=0))
    d = f - centre
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(n > 0, n, 1.0)


def suggest_axis(missing_dir: np.ndarray, seen_dirs: np.ndarray) -> str:
    """The platform axis to turn about so the field sweeps towards `missing_dir`."""
    m = seen_dirs.mean(axis=0) if seen_dirs.size else np.array([1.0, 0, 0])
    ax = np.cross(m, missing_dir)
    if np.linalg.norm(ax) < 1e-6:
        ax = np.cross(missing_dir, [1.0, 0, 0]) if abs(missing_dir[0]) < 0.9 else np.cross(missing_dir, [0, 1.0, 0])
    # a turn about an axis perpendicular to the missing direction can sweep it
    ax = np.abs(ax) * (1 - np.abs(missing_dir))
    return _AXIS_NAMES[int(np.argmax(ax))]


def coverage(field_nT: np.ndarray, *, min_count: int | None = None) -> Coverage:
    """Coverage of the field directions in (N, 3) probe samples."""
    f = np.asarray(field_nT, float)
    n = f.shape[0]
    if n == 0:
        return Coverage(0.0, np.zeros(26, int), list(_AXES), 0.0, "no samples", "")
    dirs = _directions(f)
    idx = np.argmax(dirs @ BIN_CENTRES.T, axis=1)
    counts = np.bincount(idx, minlength=26)
    need = min_count if min_count is not None else max(1, n // 2000)
    seen = counts >= need
    ev = np.linalg.eigvalsh(np.cov(f.T)) if n > 3 else np.zeros(3)
    planarity = float(np.sqrt(max(ev[0], 0) / ev[2])) if n > 3 and ev[2] > 0 else 0.0
    missing = []
    for label, v in _AXES.items():
        b = int(np.argmax(BIN_CENTRES @ np.asarray(v, float)))
        if not seen[b]:
            missing.append(label)
    reason = ""
    if planarity < 0.02 and n > 3:
        normal = np.linalg.eigh(np.cov(f.T))[1][:, 0]
        axis = _AXIS_NAMES[int(np.argmax(np.abs(normal)))]
        other = [a for a in _AXIS_NAMES if a != axis]
        reason = (f"the samples lie in one plane (a single-axis turn about {axis}): a plane section does not "
                  f"fix an ellipsoid; turn about the {other[0]} or {other[1]} axis too")
    elif missing:
        seen_dirs = dirs[seen[idx]]
        hints = sorted({suggest_axis(np.asarray(_AXES[m], float), seen_dirs) for m in missing})
        reason = (f"directions near {', '.join(missing)} not covered: turn about the "
                  f"{' or '.join(hints)} axis")
    return Coverage(float(seen.mean()), counts, missing, planarity, reason, _text_map(dirs))


def _text_map(dirs: np.ndarray, rows: int = 6, cols: int = 12) -> str:
    """Elevation bands (top: +z) by azimuth sectors; '#' seen, '.' missing."""
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


def check_excitation(field_nT: np.ndarray, *, name: str = "s1") -> None:
    """Refuse data that lie in one plane: a single-axis rotation determines no ellipsoid (rank 6 of 10)."""
    f = np.asarray(field_nT, float)
    if f.shape[0] <= 3:
        return
    ev = np.linalg.eigvalsh(np.cov(f.T))
    planarity = float(np.sqrt(max(ev[0], 0) / ev[2])) if ev[2] > 0 else 0.0
    if planarity < 0.02:
        cov = coverage(f)
        raise CalibrationRefused(f"{name}: {cov.reason}")


def design_condition(field_nT: np.ndarray) -> float:
    """Condition number of the column-scaled ten-term ellipsoid design (large = poorly determined)."""
    from .ellipsoid import quadric_design

    f = np.asarray(field_nT, float)
    s = float(np.median(np.linalg.norm(f, axis=1))) or 1.0
    phi = quadric_design(f / s)
    phi = phi / np.linalg.norm(phi, axis=0)
    sv = np.linalg.svd(phi, compute_uv=False)
    return float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
