"""Acquisition daemon and devices: ``sss devices``, ``plugins``, ``daemon start|stop|status|keys`` and
``bench daemon``. Heavy modules (zmq, numpy) load inside commands."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

if TYPE_CHECKING:
    from sssphase_daemon.security import DaemonState

console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)

def _client(timeout_s: float = 10.0, *, remote_ok: bool = False):
    """A client for the running local daemon (with ``remote_ok``, the one $SSS_DAEMON names), or None when none
    answers."""
    from sssphase_daemon.client import running_client

    return running_client(timeout_s, remote_ok=remote_ok)


def _say_local_only() -> None:
    """With $SSS_DAEMON set, say that `sss daemon start/stop/status` act on this machine's daemon, not that one."""
    from sssphase_daemon import security

    if remote := os.environ.get(security.ENV_DAEMON):
        Console(stderr=True, soft_wrap=True).print(
            f"note: {security.ENV_DAEMON}={escape(remote)} names a daemon on another machine, which `sss devices`, "
            "`sss capture` and `sss view` use; `sss daemon start/stop/status` act on this machine's own", highlight=False)


def _keyless() -> DaemonState | None:
    """The local daemon's state when it runs with a server-only CURVE key folder (no client key here to ask it)."""
    from sssphase_daemon import security

    state = security.read_state()
    if state is None or not state.curve_dir or security.has_client_key(Path(state.curve_dir)):
        return None
    return state if security.is_daemon_process(state.pid, state.started) else None


def _orphan() -> int | None:
    """The pid of a sssphase daemon serving the default ipc socket without a state file, else None."""
    from sssphase_daemon import security

    path = security.default_endpoint().removeprefix("ipc://")
    pid = security.socket_listener(path) if os.path.exists(path) else None
    return pid if pid and security.read_state() is None and security.is_daemon_process(pid) else None


def _unanswering() -> int | None:
    """The pid of the daemon the state file names when it runs but did not answer (stopped, or hung), else None."""
    from sssphase_daemon import security

    state = security.read_state()
    return state.pid if state is not None and security.is_daemon_process(state.pid, state.started) else None


def devices(as_json: Annotated[bool, typer.Option("--json", help="print JSON")] = False) -> None:
    """List devices with their stable IDs (asks the running daemon, else discovers locally)."""
    from dataclasses import asdict

    client = _client(remote_ok=True)
    if client is not None:
        from sssphase_plugins.manager import discovery_timeout_s, discovery_wait_s

        with client:  # (the daemon gives a hung plugin discovery_timeout_s, then answers without it)
            found = client.call("devices", timeout_s=discovery_wait_s(discovery_timeout_s()) + 10.0)
        devs, errors, where = found["devices"], found["errors"], "daemon"
    else:
        from sssphase_cli.output import stdout_to_stderr
        from sssphase_plugins.manager import discover_devices

        hung, keyless = _unanswering(), _keyless()
        with stdout_to_stderr():  # (stdout is the table's, or the JSON's)
            infos, errors = discover_devices()
        devs, where = [asdict(d) for d in infos], ("local discovery (no daemon running)" if hung is None else
                                                   f"local discovery: the daemon (pid {hung}) admits CURVE clients only "
                                                   "(no client key here to ask it) and may hold some of these devices"
                                                   if keyless is not None else
                                                   f"local discovery: the daemon (pid {hung}) does not answer and may "
                                                   "hold these devices; `sss daemon stop` ends it")
    if as_json:
        console.print_json(json.dumps({"devices": devs, "errors": errors}))
        return
    table = Table(title=f"devices ({where})")
    # the id whole on one line (a rig file takes it as it is): the other columns wrap first
    table.add_column("id", no_wrap=True, min_width=max((len(str(d["id"])) for d in devs), default=2))
    for col in ("kind", "plugin", "model", "serial"):
        table.add_column(col)
    for d in devs:  # (a plugin's text is not rich markup: "[" would vanish)
        table.add_row(*(escape(str(d[key])) for key in ("id", "kind", "plugin", "model", "serial")))
    console.print(table)
    for plugin, err in errors.items():
        if err.startswith("no device"):
            console.print(f"[yellow]{escape(plugin)}:[/] {escape(err)}")
        else:
            console.print(f"[red]plugin {escape(plugin)} failed:[/] {escape(err)}")


