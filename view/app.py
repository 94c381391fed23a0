"""``sss view``'s web application (Starlette): the live view and live decode over a websocket, the sessions
under a folder, and relighting through the same core runner as ``sss relight``.

Every route and the websocket need the token ``sss view`` prints (``?token=`` on the page's URL; the page
sends it as ``X-Token`` on its requests and ``?token=`` on the websocket), compared in constant time.
Session names are looked up among the sessions found under ``--sessions``, never joined into a path;
files are served only from the view's own output folder; uploads are size-limited and read by the core's
pattern reader (decompression bombs refused before decoding).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import dataclasses
import hashlib
import hmac
import json
import secrets
import time
import warnings
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote, urlsplit

import numpy as np
from starlette.applications import Starlette
from starlette.middleware import Middleware
from starlette.requests import ClientDisconnect, Request
from starlette.responses import FileResponse, HTMLResponse, JSONResponse, Response
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket, WebSocketDisconnect

from sssphase_core.capture.live import LIVE_PATTERNS
from sssphase_core.errors import InputError, SssError
from sssphase_core.processing.triangulation import StereoCalibration
from sssphase_core.relight.runner import Narrator
from sssphase_core.store.files import write_bytes
from sssphase_view.jobs import SequenceJob, Stopped, forget_old_jobs, run_sequence_job
from sssphase_view.live import LiveRig, LiveSettings

STATIC = Path(__file__).with_name("static")
MAX_UPLOAD_BYTES = 32 << 20
#: The most frames of an uploaded video the page relights (6 minutes at 25 frames/s; ~10 minutes of work at the CPU
#: preset, hours at 1080p): 32 MB of video held 30,000 frames; `sss relight` takes longer ones
MAX_UPLOAD_FRAMES = 9_000
MAX_REQUEST_BYTES = 64 << 10  # a relight request is ~100 bytes; larger JSON bodies are refused while they stream
MAX_MESSAGE_CHARS = 4096  # a live-settings message is ~100 characters
MAX_PENDING_RELIGHTS = 4  # relights run one at a time on a thread of their own; more waiting are refused (429)
MAX_LIVE_SOCKETS = 4  # live streams at once (each waits on the rig in a thread of the shared pool)
MAX_VIEW_DIGITS = 9  # a view number in a URL (a 5000-digit one was a 500 in the router, before the token check)
MAX_UPLOADS = 20  # uploads kept in ``--out``; the least recently used go first (what was relit under them stays)
#: Uploads received at once (each up to MAX_UPLOAD_BYTES in memory: 24 at once took the view from 0.5 to 1.5 GB), and
#: the seconds one may take to arrive (a body sent a byte at a time held its connection for ever).
MAX_UPLOADS_AT_ONCE = 2
UPLOAD_BODY_S = 600.0
IMAGE_MAGIC = {b"\x89PNG": ".png", b"\xff\xd8\xff": ".jpg", b"II*\x00": ".tif", b"MM\x00*": ".tif", b"BM": ".bmp",
               b"v/1\x01": ".exr"}
#: Uploads that may be pattern sequences, by their first bytes: GIF, Matroska/WebM; MP4/MOV (``ftyp`` at byte 4) and
#: AVI (``RIFF....AVI ``) are told by :func:`_upload_suffix`.
SEQUENCE_MAGIC = {b"GIF87a": ".gif", b"GIF89a": ".gif", b"\x1aE\xdf\xa3": ".mkv"}


@dataclass
class ViewState:
    """What the application serves: its ``token``, the ``sessions`` folder, a decoder ``checkpoint``, the
    ``out`` folder its relit images and uploads go to, and the live rig."""

    token: str
    out: Path
    sessions: Path | None = None
    checkpoint: Path | None = None
    live: LiveRig = field(default_factory=LiveRig)
    #: ``--calibration``'s camera-projector calibration (depth and surface maps of any session and the live decode;
    #: without one, a simulated rig's exact calibration serves its own sessions and live decode), and its file
    calibration: StereoCalibration | None = None
    calibration_path: Path | None = None
    settings: LiveSettings = field(default_factory=LiveSettings)
    probes: dict[tuple[str, int], Any] = field(default_factory=dict)  # the clicked view and its model sources
    #: relights run here, one at a time, so that they never queue the page's light requests (state, maps,
    #: pixels) behind them in the shared thread pool
    relights: ThreadPoolExecutor = field(default_factory=lambda: ThreadPoolExecutor(1, thread_name_prefix="relight"))
    pending_relights: int = 0
    #: pattern sequences relit in the background (by job id), their progress polled by the page
    jobs: dict[str, SequenceJob] = field(default_factory=dict)
    live_sockets: int = 0
    live_opened: int = 0  # live pages opened so far (each page's number)
    #: when each upload was last used (its file's time is its sequence relight's record: never touched)
    upload_used: dict[str, float] = field(default_factory=dict)
    #: uploads whose bodies are being received (each held in memory until whole)
    uploading: int = 0
    #: set at the first Ctrl-C (or SIGTERM): the relight under way stops at its next step, as every sequence does
    closing: bool = False

    def stop_work(self) -> None:
        """Stop the relights under way at their next progress report (the server is closing)."""
        self.closing = True
        for job in self.jobs.values():
            job.stop = not job.finished


def relit_folder(state: ViewState, session: Any) -> Path:
    """The folder one session's relit images go to, ``OUT/relit/<name>-<hash of its path>``: two sessions of one
    object name their outputs alike (``OBJECT_vVIEW_PATTERN_BACKEND``), so each has its own."""
    path = str(Path(session.path).resolve())
    stem = "".join(ch if ch.isascii() and (ch.isalnum() or ch in "-_.") else "_" for ch in session.name)[:40].strip(".")
    return state.out / "relit" / f"{stem or 'session'}-{hashlib.sha256(path.encode()).hexdigest()[:8]}"


def files_url(state: ViewState, path: Path) -> str:
    """The URL ``/api/files`` serves a file under ``OUT/relit`` by."""
    return "/api/files/relit/" + quote(path.relative_to(state.out / "relit").as_posix())


def _png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image[..., ::-1] if image.ndim == 3 else image))
    return buf.tobytes() if ok else b""


def _jpeg(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return buf.tobytes() if ok else b""


def display(image: np.ndarray, *, clip: float | None = None) -> np.ndarray:
    """Linear (H, W, 3) in camera units -> sRGB uint8, pixels at or above ``clip`` painted magenta."""
    from sssphase_core.processing.colour import srgb

    out = (srgb(np.clip(image, 0, 1)) * 255 + 0.5).astype(np.uint8)
    if clip is not None:
        out[(image >= clip).any(axis=-1)] = (255, 0, 255)
    return out


def colour_map(values: np.ndarray, mask: np.ndarray, lo: float | None = None, hi: float | None = None) -> tuple[bytes, float, float]:
    """A map (H, W) as a viridis PNG (grey outside ``mask``) -> (png, low, high) of its colour bar."""
    import cv2

    finite = mask & np.isfinite(values)
    lo = float(np.percentile(values[finite], 1)) if lo is None and finite.any() else (lo or 0.0)
    hi = float(np.percentile(values[finite], 99)) if hi is None and finite.any() else (hi if hi is not None else 1.0)
    scaled = np.clip((np.nan_to_num(values) - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1].copy()
    rgb[~finite] = 64
    return _png(rgb), lo, hi


# --- security ---------------------------------------------------------------------------------------------


#: The page without its token (a bookmark of the bare address, a URL cut short, a view restarted since)
TOKEN_PAGE = ("<!doctype html><html lang=en><meta charset=utf-8><title>sss view: token needed</title>"
              "<body style='font: 16px system-ui, sans-serif; background: #111; color: #ddd; padding: 2em'>"
              "<h1 style='font-size: 20px'>sss view needs its token</h1><p>Open the URL <code>sss view</code> printed "
              "when it started: it ends in <code>?token=…</code>. A view started again has a new token.</p></body></html>")


def _authorised(state: ViewState, given: str | None) -> bool:
    return given is not None and hmac.compare_digest(given.encode(), state.token.encode())


def _problem(message: str, status: int = 400) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


def _finite(value: Any) -> Any:
    """``value`` with every NaN or infinite float as None (JSON has neither: a pixel off the object, whose
    projector point is NaN, was a 500)."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, np.generic):
        return _finite(value.item())
    return value


