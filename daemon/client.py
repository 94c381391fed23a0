"""Client side of the daemon protocol: requests on a DEALER socket, frames from the job's PUSH stream.

While frames arrive a thread heartbeats the job on its own socket; if the stream goes quiet the client pings
the daemon and raises :class:`DaemonUnavailable` when the daemon does not answer (killed, crashed).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from sssphase_core.errors import SssError
from sssphase_daemon import protocol, security


class DaemonError(SssError):
    """The daemon refused a request or a job failed (``code`` is the protocol error code)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class DaemonUnavailable(SssError):
    """No daemon answers at the endpoint."""


class NoClientKey(DaemonUnavailable):
    """The local daemon admits CURVE clients only, and its key folder holds no client key (a server-only folder):
    this machine's own commands cannot ask it anything."""


@dataclass
class ReceivedFrame:
    name: str
    seq: int
    data: np.ndarray
    header: dict[str, Any]


class DaemonClient:
    """Talk to one daemon. ``DaemonClient.from_state()`` finds the local one via its state file."""

    def __init__(self, endpoint: str, token: str, *, curve_dir: Path | None = None, timeout_s: float = 10.0,
                 heartbeat_s: float = 1.0, max_message_bytes: int = protocol.DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self.endpoint, self.token = endpoint, token
        self.connection: Path | None = None  # the $SSS_DAEMON folder this client came from (a daemon elsewhere)
        self.timeout_s, self.heartbeat_s, self.max_bytes = timeout_s, heartbeat_s, max_message_bytes
        self.curve_dir = curve_dir
        self.curve = security.client_keys(curve_dir) if curve_dir is not None else None
        self.ctx = zmq.Context.instance()
        self.ids = itertools.count(1)
        self.sock = self._socket(zmq.DEALER)
        self.sock.connect(endpoint)

    @classmethod
    def from_connection(cls, folder: Path | str, **kwargs: Any) -> DaemonClient:
        """A client of the daemon on another machine that ``folder`` (``$SSS_DAEMON``) names: its endpoint and token,
        over CURVE with the keys there (:func:`~sssphase_daemon.security.read_connection`)."""
        connection = security.read_connection(folder)
        client = cls(connection.endpoint, connection.token, curve_dir=connection.keys, **kwargs)
        client.connection = connection.keys
        return client

    @classmethod
    def from_state(cls, state_file: Path | None = None, **kwargs: Any) -> DaemonClient:
        state = security.read_state(state_file)
        if state is None:
            raise DaemonUnavailable("no daemon is running (start one with `sss daemon start`)")
        curve = Path(state.curve_dir) if state.curve_dir else None
        if curve is not None and not security.has_client_key(curve):
            raise NoClientKey(f"the daemon (pid {state.pid}) on {state.endpoint} admits CURVE clients only, and its key "
                              f"folder {curve} holds no client key for this machine's own commands")
        return cls(state.endpoint, state.token, curve_dir=curve, **kwargs)

    def _socket(self, kind: int) -> zmq.Socket:
        sock = self.ctx.socket(kind)
        sock.linger = 0
        sock.ipv6 = True  # a daemon on [::1] (or a stream it binds there) is reachable; IPv4 still works
        if self.curve is not None:
            sock.curve_publickey, sock.curve_secretkey, sock.curve_serverkey = self.curve
        return sock

    def close(self) -> None:
        self.sock.close(linger=0)

    def __enter__(self) -> DaemonClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- requests --------------------------------------------------------------------------
    def send(self, op: str, *, send_timeout_s: float | None = None, **args: Any) -> int:
        """Queue a request; returns its id. Never blocks for longer than ``send_timeout_s`` (default: the
        client's timeout): a DEALER whose connection is not up (a CURVE handshake refused, a daemon
        restarting) would otherwise block forever."""
        rid = next(self.ids)
        wait = self.timeout_s if send_timeout_s is None else send_timeout_s
        message = protocol.request(rid, op, self.token, **args)
        try:
            if not self.sock.poll(int(wait * 1000) + 1, zmq.POLLOUT):
                raise zmq.Again()
            self.sock.send(message, flags=zmq.NOBLOCK)
        except zmq.Again:
            raise DaemonUnavailable(f"no connection to the daemon at {self.endpoint} within {wait:g} s (an off-loopback "
                                    "daemon needs its CURVE keys: --curve-dir)") from None
        return rid

    def _wait(self, rid: int, timeout_s: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            if not self.sock.poll(int(min(left, 1.0) * 1000) + 1):  # each second: has the daemon's process exited?
                if left > 1.0 and self._exited_pid() is not None:
                    break
                continue
            msg = protocol.unpack(self.sock.recv(), self.max_bytes)
            if isinstance(msg, dict) and msg.get("id") == rid:
                return msg
        raise DaemonUnavailable(self._gone_words(f"did not answer within {timeout_s:g} s"))

    def call(self, op: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        """Send a request and return its result; raise :class:`DaemonError` on an error reply."""
        wait = self.timeout_s if timeout_s is None else timeout_s
        msg = self._wait(self.send(op, send_timeout_s=wait, **args), wait)
        if not msg.get("ok"):
            err = msg.get("error") or {}
            code = str(err.get("code", "?"))
            if code == protocol.UNAUTHENTICATED and self.connection is not None:  # (not "read it from the state file")
                raise DaemonError(code, f"the daemon at {self.endpoint} refused the token in {self.connection}/"
                                  f"{security.CONNECTION_FILE} (it restarted since, or it is another daemon): write the "
                                  "folder again with `sss daemon connection` on its machine")
            raise DaemonError(code, f"daemon: {err.get('message', 'unknown error')}")
        return msg["result"]

    def ping(self, timeout_s: float = 2.0) -> bool:
        try:
            self.call("ping", timeout_s=timeout_s)
            return True
        except DaemonUnavailable:
            return False

    # ---- frame streams ---------------------------------------------------------------------
    def capture(self, rig: str, frames: list[dict[str, Any]], deadline_s: float | None = None) -> Iterator[ReceivedFrame]:
        """Run a capture job and yield its frames in order (see :meth:`receive`); ``deadline_s``: the longest
        one device call may take before the daemon fails the job naming the device (its default: 600 s)."""
        extra = {} if deadline_s is None else {"deadline_s": deadline_s}
        return self.receive(self.call("capture", rig=rig, frames=frames, **extra))

    def stream(self, rig: str, count: int, deadline_s: float | None = None) -> Iterator[ReceivedFrame]:
        extra = {} if deadline_s is None else {"deadline_s": deadline_s}
        return self.receive(self.call("stream", rig=rig, count=count, **extra))

    def _check_job(self, job_id: str) -> None:
        """The stream went quiet: raise if the daemon is gone or the job ended without telling us."""
        try:
            state = self.call("job", timeout_s=2.0, job=job_id)
        except DaemonUnavailable:
            raise DaemonUnavailable(self._gone_words()) from None
        except DaemonError as exc:
            raise DaemonError(exc.code, f"the capture job vanished from the daemon ({exc})") from None
        if state["state"] != "running":
            error = state.get("error")
            if isinstance(error, dict) and error.get("message"):  # the daemon's own words (a stalled device named)
                raise DaemonError(str(error.get("code", protocol.INTERNAL)), str(error["message"]))
            raise DaemonError(protocol.INTERNAL, f"the job ended ({state['state']}) but its stream did not finish")

    def _exited_pid(self) -> int | None:
        """The pid of this client's daemon when its state file names a process that is gone (killed, or a device
        plugin that called abort() took it down), else None (running, remote, or nothing to tell)."""
        if not Path("/proc/self").exists():  # (is_daemon_process reads /proc: without it, nothing can be told)
            return None
        try:
            state = security.read_state()
        except Exception:  # noqa: BLE001  (a damaged state file: nothing more can be told)
            return None
        if state is not None and state.endpoint == self.endpoint and not security.is_daemon_process(state.pid):
            return state.pid
        return None

    def _gone_words(self, quiet: str = "stopped answering mid-stream") -> str:
        """What to say of a daemon that went ``quiet``: that it exited (:meth:`_exited_pid`), else that it went quiet."""
        pid = self._exited_pid()
        if pid is not None:
            return (f"the daemon (pid {pid}) at {self.endpoint} has exited (killed, or crashed by a device "
                    f"plugin: its log is {security.log_dir() / 'daemon.log'})")
        return f"the daemon at {self.endpoint} {quiet}"

    def _heartbeat(self, job_id: str, stop: threading.Event) -> None:
        """Heartbeat the job from a thread with its own socket, so slow frame processing never starves it."""
        sock = self._socket(zmq.DEALER)
        sock.connect(self.endpoint)
        try:
            while not stop.wait(self.heartbeat_s):
                try:  # a beat that cannot go out now is dropped: the next one follows
                    sock.send(protocol.request(0, "heartbeat", self.token, job=job_id), flags=zmq.NOBLOCK)
                except zmq.Again:
                    pass
                while sock.poll(0):
                    sock.recv()
        finally:
            sock.close(linger=0)

    def receive(self, job: dict[str, Any]) -> Iterator[ReceivedFrame]:
        """Yield the job's frames (heartbeating meanwhile); raise on a failed job, a gap or a dead daemon."""
        pull = self._socket(zmq.PULL)
        pull.rcvhwm = 16
        if self.curve is None:  # the stream takes only peers that know the token
            pull.plain_username, pull.plain_password = security.STREAM_USER.encode(), self.token.encode()
        pull.connect(security.reachable_stream(job["endpoint"], self.endpoint))  # a remote client: not 0.0.0.0
        expected, finished = 0, False
        last_data = time.monotonic()
        stop = threading.Event()
        beat = threading.Thread(target=self._heartbeat, args=(job["job"], stop), daemon=True)
        beat.start()
        try:
            while True:
                try:  # receive first, poll only when nothing is queued (one syscall less per frame)
                    parts = pull.recv_multipart(flags=zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    if not pull.poll(int(self.heartbeat_s * 1000)):
                        if self._exited_pid() is not None:  # said at once, not after timeout_s of silence
                            raise DaemonUnavailable(self._gone_words()) from None
                        if time.monotonic() - last_data > self.timeout_s:
                            self._check_job(job["job"])
                            last_data = time.monotonic()
                    continue
                last_data = time.monotonic()
                header = protocol.unpack(parts[0].bytes, self.max_bytes)
                if header.get("type") == "end":
                    finished = True
                    try:  # acknowledges the end: the daemon closes the stream
                        self.send("cancel", send_timeout_s=1.0, job=job["job"])
                    except DaemonUnavailable:
                        pass
                    if not header.get("ok"):
                        err = header.get("error") or {}
                        raise DaemonError(str(err.get("code")), f"capture failed after {header.get('frames')} frames: "
                                                                f"{err.get('message')}")
                    if header.get("frames") != expected:
                        raise DaemonError(protocol.INTERNAL, f"stream ended after {expected} of {header.get('frames')} frames")
                    return
                if header.get("seq") != expected:
                    raise DaemonError(protocol.INTERNAL, f"frame {expected} lost (got {header.get('seq')})")
                expected += 1
                yield ReceivedFrame(header["name"], header["seq"], protocol.decode_frame(header, parts[1].buffer), header)
        finally:
            stop.set()
            beat.join()
            if not finished:
                try:
                    self.send("cancel", send_timeout_s=1.0, job=job["job"])
                except (zmq.ZMQError, DaemonUnavailable):
                    pass
            pull.close(linger=0)


def _last_line(path: str, start: int) -> str:
    """The last non-empty line the daemon wrote to its log from byte ``start`` (its reason for exiting)."""
    try:
        with open(path, "rb") as f:
            f.seek(start)
            lines = [ln.strip() for ln in f.read().decode(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "no log"
    return lines[-1][:300] if lines else "nothing logged"


def spawn_daemon(*, endpoint: str | None = None, extra_args: tuple[str, ...] = (), env: dict[str, str] | None = None,
                 log_path: Path | None = None, wait_s: float = 20.0) -> subprocess.Popen:
    """Start ``python -m sssphase_daemon`` detached and wait until it answers; returns the process."""
    state_file = security.state_path()
    cmd = [sys.executable, "-m", "sssphase_daemon", *(["--endpoint", endpoint] if endpoint else []), *extra_args]
    log = open(log_path or security.log_dir() / "daemon.log", "ab")  # noqa: SIM115 - handed to the child
    start = log.tell()
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            start_new_session=True, env={**os.environ, **(env or {})})
    log.close()
    deadline = time.monotonic() + wait_s
    try:
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise DaemonUnavailable(f"the daemon exited with status {proc.returncode}: {_last_line(log.name, start)} "
                                        f"(see {log.name})")
            state = security.read_state(state_file)
            if state is not None and state.pid == proc.pid and state.curve_dir and \
                    not security.has_client_key(Path(state.curve_dir)):  # a server-only key folder: nothing here can
                return proc  # ask it; it has bound its sockets (the state file is written after)
            if state is not None and state.pid == proc.pid:
                with DaemonClient(state.endpoint, state.token,
                                  curve_dir=Path(state.curve_dir) if state.curve_dir else None) as client:
                    if client.ping(timeout_s=1.0):
                        return proc
            time.sleep(0.05)
    except BaseException:  # Ctrl-C while it starts: a detached daemon nobody would stop was left running
        _stop(proc)
        raise
    proc.kill()
    raise DaemonUnavailable(f"the daemon did not start within {wait_s:g} s (see {log.name})")


def _stop(proc: subprocess.Popen) -> None:
    """Terminate a daemon this process started (killed if it does not exit within 10 s)."""
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


#: A daemon started by :func:`local_client` exits after this many seconds without a rig, a job or a client.
LOCAL_DAEMON_IDLE_S = 600


@contextlib.contextmanager
def local_client(timeout_s: float = 10.0, *, on_start: Callable[[int], None] | None = None,
                 on_stop: Callable[[int], None] | None = None,
                 on_left: Callable[[int], None] | None = None) -> Iterator[DaemonClient]:
    """A client of the running local daemon, or of one started here (sim rig) and stopped on exit, unless
    another client has a rig open or a job running on it then (a second `sss capture` that found it).

    ``on_start(pid)`` / ``on_stop(pid)`` / ``on_left(pid)`` are told when a daemon had to be started / was
    stopped / was left running for another client.
    """
    remote = remote_client(timeout_s)
    if remote is not None:  # a daemon on another machine: used, never started or stopped from here
        with remote:
            yield remote
        return
    started = None
    with start_lock():  # clients started together: one starts the daemon, the others find it running
        client = running_client(timeout_s)
        if client is None:  # it ends itself once unused: an interrupted or killed capture cannot leave it for ever
            started = spawn_daemon(extra_args=("--exit-when-idle", str(LOCAL_DAEMON_IDLE_S)))
            try:
                if on_start is not None:
                    on_start(started.pid)
                client = DaemonClient.from_state(timeout_s=timeout_s)
            except BaseException:  # (an interrupt here left the daemon this started running)
                _stop(started)
                raise
    try:
        with client:
            yield client
    finally:
        if started is not None and _used_by_others(client):
            if on_left is not None:
                on_left(started.pid)
        elif started is not None:
            gone = started.poll() is not None  # (killed meanwhile: "stopped the local daemon" was said of it)
            _stop(started)
            if on_stop is not None and not gone:
                on_stop(started.pid)


def remote_client(timeout_s: float = 10.0) -> DaemonClient | None:
    """A client of the daemon on another machine that ``$SSS_DAEMON`` names, answering; None when it is unset.
    Raises :class:`DaemonUnavailable` when that daemon does not answer within 5 s (never a fall back to this
    machine's: `sss devices` listed the local devices as if they were the remote rig's)."""
    remote = os.environ.get(security.ENV_DAEMON)
    if not remote:
        return None
    client = DaemonClient.from_connection(remote, timeout_s=timeout_s)
    if not client.ping(timeout_s=min(timeout_s, 5.0)):
        client.close()
        raise DaemonUnavailable(f"the daemon at {client.endpoint} ({security.ENV_DAEMON}={remote}) did not answer "
                                "within 5 s: is it running there, and this machine's key authorised by it?")
    return client


def running_client(timeout_s: float = 10.0, *, remote_ok: bool = False) -> DaemonClient | None:
    """A client of the local daemon when one runs and answers, else None; with ``remote_ok``, of the remote one
    ``$SSS_DAEMON`` names instead when set (:func:`remote_client`: raises when it does not answer). `sss daemon
    start/stop/status` act on this machine's daemon only: with the remote one unreachable, `stop` found no rig in
    use and stopped the local daemon under its capture."""
    if remote_ok and (remote := remote_client(timeout_s)) is not None:
        return remote
    try:
        client = DaemonClient.from_state(timeout_s=timeout_s)
    except DaemonUnavailable:
        return None
    if client.ping(timeout_s=2.0):
        return client
    client.close()
    return None


@contextlib.contextmanager
def start_lock() -> Iterator[None]:
    """An exclusive lock on the runtime dir itself (flock on the directory: no file is left behind) while a
    client looks for the local daemon and starts one: four `sss capture` started at once with no daemon found
    none and each started its own, and all but one failed ("another daemon is serving"); two `sss daemon start`
    with different endpoints both started theirs."""
    import fcntl

    fd = os.open(security.runtime_dir(), os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # (closing releases the lock)


def rigs_in_use(status: dict[str, Any]) -> list[dict[str, Any]]:
    """The open rigs of a daemon's ``status`` that a client still uses: its client heard from within the client
    timeout (a rig whose client is gone is closed by the daemon later, and holds nothing up)."""
    return [r for r in status.get("rigs", []) if r.get("client_alive", True)]


def _used_by_others(client: DaemonClient) -> bool:
    """Whether the daemon has an open rig of a live client or a running job (this client closes its own rigs first)."""
    try:
        with DaemonClient(client.endpoint, client.token, curve_dir=client.curve_dir, timeout_s=2.0) as probe:
            status = probe.call("status", timeout_s=2.0)
    except (DaemonUnavailable, DaemonError, zmq.ZMQError):
        return False
    return bool(rigs_in_use(status)) or any(j.get("state") == "running" for j in status.get("jobs", []))
