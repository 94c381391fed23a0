"""Where the daemon listens, who may talk to it, and the state file clients find it by.

* Local endpoints (``ipc://`` or ``tcp://127.0.0.1``/``localhost``/``[::1]``) need no keys: the runtime
  directory is private (mode 0700) and every request carries a random token from the state file
  (mode 0600), so other local users cannot drive the devices.
* Any other bind address requires ZeroMQ CURVE: the server's secret key and a folder of authorised
  client public keys (``sss daemon keys`` writes both), checked by pyzmq's authenticator.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import stat
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from sssphase_core.errors import SssError

LOCAL_HOSTS = {"127.0.0.1", "localhost", "::1"}
#: ``tcp://HOST:PORT`` and nothing else: a host name, an IPv4 address, ``*`` or a bracketed IPv6 address, and
#: a port or ``*``. ZeroMQ reads some other strings its own way (``tcp://0.0.0.0%1@127.0.0.1:5609`` binds
#: every interface while a URL parser sees 127.0.0.1), so nothing else is accepted.
_TCP_ENDPOINT = re.compile(r"tcp://(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<host>\*|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?)):(?P<port>\*|[0-9]{1,5})")
SERVER_CERT, CLIENT_CERT, AUTHORIZED = "server", "client", "authorized_clients"


class PrivateDirError(SssError, PermissionError):
    """A folder for the daemon's socket, token or keys that others could read or write."""


def _private(path: Path) -> bool:
    """Whether ``path`` is owned by this user and closed to everyone else."""
    st = path.stat()
    return st.st_uid == os.getuid() and not st.st_mode & 0o077


def _private_dir(path: Path, holds: str = "the daemon's socket and token",
                 or_else: str = " or point SSS_RUNTIME_DIR at a private folder") -> Path:
    blocking = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
    if blocking is not None:  # was only "[Errno 17] File exists"
        raise PrivateDirError(f"{path} must be a folder (it holds {holds}), but {blocking} is a file")
    path.mkdir(parents=True, exist_ok=True, mode=0o700)
    if not _private(path):
        raise PrivateDirError(f"{path} must be owned by you with mode 0700 (it holds {holds}): "
                              f"run 'chmod 700 {path}'{or_else}")
    return path


def runtime_dir() -> Path:
    """``$SSS_RUNTIME_DIR``, else ``$XDG_RUNTIME_DIR/sssphase``, else a per-user folder in the temp dir."""
    if os.environ.get("SSS_RUNTIME_DIR"):
        given = Path(os.environ["SSS_RUNTIME_DIR"])
        if not given.is_absolute():  # each process would find it under its own working folder: daemons unseen
            raise PrivateDirError(f"SSS_RUNTIME_DIR must be an absolute path, got {given}: a relative one names "
                                  "another folder from every working folder")
        return _private_dir(given)
    if os.environ.get("XDG_RUNTIME_DIR") and Path(os.environ["XDG_RUNTIME_DIR"]).is_absolute():  # (XDG: ignore a relative one)
        return _private_dir(Path(os.environ["XDG_RUNTIME_DIR"]) / "sssphase")
    return _private_dir(Path(tempfile.gettempdir()) / f"sssphase-{os.getuid()}")


def log_dir() -> Path:
    """Where a detached daemon writes its log: ``$SSS_LOG_DIR``, else ``$XDG_STATE_HOME/sssphase``, else
    ``~/.local/state/sssphase``. Not the runtime folder, which holds only live sockets and the state file
    and is left empty when the daemon stops."""
    if os.environ.get("SSS_LOG_DIR"):
        given = Path(os.environ["SSS_LOG_DIR"])
        if not given.is_absolute():
            raise PrivateDirError(f"SSS_LOG_DIR must be an absolute path, got {given}: a relative one names "
                                  "another folder from every working folder")
        return _private_dir(given, "the daemon's log", " or point SSS_LOG_DIR at a private folder")
    state_home = os.environ.get("XDG_STATE_HOME", "")
    state_home = state_home if Path(state_home).is_absolute() else str(Path.home() / ".local" / "state")
    return _private_dir(Path(state_home) / "sssphase")


def default_endpoint(transport: str = "ipc") -> str:
    return f"ipc://{runtime_dir() / 'control.sock'}" if transport == "ipc" else "tcp://127.0.0.1:5591"