def _json(payload: Any) -> JSONResponse:
    return JSONResponse(_finite(payload))


def guarded(handler: Any) -> Any:
    """A route that answers only with the token; an :class:`SssError` becomes one message for the page."""
    async def route(request: Request) -> Response:
        state: ViewState = request.app.state.view
        if not _authorised(state, request.headers.get("x-token") or request.query_params.get("token")):
            if request.url.path == "/":  # a person at a browser, not the page's script: a page that says what to do
                return HTMLResponse(TOKEN_PAGE, status_code=403, headers={"X-Content-Type-Options": "nosniff"})
            return _problem("a valid token is required: open the URL `sss view` printed", 403)
        try:
            response = await handler(request, state)
        except SssError as exc:
            response = _problem(_without_server_paths(str(exc), state), getattr(exc, "status", 400))
        except ClientDisconnect:  # the page went away mid-body: nobody to answer
            response = Response(status_code=499)
        response.headers["X-Content-Type-Options"] = "nosniff"
        return response
    return route


def _without_server_paths(text: str, state: ViewState) -> str:
    """``text`` as the page says it: the server's --sessions and --out folders by those names, not their paths
    (a view off loopback told every client where the server keeps its data)."""
    import re

    for folder, said in ((state.out, "--out"), (state.sessions, "--sessions")):
        if folder is not None:
            for form in sorted({str(folder), str(Path(folder).resolve())}, key=len, reverse=True):
                if form not in (".", "/"):  # (a whole path only: never a part of a word or of another path)
                    text = re.sub(rf"(?<![\w./-]){re.escape(form)}(?=/|\s|$|['\")\],:;])", said, text)
    return text


def view_number(request: Request) -> int:
    """The ``{view}`` path parameter as a view number (digits only, at most :data:`MAX_VIEW_DIGITS`)."""
    text = request.path_params["view"]
    if not (text.isascii() and text.isdigit() and len(text) <= MAX_VIEW_DIGITS):
        raise InputError(f"the view must be a view number, got {text[:20]!r}")
    return int(text)


class BodyTooLarge(InputError):
    status = 413


async def read_body(request: Request, limit: int, too_large: str) -> bytearray:
    """The request's body, refused (:class:`BodyTooLarge`, 413, saying ``too_large``) as soon as it streams past
    ``limit`` bytes, not once it is all in memory."""
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise BodyTooLarge(too_large)
    return body


async def read_json(request: Request) -> Any:
    """The request's JSON body, at most :data:`MAX_REQUEST_BYTES`."""
    body = await read_body(request, MAX_REQUEST_BYTES, f"the request body is larger than {MAX_REQUEST_BYTES >> 10} kB")
    try:
        return json.loads(bytes(body))
    except (ValueError, RecursionError):  # (JSONDecodeError, UnicodeDecodeError, a 5000-digit integer)
        raise InputError("the request body must be JSON") from None


# --- pages and sessions --------------------------------------------------------------------------------


async def index(request: Request, state: ViewState) -> Response:
    """The page, its script inline (one guarded request; the script reads the token from the URL)."""
    html = (STATIC / "index.html").read_text().replace("/*APP_JS*/", (STATIC / "app.js").read_text())
    return HTMLResponse(html, headers={"Cache-Control": "no-store", "Referrer-Policy": "no-referrer"})


def _scan(state: ViewState) -> tuple[dict[str, Any], dict[str, str]]:
    """The sessions under ``--sessions`` by name, and the folders that could not be opened (folder name ->
    why): one damaged or foreign folder does not hide the others. Two sessions of one object are named by
    their folders (``soap``, ``soap2``), so that neither hides the other."""
    from sssphase_core.store.session import Session, session_folders

    if state.sessions is None or not state.sessions.is_dir():
        return {}, {}
    opened, damaged = [], {}
    for folder in session_folders(state.sessions):
        try:
            opened.append(Session.open(folder))
        except (SssError, OSError) as exc:
            damaged[folder.name] = str(exc)
    names = [s.name for s in opened]
    found = {(s.name if names.count(s.name) == 1 else s.path.name): s for s in opened}
    return found, damaged


