"""Serve the view: the bind rule (loopback unless asked), the token, uvicorn on a socket bound first (so
that ``--port 0`` gives a free port the URL can name)."""

from __future__ import annotations

import ipaddress
import secrets
import socket
import ssl
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sssphase_core.errors import InputError
from sssphase_view.app import ViewState, build_app
from sssphase_view.live import LiveRig

#: Seconds a connection may take to send a whole request line and headers (its first request, or the next on a
#: kept-alive connection). uvicorn has no such limit: connections that never finished a request were held until
#: the client closed them, and ~20,000 of them (the file-descriptor limit) kept the page from being served.
REQUEST_HEAD_S = 10.0


def _head_deadline_protocol() -> type:
    """uvicorn's h11 protocol with :data:`REQUEST_HEAD_S`: the connection is closed when no request head has
    arrived by then (uvicorn 0.54's hooks: ``handle_events`` makes ``scope`` for each request head, including a
    websocket upgrade's, before handing the connection over; ``on_response_complete`` ends a request)."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class HeadDeadline(H11Protocol):
        _deadline = None

        def _arm(self) -> None:
            self._disarm()
            self._deadline = self.loop.call_later(REQUEST_HEAD_S, self._expire)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _expire(self) -> None:
            if not self.transport.is_closing():
                self.transport.close()

        def connection_made(self, transport):  # type: ignore[no-untyped-def]
            super().connection_made(transport)
            self._arm()

        def connection_lost(self, exc):  # type: ignore[no-untyped-def]
            self._disarm()
            super().connection_lost(exc)

        def handle_events(self) -> None:
            before = self.scope
            super().handle_events()
            if self.scope is not before:  # a request head arrived (a websocket's too: handed over, not timed)
                self._disarm()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm()  # the next request's head, on a kept-alive connection

    return HeadDeadline


def allowed_hosts(host: str, allow_remote: bool) -> list[str] | None:
    """The ``Host:`` names the view answers (None: any): on loopback only its own address and localhost, so that a
    page of another site whose name resolves to 127.0.0.1 (DNS rebinding) is refused; with ``--allow-remote`` off
    loopback, any. A loopback host keeps the check with ``--allow-remote`` too (there it opens nothing, and it
    dropped the guard)."""
    from sssphase_daemon.security import is_loopback_host

    return sorted({host, "127.0.0.1", "localhost"}) if not allow_remote or is_loopback_host(host) else None


def check_host(host: str, allow_remote: bool, tls: bool = False) -> None:
    """Loopback only unless ``allow_remote``, and off loopback only over TLS (``tls``): the token guards every route,
    and in plain HTTP it would cross the network readable, in every request and the page's URL."""
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        raise InputError(f"--host must be an IP address (or localhost), got {host!r}") from None
    if not loopback and not allow_remote:
        raise InputError(f"--host {host} is not loopback: anyone on that network could reach the rig; pass "
                         "--allow-remote (with --tls-cert and --tls-key) to serve it there anyway (the token is still "
                         "required)")
    if not loopback and not tls:
        raise InputError(f"--host {host} is not loopback: the page and its token would cross the network in plain "
                         "HTTP; give --tls-cert and --tls-key (a certificate for this machine's name and its key, PEM) "
                         "to serve it over HTTPS")


class _Encrypted(Exception):
    """The TLS key asked for its passphrase (raised from OpenSSL's password callback)."""


def check_tls(cert: Path, key: Path, ask: Callable[[str], str] | None = None) -> str | None:
    """Check a PEM certificate (chain) and its key before serving (not at the first connection): one line when they
    do not load or belong together. A key encrypted with a passphrase is asked for it once, with ``ask(prompt)``
    (OpenSSL asked on the terminal for every load: twice); without ``ask`` it is refused. Returns the passphrase
    (None: the key has none), which the server loads the key with again."""
    for given, option in ((cert, "--tls-cert"), (key, "--tls-key")):
        if not Path(given).is_file():
            raise InputError(f"{option} {given}: {'not a file' if Path(given).exists() else 'no such file'}")
    if Path(key).stat().st_mode & 0o077:
        warnings.warn(f"--tls-key {key} can be read by other users of this machine: chmod 600 it", stacklevel=2)

    def load(password: Callable[[], str] | str) -> None:
        ssl.create_default_context(ssl.Purpose.CLIENT_AUTH).load_cert_chain(cert, key, password=password)

    def refuse() -> str:
        raise _Encrypted

    try:
        load(refuse)
        return None
    except _Encrypted:
        pass
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise InputError(f"--tls-cert {cert} and --tls-key {key} do not load as a PEM certificate and its key "
                         f"({getattr(exc, 'reason', None) or exc})") from None
    if ask is None:
        raise InputError(f"--tls-key {key} is encrypted with a passphrase, and there is no terminal to ask it on: give "
                         "a key without one, readable by you only (openssl pkey -in KEY -out PLAIN.pem; chmod 600 "
                         "PLAIN.pem)")
    passphrase = ask(f"passphrase of {key}: ")
    try:
        load(passphrase)
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise InputError(f"--tls-key {key} does not open with that passphrase, or is not --tls-cert's key "
                         f"({getattr(exc, 'reason', None) or exc})") from None
    return passphrase


