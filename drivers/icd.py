"""The acquisition unit's wire format (ICD version 1): encode and parse serial frames and CAN payloads.

Whole buffers at once with numpy: no per-byte or per-frame Python loop in the common case.
Pure byte<->integer work; scaling to physical units happens in the sources.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

SYNC = b"\xa5\x5a"
VERSION = 1
MAX_PROBES = 8
DEFAULT_LSB_NT = 0.001
TEMP_LSB_C = 0.01
SATURATED_COUNTS = (2147483647, -2147483648)
DEFAULT_CAN_BASE_ID = 0x200


def frame_length(n_probes: int) -> int:
    """Serial frame length in bytes: 13 + 14 n."""
    return 13 + 14 * n_probes


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table[i] = crc & 0xFFFF
    return table


CRC_TABLE = _crc_table()


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of one byte string.

    >>> hex(crc16_ccitt_false(b"123456789"))
    '0x29b1'
    """
    crc = 0xFFFF
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ int(CRC_TABLE[((crc >> 8) ^ byte) & 0xFF])
    return crc


def _bswap16(x: np.ndarray | int) -> np.ndarray | int:
    return ((x >> 8) | (x << 8)) & 0xFFFF


def _word_table() -> np.ndarray:
    """T16[x]: the CRC register x after 16 zero bits shifted through it, so that feeding a
    big-endian 16-bit word w into register c gives T16[c ^ w] (two bytes per lookup)."""
    x = np.arange(65536, dtype=np.uint32)
    for _ in range(16):
        x = np.where(x & 0x8000, ((x << 1) ^ 0x1021) & 0xFFFF, (x << 1) & 0xFFFF)
    return x.astype(np.intp)


CRC_TABLE_WORD = _word_table()
# The parser reads words little-endian straight from the frame bytes. Keeping the register
# byte-swapped, s = bswap(crc), the word step becomes s' = bswap(T16[bswap(s ^ w_le)]) = U[s ^ w_le]:
# no per-word byte swap.
_WORD_TABLE_SWAPPED = _bswap16(CRC_TABLE_WORD[_bswap16(np.arange(65536, dtype=np.intp))])
_CRC_TABLE_INTP = CRC_TABLE.astype(np.intp)
_CRC_BLOCK_ROWS = 4096      # rows per CRC pass: keeps the working set in cache