def tcp_parts(endpoint: str) -> tuple[str, str] | None:
    """(host, port) of a well-formed ``tcp://HOST:PORT`` endpoint (IPv6 hosts without brackets), else None."""
    m = _TCP_ENDPOINT.fullmatch(endpoint)
    return None if m is None else (m["v6"] or m["host"], m["port"])


def host_of(endpoint: str) -> str:
    parts = tcp_parts(endpoint)
    return parts[0] if parts else ""


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` (a name or an address, as written) means this machine only: localhost, 127.x, ::1."""
    import ipaddress

    if host.lower() in LOCAL_HOSTS or host.lower().startswith("localhost."):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def host_problem(host: str) -> str | None:
    """Why ``host`` (``--host``) is not a host name or an address, else None."""
    if host in WILDCARD_HOSTS or tcp_parts(f"tcp://{'[' + host + ']' if ':' in host else host}:1") is None:
        return f"--host {host!r} is not a host name or an address (the one the client reaches this machine by)"
    return None


def machine_name() -> str | None:
    """A name or address other machines may reach this one by: its fully qualified name, else (a machine whose
    name is localhost) the address of the interface its default route leaves through; None when neither is known
    (no network)."""
    import socket

    name = socket.getfqdn()
    if name and not is_loopback_host(name):
        return name
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))  # (a UDP connect sends nothing: it only picks the outgoing interface)
            address = probe.getsockname()[0]
    except OSError:
        return None
    return None if is_loopback_host(address) or address == "0.0.0.0" else address


def is_ipv6(endpoint: str) -> bool:
    """A tcp endpoint with a bracketed IPv6 host (its socket needs ZeroMQ's IPV6 option)."""
    return endpoint.startswith("tcp://[")


def is_local(endpoint: str) -> bool:
    """True for ipc:// socket files and well-formed loopback tcp endpoints (no CURVE needed). An abstract
    ipc socket (``ipc://@name``) has no file permissions, so any local user could connect: not local."""
    if endpoint.startswith("ipc://"):
        return not endpoint[6:].startswith("@")
    return host_of(endpoint) in LOCAL_HOSTS


def check_bound_locally(bound: str) -> None:
    """Refuse a socket bound without CURVE whose actual address (ZeroMQ's ``LAST_ENDPOINT``) is not
    loopback or an ipc file: the last line of defence if an endpoint string was read two ways."""
    host = host_of(bound)
    if bound.startswith("tcp://") and not (host == "::1" or host.startswith("127.")):
        raise PermissionError(f"{bound} is not a loopback address: without CURVE keys the daemon listens on "
                              "loopback or ipc only (`sss daemon keys`, --curve-dir)")


IPC_PATH_MAX = 107  # bytes in a Unix socket path (sun_path holds 108 with its NUL)


def endpoint_problem(endpoint: str) -> str | None:
    """What makes an endpoint unusable before binding it (ZeroMQ takes port 99999 as 99999 - 65536, and
    a missing folder or a bad port only shows as a traceback in the daemon's log), or None."""
    if endpoint.startswith("tcp://"):
        parts = tcp_parts(endpoint)
        if parts is None and _TCP_ENDPOINT.fullmatch(endpoint + ":1"):
            return f"{endpoint}: give a port (tcp://HOST:PORT, 1 to 65535, or * for any)"
        if parts is None and _TCP_ENDPOINT.fullmatch(endpoint.rsplit(":", 1)[0] + ":1"):  # the host is fine, the port not
            return f"{endpoint}: the port must be a number from 1 to 65535 (or * for any)"
        if parts is None:
            return (f"{endpoint}: write tcp://HOST:PORT with a host name, an IPv4 address, * or an [IPv6] address "
                    "and a port from 1 to 65535 or * (no interface suffix, user, path or query)")
        if parts[1] != "*" and not 1 <= int(parts[1]) <= 65535:
            return f"{endpoint}: the port must be a number from 1 to 65535, got {int(parts[1])}"
    elif endpoint.startswith("ipc://") and not endpoint[6:].startswith("@"):
        if not endpoint[6:] or endpoint[6:] == "*" or not Path(endpoint[6:]).is_absolute():
            return (f"{endpoint}: give an absolute socket path, ipc:///PATH (a relative one is relative to the "
                    "daemon's folder, where clients elsewhere cannot find it)")
        if any(c in endpoint for c in "\n\r\0"):
            return f"{endpoint!r}: a socket path cannot hold a line break or NUL"
        folder = Path(endpoint[6:]).parent
        if not folder.is_dir():
            return f"{endpoint}: the folder {folder} does not exist"
        longest = max(len(os.fsencode(endpoint[6:])), len(os.fsencode(stream_endpoint(endpoint, "9" * 6 + "-" + "f" * 8))) - 6)
        if longest > IPC_PATH_MAX:  # each job's frame stream is a socket beside the control socket
            return (f"{endpoint}: a socket path in {folder} would be {longest} bytes, and Linux allows {IPC_PATH_MAX} "
                    "(job streams add 'stream-<job>.sock' there): choose a shorter folder")
    elif not endpoint.startswith("ipc://"):  # was called "not loopback/ipc", with advice about keys
        return f"{endpoint}: the daemon listens on tcp://HOST:PORT or ipc://PATH endpoints only"
    return None


def endpoint_collision(control: str, preview: str | None, state_file: Path | None) -> str | None:
    """Why the control endpoint, the preview endpoint and the state file would land on one another, or None
    (binding a second socket on a path unlinks the first; ``./x`` and ``x`` are one path)."""
    def where(endpoint: str | None) -> str | None:
        if endpoint and endpoint.startswith("ipc://") and not endpoint[6:].startswith("@"):
            return os.path.abspath(endpoint[6:])
        return endpoint

    if preview and where(preview) == where(control):
        return f"--preview {preview} is the control endpoint {control}: give the preview its own endpoint"
    for name, endpoint in (("control endpoint", control), ("preview", preview)):
        if state_file is not None and where(endpoint) == os.path.abspath(state_file):
            return f"the {name} {endpoint} is the state file {state_file}: give each its own path"
    return None


def stream_endpoint(control: str, job: str) -> str:
    """A fresh endpoint for one job's frame stream on the same transport/interface as ``control``."""
    if control.startswith("ipc://"):
        return f"ipc://{Path(control[6:]).parent / f'stream-{job}.sock'}"
    host = host_of(control) or "127.0.0.1"
    return f"tcp://{'[' + host + ']' if ':' in host else host}:*"


#: Hosts a daemon binds to listen on every interface: no address a client elsewhere can connect to.
WILDCARD_HOSTS = ("*", "0.0.0.0", "::", "0:0:0:0:0:0:0:0")


def reachable_stream(stream: str, control: str) -> str:
    """A job's stream endpoint as a client that reached the daemon at ``control`` connects to it: a stream bound on
    every interface (``tcp://0.0.0.0:PORT``, which on the client's machine means the client itself) takes the
    control endpoint's host. Other endpoints are returned as they are."""
    parts, host = tcp_parts(stream), host_of(control)
    if parts is None or parts[0] not in WILDCARD_HOSTS or not host or host in WILDCARD_HOSTS:
        return stream
    return f"tcp://{'[' + host + ']' if ':' in host else host}:{parts[1]}"


STREAM_USER = "sss-stream"  # ZeroMQ PLAIN user of job frame streams; the password is the daemon's token


def new_token() -> str:
    return secrets.token_urlsafe(32)


@dataclass(frozen=True)
class DaemonState:
    """What a client needs to find and address a running daemon."""

    endpoint: str
    token: str
    pid: int
    version: str
    started: float
    preview: str = ""
    curve_dir: str = ""


def state_path() -> Path:
    return runtime_dir() / "daemon.json"


def write_state(state: DaemonState, path: Path | None = None) -> Path:
    """Atomically write the state file, readable by the owner only."""
    from sssphase_core.store.files import atomic_path

    path = path or state_path()
    with atomic_path(path) as tmp, os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as f:
        json.dump(asdict(state), f)
    return path


def _lock_path(state: Path) -> Path:
    return state.with_name(state.name + ".lock")


def hold_state_lock(path: Path) -> Any:
    """Lock the file beside the state file ``path`` (``daemon.json.lock``) until :func:`release_state_lock` -- the
    daemon's life (a process that dies releases it too): two daemons started together each found no state file,
    both served, and the file named only one of them; the other ran invisibly, holding devices. The lock held is on
    the file at that path (one its holder removed on its way out, and another daemon then created anew, is not).
    -> the open lock file; PermissionError when another daemon holds it."""
    import fcntl

    lock_path = _lock_path(path)
    for _ in range(20):
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
        lock = os.fdopen(fd, "r+")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            running = read_state(path)
            who = (f"another daemon (pid {running.pid}) is serving {running.endpoint}" if running is not None
                   else "another daemon is starting")
            raise PermissionError(f"{who} (its state file: {path}): stop it first") from None
        try:
            if os.stat(lock_path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino:
                return lock
        except FileNotFoundError:
            pass
        lock.close()  # removed by the daemon that held it, as it exited: lock the one at the path now
    raise PermissionError(f"cannot lock {lock_path}: daemons keep starting and stopping there")


def release_state_lock(lock: Any, path: Path) -> None:
    """Remove the lock file of the state file ``path`` and release ``lock`` (from :func:`hold_state_lock`): a stopped
    daemon leaves its runtime folder empty."""
    try:
        _lock_path(path).unlink(missing_ok=True)
    finally:
        lock.close()


def state_file_problem(path: Path) -> str | None:
    """Why the daemon must not write (and at exit delete) its state file at ``path``, or None: something that
    is not a daemon's state file sits there, or its folder is missing."""
    if path.is_symlink() or (path.exists() and not path.is_file()):
        return f"{path} exists and is not a file: refusing to replace it (choose another --state-file)"
    if path.exists() and path.stat().st_size and read_state(path) is None:
        return f"{path} exists and is not a daemon state file: refusing to replace it (choose another --state-file)"
    if not path.parent.is_dir():
        return f"--state-file {path}: the folder {path.parent} does not exist"
    return None


def read_state(path: Path | None = None) -> DaemonState | None:
    path = path or state_path()
    try:
        return DaemonState(**json.loads(path.read_text()))
    except (OSError, ValueError, TypeError):
        return None


def curve_dir() -> Path:
    base = os.environ.get("SSS_CONFIG_DIR") or os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "sssphase" / "curve"


def generate_keys(directory: Path | None = None, *, overwrite: bool = False) -> Path:
    """Create server and client CURVE key pairs and authorise the client (``sss daemon keys``)."""
    import zmq.auth

    directory = _private_dir(directory or curve_dir(), "CURVE keys", "")
    if (directory / f"{SERVER_CERT}.key_secret").exists() and not overwrite:
        raise FileExistsError(f"keys already exist in {directory} (pass --overwrite to replace them)")
    authorized = _private_dir(directory / AUTHORIZED, "the authorised clients' keys", "")
    written = [directory / f"{n}{ext}" for n in (SERVER_CERT, CLIENT_CERT) for ext in (".key", ".key_secret")]
    for path in (*written, authorized / f"{CLIENT_CERT}.key"):  # a link there is replaced, never written through
        path.unlink(missing_ok=True)  # (the secret key went into whatever file the link named)
    for name in (SERVER_CERT, CLIENT_CERT):
        zmq.auth.create_certificates(directory, name)
    for secret in directory.glob("*.key_secret"):
        secret.chmod(0o600)
    (authorized / f"{CLIENT_CERT}.key").write_bytes((directory / f"{CLIENT_CERT}.key").read_bytes())
    return directory


def check_key_dir(directory: Path) -> None:
    """Refuse a CURVE key folder (or its authorised-clients folder) that other users could read or write:
    they could take the secret key or authorise their own."""
    for path in (p for p in (directory, directory / AUTHORIZED) if p.is_dir()):
        if not _private(path):
            raise PrivateDirError(f"{path} must be owned by you with mode 0700 (it holds CURVE keys): "
                                  f"run 'chmod -R go-rwx {directory}'")


def check_key_folder(directory: Path) -> None:
    """Refuse a key folder that is missing or not a folder (its key files were each called unreadable)."""
    if not Path(directory).is_dir():
        raise KeyFileError(f"--curve-dir {directory}: no such folder: make the keys with `sss daemon keys --dir "
                           f"{directory}`")


