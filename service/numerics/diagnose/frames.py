"""The residual per axis in the probe, platform and Earth frames, and whether it stands still in the platform.

A missing term leaves a residual with a frame of its own. An offset error, or a field the platform carries
with it, is a fixed vector in the platform frame (and in each probe's, which is the platform's turned by the
probe's mounting). A field of the site does not stand still there: a gradient across the array gives probe
k minus probe 1 the difference G^T R (r_k - r_1), which turns with the attitude R in both frames, and shows
per axis of the Earth frame (north, east, down) where the gradient's components lie.

- Difference channels (probe k minus probe 1, a vector in the common frame): the RMS per axis in the
  platform frame, in probe k's frame (turned by the rotation part of probe k's matrix) and, with the
  attitude logged, in the Earth frame (R d, R the platform-to-NED attitude); and the share of the excess
  power (above the channels' noise floors) that one fixed vector in the platform frame explains, with that
  vector in the platform and the probe frame.
- Scalar channels (|corrected| - F = n.e for an error vector e): the share a fixed vector in the platform
  frame explains (the residual regressed on the field direction n there), with the vector in the platform
  and probe frames. In the Earth frame the field's direction is itself fixed, so a fixed vector there is a
  constant, which the model's total field already takes.

Numerics only.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fluxcal.service.numerics.effects.base import EffectData
from fluxcal.service.numerics.engine import FitResult

AXES = ("x", "y", "z")
NED = ("north", "east", "down")
#: a residual stands still in the platform frame when a fixed vector there explains this share of its excess,
#: and turns with the platform when such a vector explains less than TURNS
FIXED = 0.5
TURNS = 0.2
#: ... and moves along one direction there (a vector of fixed direction whose size changes) when the largest
#: principal direction of the difference holds this share of its excess
LINE = 0.8
#: the platform turned (a field of the site would move in its frame) when the field's direction there has at
#: least this total variance (a still platform: about 0; a tumble over the sphere: about 1)
TURNED = 0.1


def _rotation_part(m: np.ndarray) -> np.ndarray:
    """The orthogonal factor R of the polar decomposition M = R S (S symmetric positive): probe frame -> common
    frame. A probe with one axis wired reversed (det M < 0) keeps its reflection, so its axes keep their signs."""
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _share(fixed_power: float, total_power: float, noise_power: float) -> float | None:
    excess = total_power - noise_power
    if excess <= 0.1 * noise_power:
        return None                                        # nothing above the floor to place in a frame
    return float(np.clip(fixed_power / excess, 0.0, 1.0))


def frames(data: EffectData, fit: FitResult, noise_nT: np.ndarray) -> list[dict[str, Any]]:
    """Per channel group (each probe's scalar channel, each difference vector): the RMS per axis and the
    share of the excess explained by a fixed vector in each frame, with that vector; JSON-ready."""
    pr, vals = fit.problem, fit.channels.values
    noise = np.asarray(noise_nT, float)
    att = data.attitude()
    att = None if att is None else att[pr.rows]
    mats = fit.state.linear.matrix
    out: list[dict[str, Any]] = []
    for k in range(pr.P):                                   # scalar channels: r = n . e
        r = vals[:, k]
        n = fit.ev.nhat[k]
        x = np.column_stack([np.ones_like(r), n])
        coef, *_ = np.linalg.lstsq(x, r, rcond=None)
        fixed = float(np.var(n @ coef[1:]))                   # the variance the direction explains
        share = _share(fixed, float(np.mean((r - r.mean()) ** 2)), float(noise[k] ** 2))
        rot = _rotation_part(mats[k])
        out.append({"channels": fit.channels.names[k], "kind": "scalar",
                    "platform": {"fixed_share": share, "vector_nT": coef[1:].tolist()},
                    "probe": {"fixed_share": share, "vector_nT": (rot.T @ coef[1:]).tolist()}})
    for k in range(1, pr.P):                                # difference vectors, common (platform) frame
        cols = pr._cols("diff", k)
        d = vals[:, cols]
        nz = float(np.sum(noise[cols] ** 2))
        total = float(np.mean(np.sum(d ** 2, axis=1)))
        rot = _rotation_part(mats[k])
        entry: dict[str, Any] = {"channels": f"{fit.channels.names[cols.start].rsplit('.', 1)[0]}.xyz",
                                 "kind": "difference"}
        for frame, v in (("platform", d), ("probe", d @ rot)):
            m = v.mean(0)
            entry[frame] = {"fixed_share": _share(float(m @ m), total, nz), "vector_nT": m.tolist(),
                            "rms_nT": dict(zip(AXES, np.sqrt(np.mean(v ** 2, axis=0)).tolist()))}
        entry["probe"]["fixed_share"] = entry["platform"]["fixed_share"]    # the same vector, turned
        # one direction of the platform frame with a size that changes (a probe's offset in time): its share
        w, vec = np.linalg.eigh(d.T @ d / max(d.shape[0], 1))
        entry["platform"]["line_share"] = _share(float(w[-1]) - float(np.max(noise[cols] ** 2)), total, nz)
        entry["probe"]["line_axis"] = (rot.T @ vec[:, -1]).tolist()
        # whether the platform turned enough that a field of the site would have moved in its frame: the spread
        # (total variance) of the field's direction there
        nh = np.asarray(fit.ev.nhat[0], float)
        entry["platform"]["turned"] = bool(np.trace(np.cov(nh.T)) >= TURNED) if nh.shape[0] > 2 else False
        if att is not None:
            known = np.all(np.isfinite(att), axis=(1, 2))               # rows whose attitude was logged
            if known.any():
                e = np.einsum("nij,nj->ni", att[known], d[known])
                entry["earth"] = {"rms_nT": dict(zip(NED, np.sqrt(np.mean(e ** 2, axis=0)).tolist()))}
        out.append(entry)
    return out


def frame_summary(entries: list[dict[str, Any]]) -> str | None:
    """One sentence: which difference vectors stand still in the platform frame, and which turn with it (then
    where they lie in the Earth frame, when the attitude is logged). Not the scalar channels: the offsets,
    fitted to them and to the differences together, leave them a fixed part the differences pull against."""
    said, loose = [], []
    for e in entries:
        share = e["platform"]["fixed_share"]
        if share is None or e["kind"] != "difference":       # a scalar channel's share is shared with the offsets'
            continue
        if share >= FIXED:
            v = np.asarray(e["probe"]["vector_nT"])
            said.append(f"{e['channels']} is {100 * share:.0f} % a fixed vector in the platform frame (an offset "
                        f"error or a field the platform carries: {np.linalg.norm(v):.2f} nT, largest on the probe's "
                        f"{AXES[int(np.argmax(np.abs(v)))]} axis)")
        elif share < TURNS and (e["platform"].get("line_share") or 0.0) >= LINE:
            v = np.abs(np.asarray(e["probe"]["line_axis"]))
            head = (f"{e['channels']} moves along one direction of the platform frame "
                    f"({100 * e['platform']['line_share']:.0f} % of the excess, mostly the probe's "
                    f"{AXES[int(np.argmax(v))]} axis) with a size that changes")
            said.append(head + (": an offset changing in time, not a field of the site (which would turn with the "
                                "platform)" if e["platform"].get("turned") else
                                ": the platform turned too little to tell an offset changing in time from a change "
                                "of the site's field"))
        elif share < TURNS and "earth" in e:
            rms = e["earth"]["rms_nT"]
            where = "; in the Earth frame " + ", ".join(f"{k} {v:.2f}" for k, v in rms.items()) + " nT rms"
            said.append(f"{e['channels']} turns with the platform ({100 * share:.0f} % fixed in it: a field of the "
                        f"site, such as a gradient across the array{where})")
        elif share < TURNS:
            # without the attitude nothing says it turns with the platform: each probe's own noise is not fixed in it
            # either (1/f noise alone on a 4-probe cross was called a field of the site, three times)
            loose.append((e["channels"], share))
    if loose:
        said.append(f"{', '.join(c for c, _ in loose)} {'is' if len(loose) == 1 else 'are'} not fixed in the platform "
                    f"frame ({', '.join(f'{100 * v:.0f}' for _, v in loose)} % fixed): not an offset error; a field of "
                    f"the site (a gradient across the array) or each probe's own noise, which the platform's attitude "
                    f"in the data (heel_deg, pitch_deg, azimuth_deg) would tell apart")
    return "; ".join(said) if said else None
