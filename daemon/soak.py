"""``sss bench soak``: weeks of a lab's use of the daemon, compressed into cycles.

Every cycle, against one daemon process: a client connects, opens a rig, streams frames to the end and closes
the rig; a client process opens a rig, starts a long stream and dies after two frames (a crashed notebook: no
``close_rig``, no ``cancel``); a peer sends bytes that are no request; and every ``capture_every`` cycles one view
is captured the user's way (``run_capture``, the simulated rig). After each cycle the daemon's resident memory,
open file descriptors and threads are read from ``/proc``, its open rigs and running jobs from ``status``.

The baseline is the same daemon in the same run: idle after one warm-up cycle (the lazily made threads and
sockets, the first capture's imports) against idle after the last cycle, once its clients are gone. A daemon that
serves a lab for weeks must end where it started: no rig, job, descriptor or thread left behind.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from sssphase_daemon import security
from sssphase_daemon.client import DaemonClient, DaemonError, DaemonUnavailable, spawn_daemon

#: Frames of the streaming clients: small, so that a cycle measures the daemon's bookkeeping, not bandwidth.
SHAPE = (120, 160, 3)
#: Seconds without a heartbeat before the daemon counts a client dead (10 by default): short, so that the rigs of
#: the clients that crash in one cycle after another (a few a second) stay below the daemon's 16 at any time.
CLIENT_TIMEOUT_S = 2.0
#: The shortest cycle: a client crashes per cycle and its rig stays until its job's heartbeats are missed (the
#: client timeout), so that at most ~10 such rigs are open at once on a fast machine (the daemon holds 16).
MIN_CYCLE_S = CLIENT_TIMEOUT_S / 8
#: The heartbeat of the soak's own clients (1 s by default): well inside the short client timeout on a busy machine.
HEARTBEAT_S = 0.25
CRASHING_CLIENT = """
import os, sys
from sssphase_daemon.client import DaemonClient
client = DaemonClient(sys.argv[1], sys.argv[2])
rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": %s, "dtype": "uint16"})["rig"]
frames = client.stream(rig, 100_000)
next(frames), next(frames)
os._exit(0)
"""


def daemon_sample(pid: int) -> dict[str, float]:
    """The daemon process's resident memory (MB), open file descriptors and threads, from ``/proc``."""
    status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return {"rss_mb": int(status["VmRSS"].split()[0]) / 1024, "fds": len(os.listdir(f"/proc/{pid}/fd")),
            "threads": int(status["Threads"])}


def streamed_client(state: security.DaemonState, frames: int) -> int:
    """A well-behaved client: open a rig, stream ``frames`` to the end, close the rig. -> frames received."""
    with DaemonClient(state.endpoint, state.token, heartbeat_s=HEARTBEAT_S) as client:
        client.call("status")
        rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": list(SHAPE), "dtype": "uint16"})["rig"]
        got = sum(1 for _ in client.stream(rig, frames))
        client.call("close_rig", rig=rig)
    return got


def crashed_client(state: security.DaemonState) -> None:
    """A client process that opens a rig, starts a long stream and exits after two frames without a word."""
    subprocess.run([sys.executable, "-c", CRASHING_CLIENT % (list(SHAPE),), state.endpoint, state.token],
                   check=True, timeout=60, capture_output=True)


def malformed_request(state: security.DaemonState) -> bool:
    """A peer that sends bytes that are no request: -> whether the daemon answered (with an error)."""
    sock = zmq.Context.instance().socket(zmq.DEALER)
    sock.linger = 0
    sock.connect(state.endpoint)
    try:
        sock.send(b"\x92\xc4\x00not a request")
        return bool(sock.poll(5000))
    finally:
        sock.close()


def one_cycle(state: security.DaemonState, frames: int, capture_into: Path | None) -> dict[str, Any]:
    """The clients of one cycle (a capture into ``capture_into``, removed after, when given): -> what they got."""
    from sssphase_core.capture import CaptureRequest, run_capture

    t0 = time.perf_counter()
    received = streamed_client(state, frames)
    crashed_client(state)
    answered = malformed_request(state)
    if capture_into is not None:
        with DaemonClient(state.endpoint, state.token, heartbeat_s=HEARTBEAT_S) as client:
            run_capture(client, CaptureRequest("apple", views=1, out=capture_into))
        shutil.rmtree(capture_into)
    seconds = time.perf_counter() - t0
    time.sleep(max(0.0, MIN_CYCLE_S - seconds))
    return {"seconds": seconds, "frames": received, "malformed_answered": answered}


def daemon_state(state: security.DaemonState, pid: int) -> dict[str, Any]:
    """Open rigs and running jobs (``status``) with the process sample."""
    with DaemonClient(state.endpoint, state.token) as client:
        status = client.call("status")
    return {"rigs": len(status.get("rigs", [])), "jobs_running": sum(j.get("state") == "running" for j in status["jobs"]),
            **daemon_sample(pid)}


def settled(state: security.DaemonState, pid: int, timeout_s: float = 30.0) -> dict[str, Any]:
    """The daemon once no rig is open and no job runs (its clients gone: crashed clients' jobs are cancelled after
    the client timeout, their rigs closed with them), waited for up to ``timeout_s``; ``waited_s``: how long."""
    t0 = time.perf_counter()
    while (now := daemon_state(state, pid))["rigs"] or now["jobs_running"]:
        if time.perf_counter() - t0 > timeout_s:
            break
        time.sleep(0.1)
    time.sleep(0.2)  # the job threads that just ended close their stream sockets
    return {**daemon_state(state, pid), "waited_s": time.perf_counter() - t0}