def _sessions(state: ViewState) -> dict[str, Any]:
    return _scan(state)[0]


def _session(state: ViewState, name: str) -> Any:
    found = _sessions(state)
    if name not in found:  # names only: '../x' or an absolute path is never a path here
        where = "under --sessions" if state.sessions is not None else "(the view was started without --sessions)"
        raise InputError(f"no session {name[:80]!r} {where} (known: {', '.join(found) or 'none'})")  # (no server path)
    return found[name]


async def api_state(request: Request, state: ViewState) -> Response:
    from sssphase_core.relight.choices import BLENDS, MODEL_FREE  # none, exact, measured; blend

    sessions = []
    found, damaged = await asyncio.to_thread(_scan, state)
    for name, s in found.items():
        if not s.views():  # (an interrupted first view: nothing to show, and its maps do not exist)
            damaged[name] = f"no complete view yet; {s.completes_it()}"
            continue
        views = []
        for v in s.views():
            arrays = s.arrays(v)
            views.append({"view": v, "references": sorted(k[4:] for k in arrays if k.startswith("ref/")),
                          "crops": "transport/crops" in arrays or "footprints/crops" in arrays, "simulated": "gt/proj_xy" in arrays})
        sessions.append({"name": name, "object": s.objects[0] if s.objects else name, "views": views})
    backends = ["analytic", *MODEL_FREE, *BLENDS, "torch"]  # (the page leaves out those that need a decoder without one)
    return JSONResponse({"sessions": sessions, "damaged": damaged, "patterns": [*LIVE_PATTERNS, "psp"], "backends": backends,
                         "checkpoint": str(state.checkpoint) if state.checkpoint else None,
                         "relight_patterns": ["checkerboard", "stripes_x", "stripes_y"]})


#: A session view's maps and their colour bar's unit; ``depth`` and ``surface`` are triangulated (their unit says how).
MAP_UNITS = {"modulation": "camera units (fringe amplitude B)", "xp": "projector px", "yp": "projector px",
             "mask": "valid (1) / not (0)", "white": "linear camera units", "depth": "", "surface": ""}


def stereo_for(state: ViewState, rig_record: dict[str, Any]) -> tuple[StereoCalibration, str]:
    """The calibration a view of the rig ``rig_record`` (a session manifest's ``rig``) is triangulated with:
    ``--calibration``'s, else a simulated rig's exact one -> (calibration, which it is); neither: one line saying
    how to get one."""
    from sssphase_core.sim import session_rig_calibration

    if state.calibration is not None:
        return state.calibration, f"calibration {state.calibration_path.name if state.calibration_path else 'given'}"
    exact = session_rig_calibration(rig_record)
    if exact is not None:
        return exact, "the simulated rig's exact calibration"
    raise InputError("no camera-projector calibration for depth: start sss view with --calibration FILE (an OpenCV "
                     "file as `sss calibrate stereo` writes it)")


def geometry_maps(kinds: tuple[str, ...], stereo: StereoCalibration, which: str, xp: np.ndarray, yp: np.ndarray,
                  mask: np.ndarray) -> dict[str, tuple[bytes, float, float, str]]:
    """Decoded correspondences (``xp``, ``yp``: (H, W) projector px, ``mask``) triangulated once with ``stereo`` ->
    per kind (PNG, colour bar low, high, unit): ``depth``, each point's distance along the camera's axis,
    colour-mapped; ``surface``, the points lit from above left (grey, dark grey where none). The unit says which
    calibration and its median reprojection error (a few px or more: not this rig's calibration)."""
    from sssphase_core.processing.triangulation import shaded, triangulate

    points = triangulate(stereo, xp, yp, mask)
    fit = f"{which}, reprojection {points.reprojection:.2f} px" if np.isfinite(points.reprojection) else which
    maps = {}
    if "depth" in kinds:
        png, lo, hi = colour_map(points.points[..., 2], mask)
        maps["depth"] = png, lo, hi, (f"{stereo.unit or 'calibration units'} from the camera ({fit}; the decoded "
                                      "points: sss geometry takes the scattering's shift out)")
    if "surface" in kinds:
        shade = shaded(points.points)
        grey = np.where(np.isfinite(shade), 40 + 215 * np.nan_to_num(shade), 24).astype(np.uint8)
        maps["surface"] = _png(np.repeat(grey[..., None], 3, -1)), 0.0, 1.0, f"surface lit from above left ({fit})"
    return maps


def session_map_png(state: ViewState, name: str, view: int, kind: str) -> tuple[bytes, float, float, str]:
    """A session view's map ``kind`` (:data:`MAP_UNITS`) as a PNG -> (png, colour bar low, high, unit)."""
    if kind not in MAP_UNITS:
        raise InputError(f"unknown map {kind!r}; choose {', '.join(MAP_UNITS)}")
    s = _session(state, name)
    if view not in s.views():
        raise InputError(f"{s.name} has no complete view {view} (has {s.views()})")
    mask = s.load(view, "corr/mask").astype(bool)
    if kind == "white":
        from sssphase_core.processing.colour import display_scale

        white = np.asarray(s.load(view, "white"), np.float32)
        scale = display_scale(white, mask)
        return _png(display(white / scale)), 0.0, scale, MAP_UNITS[kind]
    if kind == "mask":
        return (*colour_map(mask.astype(np.float32), np.ones_like(mask), 0.0, 1.0), MAP_UNITS[kind])
    if kind in ("depth", "surface"):
        stereo, which = stereo_for(state, s.manifest.get("rig", {}))
        xp, yp = (np.asarray(s.load(view, f"corr/{k}"), np.float64) for k in ("xp", "yp"))
        return geometry_maps((kind,), stereo, which, xp, yp, mask)[kind]
    return (*colour_map(np.asarray(s.load(view, f"corr/{kind}"), np.float32), mask), MAP_UNITS[kind])


#: The most points the page's 3D view is sent (evenly subsampled beyond).
MAX_CLOUD_POINTS = 60_000
#: Cropped about the turntable's axis, each view's points are picked from this many times its share.
CROP_OVERSAMPLE = 4


