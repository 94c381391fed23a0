"""A per-peer limit on connections that have not yet proven who they are, for the daemon's TCP sockets.

ZeroMQ accepts every TCP connection and drops one only when its handshake times out (``HANDSHAKE_IVL``),
so a peer that keeps reopening connections that never authenticate holds the daemon's descriptors: a good
client's connection then waits for a free one and misses its timeout (2 of 8 pings with 400 held
connections against 256 descriptors). :class:`ConnectionGuard` watches the socket's accepted and closed
connections (a ZeroMQ socket monitor, on its own thread) and keeps at most ``per_peer`` unproven
connections per peer address, and ``total`` in all: beyond them the peer's *oldest* unproven connection
is shut down, so that a fresh one (a good client's, handshaking in milliseconds) is not the one refused.
A connection is proven by the first message the daemon reads from it (:meth:`proven`, with the message's
source descriptor): only peers that passed CURVE and gave the token get that far.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
from collections import OrderedDict

import zmq

log = logging.getLogger("sssphase.daemon")

#: Unproven connections kept per peer address, and in all.
PER_PEER = 16
TOTAL = 128


class ConnectionGuard:
    """Limit unproven connections of ``sock`` (a bound TCP socket) per peer; call :meth:`close` before the
    socket closes."""

    def __init__(self, sock: zmq.Socket, *, per_peer: int = PER_PEER, total: int = TOTAL) -> None:
        self.per_peer, self.total = per_peer, total
        # fd -> (peer host, peer port): oldest first
        self.pending: OrderedDict[int, tuple[str, int]] = OrderedDict()
        self.lock = threading.Lock()
        self.evicted = 0
        self.monitor = sock.get_monitor_socket(zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CLOSED)
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._watch, name="sss-connection-guard", daemon=True)
        self.thread.start()

    def proven(self, fd: int | None) -> None:
        """The connection on descriptor ``fd`` delivered an authenticated message: no longer limited."""
        if fd is not None and fd >= 0 and self.pending:
            with self.lock:
                self.pending.pop(fd, None)

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(2)
        with contextlib.suppress(zmq.ZMQError):
            self.monitor.close(linger=0)

    def _watch(self) -> None:
        from zmq.utils.monitor import recv_monitor_message

        poller = zmq.Poller()
        poller.register(self.monitor, zmq.POLLIN)
        while not self.stopping.is_set():
            try:
                if not poller.poll(200):
                    continue
                event = recv_monitor_message(self.monitor)
            except zmq.ZMQError:
                return  # the socket (and its monitor) closed
            fd = int(event["value"])
            if event["event"] == zmq.EVENT_ACCEPTED:
                self._accepted(fd)
            else:
                with self.lock:
                    self.pending.pop(fd, None)

    def _accepted(self, fd: int) -> None:
        peer = _peer(fd)
        if peer is None:
            return
        with self.lock:
            self.pending.pop(fd, None)
            self.pending[fd] = peer
            same = [f for f, p in self.pending.items() if p[0] == peer[0]]
            victims = same[: max(0, len(same) - self.per_peer)]
            rest = [f for f in self.pending if f not in victims]
            victims += rest[: max(0, len(rest) - self.total)]
            for f in victims:
                self._shut(f, self.pending.pop(f))

    def _shut(self, fd: int, peer: tuple[str, int]) -> None:
        """Shut the connection down (ZeroMQ sees it end and closes its descriptor), if ``fd`` still is it."""
        try:
            dup = socket.socket(fileno=os.dup(fd))  # closing the duplicate leaves ZeroMQ's descriptor open
        except OSError:
            return
        try:
            if dup.getpeername()[:2] == peer:  # not a descriptor reused for another connection since
                dup.shutdown(socket.SHUT_RDWR)
                self.evicted += 1
                if self.evicted in (1, 100, 10_000):
                    log.warning("%s keeps more than %d connections that do not authenticate: closing its oldest "
                                "(%d so far)", peer[0], self.per_peer, self.evicted)
        except OSError:
            pass
        finally:
            dup.close()


def _peer(fd: int) -> tuple[str, int] | None:
    """The (host, port) of the TCP connection on descriptor ``fd``, or None (closed already, not TCP)."""
    try:
        dup = os.dup(fd)
    except OSError:
        return None
    try:
        s = socket.socket(fileno=dup)
        try:
            name = s.getpeername()
        finally:
            s.close()
    except OSError:
        return None
    return (str(name[0]), int(name[1])) if isinstance(name, tuple) else None


__all__ = ["PER_PEER", "TOTAL", "ConnectionGuard"]
