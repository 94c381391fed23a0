"""A daemon used from another machine: `sss daemon connection` writes the folder a client there sets `SSS_DAEMON` to
(its endpoint, token and CURVE keys); `sss capture` and `sss devices` then go through that daemon, and start none of
their own. Here the other machine is another runtime folder of this one, the daemon on a CURVE TCP socket."""

from __future__ import annotations

import json
import os
import shutil
import socket
import tempfile
import time
from pathlib import Path

import pytest
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
        bad = run_sss(["daemon", "connection", "--out", str(folder), "--host", "rig pc"], env=rig_pc)
        assert bad.returncode == 2 and "--host 'rig pc' is not a host name or an address" in bad.stderr, bad.stderr
        assert not folder.exists()  # refused before anything was written
        made = run_sss(["daemon", "connection", "--out", str(folder), "--host", "127.0.0.1"], env=rig_pc)
        assert made.returncode == 0 and "SSS_DAEMON" in made.stdout, made.stdout + made.stderr
        assert "note: 127.0.0.1 is the client's own machine" in made.stdout  # (here it is: the test's "other machine")
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
        (wrong / "connection.json").write_text(json.dumps({"endpoint": f"tcp://127.0.0.1:{_free_port()}", "token": "x"}))
        gone = run_sss(["devices"], env={**client, "SSS_DAEMON": str(wrong)})  # listed this machine's devices, exit 0
        assert gone.returncode == 2 and "did not answer within 5 s" in gone.stderr and "devices (" not in gone.stdout
        status = run_sss(["daemon", "status"], env={**rig_pc, "SSS_DAEMON": str(wrong)})
        assert status.returncode == 0 and f"note: SSS_DAEMON={wrong} names a daemon on another machine" in status.stderr
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


def test_a_connection_is_refused_before_writing_for_a_daemon_no_other_machine_reaches(tmp_path, monkeypatch):
    """An ipc daemon with CURVE keys got a connection folder whose endpoint no client could read back; a daemon on
    every interface got "localhost" when the machine's name was that."""
    from sssphase_daemon import security

    keys = security.generate_keys(tmp_path / "keys")
    state = security.DaemonState("ipc:///tmp/x.sock", "t" * 32, 1, "0", 0.0, curve_dir=str(keys))
    with pytest.raises(security.KeyFileError, match=r"serves ipc:///tmp/x.sock, which no other machine reaches"):
        security.write_connection(tmp_path / "conn", state, "rig-pc")
    wildcard = security.DaemonState("tcp://0.0.0.0:5609", "t" * 32, 1, "0", 0.0, curve_dir=str(keys))
    for host in ("", "*", "rig pc", "a:b:c:zz"):
        with pytest.raises(security.KeyFileError, match="is not a host name or an address"):
            security.write_connection(tmp_path / "conn", wildcard, host)
    assert not (tmp_path / "conn").exists()
    assert security.read_connection(security.write_connection(tmp_path / "conn", wildcard, "rig-pc.lab")).endpoint == \
        "tcp://rig-pc.lab:5609"
    monkeypatch.setattr(socket, "getfqdn", lambda *a: "localhost")  # a machine whose name is localhost
    name = security.machine_name()
    assert name is None or not security.is_loopback_host(name)
    monkeypatch.setattr(socket, "getfqdn", lambda *a: "rig-pc.lab")
    assert security.machine_name() == "rig-pc.lab"
    assert all(security.is_loopback_host(h) for h in ("localhost", "LOCALHOST", "127.0.1.1", "::1", "[::1]"))
    assert not any(security.is_loopback_host(h) for h in ("rig-pc", "10.0.0.2", "fe80::1"))


def test_a_daemon_with_only_its_server_keys_starts_and_admits_a_client_key_copied_in_while_it_runs(tmp_path):
    """A key folder holding the server's keys and the authorised clients' public ones (each client's secret key on its
    own machine): `sss daemon start` killed the daemon it had started (it asked it with a client key that is not
    there), and a client key authorised later took effect only at a restart, which changed the token."""
    from sssphase_daemon import security

    here = Path(tempfile.mkdtemp(prefix="sssA", dir="/tmp"))
    there = Path(tempfile.mkdtemp(prefix="sssB", dir="/tmp"))
    rig_pc = {**os.environ, "SSS_RUNTIME_DIR": str(here)}
    keys = security.generate_keys(tmp_path / "keys")
    for name in ("client.key_secret", "client.key"):
        (keys / name).unlink()
    try:
        started = run_sss(["daemon", "start", "--endpoint", f"tcp://0.0.0.0:{_free_port()}", "--curve-dir", str(keys)],
                          env=rig_pc)
        assert started.returncode == 0 and "daemon started" in started.stdout, started.stdout + started.stderr
        status = run_sss(["daemon", "status"], env=rig_pc)
        assert status.returncode == 0 and "admits CURVE clients only" in status.stdout, status.stdout + status.stderr
        folder = tmp_path / "conn"
        made = run_sss(["daemon", "connection", "--out", str(folder), "--host", "127.0.0.1"], env=rig_pc)
        assert made.returncode == 0 and "holds no client key (the server's keys only)" in made.stdout, made.stdout
        assert not (folder / "client.key_secret").exists() and (folder / "server.key").is_file()
        client = {**os.environ, "SSS_RUNTIME_DIR": str(there), "SSS_DAEMON": str(folder)}
        keyless = run_sss(["devices"], env=client)
        assert keyless.returncode == 2 and "no client.key_secret there" in keyless.stderr, keyless.stderr
        own = security.generate_keys(tmp_path / "own")  # the client machine's pair
        for name in ("client.key_secret", "client.key"):
            shutil.copyfile(own / name, folder / name)
        shutil.copyfile(own / "client.key", keys / "authorized_clients" / "lab2.key")  # authorised while it runs:
        time.sleep(2.5)  # admitted within 2 s
        listed = run_sss(["devices"], env=client)
        assert listed.returncode == 0 and "devices (daemon)" in listed.stdout, listed.stdout + listed.stderr
        stop = run_sss(["daemon", "stop"], env=rig_pc)
        assert stop.returncode == 2 and "`sss daemon stop --force` ends it" in stop.stderr, stop.stdout + stop.stderr
        stop = run_sss(["daemon", "stop", "--force"], env=rig_pc)
        assert stop.returncode == 0 and "stopped" in stop.stdout, stop.stdout + stop.stderr
    finally:
        run_sss(["daemon", "stop", "--force"], env=rig_pc)
        shutil.rmtree(here, ignore_errors=True)
        shutil.rmtree(there, ignore_errors=True)
