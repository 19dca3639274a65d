"""Where the recorder itself lost data (a full disk, a removed drive), found from the recording's own sequence and
health: a jump of the raw stream's sample counter across which the recorder's `dropped` count grew, by more samples
than the unit's own `samples_missed` grew.

A replay after such a gap cannot follow the live run past it (the live estimator saw the samples the recording
lost): `fluxcal replay` says the gap before it compares and compares only what both have. Before, a disk-full
stretch the recording's health counted (4,838 messages dropped) made replay exit 1 with "14,057 corrected samples
differ ... more than rounding can explain", blaming the pipeline, with no word of the 15 s missing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class RecorderGap:
    """Raw samples the recorder lost: the last sample before and the first after (seq, unit time), how many of
    the missing samples the unit itself lost (its samples_missed), and what the recording's health says."""

    seq_before: int
    seq_after: int
    t_before: float
    t_after: float
    unit_missed: int          # of the missing samples, those the unit's own counter says it lost
    dropped: int              # messages the recorder dropped meanwhile (its health: recording.dropped)
    why: str                  # the recorder's last error then

    @property
    def samples(self) -> int:
        """Raw samples the recorder lost (the gap less what the unit itself lost)."""
        return self.seq_after - self.seq_before - 1 - self.unit_missed

    def describe(self) -> str:
        why = f" ({self.why})" if self.why else ""
        return (f"a recorder gap: the recording's own health says {self.dropped:,} message(s) were dropped by the "
                f"recorder{why}; {self.samples:,} raw sample(s) between seq {self.seq_before} and {self.seq_after} "
                f"({self.t_after - self.t_before:.1f} s of unit time) are not in the recording")


def _health_figures(h: dict[str, Any]) -> tuple[int, int, str]:
    """(recorder's dropped messages, the unit's samples missed, the recorder's last error) of one health message."""
    rec = h.get("recording") if isinstance(h.get("recording"), dict) else {}
    counters = h.get("counters") if isinstance(h.get("counters"), dict) else {}
    return int(rec.get("dropped") or 0), int(counters.get("samples_missed") or 0), str(rec.get("last_error") or "")


def recorder_gaps(raw_blocks: list, health: list[dict[str, Any]], health_at: list[int]) -> list[RecorderGap]:
    """The recorder gaps of one unit's recording: `raw_blocks` its raw messages in order, `health` its health
    messages and `health_at` how many raw messages were recorded before each (Recording.health_at)."""
    spans = [message_spans(b, [b.n_samples]) for b in raw_blocks]
    return gaps_between(np.concatenate(spans) if spans else np.empty((0, 4)), health, health_at)


def message_spans(block: Any, sizes: np.ndarray) -> np.ndarray:
    """(M, 4) first seq, last seq, first t, last t of each of the M messages a decoded run holds (`sizes`: the
    samples of each; NaN for an empty one); what gaps_between needs, without the samples."""
    ends = np.cumsum(np.asarray(sizes, np.int64))
    starts = ends - np.asarray(sizes, np.int64)
    full = ends > starts
    out = np.full((len(sizes), 4), np.nan)
    s, e = starts[full], ends[full] - 1
    out[full] = np.column_stack([block.seq[s], block.seq[e], block.t_s[s], block.t_s[e]])
    return out


def gaps_between(spans: np.ndarray, health: list[dict[str, Any]], health_at: list[int]) -> list[RecorderGap]:
    """recorder_gaps of messages given by their spans ((M, 4) float: first seq, last seq, first t, last t; NaN for
    an empty message): a reader that does not hold the messages' samples (read_samples) asks the same question."""
    if not health or len(health) != len(health_at) or len(spans) < 2:
        return []
    figures = [_health_figures(h) for h in health]
    at = np.asarray(health_at)
    firsts, lasts = spans[:, 0], spans[:, 1]
    gaps = []
    for i in np.flatnonzero(firsts[1:] > lasts[:-1] + 1):       # message i, then a jump to i + 1 (NaN: never)
        before = np.flatnonzero(at <= i + 1)          # health recorded before message i + 1 arrived
        after = np.flatnonzero(at > i + 1)            # ... and after it
        if not after.size:
            continue                                  # nothing recorded after it says what happened
        d0, m0, _ = figures[int(before[-1])] if before.size else (0, 0, "")
        d1, m1, why = figures[int(after[0])]
        missing = int(firsts[i + 1] - lasts[i] - 1)
        if d1 > d0 and missing > m1 - m0:
            gaps.append(RecorderGap(int(lasts[i]), int(firsts[i + 1]), float(spans[i, 3]), float(spans[i + 1, 2]),
                                    max(0, m1 - m0), d1 - d0, why))
    return gaps
