"""``sss bench view``: how fast the browser view answers, measured the way a page sees it.

A session is captured and ``sss view`` started as a user starts them (subprocesses, a daemon of their
own); a websocket client stands in for the page. Live view: frames per second and latency (the frame
asked of the daemon -> delivered to the client) p50 / p99. Live decode: the refresh period of a decoded
PSP set. Relighting: the first pattern of a view (its footprints computed and cached) and each new
pattern after it (the splat alone), through ``/api/relight`` as the page calls it. The CPU preset, and
with ``paper=True`` the paper preset's 1080p camera for the live view.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np


def _sss(args: list[str], env: dict[str, str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "sssphase_cli.main", *args], capture_output=True, text=True, env=env,
                          check=True, **kwargs)


class _View:
    """``sss view`` in a subprocess; its URL, token and a JSON POST helper."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "sssphase_cli.main", "view", "--port", "0", *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        url = None
        while url is None:
            line = self.proc.stdout.readline()  # type: ignore[union-attr]
            if not line and self.proc.poll() is not None:
                raise RuntimeError("sss view exited before listening")
            m = re.search(r"(http://127\.0\.0\.1:\d+)/\?token=(\S+)", line)
            if m:
                url = m.group(1)
                self.base, self.token = url, m.group(2)

    def post(self, path: str, body: bytes, content_type: str = "application/json") -> dict[str, Any]:
        request = urllib.request.Request(self.base + path, data=body, method="POST",
                                         headers={"X-Token": self.token, "Content-Type": content_type})
        with urllib.request.urlopen(request, timeout=600) as response:
            return json.loads(response.read())

    def live(self, count: int, settings: dict[str, Any], kind: str = "frame") -> list[tuple[float, dict[str, Any]]]:
        """``count`` messages of ``kind`` (frame / decode) as (arrival time.time(), header)."""
        from websockets.sync.client import connect

        got: list[tuple[float, dict[str, Any]]] = []
        with connect(f"{self.base.replace('http', 'ws')}/ws/live?token={self.token}", max_size=2**26) as ws:
            ws.send(json.dumps(settings))
            while len(got) < count:
                message = ws.recv(timeout=600)
                if isinstance(message, bytes):
                    continue
                header = json.loads(message)
                if header.get("type") == kind:
                    got.append((time.time(), header))
                elif header.get("type") == "error":
                    raise RuntimeError(header["message"])
        return got

    def close(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()


def _live_figures(frames: list[tuple[float, dict[str, Any]]]) -> dict[str, Any]:
    frames = frames[2:]  # the first frames include the rig's opening
    latency = np.array([arrived * 1000 - h["requested_ms"] for arrived, h in frames])
    view = np.array([arrived * 1000 - h["received_ms"] for arrived, h in frames])  # after the daemon: stats, JPEG, send
    span = frames[-1][0] - frames[0][0]
    return {"frames": len(frames), "frames_per_s": (len(frames) - 1) / span if span > 0 else float("nan"),
            "latency_ms_p50": float(np.percentile(latency, 50)), "latency_ms_p99": float(np.percentile(latency, 99)),
            "view_ms_p50": float(np.percentile(view, 50)), "view_ms_p99": float(np.percentile(view, 99)),
            "shape": frames[-1][1]["shape"]}


def run_bench(*, frames: int = 40, patterns: int = 5, paper: bool = False,
              progress: Callable[[str], None] | None = None) -> tuple[dict[str, Any], str]:
    say = progress or (lambda text: None)
    result: dict[str, Any] = {"cpus": os.cpu_count(), "frames_per_run": frames}
    with tempfile.TemporaryDirectory(prefix="sssb", dir="/tmp") as tmpdir:
        tmp = Path(tmpdir)
        env = {**os.environ, "SSS_RUNTIME_DIR": str(tmp / "rt")}
        say("capturing a session (CPU preset)")
        _sss(["capture", "--object", "star", "--views", "1", "--reference", "checkerboard", "--out", str(tmp / "s")], env)
        view = _View(["--sessions", str(tmp / "s"), "--out", str(tmp / "out")], env)
        try:
            say("live view (CPU preset)")
            result["live_cpu"] = _live_figures(view.live(frames, {"pattern": "checkerboard", "decode": False}))
            say("live decode (CPU preset)")
            decodes = view.live(4, {"decode": True}, kind="decode")
            result["decode_cpu"] = {"sets": len(decodes), "refresh_s": [h["seconds"] for _, h in decodes],
                                    "refresh_s_median": float(np.median([h["seconds"] for _, h in decodes]))}
            say("relighting: the first pattern, then new ones")
            result["relight_cpu"] = _relight_figures(view, patterns)
        finally:
            view.close()
        if paper:
            say("live view (paper preset, 1080p)")
            rig = tmp / "paper.toml"
            rig.write_text('[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n[options]\npreset = "paper"\n')
            view = _View(["--rig", str(rig), "--out", str(tmp / "out_paper")], env)
            try:
                result["live_paper"] = _live_figures(view.live(max(6, frames // 8), {"pattern": "checkerboard"}))
            finally:
                view.close()
        _sss(["daemon", "stop", "--force"], env)  # its own daemon (a private runtime folder)
    return result, markdown(result)


def _relight_figures(view: _View, patterns: int) -> dict[str, Any]:
    import cv2

    first = view.post("/api/relight", json.dumps({"session": "star", "view": 0, "pattern": "checkerboard",
                                                  "backend": "analytic"}).encode())
    rng = np.random.default_rng(0)
    times = []
    for _ in range(patterns):
        img = (np.kron(rng.integers(0, 2, (12, 16)), np.ones((16, 16))) * 255).astype(np.uint8)
        name = view.post("/api/upload", cv2.imencode(".png", img)[1].tobytes(), "application/octet-stream")["name"]
        t0 = time.perf_counter()
        answer = view.post("/api/relight", json.dumps({"session": "star", "view": 0, "pattern": name,
                                                       "backend": "analytic"}).encode())
        times.append({"server_s": answer["seconds"], "round_trip_s": time.perf_counter() - t0})
    return {"first_pattern_s": first["seconds"], "new_patterns": times,
            "new_pattern_round_trip_s_median": float(np.median([t["round_trip_s"] for t in times])),
            "new_pattern_round_trip_s_max": float(max(t["round_trip_s"] for t in times))}


def markdown(r: dict[str, Any]) -> str:
    lines = [f"`sss view` answering a page ({r['cpus']} CPUs; live figures over {r['frames_per_run']} frames)", "",
             "| measure | value |", "|---|---|"]
    for key, label in (("live_cpu", "CPU preset"), ("live_paper", "paper preset")):
        if key in r:
            live = r[key]
            lines += [f"| live view, {label} ({live['shape'][1]}x{live['shape'][0]}): frames/s | {live['frames_per_s']:.1f} |",
                      f"| live view, {label}: latency p50 / p99 (asked of the daemon -> at the page) | "
                      f"{live['latency_ms_p50']:.0f} / {live['latency_ms_p99']:.0f} ms |",
                      f"| live view, {label}: the view's share of it p50 / p99 (statistics, JPEG, websocket) | "
                      f"{live['view_ms_p50']:.0f} / {live['view_ms_p99']:.0f} ms |"]
    d = r["decode_cpu"]
    lines.append(f"| live decode, CPU preset: refresh period (median of {d['sets']}) | {d['refresh_s_median']:.2f} s |")
    rel = r["relight_cpu"]
    lines += [f"| relight, CPU preset: first pattern of a view (footprints computed and cached) | {rel['first_pattern_s']:.2f} s |",
              f"| relight, CPU preset: each new pattern after it, round trip (median / max of {len(rel['new_patterns'])}) | "
              f"{rel['new_pattern_round_trip_s_median']:.2f} / {rel['new_pattern_round_trip_s_max']:.2f} s |"]
    return "\n".join(lines) + "\n"