def crc16_rows(columns: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE of K equal-length messages given column-major as a (L, K) uint8 array."""
    columns = np.asarray(columns, dtype=np.uint8)
    length, k = columns.shape
    crc = np.full(k, 0xFFFF, dtype=np.intp)
    start = length % 2
    if start:
        # an odd first byte: crc = (crc << 8) ^ T[(crc >> 8) ^ byte]
        crc = ((crc << 8) & 0xFFFF) ^ _CRC_TABLE_INTP[(crc >> 8) ^ columns[0]]
    for i in range(start, length, 2):
        # two bytes at once: crc = T16[crc ^ (b0 << 8 | b1)]
        word = (columns[i].astype(np.intp) << 8) | columns[i + 1]
        np.bitwise_xor(crc, word, out=crc)
        CRC_TABLE_WORD.take(crc, out=crc)
    return crc.astype(np.uint16)


@functools.lru_cache(maxsize=None)
def _crc_after_header(n_probes: int) -> int:
    """The CRC register after the two header bytes every valid frame shares (version, n)."""
    return crc16_ccitt_false(bytes([VERSION, n_probes]))


def _crc_frames(rows: np.ndarray, n_probes: int) -> np.ndarray:
    """CRC of candidate frames whose version and n bytes are already known to be right.

    rows: (K, W) uint8 with W even and W >= frame length, one frame per row from byte 0, so that
    the little-endian words at even offsets are aligned. Returns (K,) intp.
    """
    fl = frame_length(n_probes)
    n_words = (fl - 7) // 2                  # bytes 4 .. fl-4 as words; byte fl-3 (flags) alone
    k = rows.shape[0]
    swapped = np.empty(k, np.intp)
    s0 = _bswap16(_crc_after_header(n_probes))
    for start in range(0, k, _CRC_BLOCK_ROWS):
        block = rows[start:start + _CRC_BLOCK_ROWS]
        words = block[:, 4:4 + 2 * n_words].view("<u2")
        s = np.full(block.shape[0], s0, np.intp)
        for j in range(n_words):
            np.bitwise_xor(s, words[:, j], out=s)      # s = U[s ^ w]
            _WORD_TABLE_SWAPPED.take(s, out=s)
        swapped[start:start + _CRC_BLOCK_ROWS] = s
    crc = _bswap16(swapped)
    # the flags byte: crc = (crc << 8) ^ T[(crc >> 8) ^ byte]
    return ((crc << 8) & 0xFFFF) ^ _CRC_TABLE_INTP[(crc >> 8) ^ rows[:, fl - 3]]


def frame_dtype(n_probes: int) -> np.dtype:
    """A packed numpy record matching one serial frame byte for byte."""
    return np.dtype([
        ("sync", "<u2"), ("version", "u1"), ("n", "u1"), ("seq", "<u2"), ("t_us", "<u4"),
        ("counts", "<i4", (n_probes, 3)), ("temp", "<i2", (n_probes,)), ("flags", "u1"),
        ("crc", "<u2"),
    ])


@functools.lru_cache(maxsize=None)
def _padded_frame_dtype(n_probes: int) -> np.dtype:
    """frame_dtype with one byte of padding, for the parser's even-width rows."""
    base = frame_dtype(n_probes)
    return np.dtype({"names": list(base.names), "formats": [base.fields[f][0] for f in base.names],
                     "offsets": [base.fields[f][1] for f in base.names], "itemsize": base.itemsize + 1})


@dataclass(frozen=True)
class RawFrames:
    """Integer contents of K frames, before unwrapping and scaling."""

    seq: np.ndarray        # (K,) uint16
    t_us: np.ndarray       # (K,) uint32
    counts: np.ndarray     # (K, n, 3) int32
    temp_raw: np.ndarray   # (K, n) int16
    flags: np.ndarray      # (K,) uint8

    def __len__(self) -> int:
        return int(self.seq.shape[0])


def encode_serial(seq: np.ndarray, t_us: np.ndarray, counts: np.ndarray, temp_raw: np.ndarray,
                  flags: np.ndarray) -> bytes:
    """Serial frames for K samples: counts (K, n, 3) int32, temp_raw (K, n) int16."""
    counts = np.asarray(counts)
    k, n = counts.shape[0], counts.shape[1]
    if not 1 <= n <= MAX_PROBES:
        raise ValueError(f"number of probes: expected 1..{MAX_PROBES}, got {n}")
    rec = np.zeros(k, dtype=frame_dtype(n))
    rec["sync"] = 0x5AA5
    rec["version"] = VERSION
    rec["n"] = n
    rec["seq"] = np.asarray(seq) & 0xFFFF
    rec["t_us"] = np.asarray(t_us) & 0xFFFFFFFF
    rec["counts"] = counts
    rec["temp"] = temp_raw
    rec["flags"] = flags
    raw = rec.view(np.uint8).reshape(k, frame_length(n))
    rec["crc"] = crc16_rows(np.ascontiguousarray(raw[:, 2:-2].T))
    return rec.tobytes()


@dataclass(frozen=True)
class SerialParse:
    """What one pass over a receive buffer found."""

    frames: RawFrames
    consumed: int          # bytes of the buffer dealt with; keep buffer[consumed:] for the next pass
    crc_failures: int      # candidate frames (sync, version, n all right) whose CRC did not match
    bytes_skipped: int     # bytes in buffer[:consumed] that are not part of an accepted frame


def parse_serial(buf: bytes | bytearray | memoryview | np.ndarray, n_probes: int,
                 final: bool = False) -> SerialParse:
    """Find every intact frame of an n-probe unit in a buffer.

    A frame is accepted when its sync, version and probe count are right and its CRC matches.
    Bytes after the last accepted frame that may begin a frame not yet complete are left
    unconsumed (at most one frame length) unless `final` is set.
    """
    a = np.frombuffer(buf, dtype=np.uint8) if not isinstance(buf, np.ndarray) else buf
    size = a.shape[0]
    fl = frame_length(n_probes)
    if size >= 2:
        starts = np.flatnonzero(a[:-1] == 0xA5)
        sync = starts[a[starts + 1] == 0x5A]
    else:
        sync = np.empty(0, np.intp)
    complete = sync[:np.searchsorted(sync, size - fl, side="right")]   # sync + fl <= size
    if complete.size:
        header_ok = (a[complete + 2] == VERSION) & (a[complete + 3] == n_probes)
        cand = complete[header_ok]
        # rows one byte wider than a frame (even width), so the CRC can read aligned words
        padded = np.empty(size + 1, np.uint8)
        padded[:size] = a
        padded[size] = 0
        # every window of fl + 1 bytes as a strided view (no copy, and cheaper to make than
        # sliding_window_view for the small buffers of a live port), then the candidates' rows copied
        rows = np.ndarray((size - fl + 1, fl + 1), np.uint8, padded, 0, (1, 1))[cand]
        crc_got = rows[:, fl - 2].astype(np.intp) | (rows[:, fl - 1].astype(np.intp) << 8)
        crc_ok = _crc_frames(rows, n_probes) == crc_got
        if crc_ok.all():
            pos = cand
        else:
            pos = cand[crc_ok]
            rows = rows[crc_ok]
        if pos.size > 1 and np.any(np.diff(pos) < fl):
            pos, keep = _resolve_overlaps(pos, fl)
            rows = rows[keep]
        failed = cand[~crc_ok]
    else:
        pos = np.empty(0, np.intp)
        rows = np.empty((0, fl + 1), np.uint8)
        failed = np.empty(0, np.intp)
    last_end = int(pos[-1]) + fl if pos.size else 0

    consumed = size
    if not final:
        pending = sync[(sync + fl > size) & (sync >= last_end)]
        if pending.size:
            # a pending start must agree with whatever header bytes have arrived
            c = pending
            ok = np.ones(c.size, bool)
            has_v = c + 2 < size
            ok[has_v] &= a[c[has_v] + 2] == VERSION
            has_n = c + 3 < size
            ok[has_n] &= a[c[has_n] + 3] == n_probes
            if ok.any():
                consumed = int(c[ok][0])
        if consumed == size and size and a[-1] == 0xA5 and size - 1 >= last_end:
            consumed = size - 1

    failed = failed[failed < consumed]
    if pos.size and failed.size:
        idx = np.searchsorted(pos, failed, side="right") - 1
        inside = (idx >= 0) & (failed < pos[np.maximum(idx, 0)] + fl)
        failed = failed[~inside]
    rec = rows.view(_padded_frame_dtype(n_probes)).reshape(-1)
    frames = RawFrames(seq=rec["seq"].copy(), t_us=rec["t_us"].copy(), counts=rec["counts"].copy(),
                       temp_raw=rec["temp"].copy(), flags=rec["flags"].copy())
    return SerialParse(frames=frames, consumed=consumed, crc_failures=int(failed.size),
                       bytes_skipped=consumed - int(pos.size) * fl)


def _resolve_overlaps(pos: np.ndarray, fl: int) -> tuple[np.ndarray, np.ndarray]:
    """Greedy earliest-first choice among valid frames that overlap (rare: a sync inside a payload
    that also passes its CRC). Only runs when an overlap exists."""
    keep = np.zeros(pos.size, bool)
    end = -1
    for i, p in enumerate(pos.tolist()):
        if p >= end:
            keep[i] = True
            end = p + fl
    return pos[keep], keep


# --- CAN -------------------------------------------------------------------------------------

CAN_PAYLOAD_DTYPE = np.dtype([("value", "<i4"), ("seq", "<u2"), ("temp", "<i2")])


def can_id(base_id: int, probe: int, axis: int) -> int:
    """Arbitration id of probe k (0-based), axis a (x=0, y=1, z=2): B + 4k + a."""
    return base_id + 4 * probe + axis


def encode_can(seq: np.ndarray, counts: np.ndarray, temp_raw: np.ndarray,
               base_id: int = DEFAULT_CAN_BASE_ID) -> tuple[np.ndarray, np.ndarray]:
    """CAN frames for K samples, sample by sample, probe by probe, axis by axis.

    Returns arbitration ids (K*3n,) and payloads (K*3n, 8) uint8.
    """
    counts = np.asarray(counts)
    k, n = counts.shape[0], counts.shape[1]
    rec = np.zeros((k, n, 3), dtype=CAN_PAYLOAD_DTYPE)
    rec["value"] = counts
    rec["seq"] = (np.asarray(seq) & 0xFFFF)[:, None, None]
    rec["temp"] = np.asarray(temp_raw)[:, :, None]
    ids = base_id + 4 * np.arange(n)[:, None] + np.arange(3)[None, :]
    ids = np.broadcast_to(ids, (k, n, 3)).reshape(-1)
    return ids.astype(np.int64), rec.reshape(-1).view(np.uint8).reshape(-1, 8)


def decode_can(ids: np.ndarray, payloads: np.ndarray, n_probes: int,
               base_id: int = DEFAULT_CAN_BASE_ID) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split CAN frames into (probe, axis, value, seq, temp); frames with a foreign or reserved id
    get probe = -1."""
    ids = np.asarray(ids, dtype=np.int64)
    off = ids - base_id
    probe = off // 4
    axis = off % 4
    foreign = (off < 0) | (probe >= n_probes) | (axis == 3)
    probe = np.where(foreign, -1, probe)
    rec = np.ascontiguousarray(payloads, dtype=np.uint8).reshape(-1, 8).view(CAN_PAYLOAD_DTYPE).reshape(-1)
    return probe, axis, rec["value"], rec["seq"], rec["temp"]