def run_soak(cycles: int = 300, *, frames: int = 20, capture_every: int = 50,
             progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """One daemon through a warm-up cycle and ``cycles`` more; -> per-cycle samples, the idle daemon after the
    warm-up and after the cycles, the errors the clients met. ``capture_every``: 0 for no captures."""
    samples: list[dict[str, Any]] = []
    errors: list[str] = []
    with tempfile.TemporaryDirectory(prefix="ssss", dir="/tmp") as tmpdir:
        tmp = Path(tmpdir)
        old_runtime = os.environ.get("SSS_RUNTIME_DIR")
        os.environ["SSS_RUNTIME_DIR"] = str(tmp / "rt")
        proc = spawn_daemon(extra_args=("--client-timeout", str(CLIENT_TIMEOUT_S)))
        try:
            state = security.read_state()
            try:
                one_cycle(state, frames, tmp / "warm" if capture_every else None)
            except (DaemonError, DaemonUnavailable, subprocess.SubprocessError, OSError) as exc:
                errors.append(f"warm-up: {exc}")
            idle_warm = settled(state, proc.pid)
            for cycle in range(cycles):
                capture = capture_every and (cycle + 1) % capture_every == 0
                try:
                    got = one_cycle(state, frames, tmp / f"c{cycle}" if capture else None)
                except (DaemonError, DaemonUnavailable, subprocess.SubprocessError, OSError) as exc:
                    errors.append(f"cycle {cycle}: {exc}")
                    got = {"seconds": float("nan"), "frames": 0, "malformed_answered": False}
                samples.append({"cycle": cycle, "capture": bool(capture), **got, **daemon_state(state, proc.pid)})
                if progress is not None:
                    progress(cycle + 1, cycles)
            idle_after = settled(state, proc.pid)
            with DaemonClient(state.endpoint, state.token) as client:
                client.call("shutdown")
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
            if old_runtime is None:
                os.environ.pop("SSS_RUNTIME_DIR", None)
            else:
                os.environ["SSS_RUNTIME_DIR"] = old_runtime
    plain = [s["seconds"] for s in samples if not s["capture"] and np.isfinite(s["seconds"])]
    tenth = max(1, len(plain) // 10)
    return {"cycles": cycles, "frames_per_stream": frames, "capture_every": capture_every, "frame_shape": list(SHAPE),
            "client_timeout_s": CLIENT_TIMEOUT_S, "min_cycle_s": MIN_CYCLE_S, "cpus": os.cpu_count(), "errors": errors,
            "idle_warm": idle_warm, "idle_after": idle_after,
            "cycle_s_first_tenth": float(np.median(plain[:tenth])) if plain else float("nan"),
            "cycle_s_last_tenth": float(np.median(plain[-tenth:])) if plain else float("nan"),
            "peak": {k: max(s[k] for s in samples) for k in ("rss_mb", "fds", "threads", "rigs", "jobs_running")}
            if samples else {},
            "streamed_frames": sum(s["frames"] for s in samples), "captures": sum(s["capture"] for s in samples),
            "samples": samples}


def markdown(r: dict[str, Any]) -> str:
    """The idle daemon after the warm-up against after the cycles, the peaks while they ran, the cycle time."""
    warm, after, peak = r["idle_warm"], r["idle_after"], r["peak"]
    lines = [f"{r['cycles']} cycles ({r['cpus']} CPUs): each a client streaming {r['frames_per_stream']} frames, a "
             f"client process that crashes mid-stream, a malformed request; a sim view captured every "
             f"{r['capture_every'] or 'never'} cycles ({r['captures']} captures, {r['streamed_frames']:,} frames "
             f"streamed); client timeout {r['client_timeout_s']:g} s, cycles at least {r['min_cycle_s']:g} s apart", "",
             "| daemon | idle after warm-up | idle after the cycles | change | peak during |", "|---|---|---|---|---|"]
    for key, name, fmt in (("rigs", "open rigs", "{:.0f}"), ("jobs_running", "running jobs", "{:.0f}"),
                           ("fds", "open file descriptors", "{:.0f}"), ("threads", "threads", "{:.0f}"),
                           ("rss_mb", "resident memory (MB)", "{:.1f}")):
        lines.append(f"| {name} | {fmt.format(warm[key])} | {fmt.format(after[key])} | "
                     f"{after[key] - warm[key]:+.{1 if key == 'rss_mb' else 0}f} | {fmt.format(peak.get(key, 0))} |")
    ratio = r["cycle_s_last_tenth"] / r["cycle_s_first_tenth"]
    lines += ["", "| measure | value |", "|---|---|",
              f"| cycle without capture, first tenth (median) | {r['cycle_s_first_tenth'] * 1000:.0f} ms |",
              f"| cycle without capture, last tenth (median) | {r['cycle_s_last_tenth'] * 1000:.0f} ms ({ratio:.2f}x) |",
              f"| errors the clients met | {len(r['errors'])}{': ' + r['errors'][0] if r['errors'] else ''} |"]
    return "\n".join(lines) + "\n"
