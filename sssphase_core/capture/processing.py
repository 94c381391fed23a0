"""Frames into a view: HDR merging, PSP decoding, dot-grid crops streamed to the session as they
arrive (:class:`ViewProcessor`, the one writer of views), and the simulator's ground truth."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from sssphase_core.capture.plan import CaptureRequest, RigSpec
from sssphase_core.errors import DataError
from sssphase_core.store.session import ViewWriter

#: The share of a frame's lit values that may lie above the brightest any pattern gives and still be stray samples
#: (a path tracer's fireflies, cosmic rays: a few values in 10^5; a render at a few samples per pixel, whose noise is
#: heavy-tailed, more); beyond it the frame is of another exposure or units (a white at twice the fringes' scale:
#: 84% of its lit values, at 4x 100%; a checkerboard reference at 4x 53%).
OUTLIER_MAX_SHARE = 0.2


class FrameLike(Protocol):
    name: str
    data: np.ndarray
    header: dict[str, Any]


def develop_frame(data: np.ndarray, rig: RigSpec, exposure: float = 1.0, layout: str | None = None,
                  meta: Mapping[str, Any] | None = None) -> np.ndarray:
    """A received frame -> linear RGB float32 (H, W, 3): colour frames as sent, raw Bayer developed
    (in ``layout``, the camera's word for it, else the rig's ``bayer``). The black level and white scale
    are the rig file's; where it gives none, the camera's own (``meta``'s ``black_level`` and
    ``bit_depth``: linear 1.0 is then the sensor's full scale at the reference exposure)."""
    if data.ndim == 3:
        return colour_frame(data, rig, meta)
    if data.dtype.kind not in "iu":  # a mono camera's light, or a raw frame of floats: neither is a mosaic of codes
        raise DataError(f"the camera {rig.camera} sends {data.dtype} frames of shape {tuple(data.shape)}: an (H, W) "
                        "frame is a raw Bayer mosaic of integer codes; a mono camera's plugin sends its frame as "
                        "(H, W, 3), the grey in each channel")
    try:
        black, white = raw_levels(rig, meta)
    except DataError as exc:
        raise DataError(f"the camera {rig.camera}{str(exc).removeprefix('the camera')}") from None
    from sssphase_core.processing import isp

    return isp.develop(data, black, white * exposure, median=rig.median, layout=layout or rig.bayer)


def colour_frame(data: np.ndarray, rig: RigSpec, meta: Mapping[str, Any] | None = None) -> np.ndarray:
    """A camera's colour frame (H, W, 3) -> linear float32: floats as sent; integer codes scaled to [0, 1] by the
    frame's ``bit_depth`` (its meta), else their type's range (a uint16 RGB frame was taken as linear units, 65535x
    too bright, and `sss validate` found nothing wrong). Any other channel count is refused naming the camera (an
    RGBA frame made a session `sss validate` then refused)."""
    if data.shape[2] != 3:
        raise DataError(f"the camera {rig.camera} sends frames of shape {tuple(data.shape)}: a colour frame is (H, W, 3) "
                        "RGB (a raw Bayer frame is (H, W)): check its plugin's pixel format")
    if data.dtype.kind in "iu":
        depth = (meta or {}).get("bit_depth")
        top = float(2 ** int(depth) - 1) if isinstance(depth, int) and 1 <= depth <= 32 else float(np.iinfo(data.dtype).max)
        return np.asarray(data, np.float32) / np.float32(top)
    if data.dtype.kind != "f":
        raise DataError(f"the camera {rig.camera} sends {data.dtype} frames: give floats (linear) or integer codes")
    return np.asarray(data, np.float32)


def raw_levels(rig: RigSpec, meta: Mapping[str, Any] | None = None) -> tuple[float, float]:
    """(black level, white scale) in DN for raw frames: the rig file's, else the camera's (``meta``)."""
    meta = meta or {}
    black = rig.black_level if rig.black_level is not None else meta.get("black_level")
    bits = meta.get("bit_depth")
    white = rig.white_scale
    if white is None and black is not None and isinstance(bits, int) and 1 <= bits <= 16:
        white = float(2**bits - 1) - float(black)
    if black is None or white is None or not white > 0:
        raise DataError("the camera sends raw frames without its black level and bit depth: set [processing] "
                        "black_level and white_scale in the rig file")
    return float(black), float(white)


class CropStream:
    """One extractor's crops (``footprints.DotGridExtractor``: one per camera pixel, or
    ``DotTransportExtractor``: one per projector dot) written to ``<prefix>/crops`` float16 as the dot
    frames arrive, and their camera pixels (and projector dots) to ``<prefix>/pixels`` (``/dots``) in the
    same order on ``close``: memory holds one frame's crops and one chunk at any K (a 1080p view at K = 90
    has ~10^5 crops of 97 kB). With ``drop_noise`` the first ``NOISE_SAMPLE`` crops are held back to
    measure the noise floor (``crop_noise``), which is then zeroed in every crop (``drop_below_noise``); crops
    with nothing left (a dot whose light did not reach the camera) are not stored."""

    def __init__(self, writer: ViewWriter, prefix: str, extractor: Any, *, drop_noise: bool = False,
                 chunk_bytes: int = 2**21) -> None:
        self.writer, self.prefix, self.extractor, self.drop_noise = writer, prefix, extractor, drop_noise
        self.array = writer.growing_array(f"{prefix}/crops", (extractor.patch, extractor.patch, extractor.channels),
                                          np.float16, chunk_bytes)
        self.order: list[np.ndarray] = []
        self.held: list[tuple[np.ndarray, np.ndarray]] = []  # (rows, crops) until the noise floor is known
        self.noise: float | None = None

    def add(self, shift_x: int, shift_y: int, frame: np.ndarray) -> None:
        from sssphase_core.processing.footprints import NOISE_SAMPLE

        idx, crops = self.extractor.crops(shift_x, shift_y, frame)
        if not len(idx):
            return
        if self.drop_noise and self.noise is None:
            self.held.append((idx, crops))
            if sum(len(c) for _, c in self.held) >= NOISE_SAMPLE:
                self._release()
            return
        self._write(idx, crops)

    def _write(self, idx: np.ndarray, crops: np.ndarray) -> None:
        """Append crops (and remember their rows); with ``drop_noise`` the noise floor is zeroed and the
        crops left empty (no light of theirs reached the camera) are not stored."""
        from sssphase_core.processing.footprints import drop_below_noise, holds_light

        if self.drop_noise and self.noise:
            crops = drop_below_noise(crops, self.noise)
            seen = holds_light(crops)
            idx, crops = idx[seen], crops[seen]
        self.order.append(idx)
        self.array.extend(crops)

    def _release(self) -> None:
        from sssphase_core.processing.footprints import NOISE_SAMPLE, crop_noise

        held, self.held = self.held, []
        crops = np.concatenate([c for _, c in held]) if held else np.zeros((0, *self.array.arr.shape[1:]), np.float32)
        self.noise = crop_noise(crops[:NOISE_SAMPLE]) if len(crops) else 0.0
        if held:
            self._write(np.concatenate([i for i, _ in held]), crops)

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
            from sssphase_core.processing.footprints import DENOISE_SMOOTHING

            info["noise"] = self.noise
            info["denoise_smoothing"] = list(DENOISE_SMOOTHING)  # the masks whose union is stored
        return info


class ViewProcessor:
    """Consumes one view's frames in plan order: merges HDR brackets, decodes PSP, extracts footprints."""

    def __init__(self, writer: ViewWriter, plan: Any, spacing: int, patch: int, rig: RigSpec, req: CaptureRequest,
                 n_dots: int, camera_isp: dict[str, Any] | None = None) -> None:
        """``camera_isp``: how a camera that sends colour frames made them (``{"demosaic", "median", "bayer"}``,
        the sim camera's), recorded in the view's info; raw frames developed here record this ISP instead.
        Relighting passes relit images through it before comparing them with captures (``isp.through_camera``)."""
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
        self.camera_isp = camera_isp
        self.bound: np.ndarray | None = None  # (H, W, 1) the brightest value any pattern can give (once decoded)
        self.outliers = 0  # values above it, repaired
        self.repaired: dict[str, int] = {}  # frame key -> its values repaired (frames with any; dot grids not)
        self.unrepaired: dict[str, np.ndarray] = {}  # ref/<name> -> the reference as it came (its brightness check)
        self.sources: dict[str, str] = {}  # frame key -> the file it came from (an import's), named in its refusals
        self.lit_values = 0  # values of the pixels the white lights (the share of outliers a frame may hold is of these)
        self.hot: np.ndarray | None = None  # (H, W, C) what hot pixels add to every frame (once decoded)

    def _develop(self, data: np.ndarray, exposure: float, meta: Mapping[str, Any]) -> np.ndarray:
        layout = meta.get("bayer")
        if data.ndim == 2:  # a raw Bayer frame developed here: the camera pipeline is this ISP
            layout = layout or self.rig.bayer
            self.camera_isp = {"demosaic": "malvar", "median": bool(self.rig.median), "bayer": layout}
            if "bit_depth" in meta:  # the sensor's word, with the levels the frames were developed with
                black, white = raw_levels(self.rig, meta)
                self.camera_isp.update(bit_depth=int(meta["bit_depth"]), black_level=black, white_scale=white)
        return develop_frame(data, self.rig, exposure, layout, meta)

    def add(self, frame: FrameLike, spec: Mapping[str, Any]) -> None:
        tag = frame.header.get("meta", {}).get("pattern_tag")
        if tag is not None and tag != spec["name"]:
            raise DataError(f"frame {spec['name']} saw pattern {tag!r}: projector and camera are out of sync")
        key, exposure = spec["key"], float(spec["exposure"])
        if spec.get("kind") == "image" and "image" in spec and key not in self.patterns:  # the user's own pattern
            img = spec["image"]
            self.patterns[key] = np.frombuffer(img["data"], img["dtype"]).reshape(img["shape"])
        bracket = self.brackets.setdefault(key, [])
        bracket.append((exposure, self._develop(frame.data, exposure, frame.header.get("meta", {}))))
        if len(bracket) < self.n_exposures:
            return
        del self.brackets[key]
        image = bracket[0][1] if len(bracket) == 1 else self._merge(bracket)
        if key.startswith("psp/"):
            self.psp[key] = image
        elif key.startswith("dots/"):
            self._add_dots(key, image)
        else:  # repaired with the others at the decode, or as it comes after it
            self.images[key] = image if self.bound is None else self._repaired(image, key)

    def _merge(self, bracket: list[tuple[float, np.ndarray]]) -> np.ndarray:
        from sssphase_core.processing import isp

        if self.rig.saturation is None:
            raise DataError("HDR needs the rig's saturation level ([processing] saturation in the rig file)")
        frames = np.stack([b[1] for b in bracket])
        if (level := isp.clipping_below(frames, [b[0] for b in bracket], self.rig.saturation)) is not None:
            raise DataError(f"the camera's frames clip at {level:.4g} (linear, at exposure 1) but the rig file's "
                            f"[processing] saturation is {self.rig.saturation:g}: the HDR merge would trust clipped "
                            f"samples; set saturation = {0.98 * level:.3g} (the view is not written)")
        return isp.hdr_merge(np.stack([b[1] for b in bracket]), [b[0] for b in bracket], self.rig.saturation,
                             spread=4 if self.rig.median else 2)

    def decode(self) -> Any:
        if self.corr is None:
            from sssphase_core.processing import psp

            self._repair_outliers()
            bayer = str(self.camera_isp.get("bayer", "RGGB")) if self.camera_isp else None  # a known Bayer pipeline
            self.corr = psp.decode_camera(self.psp, self.plan.psp, (self.plan.width, self.plan.height), bayer=bayer)
        return self.corr

    def _repair_outliers(self) -> None:
        """Before anything reads the frames, in every frame (dot grids as they come): hot pixels lose what they
        add (``isp.hot_pixel_offsets``, found in the black frame), and values no pattern could make (above
        the robust white image, e.g. a path tracer's fireflies) are replaced by their neighbours' median.
        Measured on a 200 x 150 import: 6 fireflies per frame took its captured transport to -15.8 dB and
        the decoder to 14 dB; 60 hot pixels took that transport to 0.9 dB."""
        from sssphase_core.processing.isp import hot_pixel_offsets, outlier_bound, robust_white

        if "white" not in self.images:
            return
        sets: dict[str, list[np.ndarray]] = {}
        for key, image in self.psp.items():  # psp/<orientation>/p<period>/s<shift>: one set per orientation and period
            sets.setdefault(key.rsplit("/", 1)[0], []).append(image)
        if "black" in self.images:  # subtracted from every frame by _repaired
            means = [sum(frames) / np.float32(len(frames)) for frames in sets.values()]  # frame by frame, not stacked
            hot = hot_pixel_offsets(self.images["black"], [self.images["white"], *means])
            self.hot = hot if hot.any() else None
        # the bound from the frames as they came: a hot pixel's is higher by its offset, nowhere else
        white = robust_white(self.images["white"], list(sets.values()))
        self.bound = outlier_bound(white)
        brightest = white.max(axis=-1)
        self.lit_values = int((brightest > 0.1 * max(float(np.percentile(brightest, 99.9)), 0.0)).sum()) * white.shape[-1]
        for frames in (self.psp, self.images):
            for key, image in frames.items():
                frames[key] = self._repaired(image, key)

    def _repaired(self, image: np.ndarray, key: str | None = None) -> np.ndarray:
        """``image`` (the frame ``key``) less the hot pixels' offsets, its values above ``self.bound`` replaced
        (``isp.repair_outliers``, counted). A frame (not a dot grid) with more than :data:`OUTLIER_MAX_SHARE` of
        its lit values above the bound is refused: that is another exposure or units than the other frames'
        (a white rendered at twice the fringes' scale had 17,304 values "repaired" towards 0 in silence)."""
        from sssphase_core.processing.isp import repair_outliers

        if self.hot is not None:
            image = image - self.hot
        if key is not None and key.startswith("ref/"):  # a reference's exposure is checked on it as it came
            self.unrepaired[key] = image
        image, n = repair_outliers(image, self.bound)  # type: ignore[arg-type]
        if key is not None and n > OUTLIER_MAX_SHARE * max(self.lit_values, 1):
            share = (f"{n / self.lit_values:.0%} of the lit ones" if 0 < n <= self.lit_values  # (it said "123% of")
                     else f"more than the {self.lit_values:,} lit ones")
            name = self.sources.get(key, f"frame {key}")
            if key == "white":  # the bound is the median of the white and the fringe sets: here, the sets'
                raise DataError(f"{name}: {n:,} of its values ({share}) are brighter than the fringe sets say full "
                                "white is (shifted fringes average half of it): the white capture and the fringe "
                                "frames have another exposure or units; give every frame the same exposure and units")
            raise DataError(f"{name}: {n:,} of its values ({share}) are "
                            "brighter than full white could make them (from the white capture and the fringe sets): "
                            "not stray samples but another exposure or other units than the other frames; give every "
                            "frame the same exposure and units")
        self.outliers += n
        if key is not None and n:
            self.repaired[key] = n
        return image

    def _add_dots(self, key: str, image: np.ndarray) -> None:
        if self.footprints is None:
            from sssphase_core.processing.footprints import (
                DotGridExtractor,
                DotTransportExtractor,
                dark_reference,
            )

            corr = self.decode()
            self.dark = dark_reference(self.images["black"], self.images["white"])
            self.footprints = CropStream(self.writer, "footprints",
                                         DotGridExtractor(corr.xp, corr.yp, corr.mask, self.spacing, self.patch))
            if self.req.dot_stride == 1:  # a sparse lattice is no light transport: only the pixels' crops are kept
                self.transport = CropStream(self.writer, "transport",
                                            DotTransportExtractor(corr.xp, corr.yp, corr.mask, self.spacing, self.patch,
                                                                  (self.plan.width, self.plan.height)), drop_noise=True)
        sx, sy = (int(v) for v in key.split("/")[1].split("_"))
        if self.bound is not None:  # dot grids come after the decode: repaired as they come
            image = self._repaired(image)
        dots = image - self.dark
        self.footprints.add(sx, sy, dots)
        if self.transport is not None:
            self.transport.add(sx, sy, dots)
        if self.dots is not None:
            self.dots.append(image)

    def check_light(self) -> None:
        """Refuse the view's frames when they are not light in the camera's units (a driver's frames of NaN, of
        negative numbers, of huge values: what ``sss validate`` and relighting refuse), naming the camera and the
        frame, before anything of the view is written (a capture wrote them and said "complete")."""
        from sssphase_core.store.light import light_problem, white_level

        white = self.images.get("white")
        level = white_level(white) if white is not None else None
        for name, image in (*self.psp.items(), *self.images.items()):
            if (problem := light_problem(f"frame {name}", image, level)) is not None:
                raise DataError(f"the camera {self.rig.camera}: {problem} (its frames are not light as a camera "
                                "measures it: check the driver's pixel format and black level; the view is not written)")

    def finish(self) -> dict[str, Any]:
        """Write the view's arrays (the dot frames were streamed already); returns manifest info."""
        cfg, w = self.plan.psp, self.writer
        order = cfg.input_keys
        corr = self.decode()
        from sssphase_core.processing.psp import four_step

        n = cfg.n_shifts  # learning and relighting read the paper's 4 shifts per orientation: other counts are resampled
        w.write("psp", np.concatenate([four_step(np.stack([self.psp[k] for k in order[i:i + n]])) for i in (0, n)]))
        info: dict[str, Any] = {"psp_keys": order, "coverage": corr.coverage(), "camera_isp": self.camera_isp,
                                "outliers_repaired": self.outliers,
                                "hot_pixels": 0 if self.hot is None else int((self.hot > 0).any(axis=-1).sum())}
        if n != 4:
            info["psp_from_shifts"] = n  # `psp` holds the 4-step images their first harmonic gives (psp.four_step)
        unwrap = [k for k in self.psp if k not in order]
        if self.req.keep_unwrap and unwrap:
            w.write("unwrap", np.stack([self.psp[k] for k in unwrap]))
            info["unwrap_keys"] = unwrap
        for name in ("xp", "yp", "mask", "reason", "modulation", "offset"):
            w.write(f"corr/{name}", np.asarray(getattr(corr, name)))
        for key, image in self.images.items():
            w.write(key, image)
        for key, pattern in self.patterns.items():  # so that relighting can be evaluated against ref/<name>
            w.write(f"pattern/{key.removeprefix('ref/')}", np.asarray(pattern, np.float32))
        if self.footprints is not None:
            info["footprints"] = {**self.footprints.close(), "missing": len(self.footprints.extractor.missing()),
                                  "spacing": self.spacing, "dot_stride": self.req.dot_stride}
        if self.transport is not None:
            info["transport"] = {**self.transport.close(), "noise_dropped": True}
        if self.dots is not None:
            self.dots.close()
        return info


def write_sim_ground_truth(writer: ViewWriter, req: CaptureRequest, view: int, frames: list[dict[str, Any]],
                           options: dict[str, Any] | None = None) -> None:
    """Exact correspondence, material labels and noise-free renders of the references (exact
    footprints are left to ``SimScene.footprints``: they would double the session's size).
    ``options``: the sim rig's options (a projector response other than the preset's, the transport model, the
    ``device`` it renders on)."""
    from sssphase_core.compute import renders_on_torch
    from sssphase_core.processing.patterns import PlannedFrame
    from sssphase_core.sim import SimScene, rig_from_options

    rig = rig_from_options({"preset": req.preset, **(options or {})})
    device = str((options or {}).get("device", "cpu"))
    factory = None
    if renders_on_torch(device):  # renders on the GPU the daemon renders on: numpy took ~50 s per 1080p view
        from sssphase_core.sim_accel import transport_factory

        factory = transport_factory(device)
    scene = SimScene(req.object, rig=rig, view=view, n_views=req.views, seed=req.seed, transport_factory=factory)
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