def plugins() -> None:
    """List device and model-backend plugins with their versions and what each provides (broken ones named with the
    error; backend problems warned of). These are this environment's plugins: a daemon started elsewhere has its own.
    SSS_PLUGINS=mod1,mod2 adds modules as plugins; SSS_PLUGINS=-name leaves an installed one out (listed as off)."""
    from sssphase_plugins.manager import device_providers, get_plugin_manager, plugin_provides, plugin_records

    pm = get_plugin_manager()
    device_providers(pm)  # surfaces plugins whose hooks raise
    provides = plugin_provides(pm)  # (warns of backend plugins that raise, or whose names are taken)
    table = Table(title="plugins")
    for col in ("name", "kind", "version", "provides", "source"):
        table.add_column(col)
    for r in plugin_records(pm):
        bad = not r.ok and r.kind != "off"
        table.add_row(r.name, "[red]broken[/]" if bad else r.kind, r.version, ", ".join(provides.get(r.name, [])),
                      f"[red]{r.source}[/]" if bad else r.source)
    console.print(table)


# ---- daemon ---------------------------------------------------------------------------------
def daemon_start(
    endpoint: Annotated[str | None, typer.Option(help="control endpoint (default: ipc:// in the runtime dir)")] = None,
    preview: Annotated[str | None, typer.Option(help="PUB endpoint for a live preview")] = None,
    curve_dir: Annotated[Path | None, typer.Option(help="CURVE keys (required off loopback)")] = None,
    foreground: Annotated[bool, typer.Option("--foreground", help="run in this process (systemd, debugging)")] = False,
) -> None:
    """Start the acquisition daemon (detached unless --foreground)."""
    _say_local_only()
    from sssphase_core.errors import InputError
    from sssphase_daemon import security
    from sssphase_daemon.client import spawn_daemon, start_lock

    args = [*(["--endpoint", endpoint] if endpoint else []), *(["--preview", preview] if preview else []),
            *(["--curve-dir", str(curve_dir)] if curve_dir else [])]
    if curve_dir is not None:  # said only by the daemon, after it was spawned
        security.check_key_folder(curve_dir)
    for what in (e for e in (endpoint, preview) if e):
        problem = security.endpoint_problem(what)
        if problem:
            raise InputError(problem)
        if not security.is_local(what) and curve_dir is None:
            raise InputError(f"{what} is not loopback/ipc (an abstract ipc://@ socket has no file permissions either): "
                             "generate keys with `sss daemon keys` and pass --curve-dir")
        problem = security.ipc_path_problem(what)
        if problem:
            raise InputError(problem)
    problem = security.endpoint_collision(endpoint or security.default_endpoint(), preview, security.state_path())
    if problem:
        raise InputError(problem)
    with start_lock():  # two starts at once: the second finds the first's daemon (both had found none, and both ran)
        if _client() is not None:
            raise InputError("a daemon is already running (`sss daemon status`)")
        problem = None if endpoint else security.ipc_path_problem(security.default_endpoint())  # (a given one: above)
        if problem:  # a daemon that lost its state file still holds the default socket
            raise InputError(problem)
        if not foreground:
            proc = spawn_daemon(extra_args=tuple(args))
    if foreground:  # (the daemon itself refuses to run beside another: its state file's lock)
        from sssphase_daemon.__main__ import main

        sys.exit(main(args))
    state = security.read_state()
    console.print(f"daemon started (pid {proc.pid}) on {state.endpoint if state else '?'}; "
                  f"log: {security.log_dir() / 'daemon.log'}")


