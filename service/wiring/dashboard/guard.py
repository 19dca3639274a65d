"""The dashboard's HTTP server under idle and slow clients: connections wait without a thread until their request
starts, a bounded pool of workers serves them one request each, and nothing is held without end.

    waiting    accepted, nothing sent yet: no thread, at most `max_waiting` (the oldest closed to make room), each
               closed after `idle_s`
    reading    a worker reads its request: within `request_s` in all, else the connection is shut (a client that
               sends a byte at a time cannot hold a worker)
    served     one request per connection (Connection: close): no worker waits on a kept-alive socket

One thread per connection and no timeout let 1,007 idle sockets under the common 1,024-descriptor limit make every
real request time out while they lasted, and nothing was said. Now what the guard closes is counted (`stats`: in
/api/units as "connections") and said on stderr the first time of each kind.
"""

from __future__ import annotations

import selectors
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

#: accepted connections that sent nothing yet, at most; beyond it the oldest are closed
MAX_WAITING = 64
#: workers serving requests at once
WORKERS = 16
#: a connection that sends nothing for this long is closed
IDLE_S = 10.0
#: a request (its line, headers and body) must arrive within this long, in all
REQUEST_S = 10.0


class Guard:
    """Accepts and watches the connections of `server` (a socketserver TCPServer whose `finish_request` and
    `shutdown_request` serve and close one), in one thread of its own; see the module docstring."""

    def __init__(self, server: Any, say: Callable[[str], None] | None, *, max_waiting: int = MAX_WAITING,
                 workers: int = WORKERS, idle_s: float = IDLE_S, request_s: float = REQUEST_S) -> None:
        self.server, self.say = server, say
        self.max_waiting, self.idle_s, self.request_s = max_waiting, idle_s, request_s
        self._waiting: OrderedDict[socket.socket, tuple[Any, float]] = OrderedDict()
        self._reading: dict[socket.socket, float] = {}
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="fluxcal-dashboard-worker")
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._stop = threading.Event()
        self._said: set[str] = set()
        self.counts = {"accepted": 0, "served": 0, "idle_closed": 0, "evicted": 0, "slow_closed": 0}

    def stats(self) -> dict[str, int]:
        """What /api/units says of the connections: open now, the cap, and what was closed and why."""
        with self._lock:
            return {**self.counts, "waiting": len(self._waiting), "reading": len(self._reading),
                    "max_waiting": self.max_waiting}

    # --- the guard's thread ----------------------------------------------------------------------------

    def run(self, poll_s: float = 0.2) -> None:
        listener = self.server.socket
        listener.setblocking(False)
        self._sel.register(listener, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        try:
            while not self._stop.is_set():
                for key, _ in self._sel.select(poll_s):
                    if key.data == "listen":
                        self._accept(listener)
                    elif key.data == "conn":
                        self._start(key.fileobj)
                self._sweep(time.monotonic())
        finally:
            for sock in list(self._waiting):
                self._close_waiting(sock)
            self._pool.shutdown(wait=True, cancel_futures=False)
            self._sel.close()

    def _accept(self, listener: socket.socket) -> None:
        for _ in range(self.max_waiting):             # what arrived, then back to the others
            try:
                sock, addr = listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as e:                        # out of descriptors: the oldest waiting go first
                self._note("accept", f"a connection could not be accepted ({e.strerror or e}); the oldest idle "
                                     f"ones are closed to make room")
                self._evict(max(1, len(self._waiting) // 4))
                return
            sock.setblocking(True)
            if len(self._waiting) >= self.max_waiting:
                self._evict(1)
            with self._lock:
                self.counts["accepted"] += 1
                self._waiting[sock] = (addr, time.monotonic())
            self._sel.register(sock, selectors.EVENT_READ, "conn")

    def _evict(self, n: int) -> None:
        with self._lock:
            for sock in list(self._waiting)[:n]:
                self._close_waiting(sock)
                self.counts["evicted"] += 1
        self._note("evicted", f"more than {self.max_waiting} connections waited without sending a request: the "
                              f"oldest are closed to make room (counted in /api/units, connections)")

    def _close_waiting(self, sock: socket.socket) -> None:
        self._waiting.pop(sock, None)
        try:
            self._sel.unregister(sock)
        except (KeyError, ValueError):
            pass
        try:
            sock.close()
        except OSError:
            pass

    def _start(self, sock: socket.socket) -> None:
        """Its request began: off to a worker (the socket leaves the selector)."""
        with self._lock:
            addr, _ = self._waiting.pop(sock, (None, 0.0))
            self._reading[sock] = time.monotonic()
        self._sel.unregister(sock)
        self._pool.submit(self._serve, sock, addr)

    def _sweep(self, now: float) -> None:
        with self._lock:
            idle = [s for s, (_, since) in self._waiting.items() if now - since > self.idle_s]
            slow = [s for s, since in self._reading.items() if now - since > self.request_s]
            for s in idle:
                self._close_waiting(s)
                self.counts["idle_closed"] += 1
            for s in slow:
                self._reading.pop(s, None)
                self.counts["slow_closed"] += 1
        for s in slow:
            try:
                s.shutdown(socket.SHUT_RDWR)        # the worker's read ends: it closes the connection
            except OSError:
                pass
        if idle:
            self._note("idle", f"connections that sent nothing for {self.idle_s:g} s are closed (counted in "
                               f"/api/units, connections)")
        if slow:
            self._note("slow", f"a request not sent whole within {self.request_s:g} s is cut off (counted in "
                               f"/api/units, connections)")

    # --- the workers ----------------------------------------------------------------------------------

    def _serve(self, sock: socket.socket, addr: Any) -> None:
        try:
            sock.settimeout(self.request_s)
            self.server.finish_request(sock, addr)
        except Exception:  # noqa: BLE001 - one connection's end is no server's end
            pass
        finally:
            with self._lock:
                self._reading.pop(sock, None)
                self.counts["served"] += 1
            self.server.shutdown_request(sock)

    def request_read(self, sock: socket.socket) -> None:
        """The worker has read its request whole: from now on it is being answered, not waited for."""
        with self._lock:
            self._reading.pop(sock, None)

    # --- saying and stopping --------------------------------------------------------------------------------

    def _note(self, kind: str, text: str) -> None:
        if kind not in self._said and self.say is not None:
            self._said.add(kind)
            self.say(text)

    def stop(self) -> None:
        self._stop.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    def close(self) -> None:
        for s in (self._wake_r, self._wake_w):
            s.close()