def session_points(state: ViewState, name: str, view: int, max_points: int = MAX_CLOUD_POINTS,
                   radius: float | None = None) -> dict[str, Any]:
    """A session view's decoded points for the page's 3D view: triangulated with :func:`stereo_for`'s calibration,
    coloured by the white capture; where the calibration has a turntable axis and the session several views with
    recorded angles, every view's points turned into the frame of the turntable at 0 degrees; ``radius``: only the
    points within that distance of the turntable's axis (a wall behind the object left out, as ``sss geometry
    --crop-radius``). -> {"count", "views", "unit", "which", "xyz" (base64 float32 (N, 3)), "rgb" (base64 uint8 (N, 3))}."""
    from sssphase_core.processing.colour import display_scale, srgb
    from sssphase_core.processing.triangulation import distance_to_axis, triangulate_points
    from sssphase_core.relight.merged_points import recorded_angles, to_turntable_frame

    s = _session(state, name)
    if view not in s.views():
        raise InputError(f"{s.name} has no complete view {view} (has {s.views()})")
    stereo, which = stereo_for(state, s.manifest.get("rig", {}))
    if radius is not None and (stereo.turntable_axis is None or not (np.isfinite(radius) and radius > 0)):
        raise InputError("a crop radius needs the calibration's turntable axis (sss calibrate turntable)"
                         if stereo.turntable_axis is None else f"the crop radius must be a positive distance, got {radius!r}")
    angles = recorded_angles(s, s.views()) if stereo.turntable_axis is not None and len(s.views()) > 1 else None
    chosen = s.views() if angles is not None else [view]
    xyz, rgb = [], []
    for v in chosen:  # each view's share of the points picked evenly first, then triangulated (1080p: 2 M pixels a view)
        xp, yp = (np.asarray(s.load(v, f"corr/{k}"), np.float64) for k in ("xp", "yp"))
        mask = s.load(v, "corr/mask").astype(bool) & np.isfinite(xp) & np.isfinite(yp)
        rows, cols = np.nonzero(mask)
        share = max_points // len(chosen)
        # cropped, most of a view may be wall: its share is then picked from the points left (four times as many
        # triangulated first)
        pick = np.linspace(0, len(rows) - 1, min(len(rows), share * (CROP_OVERSAMPLE if radius else 1))).astype(int)
        rows, cols = rows[pick], cols[pick]
        points = triangulate_points(stereo, np.stack([cols, rows], -1), np.stack([xp[rows, cols], yp[rows, cols]], -1))
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(points).all(-1) & (points[:, 2] > 0)  # (rays that meet behind the camera: none)
            if radius is not None:  # (the distance to the axis is the same before and after the turn)
                keep &= distance_to_axis(points, stereo.turntable_axis, stereo.turntable_point) <= radius
        kept = np.flatnonzero(keep)
        if len(kept) > share:  # (cropped: the view's share, evenly, of the points within the radius)
            keep[:] = False
            keep[kept[np.linspace(0, len(kept) - 1, share).astype(int)]] = True
        if angles is not None:
            points = to_turntable_frame(points, stereo, angles[v])
        white = np.asarray(s.load(v, "white"), np.float32)
        xyz.append(points[keep])
        rgb.append((srgb(np.clip(white[rows, cols] / display_scale(white, mask), 0, 1))[keep] * 255 + 0.5).astype(np.uint8))
    points, colours = np.concatenate(xyz).astype(np.float32), np.concatenate(rgb)
    merged = f"views {', '.join(map(str, chosen))} merged by the turntable's axis" if angles is not None else f"view {view}"
    if radius is not None:
        merged += f", within {radius:g} of its axis"
    return {"count": len(points), "views": chosen, "unit": stereo.unit or "calibration units",
            "which": f"{merged}; {which}; the decoded points (sss geometry takes the scattering's shift out)",
            "xyz": base64.b64encode(points.tobytes()).decode(), "rgb": base64.b64encode(colours.tobytes()).decode()}


async def session_cloud(request: Request, state: ViewState) -> Response:
    """A view's (or a turntable session's merged) 3D points for the page's 3D view."""
    radius = request.query_params.get("radius", "")
    try:
        crop = float(radius) if radius.strip() else None
    except ValueError:
        raise InputError(f"the crop radius must be a number, got {radius[:40]!r}") from None
    return _json(await asyncio.to_thread(session_points, state, request.path_params["name"], view_number(request),
                                         radius=crop))


async def session_map(request: Request, state: ViewState) -> Response:
    """A view's decoded map as a PNG; its colour bar's range and unit in headers."""
    png, lo, hi, unit = await asyncio.to_thread(session_map_png, state, request.path_params["name"], view_number(request),
                                                request.path_params["kind"])
    return Response(png, media_type="image/png", headers={"X-Range": f"{lo:.6g},{hi:.6g}",
                                                                 "X-Unit": unit.encode("ascii", "replace").decode()})


def _mosaic(tiles: list[np.ndarray], log: bool) -> bytes:
    """(K, K, 3) tiles side by side as one PNG, each scaled to its own peak (``log``: 4 decades)."""
    from sssphase_core.processing.colour import srgb

    shown = []
    for tile in tiles:
        t = np.clip(np.nan_to_num(tile), 0, None)
        peak = float(t.max()) or 1.0
        t = np.clip(1 + np.log10(np.maximum(t / peak, 1e-4)) / 4, 0, 1) if log else srgb(t / peak)
        shown.append(np.pad((t * 255).astype(np.uint8), ((2, 2), (2, 2), (0, 0)), constant_values=40))
    return _png(np.concatenate(shown, axis=1))