def check_inputs(sessions: Path | None, checkpoint: Path | None) -> None:
    """Refuse, before serving, a ``--sessions`` folder that is not one and a ``--checkpoint`` that does not load
    (they served an empty list, or failed at the first relight)."""
    if sessions is not None and not Path(sessions).is_dir():
        what = "a file, not a folder of sessions" if Path(sessions).exists() else "no such folder"
        raise InputError(f"--sessions {sessions}: {what}")
    if checkpoint is not None:
        from sssphase_core.learning.training import load_checkpoint

        load_checkpoint(checkpoint, mmap=True)  # a run folder resolved, its tensors mapped, not read


def serve(*, host: str = "127.0.0.1", port: int = 0, sessions: Path | None = None, checkpoint: Path | None = None,
          out: Path = Path("view_out"), rig: LiveRig | None = None, allow_remote: bool = False,
          calibration: Path | None = None, on_ready: Callable[[str], None] | None = None,
          tls: tuple[Path, Path] | None = None) -> None:
    """Run the view until interrupted; ``on_ready(url)`` gets the URL with its token once it listens. A
    ``calibration`` file (the rig's camera-projector calibration) is read before serving; ``tls`` (certificate,
    key: PEM files) serves it over HTTPS, which a view off loopback needs."""
    import uvicorn

    check_host(host, allow_remote, tls is not None)
    passphrase = None
    if tls is not None:
        import getpass

        passphrase = check_tls(*tls, ask=getpass.getpass if sys.stdin.isatty() else None)
    check_inputs(sessions, checkpoint)
    stereo = None
    if calibration is not None:
        from sssphase_core.processing.triangulation import read_calibration

        stereo = read_calibration(calibration)  # a file that does not read is refused now, not at the first depth map
    try:
        Path(out).mkdir(parents=True, exist_ok=True)  # refused now, not at the first relight
    except OSError as exc:
        raise InputError(f"--out {out}: {exc.strerror}") from None
    state = ViewState(token=secrets.token_urlsafe(24), out=Path(out), sessions=sessions, checkpoint=checkpoint,
                      live=rig or LiveRig(), calibration=stereo, calibration_path=calibration)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(("127.0.0.1" if host == "localhost" else host, port))
        sock.listen(128)  # connections from now on wait for the server (the URL is printed before it runs)
    except OSError as exc:
        sock.close()
        raise InputError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
    bound = sock.getsockname()[1]
    named = host  # listening on every address: the URL names the machine as others reach it (not "localhost")
    if host in ("0.0.0.0", "::"):
        from sssphase_daemon.security import machine_name

        named = machine_name() or host
    shown = f"[{named}]" if ":" in named else named
    url = f"{'https' if tls else 'http'}://{shown}:{bound}/?token={state.token}"
    # On loopback the page is reached by its own address or as localhost only (sssphase_view.app.Guard)
    hosts = allowed_hosts(host, allow_remote)
    config = uvicorn.Config(build_app(state, hosts=hosts), log_level="warning", ws="websockets-sansio", lifespan="on",
                            http=_head_deadline_protocol(), ssl_certfile=tls[0] if tls else None,
                            ssl_keyfile=tls[1] if tls else None, ssl_keyfile_password=passphrase)
    class Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: Any) -> None:
            state.stop_work()  # at once: uvicorn waits for the requests under way, a relight's among them
            super().handle_exit(sig, frame)

    server = Server(config)
    if on_ready is not None:
        on_ready(url)
    server.run(sockets=[sock])
