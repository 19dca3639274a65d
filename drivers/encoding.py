"""Binary encoding of a raw SampleBlock, shared by Zenoh, MCAP and dashboards in other languages.

Layout `fluxcal.raw.v1` (the MCAP message encoding and the Zenoh schema name). Everything is
little-endian and tightly packed (no padding, so arrays need not be 8-byte aligned); arrays are
C order (row-major), written and read whole with numpy tobytes / frombuffer:

    offset            type             field
    0                 3 bytes          kind "FXr" (0x46 0x58 0x72)
    3                 1 byte           layout revision, ASCII "0" (0x30); any other is refused
    4                 u16              P, probes
    6                 u16              E, extra columns
    8                 u32              N, samples
    12                f64[N]           t_s, unit time in s (unwrapped)
    12 + 8N           i64[N]           seq, unwrapped sample counter
    12 + 16N          f64[N, P, 3]     field_nT (sample, probe, axis); NaN = saturated axis
    12 + 16N + 24NP   f64[N, P]        temp_C in degC; NaN = invalid
    12 + 16N + 32NP   u8[N]            flags (ICD bits: 1 saturated, 2 temp invalid, 4 clock resync)
    12 + 17N + 32NP   E times:         u16 L, L bytes UTF-8 name, f64[N] values (e.g. "ref_total")

    size = 12 + N (17 + 32 P) + sum over extras (2 + L + 8 N)

Every value survives the round trip bit for bit: NaN payloads, signed zeros and infinities
included (the arrays are copied as bytes, never converted). Extras are stored as float64 (the
sources produce float64; other dtypes are converted on encoding). `decode_raw` refuses anything that
is not exactly this layout (wrong kind, unknown revision, short or trailing bytes) with a DataError.
"""

from __future__ import annotations

import struct

import numpy as np

from .block import SampleBlock
from .errors import DataError

RAW_KIND = b"FXr"
RAW_REVISION = b"0"
RAW_MAGIC = RAW_KIND + RAW_REVISION
#: the message encoding name of this layout (MCAP channel encoding, Zenoh schema)
RAW_ENCODING = "fluxcal.raw.v1"
_RAW_HEAD = struct.Struct("<4sHHI")
_U16 = struct.Struct("<H")



def layout_text(doc: str) -> str:
    """The layout part of a module docstring: from the line starting "Layout" to the "size =" line."""
    if not doc:                                   # python -OO strips docstrings
        return "see fluxcal's drivers/encoding.py and service/io/encoding.py\n"
    lines = doc.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("Layout"))
    stop = next(i for i, ln in enumerate(lines) if ln.strip().startswith("size ="))
    return "\n".join(lines[start: stop + 1]) + "\n"


#: the layout above as text: the schema data of MCAP raw channels, so a recording documents itself
RAW_LAYOUT = layout_text(__doc__)


def check_magic(data: bytes | memoryview, kind: bytes, revision: bytes, what: str) -> None:
    """Raise DataError unless `data` starts with kind + revision; an unknown revision is named."""
    head = bytes(data[:4])
    if head[:3] != kind:
        raise DataError(f"{what}: not a {what} (starts with {head!r}, expected {kind + revision!r})")
    if head[3:4] != revision:
        raise DataError(f"{what}: layout revision {head[3:4]!r} is not supported by this fluxcal "
                        f"(supported: {revision!r}); read it with the fluxcal version that wrote it")


def encode_raw(block: SampleBlock) -> bytes:
    """The block as `fluxcal.raw.v1` bytes (layout in the module docstring)."""
    n, p = block.n_samples, block.n_probes
    parts = [_RAW_HEAD.pack(RAW_MAGIC, p, len(block.extras), n),
             np.ascontiguousarray(block.t_s, "<f8").tobytes(), np.ascontiguousarray(block.seq, "<i8").tobytes(),
             np.ascontiguousarray(block.field_nT, "<f8").tobytes(),
             np.ascontiguousarray(block.temp_C, "<f8").tobytes(), np.ascontiguousarray(block.flags, "u1").tobytes()]
    for name, arr in block.extras.items():
        b = name.encode()
        if np.shape(arr) != (n,):
            raise ValueError(f"extras[{name!r}]: expected shape ({n},), got {np.shape(arr)}")
        parts += [_U16.pack(len(b)), b, np.ascontiguousarray(arr, "<f8").tobytes()]
    return b"".join(parts)


def _raw_fields(n: int, p: int) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """(dtype, shape) of the fixed fields after the header, in layout order: t_s, seq, field_nT, temp_C, flags."""
    return ("<f8", (n,)), ("<i8", (n,)), ("<f8", (n, p, 3)), ("<f8", (n, p)), ("u1", (n,))


