"""What the bench scripts share: the machine they ran on, and the best of several timed runs."""

from __future__ import annotations

import platform
import time
from typing import Callable


def cpu_model() -> str:
    """platform.processor(), or the model name Linux reports when that is empty."""
    name = platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            name = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), name)
    except OSError:
        pass
    return name or platform.machine()


def best_of(runs: int, fn: Callable[[], object]) -> float:
    """The shortest of `runs` timed calls of fn, s: the least disturbed by whatever else the machine does."""
    best = float("inf")
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best