def server_keys(directory: Path) -> tuple[bytes, bytes]:
    check_key_folder(directory)
    check_key_dir(directory)
    public, secret = _certificate(directory / f"{SERVER_CERT}.key_secret")
    if secret is None:
        raise KeyFileError(f"{directory / f'{SERVER_CERT}.key_secret'} holds no server secret key: make the keys again "
                           "(`sss daemon keys`)")
    authorized = directory / AUTHORIZED
    if not (authorized.is_dir() and any(authorized.glob("*.key"))):  # every client would wait out its timeout
        raise KeyFileError(f"{authorized} holds no client's public key (*.key), so the daemon would refuse every "
                           f"connection: copy each client's client.key there (`sss daemon keys` authorises the "
                           "client key it makes there)")
    return public, secret


def has_client_key(directory: Path) -> bool:
    """Whether a CURVE key folder holds a client's secret key: a daemon's own folder may hold only the server's keys
    and the authorised clients' public ones (each client's secret key stays on its machine)."""
    return (Path(directory) / f"{CLIENT_CERT}.key_secret").exists()


def client_keys(directory: Path) -> tuple[bytes, bytes, bytes]:
    """(client public, client secret, server public) for a CURVE client."""
    check_key_folder(directory)
    check_key_dir(directory)
    public, secret = _certificate(directory / f"{CLIENT_CERT}.key_secret")
    server_public, _ = _certificate(directory / f"{SERVER_CERT}.key")
    if secret is None:
        raise KeyFileError(f"{directory / f'{CLIENT_CERT}.key_secret'} holds no client secret key: make the keys again "
                           "(`sss daemon keys`)")
    return public, secret, server_public


