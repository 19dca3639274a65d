"""Shared test fixtures: ICD samples whose every value is known, and a pseudo-terminal that pyserial
opens like hardware while the test writes the unit's bytes on the other end."""

from __future__ import annotations

import os
import sys
from pathlib import Path

# tests/ mirrors the source's wings (numerics, io, drivers, wiring) with end-to-end tests in e2e; their modules
# import each other's helpers by module name (`from test_recording import service_config`): every folder on the path
_HERE = Path(__file__).resolve().parent
for _folder in (_HERE, *sorted(p for p in _HERE.iterdir() if p.is_dir() and p.name[0] not in "._")):
    if str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))

# The suite multiplies small matrices while the services it starts run beside it on the other core: idle
# OpenBLAS threads spin for the cores between products (replay measured 5.8x slower that way). One thread, as
# the CLI's fit-free commands use, unless the caller says otherwise; set before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import threading  # noqa: E402
import tty  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from fluxcal.drivers import icd  # noqa: E402


@dataclass(frozen=True)
class IcdTruth(icd.RawFrames):
    """K samples of an n-probe unit, the fields of icd.RawFrames but seq and t_us unwrapped (int64; the
    wire carries them mod 2^16, 2^32)."""

    def serial_bytes(self) -> bytes:
        return icd.encode_serial(self.seq, self.t_us, self.counts, self.temp_raw, self.flags)

    def can_frames(self, base_id: int = icd.DEFAULT_CAN_BASE_ID) -> tuple[np.ndarray, np.ndarray]:
        return icd.encode_can(self.seq, self.counts, self.temp_raw, base_id)

    def take(self, keep: np.ndarray) -> "IcdTruth":
        return IcdTruth(self.seq[keep], self.t_us[keep], self.counts[keep], self.temp_raw[keep], self.flags[keep])


def make_truth(k: int, n: int, seed: int = 0, *, seq0: int = 65536 - 40, t0_us: int = 2**32 - 30_000,
               dt_us: int = 1000) -> IcdTruth:
    """Samples starting 40 before the seq wrap and 30 ms before the unit clock wraps."""
    rng = np.random.default_rng(seed)
    # within the drivers' default full scale (1e6 nT) up to 0.005 nT a count: beyond it a sample is flagged
    counts = rng.integers(-2 * 10**8 + 1, 2 * 10**8, (k, n, 3), dtype=np.int64).astype(np.int32)
    return IcdTruth(seq=seq0 + np.arange(k, dtype=np.int64), t_us=t0_us + dt_us * np.arange(k, dtype=np.int64),
                    counts=counts, temp_raw=rng.integers(-4000, 8000, (k, n)).astype(np.int16),
                    flags=np.zeros(k, np.uint8))


@pytest.fixture
def icd_truth():
    """make_truth(k, n, seed, ...): samples with known values across the seq and clock wraps."""
    return make_truth


class PtyPort:
    """A pty: `path` is the slave (what the driver opens), the test writes on the master."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        self.path = os.ttyname(self.slave)
        self._threads: list[threading.Thread] = []

    def write(self, data: bytes, chunk: int = 4096) -> threading.Thread:
        """Write in the background (the pty buffer is small and the reader runs in the test)."""
        def run() -> None:
            for i in range(0, len(data), chunk):
                try:
                    os.write(self.master, data[i:i + chunk])
                except OSError:
                    return
        t = threading.Thread(target=run, daemon=True)
        t.start()
        self._threads.append(t)
        return t

    def wait_written(self, timeout: float = 5.0) -> None:
        for t in self._threads:
            t.join(timeout)

    def close_master(self) -> None:
        """Pull the cable: the slave side's reads fail from now on."""
        if self.master >= 0:
            self.wait_written(1.0)
            os.close(self.master)
            self.master = -1

    def close(self) -> None:
        self.close_master()
        if self.slave >= 0:
            os.close(self.slave)
            self.slave = -1


@pytest.fixture
def pty_port():
    ports: list[PtyPort] = []

    def make() -> PtyPort:
        p = PtyPort()
        ports.append(p)
        return p

    yield make
    for p in ports:
        p.close()


@pytest.fixture
def clean_registry():
    """The effect registry as it was before the test: effects a test registers (its own, a discovered one) leave
    with it."""
    from fluxcal.service.numerics.effects import _REGISTERED

    before = dict(_REGISTERED)
    yield
    _REGISTERED.clear()
    _REGISTERED.update(before)
