"""A fixed-capacity ring buffer of samples: the last `capacity` samples of a stream of SampleBlocks,
kept in preallocated arrays that never grow.

>>> import numpy as np
>>> from fluxcal.drivers.block import SampleBlock
>>> def blk(seqs):
...     n = len(seqs)
...     return SampleBlock(t_s=np.asarray(seqs, float), seq=np.asarray(seqs), field_nT=np.zeros((n, 1, 3)),
...                        temp_C=np.zeros((n, 1)), flags=np.zeros(n, np.uint8))
>>> rb = RingBuffer(capacity=4, n_probes=1)
>>> rb.append(blk([1, 2, 3])); rb.append(blk([4, 5, 6]))
>>> rb.view().seq.tolist(), len(rb), rb.total_appended, rb.overwritten
([3, 4, 5, 6], 4, 6, 2)
"""

from __future__ import annotations

import numpy as np

from .block import SampleBlock


class RingBuffer:
    """The newest `capacity` samples of P probes.

    `append(block)` overwrites the oldest samples (a block longer than the capacity keeps only its
    newest samples). `latest(n)` and `view()` return SampleBlocks in time order whose arrays are
    views into the buffer when the samples are contiguous in it, and a copy only when they wrap
    around its end. Views change with the next append: copy what you keep.

    Extras (e.g. "ref_total") are kept for the keys of the first block appended; a later block
    lacking one gets NaN there, keys that appear later are ignored.
    """

    def __init__(self, capacity: int, n_probes: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: expected at least 1 sample, got {capacity}")
        self.capacity = int(capacity)
        self.n_probes = int(n_probes)
        c, p = self.capacity, self.n_probes
        self._t_s = np.zeros(c)
        self._seq = np.zeros(c, np.int64)
        self._field_nT = np.zeros((c, p, 3))
        self._temp_C = np.zeros((c, p))
        self._flags = np.zeros(c, np.uint8)
        self._extras: dict[str, np.ndarray] | None = None
        self._head = 0                 # index where the next sample goes
        self._size = 0
        self.total_appended = 0        # samples ever appended
        self.overwritten = 0           # samples lost to overwriting (including a block's own overflow)

    def __len__(self) -> int:
        return self._size

    def _arrays(self) -> list[np.ndarray]:
        return [self._t_s, self._seq, self._field_nT, self._temp_C, self._flags, *(self._extras or {}).values()]

    def append(self, block: SampleBlock) -> None:
        """Add a block's samples, overwriting the oldest when full."""
        if block.n_probes != self.n_probes:
            raise ValueError(f"block: expected {self.n_probes} probes, got {block.n_probes}")
        n = block.n_samples
        if n == 0:
            return
        if self._extras is None:
            self._extras = {k: np.full(self.capacity, np.nan) for k in block.extras}
        self.total_appended += n
        c = self.capacity
        skip = max(0, n - c)                       # a block longer than the buffer: keep its newest c
        sources = [block.t_s, block.seq, block.field_nT, block.temp_C, block.flags]
        sources += [block.extras.get(k) for k in self._extras]
        m = n - skip
        lost = max(0, self._size + m - c) + skip
        self.overwritten += lost
        # at most two slices: [head, c) then [0, rest)
        first = min(m, c - self._head)
        head, wraps = self._head, m > first
        for dst, src in zip(self._arrays(), sources):
            if src is None:
                dst[head:head + first] = np.nan
                dst[:m - first] = np.nan
                continue
            if skip:
                src = src[skip:]
            dst[head:head + first] = src if first == src.shape[0] else src[:first]
            if wraps:
                dst[:m - first] = src[first:]
        self._head = (self._head + m) % c
        self._size = min(c, self._size + m)

    def latest(self, n: int | None = None) -> SampleBlock:
        """The newest n samples (all held if None or n > len), oldest first."""
        size = self._size if n is None else max(0, min(int(n), self._size))
        start = (self._head - size) % self.capacity
        if start + size <= self.capacity:
            # contiguous in storage: views, no copy
            parts = [a[start:start + size] for a in self._arrays()]
        else:
            tail = self.capacity - start
            parts = [np.concatenate([a[start:], a[:size - tail]]) for a in self._arrays()]
        t_s, seq, field_nT, temp_C, flags, *extras = parts
        return SampleBlock(t_s=t_s, seq=seq, field_nT=field_nT, temp_C=temp_C, flags=flags,
                           extras=dict(zip(self._extras or {}, extras)))

    def view(self) -> SampleBlock:
        """Every sample held, oldest first."""
        return self.latest(None)

    def take(self, idx: np.ndarray) -> SampleBlock:
        """The samples at positions `idx` (0 = the oldest held), copied: only those rows, never the
        whole buffer (the pipeline thins 60 s of samples to a few hundred every few seconds)."""
        idx = np.asarray(idx, np.intp)
        if idx.size and (idx.min() < 0 or idx.max() >= self._size):
            raise IndexError(f"ring buffer positions must be in 0..{self._size - 1}")
        rows = (self._head - self._size + idx) % self.capacity
        t_s, seq, field_nT, temp_C, flags, *extras = [a[rows] for a in self._arrays()]
        return SampleBlock(t_s=t_s, seq=seq, field_nT=field_nT, temp_C=temp_C, flags=flags,
                           extras=dict(zip(self._extras or {}, extras)))

    def clear(self) -> None:
        """Forget the samples (the counts of appended and overwritten samples stay)."""
        self._head = 0
        self._size = 0
