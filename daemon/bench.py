"""``sss bench daemon``: frame throughput through the daemon against bare pyzmq in the same run.

The baseline is a separate process sending the same 1920x1080 16-bit RGB frames over a bare
PUSH/PULL pair (multipart, zero-copy), received here exactly like the daemon client receives; the
daemon run streams the ``sim:bench-camera`` through the full path (driver, job thread, headers,
heartbeats, sequence checks). Time is measured from the first received frame to the last, so
process start-up is excluded from both. Also: one sim view's capture at the CPU preset, peak memory
of daemon and client, and the sim-only daemon's import time and resident memory.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from sssphase_daemon import security
from sssphase_daemon.client import DaemonClient, spawn_daemon

SHAPE = (1080, 1920, 3)
SENDER = """
import sys, numpy as np, zmq
endpoint, n = sys.argv[1], int(sys.argv[2])
frame = np.random.default_rng(0).integers(0, 65535, size=(1080, 1920, 3), dtype=np.uint16)
ctx = zmq.Context()
sock = ctx.socket(zmq.PUSH)
sock.sndhwm = 8
sock.bind(endpoint)
print(sock.getsockopt_string(zmq.LAST_ENDPOINT), flush=True)
for i in range(n):
    sock.send_multipart([i.to_bytes(8, "little"), frame], copy=False)
sock.send_multipart([b"end"])
sock.close(linger=-1)
ctx.term()
"""
IMPORT_PROBE = """
import json, resource, sys, time
t = time.perf_counter()
import sssphase_daemon.server, sssphase_plugins.sim_plugin, sssphase_core.sim
from sssphase_plugins.manager import get_plugin_manager, device_providers
device_providers(get_plugin_manager())
dt = time.perf_counter() - t
hw = ("torch", "depthai", "hid", "usb", "serial")
print(json.dumps({"import_s": dt, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "loaded": [m for m in hw if m in sys.modules]}))
"""


def _peak_rss_mb(pid: int) -> float:
    """VmHWM (peak resident set) of a live process, in MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _endpoint(transport: str, tmp: Path) -> str:
    return f"ipc://{tmp / 'bare.sock'}" if transport == "ipc" else "tcp://127.0.0.1:*"


def bare_pyzmq(transport: str, n: int, tmp: Path) -> dict[str, Any]:
    proc = subprocess.Popen([sys.executable, "-c", SENDER, _endpoint(transport, tmp), str(n)], stdout=subprocess.PIPE, text=True)
    endpoint = proc.stdout.readline().strip()
    sock = zmq.Context.instance().socket(zmq.PULL)
    sock.rcvhwm = 16
    sock.connect(endpoint)
    got, t0, nbytes = 0, 0.0, 0
    while True:
        parts = sock.recv_multipart(copy=False)
        if parts[0].bytes == b"end":
            break
        arr = np.frombuffer(parts[1].buffer, np.uint16).reshape(SHAPE)
        if got == 0:
            t0 = time.perf_counter()
        else:
            nbytes += arr.nbytes
        got += 1
    dt = time.perf_counter() - t0
    sock.close()
    proc.wait()
    return {"frames": got, "lost": n - got, "seconds": dt, "gb_per_s": nbytes / dt / 1e9}


def through_daemon(client: DaemonClient, n: int) -> dict[str, Any]:
    rig = client.call("open_rig", camera="sim:bench-camera", options={"shape": list(SHAPE), "dtype": "uint16"})["rig"]
    got, t0, nbytes = 0, 0.0, 0
    for frame in client.stream(rig, n):
        if got == 0:
            t0 = time.perf_counter()
        else:
            nbytes += frame.data.nbytes
        got += 1
    dt = time.perf_counter() - t0
    client.call("close_rig", rig=rig)
    return {"frames": got, "lost": n - got, "seconds": dt, "gb_per_s": nbytes / dt / 1e9}


def sim_view_time(client: DaemonClient, tmp: Path) -> float:
    from sssphase_core.capture import CaptureRequest, run_capture

    t0 = time.perf_counter()
    run_capture(client, CaptureRequest("apple", views=1, out=tmp / "sessions"))
    return time.perf_counter() - t0


def _folder_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def capture_bench(preset: str = "paper", object_name: str = "soap", *, footprints: bool = True,
                  out: Path | None = None, progress: Any = None) -> tuple[dict[str, Any], str]:
    """One sim view captured the user's way (a daemon process, ``run_capture`` in this one): wall time,
    frames, peak RSS of the daemon and of this client process, the session's size on disk by array
    group. ``out``: where the session goes (default: a temporary folder, removed)."""
    from sssphase_core.capture import CaptureRequest, run_capture
    from sssphase_core.store.session import view_dir_name

    with tempfile.TemporaryDirectory(prefix="sssb", dir="/tmp") as tmpdir:
        tmp = Path(tmpdir)
        root = out or tmp / "sessions"
        os.environ["SSS_RUNTIME_DIR"] = str(tmp / "rt")
        proc = spawn_daemon()
        state = security.read_state()
        try:
            with DaemonClient(state.endpoint, state.token) as client:
                t0 = time.perf_counter()
                session = run_capture(client, CaptureRequest(object_name, views=1, out=root, footprints=footprints,
                                                             preset=preset), progress=progress)
                seconds = time.perf_counter() - t0
                daemon_rss = _peak_rss_mb(proc.pid)
                client.call("shutdown")
            proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
        view = session.manifest["views"]["0"]
        groups: dict[str, int] = {}
        for name in view["arrays"]:
            groups[name.split("/")[0]] = groups.get(name.split("/")[0], 0) + _folder_bytes(session.path / view_dir_name(0) / name)
        crops = view["arrays"].get("footprints/crops", {}).get("shape", [0])
        result = {"preset": preset, "object": object_name, "footprints": footprints, "cpus": os.cpu_count(),
                  "frames": view["frames"], "seconds": seconds, "frames_per_s": view["frames"] / seconds,
                  "daemon_peak_rss_mb": daemon_rss,
                  "client_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "session_bytes": _folder_bytes(session.path), "bytes_by_group": groups,
                  "footprint_crops": crops[0], "transport_dots": view.get("transport", {}).get("dots", 0),
                  "crop_float32_bytes": int(np.prod(crops)) * 4 if len(crops) > 1 else 0}
    return result, capture_markdown(result)


