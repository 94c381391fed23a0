"""The capture engine: runs the capture plan per view through a daemon client and streams frames into
core processing as they arrive (PSP decoding, dot-grid footprint extraction), writing a session.

The client is passed in (anything with ``call(op, **args) -> dict`` and ``capture(rig, frames)``
yielding frames with ``name``, ``data`` and ``header``; see ``sssphase_daemon.client``), so this
module never imports ZeroMQ. Raw dot-grid frames are kept only on request. A view is written
atomically when complete, so an interrupted capture (Ctrl-C, a dead daemon, a full disk) resumes at
the first incomplete view; sim frames are seeded per (view, pattern), so a resumed capture is
bit-identical to an uninterrupted one.
"""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from sssphase_core import __version__
from sssphase_core.errors import DataError, InputError
from sssphase_core.session import Session, ViewWriter, check_object_name

DEFAULT_HDR = (0.25, 1.0, 4.0)
DOT_SPACING_PER_PATCH = 55 / 90  # the paper's 55 px spacing for K = 90 patches


class FrameLike(Protocol):
    name: str
    data: np.ndarray
    header: dict[str, Any]


class ClientLike(Protocol):
    def call(self, op: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]: ...

    def capture(self, rig: str, frames: list[dict[str, Any]]) -> Iterable[FrameLike]: ...


def dot_spacing_for(patch: int) -> int:
    """Dot-grid spacing (projector px) for footprint crops of ``patch`` px: the paper's 55 px at K = 90."""
    return max(2, round(DOT_SPACING_PER_PATCH * patch))


@dataclass
class RigSpec:
    """Which devices to use and their options (``--rig RIG.toml``; default: the sim rig)."""

    camera: str = "sim:camera0"
    projector: str = "sim:projector0"
    turntable: str | None = "sim:turntable0"
    options: dict[str, Any] = field(default_factory=dict)
    patch: int | None = None  # footprint crop size K (sim: the preset's)
    saturation: float | None = None  # linear clipping level at exposure 1 (HDR merge; sim: the sensor's)
    black_level: float | None = None  # for raw Bayer cameras: develop with these
    white_scale: float | None = None
    median: bool = True  # the paper's 3x3 median per Bayer plane (blurs fringes only a few px wide)
    gamma: float | None = None  # projector response v**gamma ([projector], from `sss calibrate projector`; None: 2.2)
    projector_black: float | None = None  # projector black level relative to white (None: estimated/preset)
    trigger: str | None = None  # a trigger device that exposes the camera on each frame ([devices] trigger)

    @property
    def is_sim(self) -> bool:
        return self.camera.startswith("sim:")

    @classmethod
    def from_toml(cls, path: Path) -> RigSpec:
        """``[devices]`` camera/projector/turntable/trigger ids, ``[options]`` for the plugins, ``[processing]``."""
        try:
            cfg = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"cannot read rig file {path}: {exc}") from None
        dev, proc, resp = cfg.get("devices", {}), cfg.get("processing", {}), cfg.get("projector", {})
        if "camera" not in dev or "projector" not in dev:
            raise InputError(f"{path}: [devices] needs camera and projector ids (see `sss devices`)")
        bad = [k for k, v in dev.items() if k not in ("camera", "projector", "turntable", "trigger") or not isinstance(v, str)]
        if bad:
            raise InputError(f"{path}: [devices] takes camera, projector, turntable and trigger device ids (strings), "
                             f"not {', '.join(sorted(bad))}")
        unknown = set(proc) - {"patch", "saturation", "black_level", "white_scale", "median"}
        if unknown:
            raise InputError(f"{path}: unknown [processing] keys {sorted(unknown)}")
        gamma, black = resp.get("gamma"), resp.get("black")
        if gamma is not None and not (isinstance(gamma, int | float) and 0.3 <= gamma <= 5):
            raise InputError(f"{path}: [projector] gamma must be a number in [0.3, 5], got {gamma!r}")
        if black is not None and not (isinstance(black, int | float) and 0 <= black < 0.5):
            raise InputError(f"{path}: [projector] black must be a number in [0, 0.5), got {black!r}")
        return cls(dev["camera"], dev["projector"], dev.get("turntable"), dict(cfg.get("options", {})), **proc,
                   gamma=None if gamma is None else float(gamma), projector_black=None if black is None else float(black),
                   trigger=dev.get("trigger"))


