"""The view's work outside the browser: uploads kept while a sequence relights them, the relight stopped when the
view closes (Ctrl-C), each session's own output folder, and the live rig connecting again to a restarted daemon."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from sss_process import run_sss

pytest.importorskip("starlette")

from sssphase_view.app import MAX_UPLOADS, ViewState, _Closing, _forget_old_uploads, _Notes, relit_folder  # noqa: E402
from sssphase_view.jobs import SequenceJob  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def test_an_upload_a_sequence_still_relights_is_kept_and_the_least_recently_used_others_go(tmp_path):
    """Uploading new patterns removed the oldest upload with the frames relit under it while its sequence relight
    still ran (and its "frames relit so far are kept" was then untrue); using an upload no longer touches its file,
    whose time a sequence's record holds (touched, the same video could never be relit again)."""
    state = ViewState(token="t", out=tmp_path)
    uploads = tmp_path / "uploads"
    uploads.mkdir()
    names = [f"upload_{i:012x}.png" for i in range(MAX_UPLOADS + 3)]
    for i, name in enumerate(names):
        (uploads / name).write_bytes(b"x")
        os.utime(uploads / name, (1000 + i, 1000 + i))  # the first the oldest
        state.upload_used[name] = 1000.0 + i
    frames = tmp_path / "relit" / "star-0123abcd" / f"star_v0_{Path(names[0]).stem}_analytic"
    frames.mkdir(parents=True)
    (frames / "frame.png").write_bytes(b"x")
    state.jobs["j"] = SequenceJob("j", upload=names[0], status="running")
    state.upload_used[names[1]] = 5000.0  # used last
    mtime = (uploads / names[1]).stat().st_mtime_ns
    _forget_old_uploads(state)
    kept = sorted(p.name for p in uploads.iterdir())
    assert names[0] in kept and frames.is_dir(), "the running sequence's upload and frames were removed"
    assert names[1] in kept and (uploads / names[1]).stat().st_mtime_ns == mtime
    assert not {names[2], names[3]} & set(kept) and len(kept) == MAX_UPLOADS + 1  # the two least recently used
    state.jobs["j"].status = "done"
    _forget_old_uploads(state)
    # its upload goes, what was relit under it stays (a finished video was deleted while the page listed it)
    assert names[0] not in {p.name for p in uploads.iterdir()} and (frames / "frame.png").is_file()


def test_a_closing_view_stops_its_relight_at_the_next_step_and_each_session_has_its_folder(tmp_path):
    """A relight asked for by the page ran to its end after Ctrl-C (the server waited for it, silent: 51 s for a first
    1080p relight); two sessions of one object wrote into one folder, where the second was refused."""
    state = ViewState(token="t", out=tmp_path)
    progress = _Notes(state).task("star view 0: analytic")
    progress(1, 10)  # (not closing: goes on)
    state.jobs["j"] = SequenceJob("j", status="running")
    state.stop_work()
    with pytest.raises(_Closing):
        progress(2, 10)
    assert state.jobs["j"].stop

    class Found:
        def __init__(self, path: Path, name: str) -> None:
            self.path, self.name = path, name

    one, two = Found(tmp_path / "a" / "star", "star"), Found(tmp_path / "b" / "star", "star")
    odd = Found(tmp_path / "c" / "x", "söap #?%&<i>/../x")
    folders = {relit_folder(state, s) for s in (one, two, odd)}
    assert len(folders) == 3 and all(f.parent == tmp_path / "relit" for f in folders)
    assert all(re.fullmatch(r"[A-Za-z0-9_.-]+-[0-9a-f]{8}", f.name) for f in folders), folders
    assert relit_folder(state, one) == relit_folder(state, Found(tmp_path / "a" / "star", "star"))  # the same again