async def session_pixel(request: Request, state: ViewState) -> Response:
    """A clicked pixel: its PSP patch (the 8 frames) and its footprints from every source, log scale."""
    from sssphase_core.relight.probe import probe_pixel
    from sssphase_core.relight.views import load_view

    try:
        x, y = int(request.query_params["x"]), int(request.query_params["y"])
    except (KeyError, ValueError):
        return _problem("give the pixel as ?x=COLUMN&y=ROW")

    def run() -> dict[str, Any]:
        s = _session(state, request.path_params["name"])
        view = view_number(request)
        if view not in s.views():
            raise InputError(f"{s.name} has no complete view {view} (has {s.views()})")
        key = (str(s.path), view)
        if key not in state.probes:  # the view and its model sources, kept for the next click
            state.probes.clear()
            state.probes[key] = (load_view(s, view), {})
        rv, sources = state.probes[key]
        probe = probe_pixel(rv, (y, x), checkpoint=state.checkpoint, sources=sources)
        names = list(probe.footprints)
        return {"pixel": [x, y], "valid": probe.valid, "projector": list(probe.projector), "footprint_names": names,
                "skipped": probe.skipped, "patch_png": base64.b64encode(_mosaic(list(probe.patch), log=False)).decode(),
                "footprints_png": base64.b64encode(_mosaic([probe.footprints[n] for n in names], log=True)).decode()
                if names else None}

    return _json(await asyncio.to_thread(run))


# --- relighting --------------------------------------------------------------------------------------------


def _upload_path(state: ViewState, name: str) -> Path:
    folder = state.out / "uploads"
    path = folder / name
    try:
        given = path.parent == folder and path.is_file() and not path.is_symlink()  # names the server gave, nothing else
    except (OSError, ValueError):  # a NUL byte, an overlong name
        given = False
    if not given:
        raise InputError(f"no uploaded pattern {name!r} (the view keeps the last {MAX_UPLOADS}: upload it again)")
    state.upload_used[name] = time.time()  # used: kept longest (the file's own time is left alone: a sequence's record)
    return path


def _forget_old_uploads(state: ViewState) -> None:
    """Keep the ``MAX_UPLOADS`` most recently used uploads; remove the others' files, so that a long session of new
    patterns does not fill ``--out`` (each upload may be 32 MB). What was relit under them stays: the user's results
    (they were removed too, a finished video's among them, while the page still listed them). An upload a sequence
    relight is still relighting is kept."""
    def used(path: Path) -> float:
        with contextlib.suppress(OSError):
            return state.upload_used.get(path.name, path.stat().st_mtime)
        return 0.0

    busy = {job.upload for job in state.jobs.values() if not job.finished}
    uploads = sorted((state.out / "uploads").glob("upload_*"), key=used, reverse=True)
    for old in (p for p in uploads[MAX_UPLOADS:] if p.name not in busy):
        state.upload_used.pop(old.name, None)
        old.unlink(missing_ok=True)


def _upload_suffix(body: bytes) -> str | None:
    """The file suffix an upload's first bytes say it is (an image, or a video or animated image), or None."""
    for magic, suffix in (*IMAGE_MAGIC.items(), *SEQUENCE_MAGIC.items()):
        if body.startswith(magic):
            return suffix
    if body[4:8] == b"ftyp":
        return ".mp4"
    if body[:4] == b"RIFF" and body[8:12] == b"AVI ":
        return ".avi"
    return None


async def upload(request: Request, state: ViewState) -> Response:
    """An image body (PNG, JPEG, TIFF, BMP, EXR) or a pattern sequence (a video: MP4, MOV, MKV, WebM, AVI; an animated
    GIF, PNG or TIFF) -> its name for ``/api/relight`` and whether it is a sequence; checked by the pattern reader."""
    from sssphase_core.store.pattern_sequences import is_sequence

    if state.uploading >= MAX_UPLOADS_AT_ONCE:
        return _problem(f"{state.uploading} uploads are under way: send this one when they are done", status=429)
    state.uploading += 1
    try:
        body = await asyncio.wait_for(read_body(request, MAX_UPLOAD_BYTES, f"the upload is larger than "
                                                f"{MAX_UPLOAD_BYTES >> 20} MB (a longer video: sss relight SESSION "
                                                "--pattern FILE)"), UPLOAD_BODY_S)
    except TimeoutError:
        return _problem(f"the upload did not arrive within {UPLOAD_BODY_S:.0f} s", status=408)
    finally:
        state.uploading -= 1
    suffix = _upload_suffix(body)
    if suffix is None:
        return _problem("not an image or a video: upload a PNG, JPEG, TIFF, BMP or EXR image, or an MP4, MOV, MKV, "
                        "WebM, AVI or animated GIF")
    folder = state.out / "uploads"
    folder.mkdir(parents=True, exist_ok=True)
    name = f"upload_{hashlib.sha256(body).hexdigest()[:12]}{suffix}"
    if not (folder / name).is_file():  # the same bytes again: the file stays as it was (a sequence's record holds it)
        write_bytes(folder / name, bytes(body))
        try:  # a body that only starts like an image (4 bytes of a PNG signature) is no upload, and evicts none
            await asyncio.to_thread(_check_readable, folder / name)
        except (SssError, OSError) as exc:
            (folder / name).unlink(missing_ok=True)
            return _problem(str(_said_of_the_upload(exc, folder / name)))
    state.upload_used[name] = time.time()
    _forget_old_uploads(state)
    return JSONResponse({"name": name, "sequence": await asyncio.to_thread(is_sequence, folder / name)})


def _check_readable(path: Path) -> None:
    """Refuse an upload whose header does not read as the image or sequence its first bytes said."""
    from sssphase_core.store.imageio import frame_shape
    from sssphase_core.store.pattern_sequences import is_sequence, sequence_header

    if is_sequence(path):
        sequence_header(path)
    else:
        frame_shape(path)


def _said_of_the_upload(exc: SssError, path: Path | str) -> InputError:
    """``exc`` said as the page says it: "the upload", not the server's path to the uploaded file."""
    text = str(exc)
    for said in (f"--pattern {str(path)!r}", f"--pattern {path}", str(path)):
        text = text.replace(said, "the upload")
    return InputError(text)


class _Closing(KeyboardInterrupt):
    """A relight stopped because the view is closing (a KeyboardInterrupt, so that the footprints computed so far
    are kept in the cache, as at a Ctrl-C of ``sss relight``)."""