@dataclass
class CaptureRequest:
    object: str
    views: int = 4
    footprints: bool = False
    references: tuple[str, ...] = ()  # named patterns (patterns.REFERENCE_NAMES) or image files
    hdr: tuple[float, ...] = ()
    keep_dots: bool = False
    keep_unwrap: bool = False
    resume: bool = False
    out: Path = Path("sessions")
    seed: int = 0
    preset: str = "cpu"
    dot_spacing: int | None = None


Progress = Callable[[int, int, int], None]  # (view, frames done, frames total)


def _load_reference(path: Path, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    try:
        img = Image.open(path)
    except OSError as exc:
        raise InputError(f"cannot read reference image {path}: {exc}") from None
    w, h = size
    if img.size != (w, h):
        raise InputError(f"reference image {path} is {img.size[0]}x{img.size[1]}, the projector is {w}x{h}")
    arr = np.asarray(img.convert("L" if img.mode in ("L", "I;16", "1") else "RGB"), np.float32)
    return np.clip(arr / (65535.0 if np.asarray(img).dtype == np.uint16 else 255.0), 0, 1)


def build_frames(req: CaptureRequest, size: tuple[int, int], patch: int,
                 gamma: float | None = None) -> tuple[Any, list[dict[str, Any]], int]:
    """The capture plan and the daemon's frame specs (named references by plan, files as images);
    PSP patterns are pre-distorted for the projector's ``gamma`` (default 2.2)."""
    from sssphase_core.patterns import DEFAULT_GAMMA, REFERENCE_NAMES, capture_plan

    named = [r for r in req.references if r in REFERENCE_NAMES]
    files = [Path(r) for r in req.references if r not in REFERENCE_NAMES]
    spacing = req.dot_spacing or dot_spacing_for(patch)
    plan = capture_plan(*size, footprints=req.footprints, dot_spacing=spacing,
                        references=("white", "black", *named), hdr_exposures=req.hdr,
                        gamma=DEFAULT_GAMMA if gamma is None else gamma)
    frames = json.loads(plan.to_json())["frames"]
    for path in files:
        name = check_object_name(path.stem)
        img = _load_reference(path, size)
        for e in req.hdr or (1.0,):
            spec_name = f"ref/{name}" if not req.hdr else f"ref/{name}@e{e:g}"
            frames.append({"name": spec_name, "key": f"ref/{name}", "kind": "image", "exposure": e,
                           "params": {"file": path.name, "hdr": len(req.hdr) or None},
                           "image": {"dtype": img.dtype.str, "shape": list(img.shape), "data": img.tobytes()}})
    return plan, frames, spacing


def _plan_digest(frames: list[dict[str, Any]]) -> str:
    h = hashlib.sha256()
    for f in frames:
        h.update(json.dumps({k: v for k, v in f.items() if k != "image"}, sort_keys=True).encode())
        if "image" in f:
            h.update(f["image"]["data"])
    return h.hexdigest()




def develop_frame(data: np.ndarray, rig: RigSpec, exposure: float = 1.0) -> np.ndarray:
    """A received frame -> linear RGB float32 (H, W, 3): colour frames as sent, raw Bayer developed."""
    if data.ndim == 3:
        return np.asarray(data, np.float32)
    if rig.black_level is None or rig.white_scale is None:
        raise DataError("the camera sends raw frames: set [processing] black_level and white_scale in the rig file")
    from sssphase_core import isp

    return isp.develop(data, rig.black_level, rig.white_scale * exposure, median=rig.median)


class CropStream:
    """One extractor's crops (``footprints.DotGridExtractor``: one per camera pixel, or
    ``DotTransportExtractor``: one per projector dot) written to ``<prefix>/crops`` float16 as the dot
    frames arrive, and their camera pixels (and projector dots) to ``<prefix>/pixels`` (``/dots``) in the
    same order on ``close``: memory holds one frame's crops and one chunk at any K (a 1080p view at K = 90
    has ~10^5 crops of 97 kB). With ``drop_noise`` the first ``NOISE_SAMPLE`` crops are held back to
    measure the noise floor (``ring_noise``), which is then zeroed in every crop (``drop_below_noise``)."""

    def __init__(self, writer: ViewWriter, prefix: str, extractor: Any, *, drop_noise: bool = False,
                 chunk_bytes: int = 2**21) -> None:
        self.writer, self.prefix, self.extractor, self.drop_noise = writer, prefix, extractor, drop_noise
        self.array = writer.growing_array(f"{prefix}/crops", (extractor.patch, extractor.patch, extractor.channels),
                                          np.float16, chunk_bytes)
        self.order: list[np.ndarray] = []
        self.held: list[np.ndarray] = []
        self.noise: float | None = None

    def add(self, shift_x: int, shift_y: int, frame: np.ndarray) -> None:
        from sssphase_core.footprints import NOISE_SAMPLE

        idx, crops = self.extractor.crops(shift_x, shift_y, frame)
        if not len(idx):
            return
        self.order.append(idx)
        if self.drop_noise and self.noise is None:
            self.held.append(crops)
            if sum(len(c) for c in self.held) >= NOISE_SAMPLE:
                self._release()
            return
        self.array.extend(self._dropped(crops))

    def _dropped(self, crops: np.ndarray) -> np.ndarray:
        from sssphase_core.footprints import drop_below_noise

        return drop_below_noise(crops, self.noise) if self.drop_noise and self.noise else crops

    def _release(self) -> None:
        from sssphase_core.footprints import NOISE_SAMPLE, ring_noise

        held = np.concatenate(self.held) if self.held else np.zeros((0, *self.array.arr.shape[1:]), np.float32)
        self.held = []
        self.noise = ring_noise(held[:NOISE_SAMPLE]) if len(held) else 0.0
        self.array.extend(self._dropped(held))

    def close(self) -> dict[str, Any]:
        """Write the pixels (and dots) in crop order; returns manifest info (count, noise)."""
        if self.drop_noise and self.noise is None:
            self._release()
        self.array.close()
        order = np.concatenate(self.order) if self.order else np.zeros(0, np.int64)
        self.writer.write(f"{self.prefix}/pixels", self.extractor.pixels[order].astype(np.int32))
        info: dict[str, Any] = {"count": len(order)}
        if hasattr(self.extractor, "dots"):
            self.writer.write(f"{self.prefix}/dots", self.extractor.dots[order].astype(np.int32))
            info["dots"] = len(order)
        if self.drop_noise:
            info["noise"] = self.noise
        return info


class ViewProcessor:
    """Consumes one view's frames in plan order: merges HDR brackets, decodes PSP, extracts footprints."""

    def __init__(self, writer: ViewWriter, plan: Any, spacing: int, patch: int, rig: RigSpec, req: CaptureRequest,
                 n_dots: int) -> None:
        self.writer, self.plan, self.spacing, self.patch, self.rig, self.req = writer, plan, spacing, patch, rig, req
        self.n_exposures = len(req.hdr) or 1
        self.brackets: dict[str, list[tuple[float, np.ndarray]]] = {}
        self.psp: dict[str, np.ndarray] = {}
        self.images: dict[str, np.ndarray] = {}
        self.patterns: dict[str, np.ndarray] = {}  # ref/<name> -> the projected image of a file reference
        self.corr = None
        self.footprints: CropStream | None = None  # one crop per camera pixel (training targets)
        self.transport: CropStream | None = None  # one crop per projector dot (the measured backend's data)

        self.dots = writer.stream_array("dots", n_dots) if req.keep_dots and n_dots else None

    def _develop(self, data: np.ndarray, exposure: float) -> np.ndarray:
        return develop_frame(data, self.rig, exposure)

    def add(self, frame: FrameLike, spec: Mapping[str, Any]) -> None:
        tag = frame.header.get("meta", {}).get("pattern_tag")
        if tag is not None and tag != spec["name"]:
            raise DataError(f"frame {spec['name']} saw pattern {tag!r}: projector and camera are out of sync")
        key, exposure = spec["key"], float(spec["exposure"])
        if spec.get("kind") == "image" and "image" in spec and key not in self.patterns:  # the user's own pattern
            img = spec["image"]
            self.patterns[key] = np.frombuffer(img["data"], img["dtype"]).reshape(img["shape"])
        bracket = self.brackets.setdefault(key, [])
        bracket.append((exposure, self._develop(frame.data, exposure)))
        if len(bracket) < self.n_exposures:
            return
        del self.brackets[key]
        image = bracket[0][1] if len(bracket) == 1 else self._merge(bracket)
        if key.startswith("psp/"):
            self.psp[key] = image
        elif key.startswith("dots/"):
            self._add_dots(key, image)
        else:
            self.images[key] = image

    def _merge(self, bracket: list[tuple[float, np.ndarray]]) -> np.ndarray:
        from sssphase_core import isp

        if self.rig.saturation is None:
            raise DataError("HDR needs the rig's saturation level ([processing] saturation in the rig file)")
        return isp.hdr_merge(np.stack([b[1] for b in bracket]), [b[0] for b in bracket], self.rig.saturation)

    def decode(self) -> Any:
        if self.corr is None:
            from sssphase_core import psp

            self.corr = psp.decode(self.psp, self.plan.psp, (self.plan.width, self.plan.height))
        return self.corr

    def _add_dots(self, key: str, image: np.ndarray) -> None:
        if self.footprints is None:
            from sssphase_core.footprints import DotGridExtractor, DotTransportExtractor, dark_reference

            corr = self.decode()
            self.dark = dark_reference(self.images["black"], self.images["white"])
            self.footprints = CropStream(self.writer, "footprints",
                                         DotGridExtractor(corr.xp, corr.yp, corr.mask, self.spacing, self.patch))
            self.transport = CropStream(self.writer, "transport",
                                        DotTransportExtractor(corr.xp, corr.yp, corr.mask, self.spacing, self.patch,
                                                              (self.plan.width, self.plan.height)), drop_noise=True)
        sx, sy = (int(v) for v in key.split("/")[1].split("_"))
        dots = image - self.dark
        self.footprints.add(sx, sy, dots)
        self.transport.add(sx, sy, dots)
        if self.dots is not None:
            self.dots.append(image)

    def finish(self) -> dict[str, Any]:
        """Write the view's arrays (the dot frames were streamed already); returns manifest info."""
        cfg, w = self.plan.psp, self.writer
        order = cfg.input_keys
        corr = self.decode()
        w.write("psp", np.stack([self.psp[k] for k in order]))
        info: dict[str, Any] = {"psp_keys": order, "coverage": corr.coverage()}
        if self.req.keep_unwrap:
            unwrap = [k for k in self.psp if k not in order]
            w.write("unwrap", np.stack([self.psp[k] for k in unwrap]))
            info["unwrap_keys"] = unwrap
        for name in ("xp", "yp", "mask", "reason", "modulation", "offset"):
            w.write(f"corr/{name}", np.asarray(getattr(corr, name)))
        for key, image in self.images.items():
            w.write(key, image)
        for key, pattern in self.patterns.items():  # so that relighting can be evaluated against ref/<name>
            w.write(f"pattern/{key.removeprefix('ref/')}", np.asarray(pattern, np.float32))
        if self.footprints is not None and self.transport is not None:
            info["footprints"] = {**self.footprints.close(), "missing": len(self.footprints.extractor.missing()),
                                  "spacing": self.spacing}
            info["transport"] = {**self.transport.close(), "noise_dropped": True}
        if self.dots is not None:
            self.dots.close()
        return info


def write_sim_ground_truth(writer: ViewWriter, req: CaptureRequest, view: int, frames: list[dict[str, Any]],
                           options: dict[str, Any] | None = None) -> None:
    """Exact correspondence, material labels and noise-free renders of the references (exact
    footprints are left to ``SimScene.footprints``: they would double the session's size).
    ``options``: the sim rig's options (a projector response other than the preset's)."""
    from sssphase_core.patterns import PlannedFrame
    from sssphase_core.sim import SimScene, rig_preset, with_projector_response

    opts = options or {}
    rig = with_projector_response(rig_preset(req.preset), opts.get("projector_gamma"), opts.get("projector_black"))
    scene = SimScene(req.object, rig=rig, view=view, n_views=req.views, seed=req.seed)
    writer.write("gt/proj_xy", scene.proj_xy.astype(np.float32))
    writer.write("gt/labels", scene.material.astype(np.int16))
    writer.write("gt/mask", scene.mask)
    refs = {f["key"]: f for f in frames if f["kind"] in ("white", "ref", "image")}
    patterns = []
    for spec in refs.values():
        if spec["kind"] == "image":
            img = spec["image"]
            patterns.append(np.frombuffer(img["data"], img["dtype"]).reshape(img["shape"]))
        else:
            patterns.append(PlannedFrame(spec["key"], spec["kind"], spec["params"], 1.0).pattern())
    if patterns:
        colour = any(p.ndim == 3 for p in patterns)
        stack = np.stack([np.repeat(p[..., None], 3, -1) if colour and p.ndim == 2 else p for p in patterns])
        for key, image in zip(refs, scene.render(stack), strict=True):
            writer.write(f"gt/render/{key.removeprefix('ref/')}", image)


def run_capture(client: ClientLike, req: CaptureRequest, rig: RigSpec | None = None, *,
                progress: Progress | None = None, ask_move: Callable[[int, float], None] | None = None) -> Session:
    """Capture ``req.views`` views of ``req.object`` into ``req.out/<object>`` (resuming if asked)."""
    check_object_name(req.object)
    if req.views < 1:
        raise InputError(f"--views must be >= 1, got {req.views}")
    rig = rig or RigSpec()
    options = dict(rig.options)
    if rig.is_sim:
        options = {"object": req.object, "preset": req.preset, "seed": req.seed, "n_views": req.views, **options}
    opened = client.call("open_rig", camera=rig.camera, projector=rig.projector, turntable=rig.turntable,
                         trigger=rig.trigger, options=options)
    try:
        return _capture_views(client, req, rig, options, opened, progress, ask_move)
    finally:
        try:
            client.call("close_rig", timeout_s=2.0, rig=opened["rig"])
        except Exception:  # the daemon may be gone (that is what the caller is told about)
            pass


def _capture_views(client: ClientLike, req: CaptureRequest, rig: RigSpec, options: dict[str, Any],
                   opened: dict[str, Any], progress: Progress | None,
                   ask_move: Callable[[int, float], None] | None) -> Session:
    size = tuple(opened["projector_size"])
    if rig.is_sim:
        from sssphase_core.sim import rig_preset

        preset = rig_preset(str(options["preset"]))
        rig.patch = rig.patch or preset.patch
        rig.saturation = rig.saturation or preset.sensor.saturation(1.0)
    if req.footprints and rig.patch is None:
        raise InputError("footprints need the crop size: set [processing] patch in the rig file")
    plan, frames, spacing = build_frames(req, size, rig.patch or 32, rig.gamma)
    digest = _plan_digest(frames)
    session = Session.create(req.out, req.object, resume=req.resume, n_views=req.views, plan_digest=digest,
                             rig={**asdict(rig), "options": options}, devices=opened["devices"],
                             plugins=opened["plugins"], software={"sssphase": __version__},
                             plan=json.loads(plan.to_json()), reference_files=list(dict.fromkeys(f["params"]["file"] for f in frames if f["kind"] == "image")))
    if session.manifest.get("plan_digest") != digest or session.manifest.get("n_views") != req.views:
        raise InputError(f"{session.path} was captured with a different plan or view count: resume with the same options")
    n_dots = sum(1 for f in frames if f["kind"] == "dots")
    for view in range(req.views):
        if session.status(view) == "complete":
            continue
        angle = 360.0 * view / req.views
        if rig.turntable:
            client.call("move", rig=opened["rig"], angle=angle)
        elif ask_move is not None:
            ask_move(view, angle)
        writer = session.begin_view(view)
        try:
            proc = ViewProcessor(writer, plan, spacing, rig.patch or 32, rig, req, n_dots)
            for i, (frame, spec) in enumerate(zip(client.capture(opened["rig"], frames), frames, strict=False)):
                proc.add(frame, spec)
                if progress:
                    progress(view, i + 1, len(frames))
            info = proc.finish()
            if rig.is_sim:
                write_sim_ground_truth(writer, req, view, frames, options)
        except BaseException:
            writer.abort()
            session.set_view(view, {"status": "interrupted"})
            raise
        writer.commit({"angle": angle, "frames": len(frames), **info})
    return session


IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".exr")
PSP_KEY_RE = re.compile(r"^psp/([xy])/p([0-9]{1,5}(?:\.[0-9]{1,6})?)/s([0-9]{1,2})$")
DOTS_KEY_RE = re.compile(r"^dots/([0-9]{1,3})_([0-9]{1,3})$")
OTHER_KEY_RE = re.compile(r"^(white|black|(ref|pattern)/[A-Za-z0-9][A-Za-z0-9_.-]{0,63})$")
MAX_FRAME_PIXELS = 1 << 26  # 64 MP: larger frames are refused from their header, before decoding
MAX_SHIFTS = 32