def daemon_stop(
    force: Annotated[bool, typer.Option("--force", help="stop it even while it has a rig open or a capture running "
                                                        "(another command's, which then fails)")] = False,
) -> None:
    """Stop the running daemon (refused while another command uses it, unless --force)."""
    _say_local_only()
    from sssphase_core.errors import InputError
    from sssphase_daemon import security
    from sssphase_daemon.client import rigs_in_use

    if (keyless := _keyless()) is not None:  # nothing here can ask it whether a capture runs
        if not force:
            raise InputError(f"the daemon (pid {keyless.pid}) admits CURVE clients only, and {keyless.curve_dir} holds "
                             "no client key to ask it whether a capture runs: `sss daemon stop --force` ends it (SIGTERM)")
        os.kill(keyless.pid, signal.SIGTERM)
        if _wait_or_kill(keyless.pid, True, 20.0):
            console.print(f"daemon (pid {keyless.pid}) stopped")
        return
    client = _client()
    if client is None:
        state = security.read_state()
        if state is None and (orphan := _orphan()) is not None:  # serving the default socket, its state file gone
            os.kill(orphan, signal.SIGTERM)
            console.print(f"daemon (pid {orphan}) had no state file; sent SIGTERM")
            return
        if state is not None:
            if not security.is_daemon_process(state.pid, state.started):  # the pid may be another program's by now
                _forget_stale(state)
                console.print(f"no daemon running (the state file named pid {state.pid}, which is not the sssphase "
                              "daemon that wrote it; removed the stale state file)")
                return
            try:
                os.kill(state.pid, signal.SIGTERM)
                console.print(f"daemon (pid {state.pid}) did not answer; sent SIGTERM")
            except ProcessLookupError:
                _forget_stale(state)
                console.print("no daemon running (removed a stale state file)")
                return
            _wait_or_kill(state.pid, force, 5.0)
            return
        console.print("no daemon running")
        return
    with client:
        pid, status = client.call("hello")["pid"], client.call("status")
        running = [j for j in status.get("jobs", []) if j.get("state") == "running"]
        rigs = rigs_in_use(status)  # (a rig whose client is gone holds nothing up)
        if (rigs or running) and not force:  # another command's capture: stopping it would fail that one
            use = [f"{len(rigs)} rig(s) open"] if rigs else []
            use += [f"job {j['job']} running ({j['sent']}/{j['total']} frames)" for j in running]
            raise InputError(f"the daemon (pid {pid}) is in use: {', '.join(use)}; stopping it ends that capture: "
                             "wait for it (`sss daemon status`), or `sss daemon stop --force`")
        client.call("shutdown")
    if _wait_or_kill(pid, force, 20.0):  # return once it has gone, so that `start` right after works
        console.print(f"daemon (pid {pid}) stopped")


def _forget_stale(state: DaemonState) -> None:
    """Remove the state file of a daemon that is gone, and its ipc socket file when nothing listens there."""
    from sssphase_daemon import security

    security.state_path().unlink(missing_ok=True)
    if security.ipc_path_problem(state.endpoint) is None:  # (a socket nothing listens on, or none: only sockets go)
        security.remove_ipc_socket(state.endpoint)


