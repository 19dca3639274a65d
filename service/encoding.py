"""Binary encodings of the block streams (Zenoh payloads and MCAP messages).

Raw SampleBlocks: drivers/encoding.py (layout there). CorrectedBlocks:

    offset  type          field
    0       4 bytes       magic "FXc0"
    4       u8            presence bits: 1 diff_nT, 2 tensor_nT_m, 4 center_nT
    5       u16           P, probes
    7       u32           N, samples
    11      i64           cal_id, the calibration that produced the block
    19      f64[N]        t_s
    ..      i64[N]        seq
    ..      f64[N·P·3]    corrected_nT
    ..      f64[N·(P−1)·3] diff_nT        if bit 1
    ..      f64[N·9]      tensor_nT_m    if bit 2, row-major G[i, j] = dB_j/dx_i
    ..      f64[N·3]      center_nT      if bit 4

All little-endian; decoding is a few numpy.frombuffer calls. Round trips are bit for bit.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np

from drivers.encoding import decode_raw, encode_raw
from drivers.errors import DataError

from .outputs import CorrectedBlock

CORRECTED_MAGIC = b"FXc0"
_COR_HEAD = struct.Struct("<4sBHIq")


def encode_corrected(block: CorrectedBlock) -> bytes:
    bits = (block.diff_nT is not None) | (block.tensor_nT_m is not None) << 1 | (block.center_nT is not None) << 2
    parts = [_COR_HEAD.pack(CORRECTED_MAGIC, bits, block.n_probes, block.n_samples, int(block.cal_id)),
             np.ascontiguousarray(block.t_s, "<f8").tobytes(), np.ascontiguousarray(block.seq, "<i8").tobytes(),
             np.ascontiguousarray(block.corrected_nT, "<f8").tobytes()]
    for a in (block.diff_nT, block.tensor_nT_m, block.center_nT):
        if a is not None:
            parts.append(np.ascontiguousarray(a, "<f8").tobytes())
    return b"".join(parts)


def decode_corrected(data: bytes) -> CorrectedBlock:
    try:
        magic, bits, p, n, cal_id = _COR_HEAD.unpack_from(data, 0)
        if magic != CORRECTED_MAGIC:
            raise ValueError(f"not a corrected block (magic {bytes(magic)!r})")
        off = _COR_HEAD.size
        shapes = [("<f8", (n,)), ("<i8", (n,)), ("<f8", (n, p, 3))]
        shapes += [("<f8", s) if bits >> i & 1 else (None, None)
                   for i, s in enumerate([(n, p - 1, 3), (n, 3, 3), (n, 3)])]
        out: list[np.ndarray | None] = []
        for dtype, shape in shapes:
            if dtype is None:
                out.append(None)
                continue
            a = np.frombuffer(data, dtype, math.prod(shape), off).reshape(shape)
            off += a.nbytes
            out.append(a.astype(a.dtype.newbyteorder("=")))
        if off != len(data):
            raise ValueError(f"{len(data) - off} trailing bytes")
    except (struct.error, ValueError) as e:
        raise DataError(f"corrected block: {e}") from None
    return CorrectedBlock(t_s=out[0], seq=out[1], corrected_nT=out[2], diff_nT=out[3], tensor_nT_m=out[4],
                          center_nT=out[5], cal_id=int(cal_id))


def json_ready(obj: Any) -> Any:
    """Plain JSON types for the JSON streams (Zenoh and MCAP); NaN and infinities become null
    (strict JSON readers reject NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, Mapping):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        return json_ready(obj.item())
    return str(obj)


__all__ = ["encode_raw", "decode_raw", "encode_corrected", "decode_corrected", "json_ready"]