@dataclass
class _ImportedFrame:
    name: str
    data: np.ndarray
    header: dict[str, Any] = field(default_factory=dict)


def _image_shape(path: Path) -> tuple[int, ...]:
    """The pixel shape a frame file declares, read from its header only (no pixel is decoded)."""
    try:
        if path.suffix.lower() == ".npy":
            return tuple(np.load(path, mmap_mode="r", allow_pickle=False).shape)
        if path.suffix.lower() == ".exr":
            from sssphase_core import exr

            return exr.exr_size(path)
        from PIL import Image

        Image.MAX_IMAGE_PIXELS = None  # our own limit below, on the header's size
        with Image.open(path) as img:
            return (img.size[1], img.size[0])
    except (OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"cannot read {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None


def _read_image(path: Path) -> np.ndarray:
    """A linear image as float32 RGB: ``.npy`` and ``.exr`` as stored, 8/16-bit PNG/TIFF divided by the
    top code. Frames larger than ``MAX_FRAME_PIXELS`` are refused from their header."""
    shape = _image_shape(path)
    if len(shape) >= 2 and shape[0] * shape[1] > MAX_FRAME_PIXELS:
        raise InputError(f"{path} is {shape[1]}x{shape[0]}: larger than any camera frame this importer takes "
                         f"({MAX_FRAME_PIXELS // 2**20} MP)")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except ValueError as exc:  # pickled object arrays are never loaded
            raise InputError(f"cannot read {path}: {exc}") from None
        if arr.dtype.kind not in "fiub":
            raise InputError(f"{path} holds {arr.dtype} values, not an image")
    elif path.suffix.lower() == ".exr":
        from sssphase_core import exr

        arr = exr.read_exr(path)
    else:
        import cv2

        arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise InputError(f"cannot read image {path}")
        if arr.ndim == 3:
            arr = cv2.cvtColor(arr[..., :3], cv2.COLOR_BGR2RGB)
        if np.issubdtype(arr.dtype, np.integer):
            arr = arr.astype(np.float32) / np.iinfo(arr.dtype).max
    arr = np.asarray(arr, np.float32)
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] != 3):
        raise InputError(f"{path} has shape {arr.shape}: expected (H, W) or (H, W, 3)")
    if not np.isfinite(arr).all():
        raise InputError(f"{path} holds NaN or infinite values")
    return np.repeat(arr[..., None], 3, axis=-1) if arr.ndim == 2 else arr


