"""A daemon used from another machine: `sss daemon connection` writes the folder a client there sets `SSS_DAEMON` to
(its endpoint, token and CURVE keys); `sss capture` and `sss devices` then go through that daemon, and start none of
their own. Here the other machine is another runtime folder of this one, the daemon on a CURVE TCP socket."""

from __future__ import annotations

import json
import os
import shutil
import socket
import tempfile
from pathlib import Path

from sss_process import run_sss

from sssphase_core.store.session import Session
from sssphase_daemon.client import DaemonClient


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_client_elsewhere_captures_through_the_daemon_its_connection_folder_names(tmp_path):
    here = Path(tempfile.mkdtemp(prefix="sssA", dir="/tmp"))  # the daemon's machine
    there = Path(tempfile.mkdtemp(prefix="sssB", dir="/tmp"))  # the client's: no daemon of its own
    rig_pc = {**os.environ, "SSS_RUNTIME_DIR": str(here), "SSS_CONFIG_DIR": str(tmp_path / "config")}
    keys = tmp_path / "config" / "sssphase" / "curve"
    try:
        assert run_sss(["daemon", "keys"], env=rig_pc).returncode == 0
        started = run_sss(["daemon", "start", "--endpoint", f"tcp://0.0.0.0:{_free_port()}", "--curve-dir", str(keys)],
                          env=rig_pc)
        assert started.returncode == 0, started.stdout + started.stderr
        folder = tmp_path / "conn"
        made = run_sss(["daemon", "connection", "--out", str(folder), "--host", "127.0.0.1"], env=rig_pc)
        assert made.returncode == 0 and "SSS_DAEMON" in made.stdout, made.stdout + made.stderr
        assert oct(folder.stat().st_mode & 0o777) == "0o700" and (folder / "client.key_secret").is_file()
        assert json.loads((folder / "connection.json").read_text())["endpoint"].startswith("tcp://127.0.0.1:")
        again = run_sss(["daemon", "connection", "--out", str(folder)], env=rig_pc)
        assert again.returncode == 2 and "exists: give a new folder" in again.stderr
        client = {**os.environ, "SSS_RUNTIME_DIR": str(there), "SSS_DAEMON": str(folder)}
        listed = run_sss(["devices"], env=client)
        assert listed.returncode == 0 and "devices (daemon)" in listed.stdout, listed.stdout + listed.stderr
        done = run_sss(["capture", "--object", "soap", "--views", "1", "--out", str(tmp_path / "s")], env=client,
                       timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        assert Session.open(tmp_path / "s" / "soap").views() == [0] and "started a local one" not in done.stdout
        assert not (there / "daemon.json").exists()  # none started there
        stale = tmp_path / "stale"  # the daemon restarted since the folder was written: another token
        shutil.copytree(folder, stale)
        data = json.loads((stale / "connection.json").read_text())
        (stale / "connection.json").write_text(json.dumps({**data, "token": "x" * 43}))
        refused = run_sss(["devices"], env={**client, "SSS_DAEMON": str(stale)})
        assert "refused the token in" in refused.stdout + refused.stderr and "`sss daemon connection`" in refused.stderr
        wrong = tmp_path / "wrong"
        shutil.copytree(folder, wrong)
        for endpoint, token in (("tcp://127.0.0.1:1", ""), ("tcp://127.0.0.1:*", "x")):  # ("*": an internal error)
            (wrong / "connection.json").write_text(json.dumps({"endpoint": endpoint, "token": token}))
            refused = run_sss(["capture", "--object", "soap", "--views", "1", "--out", str(tmp_path / "w")],
                              env={**client, "SSS_DAEMON": str(wrong)})
            assert refused.returncode == 2 and "must hold a tcp endpoint and the daemon's token" in refused.stderr
            assert "Traceback" not in refused.stderr
        # `sss daemon stop` acts on this machine's daemon: with SSS_DAEMON set, the rig PC's daemon in use by a rig is
        # still refused a stop (it looked for rigs through SSS_DAEMON, found none, and stopped the local daemon)
        held = DaemonClient.from_connection(folder)
        with held:
            held.call("open_rig", camera="sim:camera0", projector="sim:projector0", turntable=None, options={})
            stop = run_sss(["daemon", "stop"], env={**rig_pc, "SSS_DAEMON": str(wrong)})
            assert stop.returncode != 0 and "rig" in stop.stdout + stop.stderr, stop.stdout + stop.stderr
    finally:
        run_sss(["daemon", "stop", "--force"], env=rig_pc)
        shutil.rmtree(here, ignore_errors=True)
        shutil.rmtree(there, ignore_errors=True)
