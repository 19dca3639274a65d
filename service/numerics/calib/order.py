"""Model order of the ellipsoid fit: fit only what the samples determine, and say what they do not.

Partial coverage (a hand-turned board that never pointed one way, a vehicle that only turns in the
horizontal) determines the offsets long before it separates three scales and three
non-orthogonality angles. The best hobby calibrators then fit fewer terms; so does this module:

    full    nine quadric terms: offsets, three scales, three non-orthogonality angles
    axes    six: offsets and three scales along the sensor axes (angles fixed at zero)
    sphere  four: offsets and one scale (scale ratios fixed at one, angles at zero)

each a linear restriction θ₉ = T θ_k of the nine-term quadric (ellipsoid.quadric_design). The
order is chosen on held-out time blocks: each order is fitted on four of five contiguous blocks
and scored by the RMS of |M(r − o)| − F on the fifth; the lowest order within HELDOUT_TOLERANCE
of the best wins (held-out rows of a hand-turned recording are attitudes the fit has not seen, so
an order that merely follows the noise of the training attitudes loses there). With too few
samples for five blocks the standard errors decide instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: held-out RMS within this fraction of the best: the lower order is as good (a gain must be worth having)
HELDOUT_TOLERANCE = 0.02
#: contiguous time blocks of the held-out comparison
N_BLOCKS = 5
#: samples per fitted term below which the held-out comparison is not made (the standard errors decide)
MIN_ROWS_PER_TERM = 10
#: an offset whose standard error exceeds this fraction of the field is not determined
OFFSET_SE_MAX_FRACTION = 0.1
#: a scale whose relative standard error exceeds this is not determined
SCALE_SE_MAX = 0.1


def _expansion(order: str) -> np.ndarray:
    """T (9, k): θ₉ = T θ_k."""
    eye = np.eye(9)
    if order == "full":
        return eye
    if order == "axes":
        return eye[:, [0, 1, 2, 6, 7, 8]]
    if order == "sphere":
        return np.column_stack([eye[:, 0] + eye[:, 1] + eye[:, 2], eye[:, 6], eye[:, 7], eye[:, 8]])
    raise ValueError(f"order: {order!r} is not allowed (allowed: {', '.join(ORDERS)})")


#: from the most terms to the fewest
ORDERS = ("full", "axes", "sphere")
EXPANSIONS = {o: _expansion(o) for o in ORDERS}
#: what an order holds fixed, and why a user would care
FIXED = {
    "full": [],
    "axes": ["nonorth_deg"],
    "sphere": ["nonorth_deg", "scale ratios"],
}


@dataclass(frozen=True)
class OrderChoice:
    """Which order the held-out blocks (or the standard errors) chose, and the figures behind it."""

    order: str
    heldout_rms_nT: dict[str, float]   # per order tried; empty when the standard errors decided
    by: str                            # "held-out blocks" or "standard errors"


def expand(theta_k: np.ndarray, cov_k: np.ndarray, order: str, extra: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """θ₉ (and the covariance) of a reduced fit; `extra` trailing columns (the δ column) pass through."""
    t = EXPANSIONS[order]
    if extra:
        t = np.block([[t, np.zeros((9, extra))], [np.zeros((extra, t.shape[1])), np.eye(extra)]])
    return t @ theta_k, t @ cov_k @ t.T


def block_edges(n: int, n_blocks: int = N_BLOCKS) -> np.ndarray:
    """Edges of the contiguous time blocks of n samples."""
    return np.linspace(0, n, n_blocks + 1).astype(int)


def block_normals(design, n: int, n_blocks: int = N_BLOCKS) -> tuple[np.ndarray, list, list]:
    """Edges of the contiguous time blocks, and per block ΦᵀΦ and Φᵀ1 of the nine-term design; `design(a, b)`
    gives the design of samples a..b, so only one block's design is ever held (hours of data)."""
    edges = block_edges(n, n_blocks)
    grams, rhs = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        g = r = 0.0
        for c, d in sub_chunks(a, b):               # a block's design a part at a time (hours of data)
            phi = design(c, d)
            g, r = g + phi.T @ phi, r + phi.sum(axis=0)
        grams.append(g)
        rhs.append(r)
    return edges, grams, rhs


#: rows of the design held at a time within a block (19 MB of the nine columns)
SUB_ROWS = 262_144


def sub_chunks(a: int, b: int) -> list[tuple[int, int]]:
    """Rows a..b in parts of at most SUB_ROWS (one part, itself, up to that size: the same sums as before)."""
    return [(c, min(b, c + SUB_ROWS)) for c in range(a, b, SUB_ROWS)] or [(a, b)]