def _frame_files(vdir: Path) -> dict[str, Path]:
    """Frame files of one view by plan key: ``psp__x__p20__s0.png`` or ``psp/x/p20/s0.png`` (the layout
    `sss patterns` writes) are both ``psp/x/p20/s0``. Files of other types are ignored; an image whose
    name is no plan key is refused, naming it."""
    files: dict[str, Path] = {}
    for path in sorted(vdir.rglob("*")):
        rel = path.relative_to(vdir)
        if not path.is_file() or path.suffix.lower() not in IMAGE_SUFFIXES or rel.parts[0].startswith("view_"):
            continue
        key = rel.with_suffix("").as_posix().replace("__", "/")
        if not (PSP_KEY_RE.match(key) or DOTS_KEY_RE.match(key) or OTHER_KEY_RE.match(key)):
            raise InputError(f"{path}: {key!r} is no frame name (expected psp__<x|y>__p<period>__s<n>, white, black, "
                             "ref__<name>, pattern__<name> or dots__<sx>_<sy>; see SESSION_FORMAT.md)")
        if m := PSP_KEY_RE.match(key):  # one spelling per frame: p20.0 -> p20, s01 -> s1 (the capture plan's)
            key = f"psp/{m.group(1)}/p{float(m.group(2)):g}/s{int(m.group(3))}"
        if key in files:
            raise InputError(f"{path} and {files[key]} are both frame {key!r}")
        files[key] = path
    return files


