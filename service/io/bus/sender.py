"""The bus's sender thread: the only caller of `put()`, so a slow or frozen subscriber (Zenoh's BLOCK
congestion control) holds back the sender, never the service's reading, recording and processing.

Waking a thread costs tens of microseconds of CPU (two context switches and the GIL changing hands), more than
the put itself: with `gather` the messages of one turn of the service's loop wait until `release()`, and the
thread wakes once for them all, not once per message."""

from __future__ import annotations

import queue
import threading
import time
from collections import deque
from collections.abc import Iterable

import zenoh

#: a put that waits this long is counted as a stall (a subscriber that stopped taking data; zenoh closes its link
#: after [zenoh] stall_close_ms)
STALL_S = 0.1
#: the sender takes the messages waiting in batches of about this many bytes (a turn's messages of a block or a
#: few) under one lock; what waits beyond them can still be dropped, oldest first, when the backlog overflows
BATCH_BYTES = 64 << 10


class Sender:
    """An outbox of (stream name, publisher, payload) in order, bounded in bytes, and the thread that
    empties it. Beyond the bound the oldest waiting messages are dropped and counted (stats
    "send_dropped"); every message handed over counts as "published_<name>".

    The thread is woken by a token in a SimpleQueue (a wait and a wake-up in C, not threading.Condition's Python),
    at most one token while it is not sending; `flush()` waits on a Condition of the same lock."""

    def __init__(self, stats: dict[str, int], backlog_bytes: int, thread_name: str) -> None:
        self.stats = stats
        self.stats.setdefault("send_stalls", 0)
        self.stats.setdefault("send_stalled_ms", 0)
        self.last_stall_s = 0.0
        self._outbox: deque[tuple[str, zenoh.Publisher, bytes]] = deque()
        self._outbox_bytes = 0
        self._sending = False             # the thread holds a batch (it looks at the outbox again before it waits)
        self._woken = False               # a token waits for the thread
        self._flushers = 0                # flush() calls waiting for the thread to go idle
        self._lock = threading.Lock()
        self._idle = threading.Condition(self._lock)
        self._wake: queue.SimpleQueue[None] = queue.SimpleQueue()
        self._backlog_bytes = int(backlog_bytes)
        self.gather = False               # True: put() only queues, release() wakes the thread
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._send_loop, daemon=True, name=thread_name)
        self._thread.start()

    def put(self, name: str, pub: zenoh.Publisher, payload: bytes) -> None:
        """Hand a message to the sender thread (counted as published_<name>). If the backlog is over its
        bound (subscribers that cannot keep up), the oldest waiting messages are dropped and counted."""
        self.put_all(((name, pub, payload),))

    def put_all(self, messages: Iterable[tuple[str, zenoh.Publisher, bytes]]) -> None:
        """put() of several (name, publisher, payload) in order, taking the lock once."""
        stats, outbox = self.stats, self._outbox
        with self._lock:
            for message in messages:
                outbox.append(message)
                self._outbox_bytes += len(message[2])
                stats[f"published_{message[0]}"] += 1
            while self._outbox_bytes > self._backlog_bytes and len(outbox) > 1:
                _, _, old = outbox.popleft()
                self._outbox_bytes -= len(old)
                stats["send_dropped"] += 1
            wake = not (self.gather or self._sending or self._woken)
            self._woken |= wake
        if wake:
            self._wake.put(None)          # wake the sender only when idle

    def release(self) -> None:
        """Wake the thread for the messages gathered (at most once: none when it is busy or nothing waits).
        Gathered messages that nobody releases go anyway within the thread's half-second wait."""
        with self._lock:
            wake = bool(self._outbox) and not (self._sending or self._woken)
            self._woken |= wake
        if wake:
            self._wake.put(None)

    def _take(self) -> list[tuple[str, zenoh.Publisher, bytes]] | None:
        """The next batch of about BATCH_BYTES to put; [] when nothing waits (idle), None when stopped and empty."""
        with self._lock:
            self._woken = False
            if not self._outbox:
                self._sending = False
                if self._flushers:
                    self._idle.notify_all()       # flush() waits for this
                return None if self._stop.is_set() else []
            self._sending = True
            batch, size = [], 0
            while self._outbox and (not batch or size < BATCH_BYTES):
                batch.append(self._outbox.popleft())
                size += len(batch[-1][2])
            self._outbox_bytes -= size
            return batch

    def _send_loop(self) -> None:
        """put() every message in order, taking what waits in one go; ends when stopping and nothing waits."""
        while True:
            batch = self._take()
            if batch is None:
                return
            if not batch:
                try:
                    self._wake.get(timeout=0.5)
                except queue.Empty:
                    pass
                continue
            for _name, pub, payload in batch:
                self._put(pub, payload)

    def _put(self, pub: zenoh.Publisher, payload: bytes) -> None:
        t0 = time.monotonic()
        try:
            pub.put(payload)
        except zenoh.ZError:
            self.stats["publish_errors"] += 1
        waited = time.monotonic() - t0
        if waited >= STALL_S:         # a subscriber that takes nothing held every stream back this long
            self.stats["send_stalls"] += 1
            self.stats["send_stalled_ms"] += int(waited * 1000)
            self.last_stall_s = waited

    def flush(self, timeout: float = 5.0) -> bool:
        """Wait until every message handed over has been put (True) or `timeout` passed (False)."""
        deadline = time.monotonic() + timeout
        self._wake.put(None)              # gathered messages too
        with self._lock:
            self._flushers += 1
            try:
                while self._outbox or self._sending:
                    left = deadline - time.monotonic()
                    if left <= 0 or not self._thread.is_alive():
                        return not (self._outbox or self._sending)
                    self._idle.wait(min(left, 0.5))
            finally:
                self._flushers -= 1
        return True

    def stop(self, timeout: float = 2.0) -> None:
        """End the thread; what still waits then (a subscriber frozen past the flush) is counted as dropped."""
        self._stop.set()
        self._wake.put(None)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)
        with self._lock:
            self.stats["send_dropped"] += len(self._outbox)
            self._outbox.clear()