class _Notes(Narrator):
    """The lines ``sss relight`` would print for one relight (its calibration weights, the pixels a decoder
    gave the analytic model, ...), kept for the page; the files it wrote are listed on the page already.
    Its progress stops the relight when the view closes (``state.closing``)."""

    def __init__(self, state: ViewState) -> None:
        self.lines: list[str] = []
        self.state = state

    def say(self, text: str, warning: str = "") -> None:
        if not text.startswith("wrote "):
            self.lines.append(text)

    def task(self, label: str) -> Any:
        def progress(done: int, total: int) -> None:
            if self.state.closing:
                raise _Closing
        return progress


async def relight(request: Request, state: ViewState) -> Response:
    """Relight one session view under a named or uploaded pattern with ``sss relight``'s runner; the
    footprints are cached in the output folder, so the next pattern costs only the splat."""
    from sssphase_core.processing.patterns import REFERENCE_NAMES
    from sssphase_core.relight.runner import relight_session

    args = await read_json(request)
    if not isinstance(args, dict):
        return _problem("the request body must be a JSON object")
    pattern = str(args.get("pattern") or "")  # (null: not given, as the page leaves them; it said "got 'None'")
    backend = str(args.get("backend") or "auto")[:40]
    resize = str(args.get("resize") or "")[:40]
    view = args.get("view", 0)
    if isinstance(view, bool) or not isinstance(view, int):
        return _problem("view must be a whole number")

    if pattern.startswith("upload_"):
        from sssphase_core.store.pattern_sequences import is_sequence

        path = _upload_path(state, pattern)
        if await asyncio.to_thread(is_sequence, path):
            return _start_sequence(state, str(args.get("session", "")), view, path, backend, resize)
    notes = _Notes(state)

    def pattern_spec(s: Any) -> str:
        """An uploaded pattern's file, or a pattern's name: the view's own references and the named ones. Never
        a path the page gives: any image the server can read would be relit and served."""
        if pattern.startswith("upload_"):
            return str(_upload_path(state, pattern))
        own = [k[4:] for k in s.arrays(view) if k.startswith("ref/")] if view in s.views() else []
        if pattern in (*REFERENCE_NAMES, *own):
            return pattern
        raise InputError(f"pattern {pattern!r} is neither an uploaded pattern nor one of "
                         f"{', '.join(sorted({*REFERENCE_NAMES, *own}))}")

    def run() -> tuple[Any, float]:
        s = _session(state, str(args.get("session", "")))
        spec = pattern_spec(s)
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True) as warned:  # (a transparent upload, a sideways photo): the page's
                warnings.simplefilter("always")
                result = relight_session(s, [spec], backend=backend, checkpoint=state.checkpoint,
                                         out=relit_folder(state, s), views=[view], formats=("png", "exr"), cache=True,
                                         resize=resize, narrator=notes)
        except _Closing:
            raise InputError("stopped: the view is closing (the footprints computed so far are kept for the next "
                             "relight)") from None
        except SssError as exc:
            if not pattern.startswith("upload_"):
                raise
            raise _said_of_the_upload(exc, spec) from None
        notes.lines[:0] = [str(w.message) for w in warned]
        if pattern.startswith("upload_"):  # the server's path to the upload is "the upload" on the page
            notes.lines = [str(_said_of_the_upload(InputError(line), spec)) for line in notes.lines]
        return result, time.perf_counter() - t0

    if state.pending_relights >= MAX_PENDING_RELIGHTS:
        return _problem(f"{state.pending_relights} relights are waiting: try again when they have finished", 429)
    state.pending_relights += 1  # (the event loop's thread alone counts)
    try:
        result, seconds = await asyncio.get_running_loop().run_in_executor(state.relights, run)
    finally:
        state.pending_relights -= 1
    (item,) = result.images
    files = {("display" if p.stem.endswith("_display") else p.suffix[1:]): files_url(state, p) for p in item.paths}
    return _json({"backend": result.backend, "pattern": item.pattern, "files": files, "metrics": item.metrics,
                  "figure": files_url(state, item.figure) if item.figure else None,
                  "seconds": seconds, "clipped": item.clipped, "notes": notes.lines})


def _start_sequence(state: ViewState, session: str, view: int, path: Path, backend: str, resize: str) -> Response:
    """Relight every frame of an uploaded sequence in the background, as ``sss relight --pattern`` does (frames,
    video, resumable): answered at once with the job's id, whose progress and frames ``/api/relight/jobs/{id}``
    gives."""
    from sssphase_core.relight.sequence import relight_sequence

    waiting = state.pending_relights + sum(not job.finished for job in state.jobs.values())
    if waiting >= MAX_PENDING_RELIGHTS:
        return _problem(f"{waiting} relights are waiting: try again when they have finished", 429)
    s = _session(state, session)
    job = SequenceJob(secrets.token_hex(8), upload=path.name)
    state.jobs[job.id] = job
    forget_old_jobs(state.jobs)
    out = relit_folder(state, s)

    def relight(narrator: Narrator) -> Any:
        try:
            with warnings.catch_warnings(record=True) as warned:  # the page's notes, as a still's
                warnings.simplefilter("always")
                result = relight_sequence(s, path, backend=backend, checkpoint=state.checkpoint, out=out, views=[view],
                                          resize=resize, narrator=narrator, max_frames=MAX_UPLOAD_FRAMES)
        except SssError as exc:
            if isinstance(exc, Stopped):
                raise
            raise _said_of_the_upload(exc, path) from None
        for w in dict.fromkeys(str(w.message) for w in warned):  # (a frame's warning once, not once per frame)
            narrator.say(str(_said_of_the_upload(InputError(w), path)))
        return result

    state.relights.submit(run_sequence_job, job, relight, view, files_url(state, out))
    return JSONResponse({"job": job.id}, status_code=202)


async def relight_job(request: Request, state: ViewState) -> Response:
    """A sequence relight's progress; once done, its frames' and video's URLs."""
    job = state.jobs.get(request.path_params["job"])
    if job is None:
        return _problem("no such relight (the view keeps the last 20)", 404)
    return _json(dataclasses.asdict(job))


async def stop_job(request: Request, state: ViewState) -> Response:
    """Ask a sequence relight to stop (at its next progress report; the frames relit so far are kept)."""
    job = state.jobs.get(request.path_params["job"])
    if job is None:
        return _problem("no such relight (the view keeps the last 20)", 404)
    job.stop = not job.finished
    return _json({"stopping": job.stop, "status": job.status})


