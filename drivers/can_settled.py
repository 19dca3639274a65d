"""What the CAN assembler has already put in each slot (sample seq, probe, axis): the frames of the samples it
released or gave up lately, of those it still holds, and earlier in the batch at hand. A frame whose counter steps
back to a slot filled with another value is no frame sent again (a repeat is bit for bit the same): it is
evidence that the unit started again (can_unwrap.CanUnwrap asks `differs` of frames stepping back to a counter
near zero). The unit restarting within two windows of its last start sends counters the last run sent a moment
ago: by counter alone its samples were taken for repeats and dropped (10 of 800 at 200 Hz, 0.05 s apart).
"""

from __future__ import annotations

import numpy as np


class SettledFrames:
    """The last `keep` settled samples' frames: seq (K,), value and temperature (K, n, 3), and which slots came.
    Kept as the releases came (a list, O(1) a release), joined only when asked (a frame stepping back near zero)."""

    def __init__(self, n_probes: int, keep: int) -> None:
        self.n, self.keep = n_probes, int(keep)
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._newest: int | None = None

    def add(self, seq: np.ndarray, value: np.ndarray, temp: np.ndarray, have: np.ndarray) -> None:
        """Samples settled now: those within `keep` of the newest are kept (in seq order when asked: held())."""
        if not seq.size:
            return
        self._parts.append((seq, value, temp, have))
        top = int(seq.max())
        self._newest = top if self._newest is None else max(self._newest, top)
        while len(self._parts) > 1 and int(self._parts[0][0].max()) < self._newest - self.keep:
            self._parts.pop(0)

    def held(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(seq, value, temp, have) of the samples kept, in seq order."""
        if not self._parts:
            n = self.n
            return (np.empty(0, np.int64), np.zeros((0, n, 3), np.int32), np.zeros((0, n, 3), np.int16),
                    np.zeros((0, n, 3), bool))
        if len(self._parts) > 1:
            joined = [np.concatenate(x) for x in zip(*self._parts)]
            order = np.argsort(joined[0], kind="stable")   # a sample given up by time above one still waiting
            self._parts = [tuple(x[order] for x in joined)]   # type: ignore[list-item]
        seq, value, temp, have = self._parts[0]
        keep = seq >= int(seq.max()) - self.keep
        return seq[keep], value[keep], temp[keep], have[keep]


def slot_differs(u: np.ndarray, probe: np.ndarray, axis: np.ndarray, value: np.ndarray, temp: np.ndarray,
                 seq: np.ndarray, held_value: np.ndarray, held_temp: np.ndarray, held_have: np.ndarray) -> np.ndarray:
    """Which frames (seq u, probe, axis, value, temperature) land on a slot of the held samples (sorted `seq`)
    filled with another value or temperature."""
    out = np.zeros(u.size, bool)
    if not seq.size or not u.size:
        return out
    row = np.clip(np.searchsorted(seq, u), 0, seq.size - 1)
    at = seq[row] == u
    at[at] = held_have[row[at], probe[at], axis[at]]
    r, p, a = row[at], probe[at], axis[at]
    out[at] = (held_value[r, p, a] != value[at]) | (held_temp[r, p, a] != temp[at])
    return out


def earlier_in_batch_differs(u: np.ndarray, probe: np.ndarray, axis: np.ndarray, value: np.ndarray,
                             temp: np.ndarray, idx: np.ndarray, n_probes: int) -> np.ndarray:
    """Which frames `idx` of the batch land on the slot of an earlier frame of the same batch with another value or
    temperature (the slot's first frame in the batch)."""
    key = (u * n_probes + probe) * 3 + axis
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    f = first[inverse[idx]]
    return (f < idx) & ((value[f] != value[idx]) | (temp[f] != temp[idx]))
