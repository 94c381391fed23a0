"""``sss bench basler``: frames per second from a Basler camera through the daemon, against pypylon's own
grab loop in the same run.

Both sides use pylon's camera emulation (``PYLON_CAMEMU``; a real camera with ``--camera``) at its full
1024 x 1040, raw Bayer 12-bit, with the acquisition the plugin uses: a software trigger per frame, grab
strategy one-by-one, the pixels copied out of pylon's buffer before it is released. The baseline is that
loop written directly against pypylon in this process; the daemon run streams the same camera through the
plugin, the job thread, headers and the client's receive (``DaemonClient.stream``). Time runs from the
first received frame to the last. pypylon's free-running grab (no trigger) is reported beside them as
the emulator's own ceiling.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_daemon import security
from sssphase_daemon.client import DaemonClient, spawn_daemon

WIDTH, HEIGHT, PIXEL_FORMAT = 1024, 1040, "BayerRG12"
SERIAL = "0815-0000"


def pylon_serials() -> list[str]:
    """The serial numbers of the cameras pylon sees (the emulator's with ``PYLON_CAMEMU=N``)."""
    from pypylon import pylon

    return [d.GetSerialNumber() for d in pylon.TlFactory.GetInstance().EnumerateDevices()]


def choose_serial(serial: str | None) -> str:
    """``serial``, checked against the cameras pylon sees, or (None) the first of them; else one line saying
    what pylon sees and how to get a camera."""
    from sssphase_core.errors import InputError

    seen = pylon_serials()
    if serial is None and seen:
        return seen[0]
    if serial in seen:
        return serial
    emulated = os.environ.get("PYLON_CAMEMU", "0") not in ("", "0")
    how = "" if emulated else ": connect one, or set PYLON_CAMEMU=1 for pylon's camera emulator"
    sees = f"it sees {', '.join(seen)}" if seen else f"it sees no camera{how}"
    raise InputError(f"pylon sees no camera {serial}: {sees}" if serial is not None else f"pylon {sees}")


def _open_pylon(serial: str) -> Any:
    from pypylon import pylon

    tl = pylon.TlFactory.GetInstance()
    dev = next(d for d in tl.EnumerateDevices() if d.GetSerialNumber() == serial)  # (choose_serial checked it)
    cam = pylon.InstantCamera(tl.CreateDevice(dev))
    cam.Open()
    cam.Width.Value, cam.Height.Value, cam.PixelFormat.Value = WIDTH, HEIGHT, PIXEL_FORMAT
    return cam


def pypylon_loop(n: int, serial: str = SERIAL, *, triggered: bool = True) -> dict[str, Any]:
    """Frames/s of a bare pypylon loop (software-triggered like the plugin, or free-running)."""
    from pypylon import pylon

    cam = _open_pylon(serial)
    try:
        cam.TriggerSelector.Value = "FrameStart"
        cam.TriggerMode.Value = "On" if triggered else "Off"
        cam.TriggerSource.Value = "Software"
        cam.StartGrabbing(pylon.GrabStrategy_OneByOne)
        t0, got = 0.0, 0
        for i in range(n):
            if triggered:
                cam.WaitForFrameTriggerReady(5000, pylon.TimeoutHandling_ThrowException)
                cam.ExecuteSoftwareTrigger()
            result = cam.RetrieveResult(5000, pylon.TimeoutHandling_ThrowException)
            try:
                _ = np.array(result.GetArray(), copy=True)
            finally:
                result.Release()
            if i == 0:
                t0 = time.perf_counter()
            got += 1
        seconds = time.perf_counter() - t0
        cam.StopGrabbing()
    finally:
        cam.Close()
    return {"frames": got, "seconds": seconds, "frames_per_s": (got - 1) / seconds}


def through_daemon(client: DaemonClient, n: int, serial: str = SERIAL) -> dict[str, Any]:
    options = {"basler": {"pixel_format": PIXEL_FORMAT, "roi": [0, 0, WIDTH, HEIGHT]}}
    rig = client.call("open_rig", camera=f"basler:{serial}", options=options)["rig"]
    got, t0, shape, dtype = 0, 0.0, None, None
    for frame in client.stream(rig, n):
        if got == 0:
            t0, shape, dtype = time.perf_counter(), frame.data.shape, frame.data.dtype.str
        got += 1
    seconds = time.perf_counter() - t0
    client.call("close_rig", rig=rig)
    return {"frames": got, "lost": n - got, "seconds": seconds, "frames_per_s": (got - 1) / seconds,
            "shape": list(shape or ()), "dtype": dtype}


def run_bench(n: int = 200, serial: str | None = None) -> tuple[dict[str, Any], str]:
    """The three runs on the camera ``serial`` (None: the first pylon sees; pylon's emulator where
    ``PYLON_CAMEMU`` is not set) -> (result, Markdown table)."""
    os.environ.setdefault("PYLON_CAMEMU", "1")
    serial = choose_serial(serial)
    result: dict[str, Any] = {"camera": f"basler:{serial}", "emulated": os.environ.get("PYLON_CAMEMU", "0") != "0",
                              "size": [WIDTH, HEIGHT], "pixel_format": PIXEL_FORMAT, "frames_per_run": n,
                              "cpus": os.cpu_count()}
    result["pypylon_free_running"] = pypylon_loop(n, serial, triggered=False)
    result["pypylon_triggered"] = pypylon_loop(n, serial)
    runtime = os.environ.get("SSS_RUNTIME_DIR")
    with tempfile.TemporaryDirectory(prefix="sssb", dir="/tmp") as tmpdir:
        os.environ["SSS_RUNTIME_DIR"] = str(Path(tmpdir) / "rt")  # a daemon of its own (the user's keeps running)
        proc = spawn_daemon()
        try:
            state = security.read_state()
            with DaemonClient(state.endpoint, state.token) as client:
                result["daemon"] = through_daemon(client, n, serial)
                client.call("shutdown")
            proc.wait(10)
        finally:
            if proc.poll() is None:
                proc.kill()
            if runtime is None:
                os.environ.pop("SSS_RUNTIME_DIR", None)
            else:
                os.environ["SSS_RUNTIME_DIR"] = runtime
    result["ratio"] = result["daemon"]["frames_per_s"] / result["pypylon_triggered"]["frames_per_s"]
    return result, markdown(result)


def markdown(r: dict[str, Any]) -> str:
    mb = r["size"][0] * r["size"][1] * 2 / 1e6
    cam = f"{r['camera']} ({'pylon camera emulation' if r['emulated'] else 'camera'})"
    return "\n".join([
        f"{cam}, {r['size'][0]}x{r['size'][1]} {r['pixel_format']} ({mb:.1f} MB per frame), {r['frames_per_run']} frames "
        f"per run, {r['cpus']} CPUs", "",
        "| path | frames/s | vs pypylon (triggered) |", "|---|---|---|",
        f"| pypylon, free-running (no trigger) | {r['pypylon_free_running']['frames_per_s']:.1f} | "
        f"{r['pypylon_free_running']['frames_per_s'] / r['pypylon_triggered']['frames_per_s']:.0%} |",
        f"| pypylon, software trigger per frame (baseline) | {r['pypylon_triggered']['frames_per_s']:.1f} | 100% |",
        f"| through the daemon (plugin, job thread, ZeroMQ, client) | {r['daemon']['frames_per_s']:.1f} | "
        f"{r['ratio']:.0%} |",
        f"| frames lost through the daemon | {r['daemon']['lost']} | |"]) + "\n"
