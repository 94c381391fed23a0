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

    @property
    def is_sim(self) -> bool:
        return self.camera.startswith("sim:")

    @classmethod
    def from_toml(cls, path: Path) -> RigSpec:
        """``[devices]`` camera/projector/turntable ids, ``[options]`` for the plugin, ``[processing]``."""
        try:
            cfg = tomllib.loads(Path(path).read_text())
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"cannot read rig file {path}: {exc}") from None
        dev, proc = cfg.get("devices", {}), cfg.get("processing", {})
        if "camera" not in dev or "projector" not in dev:
            raise InputError(f"{path}: [devices] needs camera and projector ids (see `sss devices`)")
        unknown = set(proc) - {"patch", "saturation", "black_level", "white_scale", "median"}
        if unknown:
            raise InputError(f"{path}: unknown [processing] keys {sorted(unknown)}")
        return cls(dev["camera"], dev["projector"], dev.get("turntable"), dict(cfg.get("options", {})), **proc)


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


def build_frames(req: CaptureRequest, size: tuple[int, int], patch: int) -> tuple[Any, list[dict[str, Any]], int]:
    """The capture plan and the daemon's frame specs (named references by plan, files as images)."""
    from sssphase_core.patterns import REFERENCE_NAMES, capture_plan

    named = [r for r in req.references if r in REFERENCE_NAMES]
    files = [Path(r) for r in req.references if r not in REFERENCE_NAMES]
    spacing = req.dot_spacing or max(2, round(DOT_SPACING_PER_PATCH * patch))
    plan = capture_plan(*size, footprints=req.footprints, dot_spacing=spacing,
                        references=("white", "black", *named), hdr_exposures=req.hdr)
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
        self.extractor = None

        self.dots = writer.stream_array("dots", n_dots) if req.keep_dots and n_dots else None

    def _develop(self, data: np.ndarray, exposure: float) -> np.ndarray:
        if data.ndim == 3:
            return np.asarray(data, np.float32)
        if self.rig.black_level is None or self.rig.white_scale is None:
            raise DataError("the camera sends raw frames: set [processing] black_level and white_scale in the rig file")
        from sssphase_core import isp

        return isp.develop(data, self.rig.black_level, self.rig.white_scale * exposure, median=self.rig.median)

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
        if self.extractor is None:
            from sssphase_core.footprints import DotGridExtractor, dark_reference

            corr = self.decode()
            self.extractor = DotGridExtractor(corr.xp, corr.yp, corr.mask, self.spacing, self.patch)
            self.dark = dark_reference(self.images["black"], self.images["white"])
        sx, sy = (int(v) for v in key.split("/")[1].split("_"))
        self.extractor.add(sx, sy, image - self.dark)
        if self.dots is not None:
            self.dots.append(image)

    def finish(self) -> dict[str, Any]:
        """Write the view's arrays (the dot frames were streamed already); returns manifest info."""
        cfg, w = self.plan.psp, self.writer
        hf = float(cfg.period)
        order = [f"psp/{o}/p{hf:g}/s{n}" for o in ("x", "y") for n in range(cfg.n_shifts)]
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
        if self.extractor is not None:
            pixels, crops = self.extractor.result()
            w.write("footprints/pixels", pixels.astype(np.int32))
            w.write("footprints/crops", crops)
            info["footprints"] = {"count": len(pixels), "missing": len(self.extractor.missing()), "spacing": self.spacing}
        if self.dots is not None:
            self.dots.close()
        return info


def write_sim_ground_truth(writer: ViewWriter, req: CaptureRequest, view: int, frames: list[dict[str, Any]]) -> None:
    """Exact correspondence, material labels and noise-free renders of the references (exact
    footprints are left to ``SimScene.footprints``: they would double the session's size)."""
    from sssphase_core.patterns import PlannedFrame
    from sssphase_core.sim import SimScene, rig_preset

    scene = SimScene(req.object, rig=rig_preset(req.preset), view=view, n_views=req.views, seed=req.seed)
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
                         options=options)
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
    plan, frames, spacing = build_frames(req, size, rig.patch or 32)
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
                write_sim_ground_truth(writer, req, view, frames)
        except BaseException:
            writer.abort()
            session.set_view(view, {"status": "interrupted"})
            raise
        writer.commit({"angle": angle, "frames": len(frames), **info})
    return session


IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
PSP_KEY_RE = re.compile(r"^psp/([xy])/p([0-9.]+)/s([0-9]+)$")


@dataclass
class _ImportedFrame:
    name: str
    data: np.ndarray
    header: dict[str, Any] = field(default_factory=dict)


def _read_image(path: Path) -> np.ndarray:
    """A linear image as float32 RGB: ``.npy`` as stored, 8/16-bit PNG/TIFF divided by the top code."""
    if path.suffix.lower() == ".npy":
        arr = np.load(path, allow_pickle=False)
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
    return np.repeat(arr[..., None], 3, axis=-1) if arr.ndim == 2 else arr


def import_folder(folder: Path, root: Path, name: str, projector_size: tuple[int, int], *, patch: int = 32) -> Session:
    """Import images from another rig: ``folder/view_NNN/`` (or ``folder`` itself for one view) holds
    one image per plan key with '/' written as '__' (``psp__x__p20__s0.png``, ``white.png``,
    ``black.png``, ``ref__checkerboard.png``, optionally ``dots__{sx}_{sy}.png``)."""
    from sssphase_core.patterns import CapturePlan, PSPConfig

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    view_dirs = sorted(p for p in folder.glob("view_*") if p.is_dir()) or [folder]
    req = CaptureRequest(check_object_name(name), views=len(view_dirs), out=Path(root))
    session = Session.create(root, name, n_views=len(view_dirs), imported_from=str(folder.resolve()),
                             rig={"imported": True, "projector_size": list(projector_size)},
                             software={"sssphase": __version__})
    for view, vdir in enumerate(view_dirs):
        files = {p.stem.replace("__", "/"): p for p in sorted(vdir.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
        psp = [(m.group(1), float(m.group(2)), int(m.group(3))) for k in files if (m := PSP_KEY_RE.match(k))]
        missing = [k for k in ("white", "black") if k not in files]
        if missing or not psp:
            raise InputError(f"{vdir}: needs white, black and psp__x__p<period>__s<n> images (missing: "
                             f"{', '.join(missing) or 'psp'})")
        periods = sorted({p for _, p, _ in psp})
        config = PSPConfig(period=periods[0], n_shifts=max(s for _, _, s in psp) + 1, unwrap_periods=tuple(periods[1:]))
        dots = [k for k in files if k.startswith("dots/")]
        spacing = 1 + max((int(v) for k in dots for v in k[5:].split("_")), default=0)
        plan = CapturePlan(*projector_size, config, ())
        writer = session.begin_view(view)
        try:
            proc = ViewProcessor(writer, plan, spacing, patch, RigSpec(camera="import", turntable=None), req, 0)
            for key in sorted(files, key=lambda k: k.startswith("dots/")):
                proc.add(_ImportedFrame(key, _read_image(files[key])), {"name": key, "key": key, "exposure": 1.0})
            info = proc.finish()
        except BaseException:
            writer.abort()
            raise
        writer.commit({"source": str(vdir), **info})
    return session