#: What ``$SSS_DAEMON`` names: a folder of a daemon on another machine (``sss daemon connection`` writes it there, to be
#: copied here): its endpoint and token in ``connection.json`` and the CURVE keys this client connects with.
ENV_DAEMON = "SSS_DAEMON"
CONNECTION_FILE = "connection.json"


@dataclass
class Connection:
    """A remote daemon as a client reaches it: its control ``endpoint``, ``token`` and the folder of the client's
    CURVE keys (``keys``: client.key_secret, and server.key, the daemon's public key)."""

    endpoint: str
    token: str
    keys: Path


def write_connection(folder: Path, state: DaemonState, host: str) -> Path:
    """Write the folder a client on another machine connects with (``sss daemon connection``): ``connection.json``
    (the endpoint, with ``host`` for a daemon bound on every interface, and the token) and the client's CURVE keys
    from the daemon's key folder when it has them, private (0700, files 0600). Refused before anything is written
    when the daemon has no CURVE keys or no tcp endpoint, ``host`` is not a host, or the folder exists."""
    import shutil

    if not state.curve_dir:
        raise KeyFileError(f"the daemon at {state.endpoint} has no CURVE keys: start it off loopback with them (`sss "
                           "daemon keys`, then `sss daemon start --endpoint tcp://0.0.0.0:5609 --curve-dir DIR`)")
    parts = tcp_parts(state.endpoint)
    if parts is None:
        raise KeyFileError(f"the daemon serves {state.endpoint}, which no other machine reaches: start it on a tcp "
                           "endpoint (`sss daemon start --endpoint tcp://0.0.0.0:5609 --curve-dir "
                           f"{state.curve_dir}`)")
    endpoint = state.endpoint
    if parts[0] in WILDCARD_HOSTS:
        problem = host_problem(host)
        if problem:
            raise KeyFileError(problem)
        endpoint = f"tcp://{'[' + host + ']' if ':' in host else host}:{parts[1]}"
    if folder.exists() or folder.is_symlink():
        raise FileExistsError(f"{folder} exists: give a new folder for the connection (it holds a secret key)")
    keys = Path(state.curve_dir)
    folder = _private_dir(folder, "a daemon's connection and a secret key", "")
    names = [f"{SERVER_CERT}.key"] + [f"{CLIENT_CERT}.key_secret", f"{CLIENT_CERT}.key"] * has_client_key(keys)
    for name in names:  # (a server-only key folder: the client puts its own key pair there)
        shutil.copyfile(keys / name, folder / name)
        (folder / name).chmod(0o600)
    path = folder / CONNECTION_FILE
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump({"format": "sssphase-daemon-connection", "endpoint": endpoint, "token": state.token}, f)
    return folder


