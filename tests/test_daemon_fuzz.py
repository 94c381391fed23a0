"""A fuzz corpus of 20,000 malformed control messages of our own making, sent to a real daemon.

Every client mistake must be answered with a client-error code (never ``internal``), the daemon log
must hold no traceback, and the daemon must answer the next good request.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq

from sssphase_daemon import protocol, security

N_MESSAGES = 20_000
# shutdown would end the run; devices takes no arguments and costs ~0.5 s of hardware discovery per call
OPS = [op for op in protocol.OPS if op not in ("shutdown", "devices")]


def _value(rng: np.random.Generator, depth: int = 0):
    kind = rng.integers(0, 11 if depth < 2 else 8)
    return [
        lambda: int(rng.integers(-2**40, 2**40)), lambda: float(rng.normal() * 10.0 ** int(rng.integers(-3, 12))),
        lambda: float("nan"), lambda: bool(rng.integers(0, 2)), lambda: None,
        lambda: "".join(chr(int(c)) for c in rng.integers(32, 0x2FF, rng.integers(0, 12))),
        lambda: bytes(rng.integers(0, 256, rng.integers(0, 16), dtype=np.uint8)),
        lambda: rng.choice(["sim:camera0", "sim:projector0", "sim:turntable0", "x", "", "../..", "apple", "dots/0_0"]).item(),
        lambda: [_value(rng, depth + 1) for _ in range(rng.integers(0, 4))],
        lambda: {str(_value(rng, 2)): _value(rng, depth + 1) for _ in range(rng.integers(0, 4))},
        lambda: {"name": "dots/0_0", "kind": rng.choice(list(protocol.OPS) + ["dots", "psp", "ref", "image", "white"]).item(),
                 "params": {k: _value(rng, depth + 1) for k in rng.choice(
                     ["width", "height", "spacing", "shift_x", "shift_y", "period", "shift", "n_shifts", "gamma",
                      "orientation", "name", "square"], rng.integers(0, 6)).tolist()},
                 "exposure": _value(rng, 2), "image": _value(rng, depth + 1)},
    ][kind]()


def _corpus(token: str, rng: np.random.Generator) -> list[bytes]:
    messages = []
    keys = ["camera", "projector", "turntable", "trigger", "options", "rig", "angle", "frames", "job", "count", "timeout_s"]
    for i in range(N_MESSAGES):
        kind = i % 5
        if kind == 0:  # not msgpack, or truncated msgpack
            messages.append(bytes(rng.integers(0, 256, rng.integers(0, 48), dtype=np.uint8)))
        elif kind == 1:  # msgpack, but not a request map
            messages.append(msgpack.packb(_value(rng), use_bin_type=True))
        elif kind == 2:  # a map with wrong fields (version, id, op, token types)
            msg = {"v": _value(rng) if rng.random() < 0.5 else 1, "id": _value(rng), "op": _value(rng) if rng.random() < 0.3
                   else rng.choice(OPS).item(), "token": token if rng.random() < 0.5 else _value(rng), "args": _value(rng)}
            messages.append(msgpack.packb(msg, use_bin_type=True))
        else:  # authenticated, well-formed, with arguments a confused client might send
            args = {k: _value(rng) for k in rng.choice(keys, rng.integers(0, 5), replace=False).tolist()}
            if rng.random() < 0.3:
                args["frames"] = [_value(rng) for _ in range(rng.integers(0, 4))]
            if rng.random() < 0.3:
                args.update(camera="sim:camera0", options={"object": _value(rng), **{k: _value(rng) for k in rng.choice(
                    ["n_views", "seed", "view", "preset", "latency_s", "frame_period_s", "raw"], rng.integers(0, 3)).tolist()}})
            messages.append(protocol.pack({"v": 1, "id": i, "op": rng.choice(OPS).item(), "token": token, "args": args}))
    return messages


@pytest.mark.slow
def test_twenty_thousand_malformed_messages_get_client_errors_and_no_traceback():
    runtime = Path(tempfile.mkdtemp(prefix="sssf", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime)}
    log = runtime / "daemon.log"
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_daemon", "--client-timeout", "30"], env=env,
                            stdout=open(log, "wb"), stderr=subprocess.STDOUT)  # noqa: SIM115
    ctx = zmq.Context()
    try:
        deadline = time.monotonic() + 30
        while (state := security.read_state(runtime / "daemon.json")) is None:
            assert time.monotonic() < deadline and proc.poll() is None, log.read_text()
            time.sleep(0.05)
        sock = ctx.socket(zmq.DEALER)
        sock.linger = 0
        sock.connect(state.endpoint)
        codes: dict[str, int] = {}
        messages = _corpus(state.token, np.random.default_rng(20261122))
        sent = received = 0
        window = 64
        while received < len(messages):
            while sent < len(messages) and sent - received < window:
                sock.send_multipart([b"", messages[sent]])
                sent += 1
            if not sock.poll(20_000):
                pytest.fail(f"no reply after {received} of {len(messages)} messages:\n{log.read_text()[-2000:]}")
            reply = protocol.unpack(sock.recv_multipart()[-1])
            received += 1
            code = "ok" if reply.get("ok") else reply["error"]["code"]
            codes[code] = codes.get(code, 0) + 1
        assert codes.get(protocol.INTERNAL, 0) == 0, codes
        assert received == N_MESSAGES and codes.get("ok", 0) < N_MESSAGES // 2, codes
        sock.send_multipart([b"", protocol.request("last", "ping", state.token)])
        assert sock.poll(10_000) and protocol.unpack(sock.recv_multipart()[-1])["ok"]
        assert "Traceback" not in log.read_text(), log.read_text()[-3000:]
    finally:
        proc.terminate()
        proc.wait(20)
        ctx.destroy(linger=0)
        shutil.rmtree(runtime, ignore_errors=True)