#: What ``/api/files`` serves from ``OUT/relit``: relit images, figures and videos (not the footprint caches).
SERVED_SUFFIXES = (".png", ".exr", ".mp4")


async def files(request: Request, state: ViewState) -> Response:
    """A file the view wrote: ``relit/<session>/<name>`` (relit images, figures, a sequence's video) or
    ``relit/<session>/<sequence>/<frame>``, inside the view's output folder, never through a link out of it."""
    root = (state.out / "relit").resolve()
    try:
        path = (root / request.path_params["path"]).resolve()
        depth = len(path.relative_to(root).parts)
        found = depth in (2, 3) and path.suffix in SERVED_SUFFIXES and path.is_file()
    except (OSError, ValueError):  # outside the folder, a NUL byte, a name longer than the file system takes
        found = False
    if not found:
        return _problem("no such file", 404)
    return FileResponse(path, filename=path.name)


# --- live view and live decode ------------------------------------------------------------------------


async def live_pixel(request: Request, state: ViewState) -> Response:
    """The latest live frame at a pixel: linear RGB (the reference exposure's units) and on the sensor."""
    frame = state.live.last
    if frame is None:
        return _problem("no live frame yet")
    try:
        x, y = int(request.query_params["x"]), int(request.query_params["y"])
    except (KeyError, ValueError):
        return _problem("give the pixel as ?x=COLUMN&y=ROW")
    h, w = frame.image.shape[:2]
    if not (0 <= x < w and 0 <= y < h):
        return _problem(f"pixel ({x}, {y}) is outside the {w}x{h} frame")
    rgb = [float(v) for v in frame.image[y, x]]
    return JSONResponse({"pixel": [x, y], "sequence": frame.sequence, "linear": rgb,
                         "sensor": [v * frame.exposure for v in rgb], "clip": frame.stats.clip})



async def live_socket(websocket: WebSocket) -> None:
    """Frames (JSON header, then JPEG bytes) or decoded sets (JSON with PNGs) as fast as the rig gives them;
    the page sends ``{"pattern", "exposure", "psp_frame", "decode"}`` to change what it sees."""
    state: ViewState = websocket.app.state.view
    if not _authorised(state, websocket.query_params.get("token")):  # accepted to be closed with the reason (a page
        await websocket.accept()  # left open across a restart of the view holds the old token: it must not retry)
        await websocket.close(code=4403, reason="wrong or missing token: the view was restarted, or the URL lost its "
                                                "token; open the URL `sss view` printed")
        return
    if state.live_sockets >= MAX_LIVE_SOCKETS:  # accepted to be closed with the reason (before accept: a bare 403)
        await websocket.accept()
        await websocket.close(code=1013, reason=f"{MAX_LIVE_SOCKETS} live views are open already: close one")
        return
    await websocket.accept()
    state.live_sockets += 1
    settings = state.settings
    state.live_opened += 1
    mine = state.live_opened  # (settings.changed_by: which page set the rig's settings last)
    receiving = asyncio.create_task(_receive_settings(websocket, settings, mine))
    last = time.perf_counter()
    try:
        while not receiving.done():
            try:
                asked = dataclasses.replace(settings)  # what this frame is taken with (the page may change it meanwhile)
                shared = _shared_settings(asked, mine)
                if asked.decode:
                    decoded, white, seconds = await asyncio.to_thread(state.live.decode, asked)
                    message = await asyncio.to_thread(_decode_message, decoded, white, seconds, state)
                    await websocket.send_text(json.dumps(_finite({**message, **shared})))
                    continue
                frame = await asyncio.to_thread(state.live.frame, asked)
            except SssError as exc:
                await websocket.send_text(json.dumps({"type": "error", "message": str(exc)}))
                await asyncio.sleep(0.5)
                continue
            now = time.perf_counter()
            header = {"type": "frame", "sequence": frame.sequence, "fps": 1.0 / max(now - last, 1e-6),
                      "requested_ms": frame.requested_s * 1000, "received_ms": frame.received_s * 1000,
                      "sent_ms": time.time() * 1000, "mean": frame.stats.mean, "histogram": frame.stats.histogram,
                      "clipped": frame.stats.clipped, "shape": list(frame.image.shape), "pattern": asked.pattern,
                      "exposure": asked.exposure, "gain": asked.gain, **shared}
            last = now
            await websocket.send_text(json.dumps(header))
            await websocket.send_bytes(_jpeg(display(frame.image * np.float32(asked.exposure), clip=frame.stats.clip)))
    except (WebSocketDisconnect, RuntimeError):
        pass
    finally:
        receiving.cancel()
        state.live_sockets -= 1


def _shared_settings(asked: LiveSettings, mine: int) -> dict[str, Any]:
    """What a frame or decode was taken with, for the page: the rig is one, so every page of the view shares its
    settings, and a page whose controls another page changed (``by_other``) shows that page's."""
    return {"settings": {"pattern": asked.pattern, "exposure": asked.exposure, "gain": asked.gain,
                         "psp_frame": asked.psp_frame, "decode": asked.decode},
            "by_other": asked.changed_by not in (0, mine)}


async def _receive_settings(websocket: WebSocket, settings: LiveSettings, mine: int) -> None:
    while True:
        try:
            received = await websocket.receive()
        except (WebSocketDisconnect, RuntimeError):
            return
        if received.get("type") == "websocket.disconnect":
            return
        text = received.get("text")  # a binary frame, or a message far longer than a setting: ignored
        if not isinstance(text, str) or len(text) > MAX_MESSAGE_CHARS:
            continue
        try:
            message = json.loads(text)
        except (ValueError, RecursionError, TypeError):  # not JSON, nested too deep, a 5000-digit number
            continue
        if isinstance(message, dict):
            apply_live_message(settings, message)
            settings.changed_by = mine