def _wait_or_kill(pid: int, force: bool, seconds: float) -> bool:
    """Wait up to ``seconds`` for the daemon ``pid`` to end; with ``force`` then SIGKILL it (a device plugin hung
    in a call that no signal interrupts kept it alive for ever). True when it has gone."""
    from sssphase_daemon import security

    deadline = time.monotonic() + seconds
    while security.is_daemon_process(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    if not security.is_daemon_process(pid):
        return True
    if not force:
        console.print(f"daemon (pid {pid}) asked to stop; it has not ended after {seconds:g} s (a device call may hang): "
                      "`sss daemon stop --force` kills it")
        return False
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 5.0
    while security.is_daemon_process(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    security.state_path().unlink(missing_ok=True)  # (a killed daemon leaves its state file)
    console.print(f"daemon (pid {pid}) did not end within {seconds:g} s: killed (SIGKILL)")
    return False


def daemon_status() -> None:
    """Show the daemon's endpoint, rigs and jobs."""
    _say_local_only()
    if (keyless := _keyless()) is not None:
        console.print(f"daemon pid {keyless.pid} version {keyless.version} on {keyless.endpoint}: it admits CURVE clients "
                      f"only, and {keyless.curve_dir} holds no client key to ask it for its rigs and jobs")
        return
    client = _client()
    if client is None:
        from sssphase_daemon import security

        orphan, hung = _orphan(), _unanswering()
        state = security.state_path()
        lost = "unreadable (damaged or not a daemon's)" if state.exists() else "gone"
        console.print(f"the daemon (pid {hung}) runs but does not answer (stopped, or hung in a device call): `sss daemon stop` "
                      "asks it to end, `sss daemon stop --force` kills it"
                      if hung is not None else "no daemon running" if orphan is None else
                      f"a daemon (pid {orphan}) serves the default socket but its state file {state} is {lost}, so "
                      "nothing can talk to it: `sss daemon stop` ends it")
        sys.exit(1)  # typer.Exit's code is dropped by cli.main
    with client:
        hello, status = client.call("hello"), client.call("status")
    console.print(f"daemon pid {hello['pid']} version {hello['version']} protocol {hello['protocol']} on {hello['endpoint']}"
                  f" (up {status['uptime_s']:.0f} s, {status['clients']} clients)")
    for rig in status["rigs"]:
        console.print(f"  rig {rig['rig']}: {rig['devices']}")
    for job in status["jobs"]:
        console.print(f"  job {job['job']}: {job['state']} {job['sent']}/{job['total']}" + (f" {job['error']}" if job["error"] else ""))


def daemon_keys(
    directory: Annotated[Path | None, typer.Option("--dir", help="where to write (default ~/.config/sssphase/curve)")] = None,
    overwrite: Annotated[bool, typer.Option(help="replace existing keys")] = False,
) -> None:
    """Generate CURVE key pairs for a daemon bound off loopback, and authorise the client key."""
    from sssphase_core.errors import InputError
    from sssphase_daemon import security

    if directory is not None and directory.exists() and not directory.is_dir():  # was "[Errno 17] File exists"
        raise InputError(f"--dir {directory} is a file: give a folder for the keys")
    state = security.read_state() if overwrite else None
    if (state is not None and state.curve_dir and security.is_daemon_process(state.pid, state.started)
            and Path(state.curve_dir).resolve() == (directory or security.curve_dir()).resolve()):
        # new keys under a running daemon: every later local command said it "runs but does not answer"
        raise InputError(f"the daemon (pid {state.pid}) serving {state.endpoint} uses the CURVE keys in "
                         f"{state.curve_dir}: stop it first (`sss daemon stop`), then replace them")
    try:
        path = security.generate_keys(directory, overwrite=overwrite)
    except FileExistsError as exc:
        raise InputError(str(exc)) from None
    console.print(f"CURVE keys written to {path}; start the daemon with --curve-dir {path}, then `sss daemon "
                  "connection --out DIR` writes the folder a client on another machine uses it with (SSS_DAEMON=DIR)")


def daemon_connection(
    out: Annotated[Path, typer.Option("--out", help="a new folder for the connection (it holds a secret key)")],
    host: Annotated[str | None, typer.Option(help="this machine's name as the client reaches it (default: its "
                                             "fully qualified name), for a daemon listening on every interface")] = None,
) -> None:
    """Write the folder a client on another machine uses this daemon with: copy it there and set SSS_DAEMON=FOLDER;
    `sss capture`, `sss view`, `sss devices` then work through this daemon over CURVE."""
    from sssphase_core.errors import InputError
    from sssphase_daemon import security

    state = security.read_state()
    if state is None or not security.is_daemon_process(state.pid, state.started):
        raise InputError("no daemon is running here: start it off loopback with CURVE keys first (`sss daemon keys`, "
                         "then `sss daemon start --endpoint tcp://0.0.0.0:5609 --curve-dir DIR`)")
    if host is None and security.host_of(state.endpoint) in security.WILDCARD_HOSTS:
        host = security.machine_name()
        if host is None:
            raise InputError("this machine's network name is not known (its name is localhost, and no interface has "
                             "a route out): give --host NAME, the name or address the client reaches it by")
    try:
        folder = security.write_connection(out, state, host or "")
    except FileExistsError as exc:
        raise InputError(str(exc)) from None
    endpoint = security.read_connection(folder, keys=False).endpoint
    secret = ("it holds the client's secret key: keep it private, mode 0700" if security.has_client_key(folder) else
              "keep it private, mode 0700")
    console.print(f"wrote {folder}: copy it to the client's machine ({secret}) and set {security.ENV_DAEMON} to its "
                  f"path there (e.g. {security.ENV_DAEMON}=~/{folder.name}); the client connects to {endpoint}",
                  highlight=False)
    if not security.has_client_key(folder):
        console.print(f"note: {state.curve_dir} holds no client key (the server's keys only): on the client's machine "
                      f"put its own client.key and client.key_secret (`sss daemon keys` makes a pair) into the folder, "
                      f"and its client.key into {Path(state.curve_dir) / security.AUTHORIZED} here (the daemon admits "
                      "it within 2 s)", highlight=False)
    if security.is_loopback_host(security.host_of(endpoint)):
        console.print(f"note: {security.host_of(endpoint)} is the client's own machine: only a client on this machine "
                      "reaches the daemon so; one on another machine needs this machine's name or address (--host)",
                      highlight=False)


def bench_daemon(
    out: Annotated[Path, typer.Option(help="JSON result file (a Markdown table is printed and written next to it)")],
    frames: Annotated[int, typer.Option(min=1, max=100_000, help="frames per throughput run")] = 200,
    md: Annotated[Path | None, typer.Option(help="Markdown table file (default: next to --out)")] = None,
) -> None:
    """Daemon frame throughput vs bare pyzmq PUSH/PULL (tcp, ipc), one sim view's capture time, peak memory."""
    from sssphase_cli.output import write_result
    from sssphase_daemon.bench import run_bench

    result, markdown = run_bench(frames)
    write_result(console, out, md, result, markdown)


def bench_basler(
    out: Annotated[Path, typer.Option(help="JSON result file (a Markdown table is printed and written next to it)")] = Path("benchmarks/basler.json"),
    frames: Annotated[int, typer.Option(min=10, max=100_000, help="frames per run")] = 200,
    serial: Annotated[str | None, typer.Option(help="the camera's serial number (default: the first camera pylon sees; "
                                                     "pylon's emulator unless PYLON_CAMEMU is set)")] = None,
    md: Annotated[Path | None, typer.Option(help="Markdown table file (default: next to --out)")] = None,
) -> None:
    """Basler camera frames/s through the daemon vs pypylon's own grab loop (the pylon emulator unless
    PYLON_CAMEMU=0 and --serial names a real camera)."""
    import importlib.util

    from sssphase_cli.output import write_result
    from sssphase_core.errors import InputError
    from sssphase_daemon.camera_bench import run_bench

    if importlib.util.find_spec("pypylon") is None:
        raise InputError("sss bench basler needs pypylon: pip install 'sssphase[basler]'")
    with console.status(f"sss bench basler: {frames} frames per run"):
        result, markdown = run_bench(frames, serial)
    write_result(console, out, md, result, markdown)


def bench_soak(
    out: Annotated[Path, typer.Option(help="JSON result file, every cycle's sample in it (a Markdown table is printed "
                                           "and written next to it)")] = Path("benchmarks/soak.json"),
    cycles: Annotated[int, typer.Option(min=1, max=1_000_000, help="cycles after the warm-up")] = 300,
    capture_every: Annotated[int, typer.Option(min=0, help="capture one sim view every N cycles (0: never)")] = 50,
    frames: Annotated[int, typer.Option(min=1, max=10_000, help="frames the well-behaved client streams per cycle")] = 20,
    md: Annotated[Path | None, typer.Option(help="Markdown table file (default: next to --out)")] = None,
) -> None:
    """A daemon under a lab's use, compressed: clients streaming, clients crashing mid-stream, malformed requests,
    captures; its rigs, jobs, descriptors, threads and memory when idle after a warm-up against after the cycles."""
    from sssphase_cli.output import write_result
    from sssphase_cli.progress import LazyBar
    from sssphase_daemon.soak import markdown, run_soak

    with LazyBar("sss bench soak: cycles") as bar:
        result = run_soak(cycles, frames=frames, capture_every=capture_every, progress=bar)
    write_result(console, out, md, result, markdown(result))


def register(groups: dict[str, typer.Typer]) -> None:
    root = groups["root"]
    root.command("devices")(devices)
    root.command("plugins")(plugins)
    groups["daemon"].command("start")(daemon_start)
    groups["daemon"].command("stop")(daemon_stop)
    groups["daemon"].command("status")(daemon_status)
    groups["daemon"].command("keys")(daemon_keys)
    groups["daemon"].command("connection")(daemon_connection)
    groups["bench"].command("daemon")(bench_daemon)
    groups["bench"].command("basler")(bench_basler)
    groups["bench"].command("soak")(bench_soak)
