"""The lossless frame stream (daemon side): one PUSH socket per job, multipart header + zero-copy buffer.

Backpressure comes from ZeroMQ's high-water mark: when the client reads slowly the send waits. The
wait polls, so a cancelled job or a client that stopped heartbeating (it died) ends the job instead
of stalling the daemon. The optional preview is a PUB socket that drops frames when nobody keeps up.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import zmq

from sssphase_daemon import protocol

SEND_HWM = 8  # frames queued per stream before the sender waits (8 x 12 MB at 1080p 16-bit RGB)
POLL_MS = 100
#: How long a connecting peer has to complete its ZeroMQ handshake (CURVE, or PLAIN with the token).
HANDSHAKE_MS = 5000


class ClientGone(Exception):
    """The job's client stopped heartbeating or cancelled; the stream is abandoned."""


def configure_curve_server(sock: zmq.Socket, curve: tuple[bytes, bytes] | None) -> None:
    if curve is not None:
        sock.curve_server = True
        sock.curve_publickey, sock.curve_secretkey = curve


def bind(sock: zmq.Socket, endpoint: str, curve: tuple[bytes, bytes] | None) -> str:
    """Bind ``sock`` (IPv6 on for a bracketed IPv6 host); returns the bound address. Without CURVE the bound
    address must be loopback or an ipc file, else the socket is closed and PermissionError raised."""
    from sssphase_daemon.security import check_bound_locally, is_ipv6

    if is_ipv6(endpoint):
        sock.ipv6 = True
    # a peer that never completes its handshake is dropped after this (ZeroMQ's default: 30 s), on every
    # socket the daemon binds: the control socket, each job's frame stream and the preview
    sock.setsockopt(zmq.HANDSHAKE_IVL, HANDSHAKE_MS)
    sock.bind(endpoint)
    bound = sock.getsockopt_string(zmq.LAST_ENDPOINT)
    if curve is None:
        try:
            check_bound_locally(bound)
        except PermissionError:
            sock.close(linger=0)
            raise
    return bound


class FrameSender:
    """Binds a PUSH socket for one job; ``send`` blocks under backpressure while ``alive()`` holds."""

    def __init__(self, ctx: zmq.Context, endpoint: str, curve: tuple[bytes, bytes] | None = None, *,
                 plain: bool = False) -> None:
        """``curve``: the daemon's CURVE keys; else ``plain``: peers must log in with the daemon's token
        (ZeroMQ PLAIN, checked by the daemon's ZAP authenticator)."""
        self.sock = ctx.socket(zmq.PUSH)
        self.sock.sndhwm = SEND_HWM
        self.sock.linger = 0
        configure_curve_server(self.sock, curve)
        if curve is None and plain:
            self.sock.plain_server = True
        self.endpoint = bind(self.sock, endpoint, curve)

    def _send(self, parts: list, alive: Callable[[], bool]) -> None:
        while True:
            try:  # try first: polling only when the queue is full saves a syscall per frame
                self.sock.send_multipart(parts, flags=zmq.NOBLOCK, copy=False)
                return
            except zmq.Again:
                pass
            if not alive():
                raise ClientGone("client gone or job cancelled")
            self.sock.poll(POLL_MS, zmq.POLLOUT)

    def send_frame(self, header: bytes, data: np.ndarray, alive: Callable[[], bool]) -> None:
        self._send([header, np.ascontiguousarray(data)], alive)

    def send_end(self, header: bytes, alive: Callable[[], bool]) -> None:
        self._send([header], alive)

    def close(self, linger_s: float = 0.0) -> None:
        """Close; with ``linger_s`` queued frames still reach a live client in the background (over the
        established connection: the ipc socket file itself is removed now, so none is left behind)."""
        self.sock.close(linger=int(linger_s * 1000))
        from sssphase_daemon.security import remove_ipc_socket

        remove_ipc_socket(self.endpoint)


class Preview:
    """Best-effort live preview (PUB): a 4x-subsampled copy of each frame, dropped when busy. Subscribers
    authenticate like job streams: CURVE, else ZeroMQ PLAIN with the daemon's token (``token``)."""

    def __init__(self, ctx: zmq.Context, endpoint: str, curve: tuple[bytes, bytes] | None = None, *,
                 token: str | None = None) -> None:
        self.sock = ctx.socket(zmq.PUB)
        self.sock.sndhwm = 2
        self.sock.linger = 0
        configure_curve_server(self.sock, curve)
        if curve is None and token is not None:
            self.sock.plain_server = True
        self.endpoint = bind(self.sock, endpoint, curve)
        self.lock = threading.Lock()

    def publish(self, job: str, seq: int, name: str, data: np.ndarray) -> None:
        small = np.ascontiguousarray(data[::4, ::4])
        header = protocol.frame_header(job, seq, name, small, 0, 1.0, {})
        with self.lock:
            try:
                self.sock.send_multipart([b"preview", header, small], flags=zmq.NOBLOCK)
            except zmq.Again:
                pass

    def close(self) -> None:
        self.sock.close(linger=0)
        from sssphase_daemon.security import remove_ipc_socket

        remove_ipc_socket(self.endpoint)