def apply_live_message(settings: LiveSettings, message: dict[str, Any]) -> None:
    """Take what the page asks of the live view (``exposure``, ``pattern``, ``gain``, ``psp_frame``, ``decode``)
    into ``settings``; a value of the wrong type or out of range is ignored, as garbage is."""
    exposure = message.get("exposure")
    if isinstance(exposure, int | float) and not isinstance(exposure, bool) and 1e-3 <= exposure <= 1e3:
        settings.exposure = float(exposure)
    if message.get("pattern") in (*LIVE_PATTERNS, "psp"):
        settings.pattern = message["pattern"]
    gain = message.get("gain", ...)
    if gain is None or (isinstance(gain, int | float) and not isinstance(gain, bool) and 0 <= gain <= 1e3):
        settings.gain = None if gain is None else float(gain)
    if isinstance(message.get("psp_frame"), int) and not isinstance(message["psp_frame"], bool):
        settings.psp_frame = message["psp_frame"]
    if isinstance(message.get("decode"), bool):  # ("no" was true, as any non-empty string is)
        settings.decode = message["decode"]


def _decode_message(decoded: Any, white: np.ndarray, seconds: float, state: ViewState) -> dict[str, Any]:
    """One live decode for the page: the mask over the white image, the modulation, the reason counts and, where a
    calibration is known (:func:`stereo_for` of the live rig), the depth and surface maps of the decoded points."""
    from sssphase_core.processing.colour import display_scale
    from sssphase_core.processing.psp import Reason

    modulation, lo, hi = colour_map(decoded.modulation, np.ones_like(decoded.mask), 0.0,
                                    max(float(np.percentile(decoded.modulation, 99)), decoded.threshold * 4))
    mask_rgb = display(white / display_scale(white))
    mask_rgb[~decoded.mask] = (mask_rgb[~decoded.mask] * 0.25).astype(np.uint8)
    reasons = {r.name: int((decoded.reason == r).sum()) for r in Reason}
    message = {"type": "decode", "seconds": seconds, "valid": float(decoded.mask.mean()), "threshold": decoded.threshold,
               "modulation_range": [lo, hi], "reasons": reasons,
               "mask_png": base64.b64encode(_png(mask_rgb)).decode(), "modulation_png": base64.b64encode(modulation).decode()}
    rig = state.live.rig
    try:
        stereo, which = stereo_for(state, {"camera": rig.camera, "options": rig.options})
    except InputError as exc:
        return {**message, "depth_note": str(exc)}
    if not decoded.mask.any():
        return {**message, "depth_note": "nothing decoded: no depth"}
    for kind, (png, lo, hi, unit) in geometry_maps(("depth", "surface"), stereo, which, decoded.xp, decoded.yp,
                                                  decoded.mask).items():
        message.update({f"{kind}_png": base64.b64encode(png).decode(), f"{kind}_range": [lo, hi], f"{kind}_unit": unit})
    return message


def _hostname(netloc: str) -> str:
    """The host of a ``Host:`` value (``127.0.0.1:8000``, ``[::1]:8000``, ``localhost``), lower case, IPv6 without
    its brackets; "" when it does not parse."""
    try:
        return urlsplit("//" + netloc).hostname or ""
    except ValueError:  # e.g. an unclosed bracket
        return ""


class Guard:
    """ASGI middleware in front of every route: a request whose ``Host:`` names none of ``hosts`` (None: any) is
    refused (a web page that re-points its own name at 127.0.0.1, DNS rebinding; Starlette's TrustedHostMiddleware
    cannot parse an IPv6 ``Host:``, so a view on ::1 went unchecked), and so is a websocket opened by a page of
    another origin (its ``Origin:`` naming another host and port than its ``Host:``). Every HTTP answer, the
    framework's own 404 and 405 too, says ``nosniff``."""

    def __init__(self, app: Any, hosts: list[str] | None = None) -> None:
        self.app, self.hosts = app, None if hosts is None else {h.lower().strip("[]") for h in hosts}

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        host = headers.get("host", "")
        refused = self.hosts is not None and _hostname(host) not in self.hosts
        if scope["type"] == "websocket":
            origin = headers.get("origin")
            if origin is not None and origin != "null":
                try:
                    refused |= urlsplit(origin).netloc.lower() != host.lower()
                except ValueError:
                    refused = True
            if refused:
                return await send({"type": "websocket.close", "code": 1008})  # before accept: answered 403
            return await self.app(scope, receive, send)
        if refused:
            return await Response("Invalid host header", 400, headers={"X-Content-Type-Options": "nosniff"})(
                scope, receive, send)

        async def nosniff(message: dict) -> None:
            if message["type"] == "http.response.start":
                names = {k.lower() for k, _ in message.get("headers", [])}
                if b"x-content-type-options" not in names:
                    message = {**message, "headers": [*message.get("headers", []), (b"x-content-type-options", b"nosniff")]}
            await send(message)

        await self.app(scope, receive, nosniff)


def build_app(state: ViewState, *, hosts: list[str] | None = None) -> Starlette:
    """The ASGI application serving ``state``; with ``hosts``, requests naming another host (``Host:``) are
    refused, which keeps a web page that re-points its own name at 127.0.0.1 (DNS rebinding) off the view."""
    routes = [
        Route("/", guarded(index)),
        Route("/api/state", guarded(api_state)),
        Route("/api/sessions/{name}/{view}/map/{kind}.png", guarded(session_map)),
        Route("/api/sessions/{name}/{view}/pixel", guarded(session_pixel)),
        Route("/api/sessions/{name}/{view}/points", guarded(session_cloud)),
        Route("/api/live/pixel", guarded(live_pixel)),
        Route("/api/upload", guarded(upload), methods=["POST"]),
        Route("/api/relight", guarded(relight), methods=["POST"]),
        Route("/api/relight/jobs/{job}", guarded(relight_job)),
        Route("/api/relight/jobs/{job}/stop", guarded(stop_job), methods=["POST"]),
        Route("/api/files/relit/{path:path}", guarded(files)),
        WebSocketRoute("/ws/live", live_socket),
    ]
    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        yield
        state.stop_work()  # (a server stopped otherwise than by a signal: the relight thread must not outlive it)
        state.relights.shutdown(wait=False, cancel_futures=True)
        await asyncio.to_thread(state.live.close)  # the rig closed, the daemon this started stopped

    app = Starlette(routes=routes, lifespan=lifespan, middleware=[Middleware(Guard, hosts=hosts)])
    app.state.view = state
    return app
