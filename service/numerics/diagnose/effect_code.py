"""The fixed text of an effect module diagnose writes (write_effect.py): its imports and the helpers its class calls to
make the features of the groups and laws discovery found, the same way the library makes them (library.py,
shapes.py, laws.py; tests/numerics/test_discover.py holds the two equal on the same data). Only text. Numerics only.
"""

from __future__ import annotations

HEADER = '''"""{doc}"""

import numpy as np

from fluxcal.effects import EffectTerm
{imports}

def offset_columns(x):
    """(N, 3, 3): x on each axis (nT per unit of x)."""
    out = np.zeros((x.size, 3, 3))
    idx = np.arange(3)
    out[:, idx, idx] = x[:, None]
    return out


def matrix_columns(x, u):
    """(N, 3, 9): 1e-6 x u_j on axis i (ppm per unit of x): the matrix follows x."""
    out = np.zeros((x.size, 3, 9))
    for i in range(3):
        out[:, i, 3 * i:3 * i + 3] = 1e-6 * x[:, None] * u
    return out


def scale_columns(x, u):
    """(N, 3, 6): x on each axis (nT per unit of x), then 1e-6 x u_i on axis i (ppm per unit of x): the offset and
    the scale factors follow x."""
    out = np.zeros((x.size, 3, 6))
    idx = np.arange(3)
    out[:, idx, idx] = x[:, None]
    out[:, idx, 3 + idx] = 1e-6 * x[:, None] * u
    return out


def wave_columns(phase):
    """(N, 3, 6): cos and sin of a phase on each axis (nT)."""
    out = np.zeros((phase.size, 3, 6))
    idx = np.arange(3)
    out[:, idx, idx] = np.cos(phase)[:, None]
    out[:, idx, 3 + idx] = np.sin(phase)[:, None]
    return out


def loop_columns(values):
    """(N, 3, 3): a per-axis value on its own axis (nT)."""
    out = np.zeros((values.shape[0], 3, 3))
    idx = np.arange(3)
    out[:, idx, idx] = values
    return out


def shape_columns(basis):
    """(N, 3, 3 m): each of the m functions of a basis (N, m) on each axis (nT), axis by axis."""
    n, m = basis.shape
    out = np.zeros((n, 3, 3 * m))
    for a in range(3):
        out[:, a, a * m:(a + 1) * m] = basis
    return out


def spline_basis(x, knots, degree, centre):
    """(N, m) the B-splines of x on `knots` less the last one (their sum is the constant), x held within the knots,
    each less its mean over the data the effect was found on (`centre`)."""
    from scipy.interpolate import BSpline

    knots = np.asarray(knots, dtype=np.float64)
    z = np.clip(np.asarray(x, dtype=np.float64), knots[0], knots[-1])
    return BSpline.design_matrix(z, knots, degree).toarray()[:, :-1] - np.asarray(centre)


def turn_basis(x, radians_per_unit, harmonics, centre):
    """(N, 2 K) cos and sin of 1..K times the angle x (in its own unit), each less its mean (`centre`)."""
    a = np.asarray(x, dtype=np.float64) * radians_per_unit
    return np.column_stack([f(h * a) for h in range(1, harmonics + 1) for f in (np.cos, np.sin)]) - np.asarray(centre)


def centred(view, key, x):
    """x less its mean over the data the effect was fitted to (kept with the calibration: a `ref:` key)."""
    key = "ref:" + key
    if key not in view.cache:
        view.cache[key] = float(np.mean(x))
    return x - view.cache[key]


def column(data, name):
    """A logged column, gaps (NaN) filled by interpolation in time."""
    x = np.asarray(data.extras[name], dtype=np.float64)
    ok = np.isfinite(x)
    return x if ok.all() else np.interp(data.t_s, data.t_s[ok], x[ok])


def phase_of(t_s, x, cycles_per_unit):
    """2 pi cycles_per_unit times the time integral of x from the first sample (trapezoids), rad."""
    inc = 0.5 * (x[1:] + x[:-1]) * np.diff(t_s)
    return 2 * np.pi * cycles_per_unit * np.concatenate([[0.0], np.cumsum(inc)])


def angular_rate_deg_s(data):
    """|w| of probe 1's field direction, deg/s."""
    s, r = data.smooth(0), data.rate(0)
    return np.degrees(np.linalg.norm(np.cross(s, r), axis=1) / np.sum(s * s, axis=1))
'''

LAW_PARTS = '''

def law_parts(data, k, theta, probes, law, x, ref, span):
    """A law's field at probe k (N, 3) and its derivative (N, 3, m) in its parameters theta (each probe of `probes`
    its field along the law, nT; then the law's own): zeros where probe k is not among them."""
    n_amp = 3 * len(probes)
    name = data.probe_names[k]
    if name not in probes:
        return np.zeros((x.size, 3)), np.zeros((x.size, 3, theta.size))
    i = probes.index(name)
    a = theta[3 * i:3 * i + 3]
    with np.errstate(all="ignore"):
        f, df = law(x, theta[n_amp:], ref, span)
    jac = np.zeros((x.size, 3, theta.size))
    idx = np.arange(3)
    jac[:, idx, 3 * i + idx] = f[:, None]
    jac[:, :, n_amp:] = df[:, None, :] * a[None, :, None]
    return np.outer(f, a), jac
'''

SHARED_VIEW = '''

class _Data:
    """What the common groups look at: the data, and their references (the means of the data fitted), kept on
    the data under a `ref:` key, which travels with a fitted calibration to other data as a probe's do."""

    def __init__(self, data):
        self.data = data
        self.cache = data._cache.setdefault("ref:discovered", {})      # a `ref:` key: kept with the calibration
'''