def _psp_config(vdir: Path, keys: Iterable[str]) -> Any:
    """The PSP configuration the frame names describe; every (orientation, period) needs shifts 0..N-1."""
    from sssphase_core.patterns import PSPConfig

    sets: dict[tuple[str, float], set[int]] = {}
    for key in keys:
        if m := PSP_KEY_RE.match(key):
            sets.setdefault((m.group(1), float(m.group(2))), set()).add(int(m.group(3)))
    if not sets:
        raise InputError(f"{vdir}: no psp__<x|y>__p<period>__s<n> frames")
    n = max(len(v) for v in sets.values())
    for (o, period), shifts in sorted(sets.items()):
        if shifts != set(range(n)) or not 3 <= n <= MAX_SHIFTS:
            raise InputError(f"{vdir}: PSP frames {o}, period {period:g} have shifts {sorted(shifts)[:8]}; every set "
                             f"needs shifts 0..N-1 with 3 <= N <= {MAX_SHIFTS}")
    periods = sorted({p for _, p in sets})
    for o in ("x", "y"):
        if (o, periods[0]) not in sets:
            raise InputError(f"{vdir}: the {o} orientation has no PSP frames at period {periods[0]:g}")
    if periods[0] <= 0:
        raise InputError(f"{vdir}: a PSP period must be positive")
    return PSPConfig(period=periods[0], n_shifts=n, unwrap_periods=tuple(periods[1:]))


