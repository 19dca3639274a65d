"""Fuzzing the serial framer: streams with garbage, truncation, bit flips and dropped bytes, fed in
random chunk sizes. It never raises, never yields a frame that was not sent intact, yields every
frame that was (but for the 2^-16 chance that a damaged frame passes CRC-16), and its counters add up: accepted x frame length + skipped + pending == bytes fed."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fluxcal.drivers import icd
from fluxcal.drivers.assemble import SerialFramer


def frame_bytes(rng: np.random.Generator, k: int, n: int) -> list[bytes]:
    buf = icd.encode_serial(rng.integers(0, 65536, k), rng.integers(0, 2**32, k),
                            rng.integers(-2**31, 2**31, (k, n, 3), dtype=np.int64).astype(np.int32),
                            rng.integers(-32768, 32768, (k, n)).astype(np.int16), rng.integers(0, 8, k).astype(np.uint8))
    fl = icd.frame_length(n)
    return [buf[i:i + fl] for i in range(0, len(buf), fl)]


def frame_keys(frames: icd.RawFrames, n: int) -> list[bytes]:
    """The frames' bytes, re-encoded from what the parser returned."""
    buf = icd.encode_serial(frames.seq, frames.t_us, frames.counts, frames.temp_raw, frames.flags)
    fl = icd.frame_length(n)
    return [buf[i:i + fl] for i in range(0, len(buf), fl)]


def run_framer(stream: bytes, n: int, chunks: list[int]) -> tuple[list[bytes], SerialFramer]:
    framer = SerialFramer(n)
    got: list[bytes] = []
    i, c = 0, 0
    fl = icd.frame_length(n)
    while i < len(stream):
        size = chunks[c % len(chunks)] if chunks else len(stream)
        c += 1
        frames = framer.feed(stream[i:i + size])
        i += size
        got += frame_keys(frames, n)
        cnt = framer.counters
        assert cnt.frames_accepted * fl + cnt.bytes_skipped + framer.pending_bytes == framer.bytes_fed
        assert framer.pending_bytes < fl
    frames = framer.finish()
    got += frame_keys(frames, n)
    cnt = framer.counters
    assert framer.pending_bytes == 0
    assert cnt.frames_accepted * fl + cnt.bytes_skipped == framer.bytes_fed == len(stream)
    return got, framer


def damage(rng: np.random.Generator, frames: list[bytes], p: float, n: int) -> tuple[bytes, list[tuple[int, bytes]]]:
    """A stream made of the frames, some damaged, with garbage between some; the intact frames
    with their offsets."""
    out, intact = bytearray(), []
    for f in frames:
        r = rng.random()
        if r < p:                                   # one bit flipped: CRC-16 always sees it
            g = bytearray(f)
            pos = int(rng.integers(0, len(g)))
            g[pos] ^= 1 << int(rng.integers(0, 8))
            out += g
        elif r < 2 * p:                              # bytes dropped
            cut = int(rng.integers(0, len(f)))
            out += f[:cut] + f[cut + int(rng.integers(1, 10)):]
        else:
            intact.append((len(out), f))
            out += f
        if rng.random() < p:                        # garbage, sometimes with a plausible header
            junk = rng.integers(0, 256, int(rng.integers(1, 80)), dtype=np.uint8).tobytes()
            if rng.random() < 0.5:
                junk = icd.SYNC + bytes([icd.VERSION, n]) + junk
            out += junk
    return bytes(out), intact


# derandomize: a damaged candidate passes CRC-16 by chance with probability 2^-16, which is the ICD's
# own limit, not the parser's; a fixed example sequence keeps the test from tripping on it at random
@settings(max_examples=100, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(n=st.integers(1, 8), k=st.integers(0, 30), seed=st.integers(0, 2**32 - 1),
       p=st.sampled_from([0.0, 0.05, 0.3]), head=st.integers(0, 60), tail=st.integers(0, 60),
       chunks=st.lists(st.integers(1, 300), min_size=1, max_size=8))
def test_framer_on_damaged_streams(n, k, seed, p, head, tail, chunks):
    rng = np.random.default_rng(seed)
    frames = frame_bytes(rng, k, n)
    stream, intact = damage(rng, frames, p, n)
    start, stop = min(head, len(stream)), max(min(head, len(stream)), len(stream) - tail)
    stream = stream[start:stop]                       # starts mid-frame, truncated at the end
    fl = icd.frame_length(n)
    survivors = [f for pos, f in intact if pos >= start and pos + fl <= stop]
    got, framer = run_framer(stream, n, chunks)
    assert got == survivors
    assert framer.counters.frames_accepted == len(survivors)
    assert set(got) <= set(frames)
    assert framer.counters.bytes_skipped == len(stream) - len(got) * fl


@settings(max_examples=100, deadline=None, derandomize=True)
@given(data=st.binary(max_size=600), n=st.integers(1, 8), chunks=st.lists(st.integers(1, 64), min_size=1, max_size=5))
def test_framer_never_raises_on_arbitrary_bytes(data, n, chunks):
    got, _ = run_framer(data, n, chunks)
    # a frame found was in the input verbatim, CRC included (frame_keys re-encodes with a fresh CRC)
    assert all(f in data for f in got)


def test_framer_seeded_large_stream():
    rng = np.random.default_rng(2024)
    n = 4
    frames = frame_bytes(rng, 4000, n)
    stream, intact = damage(rng, frames, 0.03, n)
    stream = stream[17:]
    survivors = [f for pos, f in intact if pos >= 17]
    chunks = rng.integers(1, 5000, 200).tolist()
    got, framer = run_framer(stream, n, chunks)
    assert got == survivors
    assert len(got) > 3500
    c = framer.counters
    # every damaged frame whose header survived and that was complete was a CRC failure or a resync
    assert c.crc_failures > 0
    assert c.frames_accepted * icd.frame_length(n) + c.bytes_skipped == len(stream)