def read_connection(folder: Path | str, *, keys: bool = True) -> Connection:
    """The remote daemon ``$SSS_DAEMON`` names, checked: a private folder with ``connection.json`` (a tcp endpoint
    and a token) and (``keys``) the client's key pair; one line naming what is wrong otherwise."""
    folder = Path(folder)
    where = f"{ENV_DAEMON}={folder}"
    if not (folder / CONNECTION_FILE).is_file():
        raise KeyFileError(f"{where}: no {CONNECTION_FILE} there: give the folder `sss daemon connection --out DIR` "
                           "wrote on the daemon's machine (copied here)")
    check_key_dir(folder)
    try:
        data = json.loads((folder / CONNECTION_FILE).read_text())
    except (OSError, ValueError) as exc:
        raise KeyFileError(f"{where}: {CONNECTION_FILE} does not read as JSON ({exc})") from None
    endpoint, token = (data.get(k) if isinstance(data, dict) else None for k in ("endpoint", "token"))
    parts = tcp_parts(endpoint) if isinstance(endpoint, str) else None
    port = parts[1] if parts else ""
    if not (parts and port.isdigit() and 0 < int(port) < 65536 and isinstance(token, str) and token):  # (not "*")
        raise KeyFileError(f"{where}: {CONNECTION_FILE} must hold a tcp endpoint and the daemon's token: write it "
                           "again with `sss daemon connection`")
    if keys and not has_client_key(folder):
        raise KeyFileError(f"{where}: no {CLIENT_CERT}.key_secret there: put this machine's client key pair in it "
                           f"(`sss daemon keys` makes one), and its {CLIENT_CERT}.key into the daemon's {AUTHORIZED}")
    return Connection(endpoint, token, folder)