def _array(data: bytes | memoryview, dtype: str, shape: tuple[int, ...], off: int) -> np.ndarray:
    count = 1
    for s in shape:
        count *= s
    # astype copies into an aligned, writable, native-order array (frombuffer views are read-only)
    a = np.frombuffer(data, dtype, count, off).reshape(shape)
    return a.astype(a.dtype.newbyteorder("="))


def decode_raw(data: bytes | memoryview) -> SampleBlock:
    """Inverse of encode_raw; anything else is a DataError that says what is wrong."""
    if len(data) < _RAW_HEAD.size:
        raise DataError(f"raw block: {len(data)} bytes, shorter than the {_RAW_HEAD.size}-byte header")
    check_magic(data, RAW_KIND, RAW_REVISION, "raw block")
    _, p, n_ext, n = _RAW_HEAD.unpack_from(data, 0)
    fixed = _RAW_HEAD.size + n * (17 + 32 * p)
    if len(data) < fixed:
        raise DataError(f"raw block: {len(data)} bytes, the header announces N={n} samples of P={p} probes "
                        f"which need {fixed} bytes before the extras (truncated?)")
    off = _RAW_HEAD.size
    out = []
    for dtype, shape in _raw_fields(n, p):
        out.append(_array(data, dtype, shape, off))
        off += out[-1].nbytes
    extras: dict[str, np.ndarray] = {}
    for k in range(n_ext):
        try:
            (ln,) = _U16.unpack_from(data, off)
            name = bytes(data[off + 2: off + 2 + ln]).decode()
        except (struct.error, UnicodeDecodeError) as e:
            raise DataError(f"raw block: extra column {k + 1} of {n_ext}: bad name ({e})") from None
        off += 2 + ln
        if off + 8 * n > len(data) or len(name.encode()) != ln:
            raise DataError(f"raw block: extra column {name!r} is cut short ({len(data)} bytes in all)")
        if name in extras:
            raise DataError(f"raw block: extra column {name!r} appears twice")
        extras[name] = _array(data, "<f8", (n,), off)
        off += 8 * n
    if off != len(data):
        raise DataError(f"raw block: {len(data) - off} trailing bytes after the last field")
    return SampleBlock(t_s=out[0], seq=out[1], field_nT=out[2], temp_C=out[3], flags=out[4], extras=extras)


def decode_raw_runs(payloads: list[bytes]) -> list[tuple[SampleBlock, np.ndarray]]:
    """decode_raw of many consecutive messages at once: each run of messages with the same header and size
    (a recording's blocks of one layout, the usual case) is decoded by one strided copy per field into one
    block; returns (block, samples per message) per run, in order. The values are decode_raw's, bit for bit;
    the first message of every run goes through decode_raw itself, so a damaged one fails with its message."""
    out: list[tuple[SampleBlock, np.ndarray]] = []
    i, m = 0, len(payloads)
    while i < m:
        first = payloads[i]
        one = decode_raw(first)                              # validates the layout of the whole run
        size, n, p = len(first), one.n_samples, one.n_probes
        # what must be equal byte for byte: the header and the extras' names
        marks, off = [slice(0, _RAW_HEAD.size)], _RAW_HEAD.size + n * (17 + 32 * p)
        for name in one.extras:
            label = len(name.encode())
            marks.append(slice(off, off + 2 + label))
            off += 2 + label + 8 * n
        heads = [first[sl] for sl in marks]
        j = i + 1
        while j < m and len(payloads[j]) == size and all(payloads[j][sl] == h for sl, h in zip(marks, heads)):
            j += 1
        if j - i == 1:
            out.append((one, np.array([one.n_samples])))
            i = j
            continue
        rows = np.frombuffer(b"".join(payloads[i:j]), np.uint8).reshape(j - i, size)
        fields, off = [], _RAW_HEAD.size
        for dtype, shape in _raw_fields(n, p):
            width = int(np.dtype(dtype).itemsize * np.prod(shape))
            a = np.array(rows[:, off:off + width], copy=True).view(dtype)       # writeable, even when empty
            fields.append(a.reshape(((j - i) * n,) + shape[1:]).astype(a.dtype.newbyteorder("="), copy=False))
            off += width
        extras: dict[str, np.ndarray] = {}
        for name in one.extras:
            off += 2 + len(name.encode())
            a = np.array(rows[:, off:off + 8 * n], copy=True).view("<f8")
            extras[name] = a.reshape(-1).astype(a.dtype.newbyteorder("="), copy=False)
            off += 8 * n
        block = SampleBlock(t_s=fields[0], seq=fields[1], field_nT=fields[2], temp_C=fields[3], flags=fields[4],
                            extras=extras)
        out.append((block, np.full(j - i, n)))
        i = j
    return out


__all__ = ["RAW_ENCODING", "RAW_LAYOUT", "RAW_MAGIC", "check_magic", "decode_raw", "decode_raw_runs", "encode_raw", "layout_text"]
