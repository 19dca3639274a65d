"""Binary encoding of a SampleBlock, shared by Zenoh, MCAP and any dashboard in another language.

Little-endian, a fixed header, then whole arrays (numpy tobytes / frombuffer, no per-sample loop):

    offset  type          field
    0       4 bytes       magic "FXr0" (raw block, version 0 of this layout)
    4       u16           P, probes
    6       u16           E, extra columns
    8       u32           N, samples
    12      f64[N]        t_s, unit time, s (unwrapped)
    ..      i64[N]        seq, unwrapped sample counter
    ..      f64[N·P·3]    field_nT, row-major (sample, probe, axis); NaN = saturated axis
    ..      f64[N·P]      temp_C; NaN = invalid
    ..      u8[N]         flags (ICD bits)
    then E times:  u16 name length, UTF-8 name, f64[N] values (e.g. "ref_total")

Every value survives the round trip bit for bit (NaN payloads included).
"""

from __future__ import annotations

import math
import struct

import numpy as np

from .block import SampleBlock
from .errors import DataError

RAW_MAGIC = b"FXr0"
_RAW_HEAD = struct.Struct("<4sHHI")


def encode_raw(block: SampleBlock) -> bytes:
    n, p = block.n_samples, block.n_probes
    parts = [_RAW_HEAD.pack(RAW_MAGIC, p, len(block.extras), n),
             np.ascontiguousarray(block.t_s, "<f8").tobytes(), np.ascontiguousarray(block.seq, "<i8").tobytes(),
             np.ascontiguousarray(block.field_nT, "<f8").tobytes(),
             np.ascontiguousarray(block.temp_C, "<f8").tobytes(), np.ascontiguousarray(block.flags, "u1").tobytes()]
    for name, arr in block.extras.items():
        b = name.encode()
        parts += [struct.pack("<H", len(b)), b, np.ascontiguousarray(arr, "<f8").tobytes()]
    return b"".join(parts)


def decode_raw(data: bytes) -> SampleBlock:
    """Inverse of encode_raw; anything else is a DataError."""
    try:
        magic, p, n_ext, n = _RAW_HEAD.unpack_from(data, 0)
        if magic != RAW_MAGIC:
            raise ValueError(f"not a raw block (magic {bytes(magic)!r}, expected {RAW_MAGIC!r})")
        off = _RAW_HEAD.size
        out = []
        for dtype, shape in (("<f8", (n,)), ("<i8", (n,)), ("<f8", (n, p, 3)), ("<f8", (n, p)), ("u1", (n,))):
            a = np.frombuffer(data, dtype, math.prod(shape), off).reshape(shape)
            off += a.nbytes
            out.append(a.astype(a.dtype.newbyteorder("=")))
        extras = {}
        for _ in range(n_ext):
            (ln,) = struct.unpack_from("<H", data, off)
            name = bytes(data[off + 2: off + 2 + ln]).decode()
            off += 2 + ln
            extras[name] = np.frombuffer(data, "<f8", n, off).astype(float)
            off += 8 * n
        if off != len(data):
            raise ValueError(f"{len(data) - off} trailing bytes")
    except (struct.error, ValueError, UnicodeDecodeError) as e:
        raise DataError(f"raw block: {e}") from None
    return SampleBlock(t_s=out[0], seq=out[1], field_nT=out[2], temp_C=out[3], flags=out[4], extras=extras)