def import_folder(folder: Path, root: Path, name: str, projector_size: tuple[int, int], *, patch: int = 32,
                  gamma: float = 2.2) -> Session:
    """Import frames captured by another rig into a session, processed by the capture engine's
    :class:`ViewProcessor` exactly like a capture.

    ``folder/view_NNN/`` (or ``folder`` itself for one view) holds one image per plan key, with '/'
    written as '__' or as folders (``psp__x__p20__s0.png`` or ``psp/x/p20/s0.png``, ``white.png``,
    ``black.png``, ``ref__checkerboard.png``, optionally ``dots__{sx}_{sy}.png``); PNG/TIFF (8/16-bit),
    ``.npy`` or EXR. A reference that is not a named pattern needs its projected image as
    ``pattern__<name>.png``. A failed import leaves nothing behind.
    """
    import shutil

    from sssphase_core.patterns import REFERENCE_NAMES, CapturePlan, _reference_params
    from sssphase_core.relight import read_pattern

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    w, h = (int(v) for v in projector_size)
    if not (0 < w <= 16384 and 0 < h <= 16384):
        raise InputError(f"projector size must be positive and at most 16384, got {w}x{h}")
    view_dirs = sorted(p for p in folder.glob("view_*") if p.is_dir()) or [folder]
    req = CaptureRequest(check_object_name(name), views=len(view_dirs), out=Path(root))
    views = [(vdir, _frame_files(vdir)) for vdir in view_dirs]  # refuse bad names before writing anything
    for (vdir, files) in views:
        missing = [k for k in ("white", "black") if k not in files]
        if missing:
            raise InputError(f"{vdir}: needs white, black and psp__x__p<period>__s<n> frames (missing: {', '.join(missing)})")
    configs = [_psp_config(vdir, files) for vdir, files in views]
    path = Path(root) / name
    if path.exists():
        raise InputError(f"{path} already exists: import into another --out or choose another --object")
    frames: list[dict[str, Any]] = []
    for key in sorted({k for _, files in views for k in files if k.startswith("ref/")}):
        ref = key.removeprefix("ref/")
        k, kind, params = _reference_params(ref, w, h) if ref in REFERENCE_NAMES else (key, "image", {"file": ref})
        frames.append({"name": key, "key": key, "kind": kind, "params": {"width": w, "height": h, **params},
                       "exposure": 1.0})
    plan_json = {"projector": [w, h], "gamma": float(gamma), "psp": asdict(configs[0]), "frames": frames}
    session = Session.create(root, name, n_views=len(view_dirs), imported_from=str(folder.resolve()),
                             rig={"camera": "import", "projector_size": [w, h], "patch": patch, "imported": True},
                             plan=plan_json, software={"sssphase": __version__})
    try:
        for view, ((vdir, files), config) in enumerate(zip(views, configs, strict=True)):
            dots = [DOTS_KEY_RE.match(k) for k in files if k.startswith("dots/")]
            spacing = 1 + max((int(v) for m in dots for v in m.groups()), default=0)
            plan = CapturePlan(w, h, config, (), gamma)
            writer = session.begin_view(view)
            try:
                proc = ViewProcessor(writer, plan, spacing, patch, RigSpec(camera="import", turntable=None), req, 0)
                shape = None
                for key in sorted((k for k in files if not k.startswith("pattern/")), key=lambda k: k.startswith("dots/")):
                    image = _read_image(files[key])
                    if shape is not None and image.shape != shape:
                        raise InputError(f"{files[key]} is {image.shape[1]}x{image.shape[0]}, the other frames "
                                         f"{shape[1]}x{shape[0]}")
                    shape = image.shape
                    proc.add(_ImportedFrame(key, image), {"name": key, "key": key, "exposure": 1.0})
                for key in (k for k in files if k.startswith("pattern/")):
                    proc.patterns[f"ref/{key.removeprefix('pattern/')}"] = read_pattern(files[key], (w, h))
                info = proc.finish()
            except BaseException:
                writer.abort()
                raise
            writer.commit({"source": str(vdir), **info})
    except BaseException:
        shutil.rmtree(session.path, ignore_errors=True)  # nothing half-imported blocks the name
        raise
    return session