def heldout_rms(normals: tuple[np.ndarray, list, list], raw: np.ndarray, total: np.ndarray, known: bool,
                order: str, calibrate) -> float:
    """RMS of |M(r − o)| − F on each block, fitted on the other blocks (normals: `block_normals` of the
    nine-term design of the centred, scaled samples; calibrate(θ₉ (K, 9), f2_ref (K,)) -> (offsets (K, 3),
    matrices (K, 3, 3)), every fold at once, raising LinAlgError when a quadric is not an ellipsoid). An unknown F
    is the fold's unit_volume_total."""
    edges, grams9, rhs9 = normals
    t = EXPANSIONS[order]
    grams = t.T @ np.stack(grams9) @ t                       # (K, k, k): each fold's block, then its complement
    rhs = np.stack(rhs9) @ t
    g, r = grams.sum(axis=0) - grams, rhs.sum(axis=0) - rhs
    col = np.sqrt(np.maximum(np.diagonal(g, axis1=1, axis2=2), 1e-300))
    n = raw.shape[0]
    sizes = np.diff(edges)
    if known:                                   # the training rows' mean F²
        held_f2 = np.array([float(np.sum(total[a:b] ** 2)) for a, b in zip(edges[:-1], edges[1:])])
        f2 = (float(np.sum(total ** 2)) - held_f2) / (n - sizes)
    else:                                       # the unit-volume convention of an unknown field
        f2 = np.ones(len(sizes))
    try:
        scaled = np.linalg.solve(g / (col[:, :, None] * col[:, None, :]), (r / col)[..., None])[..., 0]
        offsets, matrices = calibrate((scaled / col) @ t.T, f2)
        unit = None if known else np.linalg.det(matrices) ** (-1.0 / 3.0)   # each fold's unit-volume field
        if unit is not None:
            matrices = matrices * unit[:, None, None]
    except np.linalg.LinAlgError:
        return float("inf")
    sq = 0.0
    for i, (a, b) in enumerate(zip(edges[:-1], edges[1:])):       # a block at a time: no (N, 3, 3) gathers
        resid = np.linalg.norm((raw[a:b] - offsets[i]) @ matrices[i].T, axis=1) - (total[a:b] if unit is None else unit[i])
        sq += float(resid @ resid)
    return float(np.sqrt(sq / n))


def choose_order(normals: tuple[np.ndarray, list, list], raw: np.ndarray, total: np.ndarray, known: bool,
                 calibrate) -> OrderChoice | None:
    """The order the held-out blocks choose, or None when there are too few samples to compare."""
    n = raw.shape[0]
    if n < N_BLOCKS * MIN_ROWS_PER_TERM * 9 // (N_BLOCKS - 1):
        return None
    scores = {o: heldout_rms(normals, raw, total, known, o, calibrate) for o in ORDERS}
    best = min(scores.values())
    if not np.isfinite(best):
        return OrderChoice("full", scores, "held-out blocks")
    for o in reversed(ORDERS):                    # fewest terms first
        if scores[o] <= best * (1.0 + HELDOUT_TOLERANCE):
            return OrderChoice(o, scores, "held-out blocks")
    return OrderChoice("full", scores, "held-out blocks")


def undetermined(offset: np.ndarray, offset_se: np.ndarray, scale: np.ndarray, scale_se: np.ndarray,
                 field_nT: float) -> list[str]:
    """Names of the parameters whose standard errors say the samples did not determine them."""
    out = [f"offset_nT.{a}" for a, s in zip("xyz", offset_se) if not np.isfinite(s) or s > OFFSET_SE_MAX_FRACTION * field_nT]
    out += [f"scale.c_{a}" for a, c, s in zip("xyz", scale, scale_se)
            if not np.isfinite(s) or s > SCALE_SE_MAX * abs(c)]
    return out


def order_warnings(cal: Any, order: str, missing: list[str], choice: OrderChoice | None) -> list[str]:
    """What a user must know before trusting the fit: terms held fixed, parameters not determined."""
    name, p = cal.name, cal.params
    out = []
    if order != "full":
        why = ("the held-out blocks do not gain from more terms (RMS " +
               ", ".join(f"{k} {v:.4g} nT" for k, v in choice.heldout_rms_nT.items()) + ")"
               if choice is not None and choice.order == order else
               "the standard errors of a larger order exceed its parameters")
        out.append(f"{name}: fitted the {order} model; {' and '.join(FIXED[order])} not determined by "
                   f"these samples ({why}): held fixed")
    out += [f"{name}: {m} not determined by these samples (standard error too large)" for m in missing]
    return out + size_warnings(name, p)


#: the named parameters whose standard errors are compared with their size
SIZED = ("offset_nT", "scale", "nonorth_deg")
SIZE_WARNING = "its standard error exceeds its size"


def size_warnings(name: str, params: dict) -> list[str]:
    """A warning for each offset or named parameter (SIZED) whose standard error exceeds its size."""
    out = []
    for key in SIZED:
        entry = params.get(key)
        if entry is None or entry.get("se") is None:
            continue
        labels = entry.get("names") or list("xyz")
        for lab, v, se in zip(labels, np.atleast_1d(entry["value"]), np.atleast_1d(entry["se"])):
            if np.isfinite(se) and se > abs(v):
                out.append(f"{name}: {key}.{lab} = {v:.4g} ± {se:.2g}: {SIZE_WARNING}")
    return out
