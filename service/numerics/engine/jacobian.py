"""The Jacobian of the residual channels, built a time block and a chunk at a time, never for all rows at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .residuals import _Eval
from .state import _SYM, State, _Slot

#: bytes of one chunk of Jacobian rows (3 rows per sample, 8 bytes per column): well under glibc's 32 MiB
#: mmap threshold, so the allocator reuses memory instead of faulting fresh pages in every time, and
#: large enough that per-chunk Python work stays small
CHUNK_BYTES = 12 * 2 ** 20
CHUNK_SAMPLES = 4096


def _chunks(block: slice, n_params: int = 0) -> list[slice]:
    """A time block cut into chunks of at most ~CHUNK_BYTES of Jacobian (CHUNK_SAMPLES if n_params is 0)."""
    size = CHUNK_SAMPLES if n_params <= 0 else int(np.clip(CHUNK_BYTES // (24 * n_params), 1024, 65536))
    return [slice(a, min(a + size, block.stop)) for a in range(block.start, block.stop, size)]


@dataclass
class _Jac:
    """The Jacobian's sources at one state (built block by block by Problem._block)."""

    state: "State"
    ev: _Eval
    sources: list[Any]


def block_jacobian(pr: Any, jac: _Jac, sl: slice) -> list[tuple[_Slot, dict[int, np.ndarray], np.ndarray | None]]:
    """Per slot, for rows sl: v-space blocks {probe: (m_b, 3, m)} and a scalar-only block (m_b, m)."""
    rows = pr.rows[sl]
    nb = rows.size
    st, ev = jac.state, jac.ev
    out = []
    for s, src in zip(pr.slots, jac.sources):
        vb: dict[int, np.ndarray] = {}
        sb = None
        if s.kind == "offset":
            vb[s.k] = np.broadcast_to(-st.linear.matrix[s.k], (nb, 3, 3))           # dv/do = -M
        elif s.kind == "matrix":
            v0 = ev.v0[s.k][rows]
            if s.size == 6:                                                         # symmetric X
                cols = np.zeros((nb, 3, 6))
                for c, (i, j) in enumerate(_SYM):
                    cols[:, i, c] += v0[:, j]
                    if i != j:
                        cols[:, j, c] += v0[:, i]
            else:                                                                   # general X
                cols = np.zeros((nb, 3, 9))
                for i in range(3):
                    cols[:, i, 3 * i:3 * i + 3] = v0                                # e_i v0_j
            vb[s.k] = cols
        elif s.kind == "term":
            if s.term.frame == "raw":
                vb[s.k] = -np.matmul(st.linear.matrix[s.k], src[rows])              # dv/dtheta = -M phi
            else:
                vb[s.k] = -src[rows]                                                # -psi
        else:                                                                       # shared
            vcols, scols = src
            for k, c in vcols.items():
                vb[k] = -c[rows]
            if scols is not None:
                sb = -scols[rows]                                                   # dF adds to F
        out.append((s, vb, sb))
    return out


def local_jacobian(blk, nhat_k: np.ndarray | None, k: int, kind: str,
           weight: np.ndarray | float = 1.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Weighted local Jacobian of probe k's scalar channel (m_b, m), or of its difference to probe 1
    ("diff") or to the reference vector ("vec"), the three components interleaved sample by sample
    (3 m_b, m); and the global parameter indices. Built in one preallocated array (every copy of a
    chunk of Jacobian costs as much as the arithmetic)."""
    use = []
    for s, vb, sb in blk:
        if kind == "vec":
            on = k in vb
        elif kind == "diff":
            on = k in vb or 0 in vb
        else:
            on = k in vb or sb is not None
        if on:
            use.append((s, vb, sb))
    if not use:
        return None
    m = sum(s.size for s, _, _ in use)
    nb = blk[0][1][next(iter(blk[0][1]))].shape[0] if blk[0][1] else blk[0][2].shape[0]
    idx = np.concatenate([np.arange(s.start, s.stop) for s, _, _ in use])
    if kind == "scalar":
        jl = np.empty((nb, m))
        c = 0
        for s, vb, sb in use:
            out = jl[:, c:c + s.size]
            if k in vb:
                np.einsum("na,nam->nm", nhat_k, vb[k], out=out)
                if sb is not None:
                    out += sb
            else:
                out[...] = sb
            c += s.size
        jl *= weight
        return jl, idx
    jl = np.empty((nb, 3, m))
    c = 0
    for s, vb, sb in use:
        out = jl[:, :, c:c + s.size]
        if kind == "vec":
            out[...] = vb[k]
        elif k in vb and 0 in vb:
            np.subtract(vb[k], vb[0], out=out)
        elif k in vb:
            out[...] = vb[k]
        else:
            np.negative(vb[0], out=out)
        c += s.size
    jl *= np.asarray(weight)[None, :, None]
    return jl.reshape(nb * 3, m), idx                   # rows n*3 + a, sample by sample
