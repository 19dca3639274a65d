"""Replay's gate checks worked out ahead in a second process, so that they overlap the rest of the replay.

A replay knows all of its blocks and commands before it starts, and the gate's checks depend on the raw samples
and the commands alone, never on the outputs. A forked copy of the pipeline runs the same blocks and commands,
and sends each check's results (the candidate, or why there is none, and its evaluation) down a pipe; the replay's
own pipeline takes them in order instead of working them out, solving its estimators where the copy's check
solved them (a solve moves the estimator's anchor). Same code, same inputs: the same results, bit for bit, which
tests/wiring/test_gate_ahead.py checks against the replay worked out in one process.

A check whose results do not arrive, or arrive for another state of the ring buffer, is worked out by the replay
itself, and so is every later one: the second process can cost time, never a result. It is used only where a
fork is safe and pays (gate_ahead_worth: Linux, no other thread in the process, two cores, enough checks)."""

from __future__ import annotations

import multiprocessing
import os
import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

from fluxcal.drivers.ringbuffer import RingBuffer
from fluxcal.service.numerics.calib.model import ArrayCalibration

from .gate import Gate, GateResult

#: checks from which a replay forks the second process (fewer cost more to fork than they take: a check is
#: 10-20 ms, a fork of the replay's process a few ms to tens of ms)
MIN_CHECKS = 8


def gate_ahead_worth(n_samples: int, check_every_samples: int) -> bool:
    """Whether a replay of n_samples should work its gate checks out in a second process."""
    if not sys.platform.startswith("linux") or threading.active_count() != 1:
        return False                    # a fork copies no other thread: one holding a lock would hang the copy
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores >= 2 and n_samples >= MIN_CHECKS * max(int(check_every_samples), 1)


def _key(estimators: Sequence[Any], ring: RingBuffer) -> tuple:
    """The state a check is asked in: the samples the ring buffer took and holds, each estimator's samples."""
    return ring.total_appended, len(ring), tuple(int(est.n_samples_) for est in estimators)


class _SendingGate(Gate):
    """The second process's gate: works each check out and sends its results."""

    conn: Any

    def candidate(self, estimators: Sequence[Any], ring: RingBuffer) -> ArrayCalibration | None:
        cand = super().candidate(estimators, ring)
        self.conn.send(("candidate", _key(estimators, ring), cand, self.refusal, self.asked))
        return cand

    def evaluate(self, cal: ArrayCalibration, estimators: Sequence[Any], ring: RingBuffer) -> GateResult:
        result = super().evaluate(cal, estimators, ring)
        self.conn.send(("evaluate", _key(estimators, ring), result))
        return result


class _TakingGate(Gate):
    """The replay's gate: takes each check's results from the second process; works them out itself once they
    stop coming as asked (`fallback` says why)."""

    conn: Any
    taken: int
    fallback: str | None

    def candidate(self, estimators: Sequence[Any], ring: RingBuffer) -> ArrayCalibration | None:
        got = self._take("candidate", estimators, ring)
        if got is None:
            return super().candidate(estimators, ring)
        cand, self.refusal, self.asked = got
        for est in list(estimators)[:self.asked]:
            est.solve()                 # where the check solved them: a solve moves the anchor
        return cand

    def evaluate(self, cal: ArrayCalibration, estimators: Sequence[Any], ring: RingBuffer) -> GateResult:
        got = self._take("evaluate", estimators, ring)
        return super().evaluate(cal, estimators, ring) if got is None else got[0]

    def _take(self, kind: str, estimators: Sequence[Any], ring: RingBuffer) -> tuple | None:
        if self.conn is None:
            return None
        try:
            msg = self.conn.recv()
        except (EOFError, OSError) as e:
            msg = ("failed", f"the pipe closed ({type(e).__name__})")
        if msg[0] != kind or msg[1] != _key(estimators, ring):
            self.stop(msg[1] if msg[0] == "failed" else f"it sent {msg[0]!r} for another check")
            return None
        self.taken += 1
        return msg[2:]

    def stop(self, why: str | None) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None
            self.fallback = why


def _like(cls: type, gate: Gate, conn: Any) -> Any:
    """A gate of class `cls` with `gate`'s settings and state."""
    g = cls.__new__(cls)
    g.__dict__.update(gate.__dict__)
    g.conn, g.taken, g.fallback = conn, 0, None
    return g


def _second(pipeline: Any, run: Callable[[Any], None], conn: Any) -> None:
    """The second process: the pipeline's copy through `run`, each check sent; what stops it is sent too."""
    try:
        pipeline.gate = _like(_SendingGate, pipeline.gate, conn)
        pipeline.corrects = False       # the replay corrects; this copy only decides
        run(pipeline)
        conn.send(("end", None))
    except BaseException as e:          # (Ctrl-C too) the replay works out what did not come
        try:
            conn.send(("failed", f"{type(e).__name__}: {e}"))
        except (OSError, ValueError):
            pass
    finally:
        conn.close()
        os._exit(0)                     # no exit handlers, no flush of the replay's own output buffers (a copy)


class GateAhead:
    """The second process for one replay: `GateAhead(pipeline, run)` forks it (run(pipeline_copy) must apply
    the same blocks and commands the replay will) and gives the pipeline the gate that takes its results;
    `close()` ends it. `taken`: checks whose results came from it; `fallback`: why it stopped serving, if it did."""

    def __init__(self, pipeline: Any, run: Callable[[Any], None]) -> None:
        ctx = multiprocessing.get_context("fork")
        recv, send = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_second, args=(pipeline, run, send), daemon=True, name="fluxcal-gate-ahead")
        self._proc.start()
        send.close()
        self.gate = _like(_TakingGate, pipeline.gate, recv)
        pipeline.gate = self.gate

    @property
    def taken(self) -> int:
        return self.gate.taken

    @property
    def fallback(self) -> str | None:
        return self.gate.fallback

    def close(self) -> None:
        """End the second process (its pipe first: a copy blocked on a full pipe ends too)."""
        self.gate.stop(self.gate.fallback)
        self._proc.join(timeout=1.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=1.0)
