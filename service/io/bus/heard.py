"""Which of a service's data streams some subscriber hears: Zenoh's matching status of each publisher, kept by a
listener on Zenoh's thread. A message of a stream nobody hears costs its encoding, a wake-up of the sender thread
and Zenoh's routing, and goes nowhere: the bus does not make it, and counts it (stats "unheard_<stream>")."""

from __future__ import annotations

from typing import Any

import zenoh

#: the data streams made only while a subscriber somewhere matches them (and corrected/<probe>, counted together as
#: unheard_corrected_probe); the calibration and health streams always go (rare, and the bus keeps the last of each)
HEARD_STREAMS = ("raw", "corrected", "diff", "tensor", "error")


def unheard_stats() -> dict[str, int]:
    """The counters of messages not made, each at zero."""
    return {**{f"unheard_{name}": 0 for name in HEARD_STREAMS}, "unheard_corrected_probe": 0}


class Heard:
    """`heard(stream)`: whether a subscriber matches the data stream now (a stream never watched: True); False is
    counted in `stats`. `watch(stream, pub)` starts following a publisher and returns its listener (to undeclare)."""

    def __init__(self, stats: dict[str, int]) -> None:
        self.stats = stats
        self._matching: dict[str, bool] = {}

    def watch(self, stream: str, pub: zenoh.Publisher) -> Any:
        """Follow `pub` as `stream`; the status is read after the listener exists, so no change falls between."""
        def changed(status: zenoh.MatchingStatus) -> None:
            self._matching[stream] = bool(status.matching)

        listener = pub.declare_matching_listener(changed)
        self._matching[stream] = bool(pub.matching_status.matching)
        return listener

    def known(self, stream: str) -> bool | None:
        """What the bus knows of `stream` (None: not watched)."""
        return self._matching.get(stream)

    def __call__(self, stream: str) -> bool:
        if self._matching.get(stream, True):
            return True
        self.stats["unheard_corrected_probe" if stream.startswith("corrected/") else f"unheard_{stream}"] += 1
        return False
