"""`sss view` in a real browser (Debian's chromium, headless, over the DevTools protocol): the token, live
frames that follow the exposure and the pattern, live decode, a session's maps, relighting an uploaded
pattern to the same image `sss relight` writes, and hostile input answered on the page."""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
import zlib
from pathlib import Path

import numpy as np
import pytest
from sss_process import run_sss

pytest.importorskip("starlette")
pytest.importorskip("websocket", reason="websocket-client (dev extra) drives the browser")
cdp = pytest.importorskip("cdp")

if not cdp.available():
    pytest.skip("/usr/bin/chromium is not installed (Debian package `chromium`)", allow_module_level=True)

pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("view")]
REPO = Path(__file__).resolve().parents[2]


def _sss(*args: str, env: dict[str, str], timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return run_sss([*args], env=env, cwd=REPO, timeout=timeout)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A session with a reference capture, and `sss view` serving it (its own daemon for the live view)."""
    root = tmp_path_factory.mktemp("view")
    runtime = Path(tempfile.mkdtemp(prefix="sssv", dir="/tmp"))
    env = {**os.environ, "SSS_RUNTIME_DIR": str(runtime), "COLUMNS": "200"}
    done = _sss("capture", "--object", "star", "--views", "1", "--reference", "checkerboard", "--out",
                str(root / "sessions"), env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_cli.main", "view", "--port", "0", "--sessions",
                             str(root / "sessions"), "--out", str(root / "out")], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO)
    url = None
    deadline = time.monotonic() + 60
    while url is None and time.monotonic() < deadline:
        line = proc.stdout.readline()
        m = re.search(r"(http://127\.0\.0\.1:\d+/\?token=\S+)", line)
        url = m.group(1) if m else None
        assert line or proc.poll() is None, "sss view exited"
    assert url, "sss view printed no URL"
    yield {"url": url, "base": url.split("/?")[0], "token": url.split("token=")[1], "root": root, "env": env}
    proc.terminate()
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
    _sss("daemon", "stop", env=env)


@pytest.fixture(scope="module")
def page(served, tmp_path_factory):
    browser = cdp.Browser(tmp_path_factory.mktemp("profile"))
    browser.open(served["url"])
    yield browser
    browser.close()


def _get(url: str, token: str | None = None) -> tuple[int, bytes]:
    request = urllib.request.Request(url, headers={"X-Token": token} if token else {})
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def test_every_route_needs_the_token(served):
    import websocket

    base = served["base"]
    assert _get(base + "/")[0] == 403 and _get(base + "/?token=wrong")[0] == 403
    assert b"sss view needs its token" in _get(base + "/?token=wrong")[1]  # (a page for a person, not JSON)
    assert _get(base + "/api/state")[0] == 403 and _get(base + "/api/state", "wrong")[0] == 403
    assert _get(base + "/api/state", served["token"])[0] == 200
    # a websocket is closed with the reason, no frame sent first (a page left open across a restart of the view
    # holds the old token: it says so and stops retrying, where a refused handshake read as a dropped connection)
    ws = websocket.create_connection(base.replace("http", "ws") + "/ws/live?token=wrong", timeout=10)
    opcode, data = ws.recv_data(control_frame=True)
    assert opcode == websocket.ABNF.OPCODE_CLOSE and int.from_bytes(data[:2], "big") == 4403
    assert data[2:].decode().startswith("wrong or missing token: the view was restarted")


def test_a_missing_sessions_folder_or_a_checkpoint_that_does_not_load_is_refused_before_serving(tmp_path):
    """Both served: an empty session list, and an error at the first relight; a calibration file is read first too."""
    env = {**os.environ, "SSS_RUNTIME_DIR": str(tmp_path / "rt")}
    (tmp_path / "bad.pt").write_text("not a checkpoint")
    for args, expected in ((["--sessions", str(tmp_path / "none")], "no such folder"),
                           (["--sessions", str(tmp_path / "bad.pt")], "a file, not a folder of sessions"),
                           (["--checkpoint", str(tmp_path / "bad.pt")], "not a checkpoint file"),
                           (["--calibration", str(tmp_path / "bad.pt")], "not an OpenCV calibration file"),
                           (["--calibration", str(tmp_path / "none.yml")], "no such file")):
        done = _sss("view", "--port", "0", "--out", str(tmp_path / "out"), *args, env=env, timeout=60)
        out = done.stdout + done.stderr
        assert done.returncode == 2 and expected in out and len(out.strip().splitlines()) == 1, out


def _post(url: str, token: str, body: bytes) -> tuple[int, dict]:
    request = urllib.request.Request(url, data=body, method="POST",
                                     headers={"X-Token": token, "Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


def test_requests_the_page_never_sends_are_answered_not_crashed_on(served, tmp_path):
    """Found by hand (each was a 500 with a traceback in the server's log, or worse): a click off the object
    (its projector point is NaN, which JSON has not), a NUL byte or an overlong file name, a view of Infinity,
    a body nested 30,000 deep; and a pattern given as a path on the server, which was read, relit and served."""
    base, token = served["base"], served["token"]
    name = json.loads(_get(base + "/api/state", token)[1])["sessions"][0]["name"]
    status, body = _get(base + f"/api/sessions/{name}/0/pixel?x=0&y=0", token)
    assert status == 200 and json.loads(body)["valid"] is False and None in json.loads(body)["projector"]
    assert _get(base + "/api/files/relit/%00", token)[0] == 404
    assert _get(base + "/api/files/relit/" + "a" * 5000, token)[0] == 404
    for radius in ("abc", "nan", "-1", "1e999"):  # a crop radius the page's number box would not send
        status, body = _get(base + f"/api/sessions/{name}/0/points?radius={radius}", token)
        assert status == 400 and "crop radius" in json.loads(body)["error"], (radius, body)
    assert _post(base + "/api/relight", token, b'{"session": "%s", "view": Infinity}' % name.encode())[0] == 400
    assert _post(base + "/api/relight", token, b'{"session": "%s", "view": true}' % name.encode())[0] == 400
    assert _post(base + "/api/relight", token, b'{"a":' + b"[" * 30_000 + b"]" * 30_000 + b"}")[0] == 400  # (< 64 kB)
    secret = tmp_path / "secret.png"
    import cv2

    cv2.imwrite(str(secret), np.full((192, 256), 255, np.uint8))  # any image the server can read
    status, answer = _post(base + "/api/relight", token, json.dumps(
        {"session": name, "view": 0, "pattern": str(secret), "backend": "none"}).encode())
    assert status == 400 and "is neither an uploaded pattern nor one of" in answer["error"]
    assert not list((served["root"] / "out").rglob("*secret*"))
    assert _get(base + "/api/state", token)[0] == 200  # still serving


def _live(base: str, token: str, wait_s: float = 60.0):
    """A live-stream websocket, once the view takes one more: at most 4 are open at once, and one a test just
    closed counts until the server has finished the frame it was taking for it (seconds on a loaded machine)."""
    import websocket

    deadline = time.monotonic() + wait_s
    while True:
        try:
            return websocket.create_connection(base.replace("http", "ws") + f"/ws/live?token={token}", timeout=60)
        except websocket.WebSocketBadStatusException:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def test_oversized_numbers_and_bodies_binary_messages_and_a_damaged_session_are_answered(served):
    """Found by an adversarial sweep: a 5000-digit view in a URL was a 500 before the token was checked, and one
    in a relight body a 500; a 300 MB relight body was read whole (+880 MB); a binary or 5000-digit websocket
    message ended the live stream; one damaged session folder made every session unreachable; any Host was served."""
    import websocket

    base, token = served["base"], served["token"]
    name = json.loads(_get(base + "/api/state", token)[1])["sessions"][0]["name"]
    huge = "9" * 5000
    assert _get(base + f"/api/sessions/{name}/{huge}/pixel?x=1&y=1")[0] == 403  # the token first
    status, body = _get(base + f"/api/sessions/{name}/{huge}/map/xp.png", token)
    assert status == 400 and "the view must be a view number" in json.loads(body)["error"]
    status, answer = _post(base + "/api/relight", token, b'{"session": "%s", "view": %s}' % (name.encode(), huge.encode()))
    assert status == 400 and answer["error"] == "the request body must be JSON"
    status, answer = _post(base + "/api/relight", token, b'{"pad": "' + b"x" * (1 << 20) + b'"}')
    assert status == 413 and "larger than 64 kB" in answer["error"]
    request = urllib.request.Request(base + "/api/state", headers={"X-Token": token})
    with urllib.request.urlopen(request, timeout=30) as response:
        assert response.headers["X-Content-Type-Options"] == "nosniff"
    rebound = urllib.request.Request(base + "/api/state", headers={"X-Token": token, "Host": "evil.example"})
    with pytest.raises(urllib.error.HTTPError, match="400"):  # a name re-pointed at 127.0.0.1 (DNS rebinding)
        urllib.request.urlopen(rebound, timeout=30)
    ws = _live(base, token)
    others: list = []
    try:
        ws.send_binary(b"\x00\x01")
        ws.send(f'{{"exposure": {huge}}}')
        ws.send('{"a":' * 5000 + "1" + "}" * 5000)
        seen = set()
        deadline = time.monotonic() + 60
        while len(seen) < 3 and time.monotonic() < deadline:  # frames keep coming after all three
            message = ws.recv()
            if isinstance(message, str) and json.loads(message).get("type") == "frame":
                seen.add(json.loads(message)["sequence"])
        assert len(seen) == 3
        # live streams are capped (each holds a thread waiting on the rig): the fifth is closed saying why (it was
        # refused as a bad token is, a bare 403)
        for _ in range(4):
            others.append(websocket.create_connection(base.replace("http", "ws") + f"/ws/live?token={token}", timeout=60))
        opcode, frame = others[-1].recv_data_frame(control_frame=True)
        while opcode != websocket.ABNF.OPCODE_CLOSE:  # (the fifth gets no frame before its close)
            opcode, frame = others[-1].recv_data_frame(control_frame=True)
        assert struct.unpack("!H", frame.data[:2])[0] == 1013 and b"live views are open already" in frame.data[2:]
    finally:
        ws.close()
        for other in others:
            other.close()
    damaged = served["root"] / "sessions" / "zz_damaged"
    damaged.mkdir()
    try:
        (damaged / "manifest.json").write_text("")
        state = json.loads(_get(base + "/api/state", token)[1])
        assert [s["name"] for s in state["sessions"]] == [name] and "zz_damaged" in state["damaged"]
        assert _get(base + f"/api/sessions/{name}/0/map/xp.png", token)[0] == 200
    finally:
        (damaged / "manifest.json").unlink()
        damaged.rmdir()


def test_connections_that_never_finish_a_request_are_closed_and_a_live_stream_is_not(served):
    """Connections that never sent a whole request head were held until the client closed them: ~20,000 of them
    (the file-descriptor limit) kept the page from being served, without the token."""
    import socket

    from sssphase_view.server import REQUEST_HEAD_S

    base, token = served["base"], served["token"]
    host, port = base.removeprefix("http://").split(":")
    ws = _live(base, token)
    started = time.monotonic()
    idle = socket.create_connection((host, int(port)), timeout=REQUEST_HEAD_S * 4)
    slow = socket.create_connection((host, int(port)), timeout=REQUEST_HEAD_S * 4)
    slow.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # the head never ends
    try:
        assert idle.recv(1) == b"" and slow.recv(1) == b""  # closed by the server
        assert REQUEST_HEAD_S - 1 < time.monotonic() - started < REQUEST_HEAD_S * 3
        ws.recv()  # the live stream, older than the deadline, still streams
        assert _get(base + "/api/state", token)[0] == 200
    finally:
        for s in (idle, slow):
            s.close()
        ws.close()


def _set(page, element: str, value) -> None:
    page.evaluate(f"(() => {{ const e = document.getElementById({json.dumps(element)}); "
                  f"if (e.type === 'checkbox') e.checked = {json.dumps(value)}; else e.value = {json.dumps(value)}; "
                  "e.dispatchEvent(new Event('change')); })()")


def _frame_mean(page) -> float:
    return page.evaluate("Number(document.getElementById('mean').textContent.split(' / ')[1])")


def _frame_green(page) -> np.ndarray:
    """The green channel of the frame the page shows, as the page has it (H, W). A live frame may be loading when
    asked (its naturalWidth reads 0 until it is decoded): the page's image is read once it is whole, in the same
    task, so no later frame replaces it in between."""
    values = page.evaluate("""(async () => { const img = document.getElementById('live-image');
        for (let i = 0; i < 500 && !(img.complete && img.naturalWidth > 0); i++) await new Promise(r => setTimeout(r, 10));
        const c = document.createElement('canvas'); c.width = img.naturalWidth; c.height = img.naturalHeight;
        const g = c.getContext('2d'); g.drawImage(img, 0, 0); const d = g.getImageData(0, 0, c.width, c.height).data;
        const out = []; for (let i = 1; i < d.length; i += 4) out.push(d[i]); return [c.height, c.width, out]; })()""")
    return np.asarray(values[2], np.float32).reshape(values[0], values[1])


def test_live_frames_arrive_and_follow_the_exposure_and_the_pattern(page, tmp_path):
    page.wait_for("Number(document.getElementById('frame-count').textContent) > 3", 60)
    # the count rises as the next frame starts loading (its naturalWidth reads 0 until it is decoded): read the
    # width once the image is whole, in the same task, as _frame_green does
    assert page.evaluate("""(async () => { const img = document.getElementById('live-image');
        for (let i = 0; i < 500 && !(img.complete && img.naturalWidth > 0); i++) await new Promise(r => setTimeout(r, 10));
        return img.naturalWidth; })()""") == 256
    assert float(page.evaluate("document.getElementById('fps').textContent")) > 0
    assert float(page.evaluate("document.getElementById('latency').textContent")) >= 0
    _set(page, "pattern", "white")
    _set(page, "exposure", 1)
    page.wait_for("state.shown.exposure === 1 && state.shown.pattern === 'white'", 30)
    bright, white = _frame_mean(page), _frame_green(page)
    assert (white > 60).mean() > 0.02  # the object, lit
    _set(page, "exposure", 0.5)
    page.wait_for("state.shown.exposure === 0.5", 30)
    assert abs(_frame_mean(page) - bright / 2) < 0.1 * bright  # the camera's signal halves with the exposure
    _set(page, "exposure", 1)
    _set(page, "pattern", "checkerboard")
    page.wait_for("state.shown.exposure === 1 && state.shown.pattern === 'checkerboard'", 30)
    assert abs(_frame_mean(page) - bright / 2) < 0.15 * bright  # half the squares lit
    # the frame on the page shows the checkerboard: of the pixels lit under white, some stay as bright (the lit
    # squares) and some are far darker (the dark squares, lit only by light scattered under the surface)
    ratio = _frame_green(page)[white > 60] / white[white > 60]  # display (sRGB) values
    assert (white > 60).sum() > 500 and (ratio > 0.9).mean() > 0.2 and (ratio < 0.7).mean() > 0.2, np.percentile(ratio, [10, 50, 90])
    # zoom in, and a click on the frame reads that pixel's value from the frame itself
    _set(page, "zoom", "2")
    assert page.evaluate("document.getElementById('live-image').getBoundingClientRect().width") == 512
    # click while the next frame is still loading (the image's naturalWidth reads 0 then): the page maps the click
    # with the size of the frame it shows
    loading = page.evaluate("state.liveProbe = null; (async () => { const img = document.getElementById('live-image'); "
                            "const r = img.getBoundingClientRect(); img.onload = null; "
                            "const again = await (await fetch(img.src)).blob(); "
                            "img.src = URL.createObjectURL(again); await Promise.resolve(); const natural = img.naturalWidth; "
                            "img.dispatchEvent(new MouseEvent('click', "
                            "{clientX: r.left + 0.5 * r.width, clientY: r.top + 0.5 * r.height})); "
                            "const q = img.getBoundingClientRect(); return [natural, q.width, q.height]; })()")
    assert loading[0] == 0, loading
    probe = page.wait_for("state.liveProbe", 30)
    assert abs(probe["pixel"][0] - 128) <= 1 and abs(probe["pixel"][1] - 96) <= 1
    assert len(probe["linear"]) == 3 and probe["sensor"] == probe["linear"]  # at exposure 1
    _set(page, "zoom", "0")
    page.screenshot(tmp_path / "live.png")


def test_live_decode_shows_where_the_object_decodes(page):
    _set(page, "pattern", "white")
    _set(page, "decode", True)
    try:
        page.wait_for("state.decodes >= 1", 90)
        valid = float(page.evaluate("document.getElementById('decode-valid').textContent").rstrip("%"))
        assert 5 < valid < 95  # the star decodes, the background does not
        reasons = page.evaluate("document.getElementById('reasons').textContent")
        assert "VALID" in reasons and "LOW_MODULATION" in reasons
        assert page.evaluate("document.getElementById('decode-mask').naturalWidth") == 256
        # the simulated rig's exact calibration: the decoded points' depth (the star stands ~400 mm from the camera)
        page.wait_for("document.getElementById('decode-depth').naturalWidth === 256", 30)
        lo, hi = (float(v) for v in page.evaluate("document.getElementById('depth-range').textContent").split(" … "))
        assert 350 < lo < hi < 450, (lo, hi)
        assert page.evaluate("document.getElementById('depth-unit').textContent").startswith("mm from the camera (the simulated")
        assert page.evaluate("document.getElementById('decode-surface').naturalWidth") == 256
    finally:
        _set(page, "decode", False)


def test_a_page_shows_the_settings_another_page_gave_the_rig(served, page):
    """The rig is one and its pages share its settings: a second page that turned live decode on left the first
    saying "no frame for 7 s (waiting for the rig)" with its box unticked; the first page now takes the other's
    settings into its controls and says who set them."""
    other = _live(served["base"], served["token"])
    try:
        other.send(json.dumps({"pattern": "grey", "exposure": 0.7, "gain": None, "psp_frame": 0, "decode": False}))
        page.wait_for("document.getElementById('pattern').value === 'grey' && "
                      "document.getElementById('exposure').value === '0.7' && "
                      "document.getElementById('status').textContent.includes('set by another page of this view')", 60)
    finally:
        other.close()
    _set(page, "pattern", "white")
    _set(page, "exposure", 1)
    page.wait_for("state.shown.pattern === 'white' && !document.getElementById('status').textContent.includes('another')", 60)


def test_a_session_without_a_complete_view_is_listed_as_left_out_with_how_to_complete_it(served):
    """A capture that stopped in its first view was listed; choosing it showed a bare "Not Found" under the
    previous session's image."""
    sessions = served["root"] / "sessions"
    star = next(p for p in sessions.iterdir() if p.is_dir())
    stopped = sessions / "stopped"
    shutil.copytree(star, stopped)
    try:
        manifest = json.loads((stopped / "manifest.json").read_text())
        manifest["views"]["0"]["status"], manifest["object"] = "capturing", "stopped"
        (stopped / "manifest.json").write_text(json.dumps(manifest))
        state = json.loads(_get(served["base"] + "/api/state", served["token"])[1])
        assert "stopped" not in [s["name"] for s in state["sessions"]] and len(state["sessions"]) == 1
        assert state["damaged"]["stopped"] == "no complete view yet; `sss capture ... --resume` completes it"
    finally:
        shutil.rmtree(stopped)


def test_a_sessions_maps_have_their_colour_bar_and_unit(page):
    page.evaluate("document.querySelector('nav button[data-tab=sessions]').click()")
    # the 3D view: the view's points drawn on the canvas, turned by a drag
    _set(page, "map", "points")
    cloud = page.wait_for("state.cloud", 30)
    assert cloud["count"] > 1000 and cloud["views"] == [0], cloud
    lit = """(() => { const c = document.getElementById('map-canvas'), d = c.getContext('2d').getImageData(0, 0, c.width,
        c.height).data; let n = 0, h = 0; for (let i = 0; i < d.length; i += 4) if (d[i] + d[i + 1] + d[i + 2] > 30) { n++;
        h = (h * 31 + i) % 1000003; } return [n, h]; })()"""
    before = page.evaluate(lit)
    assert before[0] > 1000 and page.evaluate("document.getElementById('map-image').hidden")
    page.evaluate("""(() => { const c = document.getElementById('map-canvas'), r = c.getBoundingClientRect();
        const ev = (t, x, y) => c.dispatchEvent(new PointerEvent(t, {clientX: r.left + x, clientY: r.top + y, pointerId: 1}));
        ev('pointerdown', 300, 200); for (let i = 1; i <= 5; i++) ev('pointermove', 300 + 20 * i, 200); ev('pointerup', 400, 200); })()""")
    assert page.evaluate("cloud.draws") >= 6 and page.evaluate(lit) != before  # turned: other pixels lit
    page.evaluate("state.cloud = null")
    _set(page, "crop", "5")  # only the points within 5 mm of the simulated turntable's axis
    cropped = page.wait_for("state.cloud", 30)
    assert 0 < cropped["count"] < cloud["count"] and "within 5 of its axis" in cropped["which"], cropped
    _set(page, "crop", "")
    _set(page, "map", "modulation")
    page.wait_for("document.getElementById('map-unit').textContent.includes('fringe amplitude')", 30)
    assert page.evaluate("document.getElementById('map-canvas').hidden")
    page.wait_for("document.getElementById('map-image').naturalWidth === 256", 30)
    lo, hi = (float(v) for v in page.evaluate("document.getElementById('map-range').textContent").split(" … "))
    assert 0 <= lo < hi
    _set(page, "map", "depth")  # triangulated with the simulated rig's exact calibration
    page.wait_for("document.getElementById('map-unit').textContent.startsWith('mm from the camera')", 30)
    lo, hi = (float(v) for v in page.evaluate("document.getElementById('map-range').textContent").split(" … "))
    assert 350 < lo < hi < 450, (lo, hi)
    _set(page, "map", "modulation")
    page.wait_for("document.getElementById('map-unit').textContent.includes('fringe amplitude')", 30)
    # a click on the object: its PSP patch and footprints side by side (analytic, and exact: a simulated session)
    page.evaluate("state.probe = null; (() => { const img = document.getElementById('map-image'); "
                  "const r = img.getBoundingClientRect(); img.dispatchEvent(new MouseEvent('click', "
                  "{clientX: r.left + 0.5 * r.width, clientY: r.top + 0.55 * r.height})); })()")
    probe = page.wait_for("state.probe", 120)
    assert probe["valid"] and probe["footprint_names"] == ["analytic", "exact"], probe
    assert "no dot-grid crop" in probe["skipped"]["captured"] and "no decoder checkpoint" in probe["skipped"]["torch"]
    page.wait_for("document.getElementById('probe-footprints').naturalWidth === 2 * (32 + 4)", 30)
    assert page.evaluate("document.getElementById('probe-patch').naturalWidth") == 8 * (32 + 4)


def _relight_on_page(page, timeout: float = 120) -> dict:
    page.evaluate("state.relit = null; document.getElementById('relight-button').click()")
    return page.wait_for("state.relit || (document.getElementById('message').textContent || null)", timeout)


def test_relighting_an_uploaded_pattern_gives_the_image_sss_relight_writes(served, page, tmp_path):
    from PIL import Image

    from sssphase_core.store.exr import read_exr

    rng = np.random.default_rng(1)
    pattern = tmp_path / "blocks.png"
    Image.fromarray(np.kron(rng.integers(0, 2, (12, 16)) * 255, np.ones((16, 16))).astype(np.uint8)).save(pattern)
    page.evaluate("document.querySelector('nav button[data-tab=relight]').click()")
    _set(page, "backend", "exact")  # the simulator's footprints: cached like a model's, 3x faster
    page.evaluate("state.uploaded = null")
    page.set_file("#upload", pattern)
    page.wait_for("state.uploaded", 30)
    result = _relight_on_page(page)
    assert isinstance(result, dict), result
    status, exr = _get(served["base"] + result["files"]["exr"], served["token"])
    assert status == 200
    (tmp_path / "page.exr").write_bytes(exr)
    session = served["root"] / "sessions" / "star"
    slot = result["files"]["exr"].split("/")[-2]  # the session's own folder (OUT/relit/<name>-<hash of its path>)
    relit = served["root"] / "out" / "relit" / slot  # sss relight into the view's folder: its footprint cache serves both
    done = _sss("relight", str(session), "--pattern", str(pattern), "--backend", "exact", "--resize", "fit",
                "--format", "exr", "--out", str(relit), env=served["env"])
    assert done.returncode == 0, done.stdout + done.stderr
    cli_exr = relit / "star_v0_blocks_exact.exr"
    np.testing.assert_array_equal(read_exr(tmp_path / "page.exr"), read_exr(cli_exr))  # bit-identical
    # the view's own reference pattern, chosen after the upload (which the relight took again): relit beside its
    # capture, with scores
    _set(page, "relight-pattern", "checkerboard")
    scored = _relight_on_page(page)
    assert scored["pattern"] == "checkerboard" and not page.evaluate("state.uploaded"), scored["pattern"]
    assert scored["metrics"]["psnr"] > 20 and scored["figure"] and scored["backend"] == "exact"
    page.wait_for("!document.getElementById('compare-image').hidden && "
                  "document.getElementById('compare-image').naturalWidth > 0", 30)
    # a pattern drawn on the page's canvas (a stroke of the mouse), used like an upload
    page.evaluate("""(() => { const c = document.getElementById('draw'), r = c.getBoundingClientRect();
        const ev = (type, fx, fy) => new MouseEvent(type, {clientX: r.left + fx * r.width, clientY: r.top + fy * r.height, bubbles: true});
        c.dispatchEvent(ev('mousedown', 0.2, 0.5)); c.dispatchEvent(ev('mousemove', 0.5, 0.5));
        c.dispatchEvent(ev('mousemove', 0.8, 0.5)); window.dispatchEvent(ev('mouseup', 0.8, 0.5));
        state.uploaded = null; document.getElementById('draw-use').click(); })()""")
    page.wait_for("state.uploaded", 30)
    drawn = _relight_on_page(page)
    assert isinstance(drawn, dict) and drawn["pattern"].startswith("upload_") and drawn["metrics"] is None
    # a model: what sss relight would say about it (its calibration to the view) is on the page under the image
    _set(page, "backend", "analytic")
    page.evaluate("state.uploaded = null")
    _set(page, "relight-pattern", "checkerboard")
    modelled = _relight_on_page(page)
    assert any("calibrated to the view's fringe captures" in line for line in modelled["notes"]), modelled["notes"]
    assert not any(line.startswith("wrote ") for line in modelled["notes"])
    assert "calibrated to the view" in page.evaluate("document.getElementById('relight-notes').textContent")
    page.screenshot(tmp_path / "relight.png")


def test_a_video_uploaded_on_the_page_is_relit_frame_by_frame_and_played(served, page, tmp_path):
    """A video uploaded to the relight tab: every frame relit in the background by `sss relight --pattern`'s own
    runner while the page follows its progress, then played as a flipbook at the video's frame rate, its MP4
    offered; each frame is the one `sss relight` writes. A file that only looks like a video fails in one line."""
    import cv2

    base, token = served["base"], served["token"]
    clip = tmp_path / "sweep.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 8.0, (256, 192))
    for i in range(4):  # a bar sweeping across the projector
        frame = np.zeros((192, 256, 3), np.uint8)
        frame[:, 64 * i : 64 * (i + 1)] = 255
        writer.write(frame)
    writer.release()
    page.evaluate("document.querySelector('nav button[data-tab=relight]').click()")
    page.wait_for("document.getElementById('backend').options.length > 0", 30)  # (the page has its backends)
    _set(page, "backend", "none")
    page.evaluate("state.uploaded = null")
    page.set_file("#upload", clip)
    page.wait_for("state.uploaded", 30)
    assert "a sequence: every frame is relit" in page.evaluate("document.getElementById('relight-info').textContent")
    result = _relight_on_page(page)
    assert isinstance(result, dict) and result["sequence"]["status"] == "done", result
    job = result["sequence"]
    assert len(job["frames"]) == job["total"] == 4 and job["fps"] == pytest.approx(8.0), job
    page.wait_for("state.frame >= 6", 10)  # played: the frames follow each other, round again
    page.evaluate("document.getElementById('relit-image').click()")  # paused on the frame it shows
    paused = page.evaluate("[state.frame, document.getElementById('relit-frame').textContent]")
    time.sleep(0.5)
    assert page.evaluate("state.frame") == paused[0] and "(paused: click to play)" in paused[1], paused
    page.evaluate("document.getElementById('relit-image').click()")
    page.wait_for(f"state.frame >= {paused[0] + 2}", 10)  # and played again
    assert page.evaluate("document.getElementById('relit-image').src").split("?")[0].endswith("_none_display.png")
    assert "video (MP4" in page.evaluate("document.getElementById('downloads').textContent")
    status, video = _get(base + job["video"], token)
    assert status == 200 and video[4:8] == b"ftyp"
    done = _sss("relight", str(served["root"] / "sessions" / "star"), "--pattern", str(clip), "--backend", "none",
                "--out", str(tmp_path / "cli"), env=served["env"])
    assert done.returncode == 0, done.stdout + done.stderr
    for i, url in enumerate(job["frames"]):
        status, png = _get(base + url, token)
        cli = tmp_path / "cli" / "star_v0_sweep_none" / f"star_v0_sweep-{i:06d}_none_display.png"
        assert status == 200 and np.array_equal(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED),
                                                cv2.imread(str(cli), cv2.IMREAD_UNCHANGED)), i
    # the same video again (uploaded again, the same bytes): its frames are there, nothing is relit or refused
    request = urllib.request.Request(base + "/api/upload", data=clip.read_bytes(), method="POST", headers={"X-Token": token})
    with urllib.request.urlopen(request, timeout=60) as response:
        assert json.loads(response.read())["name"] == page.evaluate("state.uploaded")
    again = _relight_on_page(page)
    assert isinstance(again, dict) and again["sequence"]["frames"] == job["frames"], again
    folder = job["frames"][0].split("/")[-2]
    assert _get(base + f"/api/files/relit/{folder}/..%2F..%2Fuploads", token)[0] == 404
    assert _get(base + "/api/files/relit/uploads/" + Path(job["frames"][0]).name, token)[0] == 404
    assert _get(base + "/api/relight/jobs/nope", token)[0] == 404
    # a file that starts like an MP4 and is not one: refused at its upload in one line (it was kept, and its relight
    # failed), naming "the upload", not the server's path
    request = urllib.request.Request(base + "/api/upload", data=b"\0\0\0\x18ftypisom" + os.urandom(4096),
                                     method="POST", headers={"X-Token": token})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=60)
    said = json.loads(refused.value.read())["error"]
    assert refused.value.code == 400 and said.startswith("the upload: not a video") and "uploads/" not in said, said
    # a relight asked to stop stops at its next progress report (here in the first frame's footprints), said so
    writer = cv2.VideoWriter(str(tmp_path / "long.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 8.0, (256, 192))
    for i in range(30):
        writer.write(np.full((192, 256, 3), 8 * i, np.uint8))
    writer.release()
    request = urllib.request.Request(base + "/api/upload", data=(tmp_path / "long.mp4").read_bytes(), method="POST",
                                     headers={"X-Token": token})
    with urllib.request.urlopen(request, timeout=60) as response:
        long = json.loads(response.read())
    status, answer = _post(base + "/api/relight", token, json.dumps(
        {"session": "star", "view": 0, "pattern": long["name"], "backend": "analytic"}).encode())
    assert status == 202 and _post(base + f"/api/relight/jobs/{answer['job']}/stop", token, b"")[1]["stopping"]
    deadline = time.monotonic() + 120
    while (state := json.loads(_get(base + f"/api/relight/jobs/{answer['job']}", token)[1]))["status"] not in (
            "done", "failed", "stopped"):
        assert time.monotonic() < deadline
        time.sleep(0.2)
    assert state["status"] == "stopped" and state["error"].startswith("stopped at "), state
    page.screenshot(tmp_path / "relight_sequence.png")


def _answer_the_next_one_late(page, url_part: str, delay_ms: int = 1500) -> None:
    """The page's next request whose URL contains ``url_part`` is answered ``delay_ms`` late (then
    ``window.lateAnswered`` turns true); the others at once, as before."""
    late = """((part, delay) => { const fetch0 = window.fetch0 || window.fetch; let first = true;
        window.fetch0 = fetch0; window.lateAnswered = false;
        window.fetch = (url, options) => { const answer = fetch0(url, options);
            if (!String(url).includes(part) || !first) return answer;
            first = false;
            return answer.then(r => new Promise(done => setTimeout(() => { window.lateAnswered = true; done(r); }, delay)));
        }; })"""
    page.evaluate(f"{late}({json.dumps(url_part)}, {int(delay_ms)})")


def test_a_map_picked_after_another_stays_when_the_first_answers_last(page):
    page.evaluate("document.querySelector('nav button[data-tab=sessions]').click()")
    _set(page, "map", "white")
    page.wait_for("document.getElementById('map-unit').textContent === 'linear camera units'", 30)
    _answer_the_next_one_late(page, "/map/")
    _set(page, "map", "xp")  # answered late
    _set(page, "map", "mask")
    page.wait_for("window.lateAnswered", 30)
    time.sleep(0.3)
    assert page.evaluate("document.getElementById('map-unit').textContent") == "valid (1) / not (0)"
    assert page.evaluate("document.getElementById('map').value") == "mask"


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width x height`` (a decompression bomb's promise) and whose data is tiny."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))


def test_hostile_input_is_one_message_on_the_page_and_the_server_keeps_serving(served, page, tmp_path):
    import cv2

    page.evaluate("document.querySelector('nav button[data-tab=relight]').click()")
    text = tmp_path / "notes.png"
    text.write_text("not an image at all")
    page.set_file("#upload", text)
    page.wait_for("document.getElementById('message').textContent.includes('not an image')", 30)
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.full((192, 256), 200, np.uint8))
    # the user picks a wrong file and at once the right one; the wrong one's answer comes last and changes nothing
    _answer_the_next_one_late(page, "/api/upload")
    late = tmp_path / "notes_again.png"
    late.write_text("still not an image")
    page.set_file("#upload", late)
    page.set_file("#upload", good)
    page.wait_for("state.uploaded && window.lateAnswered", 30)
    time.sleep(0.3)
    assert page.evaluate("state.uploaded").startswith("upload_")
    assert "not an image" not in page.evaluate("document.getElementById('message').textContent")
    bomb = tmp_path / "bomb.png"  # (a decompression bomb's header: refused at its upload, never decoded nor kept)
    bomb.write_bytes(_png_header_only(40000, 40000))
    page.set_file("#upload", bomb)
    page.wait_for("document.getElementById('message').textContent.includes('refused without decoding it')", 30)
    assert "the upload declares an image of over 179 MP" in page.evaluate("document.getElementById('message').textContent")
    escape = page.evaluate("""fetch('/api/relight', {method: 'POST', headers: {'X-Token': TOKEN,
        'Content-Type': 'application/json'}, body: JSON.stringify({session: '../../etc', view: 0, pattern: 'checkerboard'})})
        .then(r => r.json())""")
    assert "no session '../../etc'" in escape["error"]
    assert _get(served["base"] + "/api/state", served["token"])[0] == 200  # still serving
    outside = [p for p in served["root"].parent.iterdir() if p.name == "etc"]
    assert not outside and {p.name for p in (served["root"] / "out").iterdir()} <= {"relit", "uploads"}


def test_the_view_keeps_the_most_recently_used_uploads_and_forgets_the_rest(served):
    """Each upload may be 32 MB: a long session of new patterns must not fill ``--out``. The uploads used last
    stay; the others' files go (what was relit under them stays), and relighting one of them says to upload it
    again. A body that only starts like an image is refused, and evicts nothing."""
    import cv2

    from sssphase_view.app import MAX_UPLOADS

    base, token = served["base"], served["token"]
    name = json.loads(_get(base + "/api/state", token)[1])["sessions"][0]["name"]

    def upload(i: int) -> str:
        png = cv2.imencode(".png", np.full((192, 256), i, np.uint8))[1].tobytes()
        request = urllib.request.Request(base + "/api/upload", data=png, method="POST", headers={"X-Token": token})
        with urllib.request.urlopen(request, timeout=60) as response:
            return json.loads(response.read())["name"]

    def relight(pattern: str) -> tuple[int, dict]:
        return _post(base + "/api/relight", token, json.dumps(
            {"session": name, "view": 0, "pattern": pattern, "backend": "none", "resize": "fit"}).encode())

    first, second = upload(1), upload(2)
    assert relight(first)[0] == 200 and relight(second)[0] == 200
    relit = served["root"] / "out" / "relit"
    assert list(relit.glob(f"*/*_{Path(second).stem}_*"))
    time.sleep(0.05)
    relight(first)  # used again: kept longer than the second
    later = [upload(10 + i) for i in range(MAX_UPLOADS - 1)]
    kept = {p.name for p in (served["root"] / "out" / "uploads").iterdir()}
    assert len(kept) == MAX_UPLOADS and first in kept and second not in kept and set(later) <= kept
    assert list(relit.glob(f"*/*_{Path(second).stem}_*")) and list(relit.glob(f"*/*_{Path(first).stem}_*"))
    junk = urllib.request.Request(base + "/api/upload", data=b"\x89PNG\r\n\x1a\n" + bytes(8), method="POST",
                                  headers={"X-Token": token})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(junk, timeout=60)
    said = json.loads(refused.value.read())["error"]
    assert refused.value.code == 400 and "the upload" in said and "uploads/" not in said, said
    assert {p.name for p in (served["root"] / "out" / "uploads").iterdir()} == kept  # nothing kept, none evicted
    # a still upload that cannot be relit is named as the page names it, not by the server's path to it
    png = cv2.imencode(".png", np.zeros((10, 12), np.uint8))[1].tobytes()
    request = urllib.request.Request(base + "/api/upload", data=png, method="POST", headers={"X-Token": token})
    with urllib.request.urlopen(request, timeout=60) as response:
        small = json.loads(response.read())["name"]
    status, said = _post(base + "/api/relight", token, json.dumps(
        {"session": name, "view": 0, "pattern": small, "backend": "none"}).encode())
    assert status == 400 and "the upload" in said["error"] and "uploads" not in said["error"], said
    status, answer = relight(second)
    assert status == 400 and "upload it again" in answer["error"]
    planted = served["root"] / "out" / "uploads" / "upload_planted000.png"  # a link to an image outside --out
    cv2.imwrite(str(served["root"] / "outside.png"), np.full((192, 256), 255, np.uint8))
    planted.symlink_to(served["root"] / "outside.png")
    try:
        status, answer = relight(planted.name)
        assert status == 400 and "no uploaded pattern" in answer["error"]
    finally:
        planted.unlink()


def test_errors_the_page_gets_name_no_server_path(served):
    """A view off loopback told every client where the server keeps its sessions; null options read "got 'None'"."""
    base, token = served["base"], served["token"]
    name = json.loads(_get(base + "/api/state", token)[1])["sessions"][0]["name"]
    for body, said in (({"session": name, "view": 99, "pattern": "checkerboard"}, "--sessions/"),
                       ({"session": "nope", "view": 0, "pattern": "checkerboard"}, "no session 'nope' under --sessions"),
                       ({"session": name, "view": 0, "pattern": "checkerboard", "backend": None, "resize": None}, None)):
        status, answer = _post(base + "/api/relight", token, json.dumps(body).encode())
        text = json.dumps(answer)
        assert str(served["root"]) not in text and "None" not in text, text
        assert (status == 400 and said in answer["error"]) if said else status == 200, (status, answer)


def test_uploads_received_at_once_are_bounded(served):
    """24 uploads of 32 MB sent at once were all held in memory (0.5 -> 1.5 GB); a third now waits its turn."""
    import socket

    from sssphase_view.app import MAX_UPLOADS_AT_ONCE

    base, token = served["base"], served["token"]
    host, port = base.removeprefix("http://").split(":")
    slow = []
    try:
        for _ in range(MAX_UPLOADS_AT_ONCE):  # bodies still arriving
            sock = socket.create_connection((host, int(port)), timeout=10)
            sock.sendall(f"POST /api/upload HTTP/1.1\r\nHost: {host}:{port}\r\nX-Token: {token}\r\n"
                         "Content-Length: 1000000\r\n\r\n".encode() + b"\x89PNG" + bytes(1000))
            slow.append(sock)
        time.sleep(0.5)
        import cv2

        png = cv2.imencode(".png", np.full((192, 256), 7, np.uint8))[1].tobytes()
        third = urllib.request.Request(base + "/api/upload", data=png, method="POST", headers={"X-Token": token})
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(third, timeout=30)
        assert refused.value.code == 429 and "uploads are under way" in json.loads(refused.value.read())["error"]
    finally:
        for sock in slow:
            sock.close()
    deadline = time.monotonic() + 10
    while True:  # their connections closed, the next upload is taken
        try:
            with urllib.request.urlopen(third, timeout=30) as response:
                assert response.status == 200
            break
        except urllib.error.HTTPError as exc:
            assert exc.code == 429 and time.monotonic() < deadline
            time.sleep(0.2)


def test_two_sessions_of_one_object_are_each_relit_into_a_folder_of_their_own(served):
    """Both sessions of one object (a re-capture, a copy) are listed by their folders, but their relit images went to
    one folder, where the second session was refused ("holds outputs of 'star' from another session")."""
    import shutil

    base, token = served["base"], served["token"]
    copy = served["root"] / "sessions" / "star_again"
    shutil.copytree(served["root"] / "sessions" / "star", copy)
    try:
        names = {s["name"] for s in json.loads(_get(base + "/api/state", token)[1])["sessions"]}
        assert {"star", "star_again"} <= names, names
        answers = [_post(base + "/api/relight", token, json.dumps(
            {"session": name, "view": 0, "pattern": "checkerboard", "backend": "none"}).encode()) for name in
            ("star", "star_again")]
        assert [status for status, _ in answers] == [200, 200], answers
        (one, two) = (answer["files"]["exr"] for _, answer in answers)
        assert one.split("/")[-2] != two.split("/")[-2] and _get(base + two, token)[0] == 200, (one, two)
    finally:
        shutil.rmtree(copy)