def capture_markdown(r: dict[str, Any]) -> str:
    gb = 1e9
    lines = [f"One sim view, `{r['preset']}` preset, {r['object']}, {'with' if r['footprints'] else 'without'} "
             f"footprints, through the daemon ({r['cpus']} CPUs)", "",
             "| measure | value |", "|---|---|",
             f"| frames | {r['frames']:,} |",
             f"| wall time | {r['seconds']:.0f} s ({r['frames_per_s']:.2f} frames/s) |",
             f"| daemon peak RSS | {r['daemon_peak_rss_mb']:,.0f} MB |",
             f"| client peak RSS | {r['client_peak_rss_mb']:,.0f} MB |",
             f"| session on disk | {r['session_bytes'] / gb:.2f} GB |"]
    for group, size in sorted(r["bytes_by_group"].items(), key=lambda kv: -kv[1]):
        lines.append(f"| &nbsp; {group}/ | {size / gb:.3f} GB |")
    if r["footprint_crops"]:
        lines.append(f"| footprint crops (one per camera pixel) | {r['footprint_crops']:,} "
                     f"({r['bytes_by_group'].get('footprints', 0) / r['crop_float32_bytes']:.1%} of float32) |")
        lines.append(f"| transport crops (one per projector dot) | {r['transport_dots']:,} |")
    return "\n".join(lines) + "\n"


def run_bench(n: int = 200) -> tuple[dict[str, Any], str]:
    result: dict[str, Any] = {"frame": {"shape": list(SHAPE), "dtype": "uint16", "bytes": int(np.prod(SHAPE)) * 2},
                              "frames_per_run": n, "cpus": os.cpu_count(), "runs": {}}
    probe = subprocess.run([sys.executable, "-c", IMPORT_PROBE], capture_output=True, text=True, check=True)
    result["sim_daemon_imports"] = json.loads(probe.stdout)
    with tempfile.TemporaryDirectory(prefix="sssb", dir="/tmp") as tmpdir:
        tmp = Path(tmpdir)
        os.environ["SSS_RUNTIME_DIR"] = str(tmp / "rt")
        for transport in ("tcp", "ipc"):
            bare = bare_pyzmq(transport, n, tmp)
            endpoint = None if transport == "ipc" else "tcp://127.0.0.1:*"
            proc = spawn_daemon(endpoint=endpoint)
            try:  # a failed or interrupted run ends its daemon: its runtime folder goes with the temporary one
                state = security.read_state()
                with DaemonClient(state.endpoint, state.token) as client:
                    daemon = through_daemon(client, n)
                    if transport == "ipc":
                        result["sim_view_capture_s"] = sim_view_time(client, tmp)
                    result[f"daemon_peak_rss_mb_{transport}"] = _peak_rss_mb(proc.pid)
                    client.call("shutdown")
                proc.wait(10)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(10)
            result["runs"][transport] = {"bare": bare, "daemon": daemon, "ratio": daemon["gb_per_s"] / bare["gb_per_s"]}
    result["client_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result, markdown(result)


def markdown(r: dict[str, Any]) -> str:
    lines = ["| transport | bare pyzmq GB/s | daemon GB/s | ratio | frames lost |", "|---|---|---|---|---|"]
    for t, run in r["runs"].items():
        lines.append(f"| {t} | {run['bare']['gb_per_s']:.2f} | {run['daemon']['gb_per_s']:.2f} | {run['ratio']:.0%} | "
                     f"{run['daemon']['lost']} |")
    imp = r["sim_daemon_imports"]
    lines += ["", "| measure | value |", "|---|---|",
              f"| one sim view, CPU preset (capture + decode + write) | {r['sim_view_capture_s']:.1f} s |",
              f"| daemon peak RSS (ipc run, after the sim view) | {r['daemon_peak_rss_mb_ipc']:.0f} MB |",
              f"| client peak RSS | {r['client_peak_rss_mb']:.0f} MB |",
              f"| sim-only daemon import time | {imp['import_s']:.2f} s |",
              f"| sim-only daemon RSS after import | {imp['rss_mb']:.0f} MB |",
              f"| torch / hardware modules loaded by the sim daemon | {', '.join(imp['loaded']) or 'none'} |"]
    return "\n".join(lines) + "\n"
