"""A per-peer limit on connections that have not yet proven who they are, for the daemon's TCP sockets.

ZeroMQ accepts every TCP connection and drops one only when its handshake times out (``HANDSHAKE_IVL``),
so a peer that keeps reopening connections that never authenticate holds the daemon's descriptors: a good
client's connection then waits for a free one and misses its timeout (2 of 8 pings with 400 held
connections against 256 descriptors). :class:`ConnectionGuard` watches the socket's accepted and closed
connections (a ZeroMQ socket monitor, on its own thread) and keeps at most ``per_peer`` unproven
connections per peer address, and ``total`` in all: beyond them the peer's oldest unproven connection
that never sent a byte (then its oldest) is shut down, so that a good client's (which sends ZeroMQ's
greeting as it connects, and handshakes in milliseconds) is not the one refused.
A connection is proven by the first message the daemon reads from it (:meth:`proven`, with the message's
source descriptor): only peers that passed CURVE and gave the token get that far.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections.abc import Iterator

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
        self.pending: dict[int, tuple[str, int]] = {}  # fd -> (peer host, peer port), oldest first
        self.by_peer: dict[str, dict[int, int]] = {}  # peer host -> {fd: port}, oldest first
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
                self._forget(fd)

    def _forget(self, fd: int) -> tuple[str, int] | None:
        peer = self.pending.pop(fd, None)
        if peer is not None:
            fds = self.by_peer.get(peer[0], {})
            fds.pop(fd, None)
            if not fds:
                self.by_peer.pop(peer[0], None)
        return peer

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
                    self._forget(fd)

    def _accepted(self, fd: int) -> None:
        """Track a new connection; over a limit, close half the limit's worth of the peer's (or all peers')
        unproven connections at once, silent ones first (one scan per batch, not per connection: an attacker
        in its own process opens thousands a second)."""
        peer = _peer(fd)
        if peer is None:
            return
        with self.lock:
            self._forget(fd)
            self.pending[fd] = peer
            fds = self.by_peer.setdefault(peer[0], {})
            fds[fd] = peer[1]
            victims: list[int] = []
            if len(fds) > self.per_peer:
                victims = _silent_first(list(fds))[: len(fds) - self.per_peer // 2]
            elif len(self.pending) > self.total:
                victims = _silent_first(list(self.pending))[: len(self.pending) - self.total // 2]
            for f in victims:
                if (known := self._forget(f)) is not None:
                    self._shut(f, known)

    def _shut(self, fd: int, peer: tuple[str, int]) -> None:
        """Shut the connection down (ZeroMQ sees it end and closes its descriptor), if ``fd`` still is it."""
        with _borrowed(fd) as s:
            if s is not None and _address(s) == peer:  # not a descriptor reused for another connection since
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)
                    self.evicted += 1
                    if self.evicted in (1, 100, 10_000):
                        log.warning("%s keeps more than %d connections that do not authenticate: closing its oldest "
                                    "(%d so far)", peer[0], self.per_peer, self.evicted)


@contextlib.contextmanager
def _borrowed(fd: int) -> Iterator[socket.socket | None]:
    """ZeroMQ's descriptor ``fd`` as a socket object, without duplicating it (a daemon out of descriptors,
    which is when the guard must act, cannot ``dup``) and without closing it; None if it is no socket."""
    try:
        s = socket.socket(fileno=fd)
    except OSError:
        yield None
        return
    try:
        yield s
    finally:
        s.detach()


def _address(s: socket.socket) -> tuple[str, int] | None:
    try:
        name = s.getpeername()
    except OSError:
        return None
    return (str(name[0]), int(name[1])) if isinstance(name, tuple) else None


#: ``struct tcp_info``'s ``tcpi_bytes_received`` (Linux >= 4.1): a u64 at this offset.
_BYTES_RECEIVED = slice(128, 136)


def _bytes_received(fd: int) -> int | None:
    """How many bytes the peer on ``fd`` has sent (Linux ``TCP_INFO``), or None where unknown."""
    with _borrowed(fd) as s:
        if s is None:
            return None
        try:
            info = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 232)
        except (OSError, AttributeError):
            return None
        return int.from_bytes(info[_BYTES_RECEIVED], "little") if len(info) >= _BYTES_RECEIVED.stop else None


def _silent_first(fds: list[int]) -> list[int]:
    """``fds`` (oldest first) reordered so that connections whose peer never sent a byte come first: a ZeroMQ
    client sends its greeting as it connects, so a silent connection is the one to close."""
    silent = [f for f in fds if _bytes_received(f) == 0]
    return silent + [f for f in fds if f not in silent]


def _peer(fd: int) -> tuple[str, int] | None:
    """The (host, port) of the TCP connection on descriptor ``fd``, or None (closed already, not TCP)."""
    with _borrowed(fd) as s:
        return None if s is None else _address(s)


__all__ = ["PER_PEER", "TOTAL", "ConnectionGuard"]