class KeyFileError(SssError, ValueError):
    """A CURVE key file that is missing, damaged or of the wrong kind."""


def _certificate(path: Path) -> tuple[bytes, bytes | None]:
    """``zmq.auth.load_certificate`` with one clear error for a damaged or missing file (it was an internal error)."""
    import zmq.auth

    try:
        return zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        raise KeyFileError(f"{path}: not a readable CURVE key file ({str(exc).splitlines()[0][:100]}): make the keys "
                           "again (`sss daemon keys`) or copy them intact") from None


def process_start_time(pid: int) -> float | None:
    """When process ``pid`` started (seconds since the epoch, from /proc; None where that cannot be told)."""
    try:
        stat_line = Path(f"/proc/{int(pid)}/stat").read_text()
        ticks = int(stat_line[stat_line.rindex(")") + 2:].split()[19])  # field 22, starttime (after the command's name)
        boot = next(float(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                    if line.startswith("btime "))
        return boot + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return None


def is_daemon_process(pid: int, started: float | None = None) -> bool:
    """Whether ``pid`` runs ``python -m sssphase_daemon`` (read from /proc; False where that cannot be
    told), so that a stale state file never makes us signal an unrelated process that reused the pid; with
    ``started`` (the state file's start time), also that the process started before it (another daemon that reused
    the pid of one killed started after)."""
    try:
        argv = Path(f"/proc/{int(pid)}/cmdline").read_bytes().split(b"\0")
    except (OSError, ValueError):
        return False
    if not any(arg == b"sssphase_daemon" or arg.endswith(b"/sssphase_daemon") or b"sssphase_daemon/__main__" in arg
               for arg in argv):
        return False
    begun = process_start_time(pid) if started is not None else None
    return begun is None or begun <= float(started) + 2.0  # (the clock ticks' rounding)


def ipc_path_problem(endpoint: str) -> str | None:
    """Why the daemon must not bind ``endpoint``'s ipc path (a file that is not a socket sits there), or None."""
    if not endpoint.startswith("ipc://") or endpoint[6:].startswith("@"):
        return None
    path = Path(endpoint[6:])
    if path.exists() and not stat.S_ISSOCK(path.stat().st_mode):
        return f"{path} exists and is not a socket: refusing to replace it (choose another --endpoint)"
    if path.exists() and (pid := socket_listener(path)) is not None:
        who = f"pid {pid}" if pid > 0 else "a process"
        return (f"{who} is listening on {path} (a daemon whose state file is gone? binding would take its socket and "
                "leave it running unreachable): " + (f"`sss daemon stop` ends it, or `kill {pid}`" if pid > 0 else "stop it")
                + "; or choose another --endpoint")
    return None


def socket_listener(path: Path | str) -> int | None:
    """The pid of the process accepting connections on the Unix socket ``path`` (0 when the kernel does not say),
    or None when none does. ZeroMQ drops a peer that never completes its handshake, so probing it is harmless."""
    import socket
    import struct

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(str(path))
        except OSError:  # refused (a dead daemon's socket file), or not ours to open
            return None
        try:  # Linux: the listener's credentials (pid, uid, gid)
            return int(struct.unpack("3i", probe.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))[0])
        except (AttributeError, OSError):
            return 0


def remove_ipc_socket(endpoint: str) -> None:
    """Remove the socket file of an ipc endpoint; never any other kind of file."""
    if not endpoint.startswith("ipc://") or endpoint[6:].startswith("@"):
        return
    path = Path(endpoint[6:])
    try:
        if stat.S_ISSOCK(path.lstat().st_mode):
            path.unlink()
    except FileNotFoundError:
        pass
