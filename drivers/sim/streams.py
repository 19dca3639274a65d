"""Random numbers addressed by sample index, one stream per purpose, so a run cut into blocks of any size
gives the same samples and one purpose never shifts another.
"""

from __future__ import annotations

import threading

import numpy as np

# random streams (spawned from the seed, one per purpose, so one does not shift another)
STREAM_MOTION, STREAM_NOISE, STREAM_REF, STREAM_TEMP_INVALID, STREAM_SERIAL, STREAM_GARBAGE, STREAM_CAN = range(1, 8)
STREAM_PINK, STREAM_AMBIENT = 8, 9
STREAM_IMPLAUSIBLE, STREAM_WIRE_REPEAT, STREAM_GARBLE = 10, 11, 12


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
        return join_chunks(self._chunk, start, stop)             # one numpy call per 4096 samples


def join_chunks(chunk, start: int, stop: int) -> np.ndarray:
    """Samples [start, stop) from chunk(c), which returns samples [c CHUNK, (c + 1) CHUNK)."""
    c0, c1 = start // ChunkedRandom.CHUNK, (stop - 1) // ChunkedRandom.CHUNK
    parts = [chunk(c) for c in range(c0, c1 + 1)]
    joined = parts[0] if len(parts) == 1 else np.concatenate(parts)
    base = c0 * ChunkedRandom.CHUNK
    return joined[start - base:stop - base].copy()


class OneOverF:
    """Noise with a 1/f power spectrum between f_lo and f_hi, as a function of time (so any instants, in any
    order and cut any way, give the same values), for a stack of channels.

    Per channel a sum of sinusoids, one in each of K equal bins of log frequency (PER_DECADE per decade), at a
    random frequency inside its bin and a random phase. A bin [f, r f] of a 1/f spectrum of density `s` at
    1 Hz (S(f) = s^2 / f) holds the power s^2 ln r, whatever f: every sinusoid has the amplitude
    s sqrt(2 ln r). The variance over the band is s^2 ln(f_hi / f_lo)."""

    PER_DECADE = 16
    ROWS = 4096                    # instants evaluated at once: memory ROWS x K x channels

    def __init__(self, seed: int, stream: int, density_at_1Hz: np.ndarray, f_lo: float, f_hi: float) -> None:
        if not 0 < f_lo < f_hi:
            raise ValueError(f"OneOverF: expected 0 < f_lo < f_hi, got {f_lo}, {f_hi}")
        self.density = np.asarray(density_at_1Hz, dtype=np.float64)
        k = max(1, int(np.ceil(np.log10(f_hi / f_lo) * self.PER_DECADE)))
        ln_r = np.log(f_hi / f_lo) / k
        rng = np.random.default_rng([int(seed), int(stream)])
        shape = (k, *self.density.shape)
        self.freq_hz = f_lo * np.exp(ln_r * (np.arange(k).reshape((k,) + (1,) * self.density.ndim)
                                             + rng.random(shape)))
        self.phase = rng.uniform(0.0, 2.0 * np.pi, shape)
        self.amplitude = self.density * np.sqrt(2.0 * ln_r)
        self.band_hz = (float(f_lo), float(f_hi))

    @property
    def rms(self) -> np.ndarray:
        """The standard deviation of each channel over the band."""
        return self.density * np.sqrt(np.log(self.band_hz[1] / self.band_hz[0]))

    def at(self, t_s: np.ndarray, derivative: bool = False) -> np.ndarray:
        """(*t.shape, *channels) the noise (or its time derivative, per s) at instants t."""
        t = np.asarray(t_s, dtype=np.float64)
        flat = t.reshape(-1)
        out = np.empty((flat.size, *self.density.shape))
        w = 2.0 * np.pi * self.freq_hz
        for a in range(0, flat.size, self.ROWS):                    # a loop over blocks of instants
            tt = flat[a:a + self.ROWS].reshape((-1,) + (1,) * (self.density.ndim + 1))
            arg = w * tt + self.phase
            terms = np.cos(arg) * w if derivative else np.sin(arg)
            out[a:a + self.ROWS] = self.amplitude * terms.sum(axis=1)
        return out.reshape(*t.shape, *self.density.shape)


class PinkNoise:
    """Noise with a 1/f spectrum of density `s` at 1 Hz (S(f) = s^2 / f) between f_lo and f_hi, sampled at a
    uniform rate, addressed by sample index like ChunkedRandom.

    A sum of K first-order Gauss-Markov processes (Ornstein-Uhlenbeck, AR(1) when sampled) with time
    constants spaced evenly in log between 1 / (2 pi f_hi) and 1 / (2 pi f_lo), PER_DECADE per decade, each
    started in its stationary state. Lorentzians of equal variance sigma^2 spaced by a factor r add up to
    sigma^2 / (f ln r): sigma^2 = s^2 ln r gives the density asked for (within about 1 dB between the
    corners; one-sided densities). The recursion runs chunk by chunk from the state kept at each chunk's start, so any range in
    any order gives the same numbers."""

    PER_DECADE = 3

    def __init__(self, seed: int, stream: int, density_at_1Hz: np.ndarray, f_lo: float, f_hi: float,
                 rate_hz: float) -> None:
        if not 0 < f_lo < f_hi:
            raise ValueError(f"PinkNoise: expected 0 < f_lo < f_hi, got {f_lo}, {f_hi}")
        self.density = np.asarray(density_at_1Hz, dtype=np.float64)
        tau_min, tau_max = 1.0 / (2 * np.pi * f_hi), 1.0 / (2 * np.pi * f_lo)
        k = max(2, int(np.ceil(np.log10(tau_max / tau_min) * self.PER_DECADE)) + 1)
        self.tau_s = np.geomspace(tau_min, tau_max, k)
        ln_r = np.log(tau_max / tau_min) / (k - 1)
        self.sigma = self.density * np.sqrt(ln_r)                           # every process, per channel
        self.a = np.exp(-1.0 / (rate_hz * self.tau_s))
        self.b = np.sqrt(1.0 - self.a ** 2)
        self._eps = ChunkedRandom(seed, stream, (k, *self.density.shape))
        start = np.random.default_rng([int(seed), int(stream), 2**31]).standard_normal((k, *self.density.shape))
        self._state: dict[int, np.ndarray] = {0: start}          # unit-variance state before chunk c
        self._done: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()

    def _chunk(self, c: int) -> np.ndarray:
        from scipy.signal import lfilter

        got = self._done.get(c)
        if got is not None:
            return got
        first = max(i for i in self._state if i <= c)
        for i in range(first, c + 1):                             # a loop over chunks, not samples
            x0 = self._state[i]
            eps = self._eps.draw(i * ChunkedRandom.CHUNK, (i + 1) * ChunkedRandom.CHUNK)
            x = np.empty_like(eps)
            for j in range(self.tau_s.size):                     # a loop over the K processes
                x[:, j], _ = lfilter([self.b[j]], [1.0, -self.a[j]], eps[:, j], axis=0,
                                     zi=(self.a[j] * x0[j])[None])
            self._state[i + 1] = x[-1].copy()
            got = np.einsum("nk...,k...->n...", x, np.broadcast_to(self.sigma, x.shape[1:]))
        if len(self._done) >= 4:
            self._done.pop(next(iter(self._done)))
        self._done[c] = got
        return got

    def draw(self, start: int, stop: int) -> np.ndarray:
        if stop <= start:
            return np.empty((0, *self.density.shape))
        with self._lock:
            return join_chunks(self._chunk, start, stop)
