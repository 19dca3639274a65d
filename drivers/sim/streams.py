"""Random numbers addressed by sample index, one stream per purpose, so a run cut into blocks of any size
gives the same samples and one purpose never shifts another.
"""

from __future__ import annotations

import threading

import numpy as np

# random streams (spawned from the seed, one per purpose, so one does not shift another)
STREAM_MOTION, STREAM_NOISE, STREAM_REF, STREAM_TEMP_INVALID, STREAM_SERIAL, STREAM_GARBAGE, STREAM_CAN = range(1, 8)


class ChunkedRandom:
    """Random numbers for samples [start, stop): chunk c of a stream comes from default_rng([seed, stream, c]).

    Any range gives the same numbers however the run is cut into blocks, and ranges can be asked for
    in any order (a reader that reconnects, a test that regenerates one stretch)."""

    CHUNK = 4096

    def __init__(self, seed: int, stream: int, per_sample: tuple[int, ...] = (), kind: str = "normal") -> None:
        if kind not in ("normal", "uniform", "bytes"):
            raise ValueError(f"kind: expected 'normal', 'uniform' or 'bytes', got {kind!r}")
        self.seed, self.stream, self.per_sample, self.kind = int(seed), int(stream), tuple(per_sample), kind
        self._cache: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()          # an emitter thread and its owner may both draw

    def _chunk(self, c: int) -> np.ndarray:
        with self._lock:
            return self._chunk_locked(c)

    def _chunk_locked(self, c: int) -> np.ndarray:
        got = self._cache.get(c)
        if got is None:
            rng = np.random.default_rng([self.seed, self.stream, c])
            shape = (self.CHUNK, *self.per_sample)
            if self.kind == "normal":
                got = rng.standard_normal(shape)
            elif self.kind == "uniform":
                got = rng.random(shape)
            else:
                got = rng.integers(0, 256, size=shape, dtype=np.uint8)
            if len(self._cache) >= 4:
                self._cache.pop(next(iter(self._cache)))
            self._cache[c] = got
        return got

    def draw(self, start: int, stop: int) -> np.ndarray:
        if stop <= start:
            return np.empty((0, *self.per_sample), dtype=np.uint8 if self.kind == "bytes" else np.float64)
        c0, c1 = start // self.CHUNK, (stop - 1) // self.CHUNK
        parts = [self._chunk(c) for c in range(c0, c1 + 1)]   # one numpy call per 4096 samples
        joined = parts[0] if len(parts) == 1 else np.concatenate(parts)
        base = c0 * self.CHUNK
        return joined[start - base:stop - base].copy()