@pytest.mark.slow
def test_ctrl_c_stops_a_sequence_the_view_is_relighting_and_the_view_exits(tmp_path):
    """Ctrl-C while the page's video relit left a silent process relighting every frame to the end (119 s for a
    3,000-frame clip, hours for a long one at 1080p); it now stops at the next frame and the view exits."""
    import cv2

    runtime = Path(tempfile.mkdtemp(prefix="sssw", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "200"}
    done = run_sss(["capture", "--object", "star", "--views", "1", "--out", str(tmp_path / "sessions")], env=env,
                   cwd=REPO, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    clip = tmp_path / "long.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (256, 192))
    for i in range(2000):
        writer.write(np.full((192, 256, 3), i % 256, np.uint8))
    writer.release()
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_cli.main", "view", "--port", "0", "--sessions",
                             str(tmp_path / "sessions"), "--out", str(tmp_path / "out")], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
    try:
        url = None
        while url is None:
            line = proc.stdout.readline()
            assert line, "sss view exited"
            url = (m.group(1) if (m := re.search(r"(http://127\.0\.0\.1:\d+)/\?token=(\S+)", line)) else None)
            token = m.group(2) if m else None
        import json
        import urllib.request

        def call(path: str, data: bytes | None = None) -> dict:
            request = urllib.request.Request(url + path, data=data, method="POST" if data is not None else "GET",
                                             headers={"X-Token": token})
            with urllib.request.urlopen(request, timeout=60) as response:
                return json.loads(response.read())

        name = call("/api/upload", clip.read_bytes())["name"]
        job = call("/api/relight", json.dumps({"session": "star", "view": 0, "pattern": name,
                                               "backend": "none"}).encode())["job"]
        deadline = time.monotonic() + 120
        relit = tmp_path / "out" / "relit"
        while len(list(relit.rglob("star_v0_upload_*-*_none_display.png"))) < 20:  # frames relit, many more to come
            assert time.monotonic() < deadline and call(f"/api/relight/jobs/{job}")["status"] in ("waiting", "running")
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        asked = time.monotonic()
        out, _ = proc.communicate(timeout=60)
        took = time.monotonic() - asked
    finally:
        if proc.poll() is None:
            proc.kill()
        run_sss(["daemon", "stop"], env=env, cwd=REPO)
        shutil.rmtree(runtime, ignore_errors=True)
    assert "Traceback" not in out and f"the view stopped; the images it relit are kept in {tmp_path / 'out'}" in out, out
    frames = list(relit.rglob("star_v0_upload_*-*_none_display.png"))
    assert 20 <= len(frames) < 1000 and took < 15, (len(frames), took)  # stopped soon, the frames relit so far kept


@pytest.mark.slow
def test_the_live_rig_connects_again_to_a_restarted_daemon(tmp_path, monkeypatch):
    """After the daemon died and another started, every live frame failed with "missing or wrong token" until
    `sss view` was restarted; then the first frame after the restart failed with it on the page. The frame after
    a restart now connects to the new daemon at once."""
    from sssphase_view.live import LiveRig, LiveSettings

    runtime = Path(tempfile.mkdtemp(prefix="sssr", dir="/tmp"))
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(runtime))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime)}
    rig = LiveRig()
    try:
        assert run_sss(["daemon", "start"], env=env, cwd=REPO).returncode == 0
        first = rig.frame(LiveSettings())
        stopped = run_sss(["daemon", "stop", "--force"], env=env, cwd=REPO)
        assert stopped.returncode == 0, stopped.stdout + stopped.stderr
        assert run_sss(["daemon", "start"], env=env, cwd=REPO).returncode == 0  # another daemon, another token
        again = rig.frame(LiveSettings())
        assert again.image.shape == first.image.shape and again.sequence == first.sequence + 1
    finally:
        rig.close()
        run_sss(["daemon", "stop", "--force"], env=env, cwd=REPO)
        shutil.rmtree(runtime, ignore_errors=True)


