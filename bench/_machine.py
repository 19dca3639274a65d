"""What the benchmarks print about the machine they ran on (shared by the bench scripts)."""

from __future__ import annotations

import platform


def cpu_model() -> str:
    """platform.processor(), or the model name Linux reports when that is empty."""
    name = platform.processor()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            name = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), name)
    except OSError:
        pass
    return name or platform.machine()