def test_a_view_off_loopback_needs_tls_and_serves_its_page_over_https(tmp_path):
    """`--allow-remote` served plain HTTP: the token crossed the network readable in every request and in the
    page's URL. Off loopback the view now needs a certificate; with one it serves HTTPS (loopback too)."""
    import json
    import ssl
    import urllib.request

    from sssphase_core.errors import InputError
    from sssphase_view.server import allowed_hosts, check_host, check_tls

    with pytest.raises(InputError, match=r"would cross the network in plain HTTP; give --tls-cert and --tls-key"):
        check_host("0.0.0.0", allow_remote=True, tls=False)
    with pytest.raises(InputError, match=r"not loopback: anyone on that network could reach the rig"):
        check_host("192.168.1.20", allow_remote=False, tls=True)
    check_host("0.0.0.0", allow_remote=True, tls=True)
    check_host("::1", allow_remote=False, tls=False)
    # --allow-remote on loopback dropped the DNS-rebinding guard
    assert allowed_hosts("127.0.0.1", allow_remote=True) == allowed_hosts("127.0.0.1", False) == ["127.0.0.1", "localhost"]
    assert allowed_hosts("::1", allow_remote=True) == ["127.0.0.1", "::1", "localhost"]
    assert allowed_hosts("0.0.0.0", allow_remote=True) is None
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("no openssl command to make a test certificate")
    cert, key, other = tmp_path / "cert.pem", tmp_path / "key.pem", tmp_path / "other.pem"
    for out_key in (key, other):
        made = subprocess.run([openssl, "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(out_key),
                               "-out", str(cert), "-days", "1", "-subj", "/CN=localhost",
                               "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost"], capture_output=True, timeout=60)
        assert made.returncode == 0, made.stderr
    with pytest.raises(InputError, match=r"do not load as a PEM certificate and its key"):
        check_tls(cert, key)  # the certificate is the second key's
    with pytest.raises(InputError, match=r"--tls-key .*: no such file"):
        check_tls(cert, tmp_path / "missing.pem")
    # a key under a passphrase is asked for it once (OpenSSL asked on the terminal at each of two loads), refused
    # in one line where nobody can be asked
    locked, locked_cert = tmp_path / "locked.pem", tmp_path / "locked_cert.pem"
    made = subprocess.run([openssl, "req", "-x509", "-newkey", "rsa:2048", "-passout", "pass:s3cret", "-keyout",
                           str(locked), "-out", str(locked_cert), "-days", "1", "-subj", "/CN=localhost"],
                          capture_output=True, timeout=60, stdin=subprocess.DEVNULL)
    assert made.returncode == 0, made.stderr
    locked.chmod(0o600)
    with pytest.raises(InputError, match=r"is encrypted with a passphrase, and there is no terminal to ask it on"):
        check_tls(locked_cert, locked)
    asked: list[str] = []
    assert check_tls(locked_cert, locked, ask=lambda prompt: asked.append(prompt) or "s3cret") == "s3cret"
    assert asked == [f"passphrase of {locked}: "]
    with pytest.raises(InputError, match=r"does not open with that passphrase"):
        check_tls(locked_cert, locked, ask=lambda prompt: "wrong")
    other.chmod(0o644)
    with pytest.warns(UserWarning, match=r"can be read by other users of this machine: chmod 600 it"):
        assert check_tls(cert, other) is None
    other.chmod(0o600)
    refused = run_sss(["view", "--host", "0.0.0.0", "--allow-remote"], cwd=tmp_path)
    assert refused.returncode != 0 and "plain HTTP" in refused.stdout + refused.stderr
    assert "Traceback" not in refused.stdout + refused.stderr
    runtime = Path(tempfile.mkdtemp(prefix="ssss", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime)}
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_cli.main", "view", "--port", "0", "--tls-cert",
                             str(cert), "--tls-key", str(other), "--out", str(tmp_path / "out")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
    try:
        line = proc.stdout.readline()
        m = re.search(r"(https://127\.0\.0\.1:\d+)/\?token=(\S+)", line)
        assert m, line
        trusting = ssl.create_default_context(cafile=str(cert))
        request = urllib.request.Request(m.group(1) + "/api/state", headers={"X-Token": m.group(2)})
        with urllib.request.urlopen(request, timeout=30, context=trusting) as response:
            assert response.status == 200 and "sessions" in json.loads(response.read())
        with pytest.raises(OSError):  # plain HTTP to the HTTPS port gets no page
            urllib.request.urlopen(m.group(1).replace("https", "http") + "/api/state", timeout=10).read()
    finally:
        proc.terminate()
        proc.wait(20)
        shutil.rmtree(runtime, ignore_errors=True)


def test_the_live_gain_brightens_like_a_cameras_and_clipping_is_seen_in_frames_and_decodes(tmp_path, monkeypatch):
    """On the sim camera a gain made the frame darker and flat grey without one clipped pixel (the sim divided it
    out and the view measured against 1, not the sensor's full well), a gain of 0 failed every frame until a 1 was
    typed, an emptied gain field kept the last gain, and live decode never counted a SATURATED pixel."""
    from sssphase_core.errors import SssError
    from sssphase_view.live import LiveRig, LiveSettings

    runtime = Path(tempfile.mkdtemp(prefix="sssr", dir="/tmp"))
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(runtime))
    rig = LiveRig()
    try:
        plain = rig.frame(LiveSettings(exposure=0.5))
        bright = rig.frame(LiveSettings(exposure=0.5, gain=4.0))
        lit = plain.image.max(axis=-1) > 0.05
        ratio = np.median(bright.image[lit] / np.maximum(plain.image[lit], 1e-6))
        assert 3.5 < ratio < 4.5, ratio
        assert plain.stats.clipped < 0.01 < bright.stats.clipped and bright.stats.clip == plain.stats.clip > 1
        with pytest.raises(SssError, match="the sim camera's gain is a factor on the signal and must be positive, got 0"):
            rig.frame(LiveSettings(exposure=0.5, gain=0.0))
        back = rig.frame(LiveSettings(exposure=0.5, gain=None))  # the field emptied: the gain the rig opened with
        np.testing.assert_allclose(np.median(back.image[lit]), np.median(plain.image[lit]), rtol=0.02)
        calm, _, _ = rig.decode(LiveSettings(exposure=1.0, decode=True))
        blown, _, _ = rig.decode(LiveSettings(exposure=8.0, decode=True))
        assert calm.coverage.get("SATURATED", 0) < 0.01 * calm.mask.size
        assert blown.coverage["SATURATED"] > 0.1 * calm.mask.sum(), blown.coverage
    finally:
        rig.close()
        run_sss(["daemon", "stop", "--force"], env={**os.environ, "SSS_RUNTIME_DIR": str(runtime)}, cwd=REPO)
        shutil.rmtree(runtime, ignore_errors=True)
