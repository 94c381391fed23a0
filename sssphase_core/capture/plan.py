"""What to capture: the rig (devices and processing, ``--rig RIG.toml``), the request (object, views,
footprints, references, HDR) and the frame list it becomes."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sssphase_core.errors import InputError
from sssphase_core.store.imageio import read_pattern
from sssphase_core.store.session import check_object_name

DEFAULT_HDR = (0.25, 1.0, 4.0)
#: The sim rig's noise seeds (plugins/sim_plugin.py takes 0 to 2**63 - 1).
MAX_SEED = 2**63 - 1
DOT_SPACING_PER_PATCH = 55 / 90  # the paper's 55 px spacing for K = 90 patches


def dot_spacing_for(patch: int) -> int:
    """Dot-grid spacing (projector px) for footprint crops of ``patch`` px: the paper's 55 px at K = 90."""
    return max(2, round(DOT_SPACING_PER_PATCH * patch))


#: The tables of a rig file, and the keys of its [projector] table (what `sss calibrate projector` writes).
RIG_TABLES = ("devices", "processing", "projector", "options")
#: The projector responses a rig file may give: gamma in [0.3, 5] (each colour's and their mean), black relative to
#: white in [0, 0.5) (each colour's up to 0.5) -- `sss calibrate projector` refuses a fit outside them.
GAMMA_RANGE = (0.3, 5.0)
BLACK_LIMIT = 0.5
PROJECTOR_KEYS = frozenset({"gamma", "black", "gamma_rgb", "black_rgb", "levels", "response_rgb", "rms", "pixels"})


def _numbers(v: Any, lo: float, hi: float) -> bool:
    """Whether ``v`` is a list of numbers (not booleans) in [lo, hi] (NaN and inf outside any range)."""
    return isinstance(v, list) and all(isinstance(x, int | float) and not isinstance(x, bool) and lo <= x <= hi
                                       for x in v)


def _check_fit_record(path: Path, resp: dict[str, Any]) -> None:
    """The record of the fit that `sss calibrate projector` keeps beside gamma and black (``levels``: the ramp's
    grey levels in [0, 1], ``response_rgb``: the light measured at each per colour, ``rms``: the fit's error,
    ``pixels``: how many it used), checked as a rig file's other values are: read by people and tools, not
    by capture, so a damaged one is named rather than carried into every session's manifest."""
    levels = resp.get("levels")
    if levels is not None and not (_numbers(levels, 0.0, 1.0) and len(levels) >= 2
                                   and all(a < b for a, b in zip(levels, levels[1:], strict=False))):
        raise InputError(f"{path}: [projector] levels must be the ramp's grey levels, increasing numbers in [0, 1], "
                         f"got {levels!r}")
    response = resp.get("response_rgb")
    if response is not None and not (isinstance(response, list) and len(response) == 3 and all(
            _numbers(r, -1e12, 1e12) and len(r) == len(levels or r) for r in response)):
        raise InputError(f"{path}: [projector] response_rgb must be three lists of finite numbers, one per "
                         f"level, got {response!r}"[:300])
    rms, pixels = resp.get("rms"), resp.get("pixels")
    if rms is not None and not _numbers([rms], 0.0, 1e12):
        raise InputError(f"{path}: [projector] rms must be a finite number >= 0, got {rms!r}")
    if pixels is not None and (isinstance(pixels, bool) or not isinstance(pixels, int) or pixels < 0):
        raise InputError(f"{path}: [projector] pixels must be a whole number >= 0, got {pixels!r}")


def _check_real_rig_options(path: Path, options: dict[str, Any], device_ids: Any) -> None:
    """A rig without simulated devices: each plugin's settings are in its own table (``[options.basler]``); a key
    outside every table (``[options] exposure_us = 1000``) was ignored without a word. (A table named after no
    installed plugin is refused by the daemon, which knows its plugins.)"""
    plugins = sorted({str(d).partition(":")[0] for d in device_ids})
    for key, value in options.items():
        if key in plugins and not isinstance(value, dict):
            raise InputError(f"{path}: [options] {key} must be a table of {key} settings ([options.{key}]), got "
                             f"{type(value).__name__}")
    bare = sorted(str(k) for k, v in options.items() if not isinstance(v, dict))
    if bare:
        raise InputError(f"{path}: [options] {', '.join(bare)[:200]} outside every plugin's table: a device's settings "
                         f"go in its plugin's table, e.g. [options.{plugins[0]}] {bare[0]} = ... (this rig's plugins: "
                         f"{', '.join(plugins)})")


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
    bayer: str = "RGGB"  # the raw frames' Bayer layout where the camera does not say (RGGB, GRBG, GBRG, BGGR)
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
            from sssphase_core.store.files import read_toml_input

            cfg = read_toml_input(path, "rig file")
        except OSError as exc:
            raise InputError(f"cannot read rig file {path}: {exc}") from None
        dev, proc, resp = cfg.get("devices", {}), cfg.get("processing", {}), cfg.get("projector", {})
        for table in RIG_TABLES:
            if not isinstance(cfg.get(table, {}), dict):
                raise InputError(f"{path}: {table} must be a [{table}] table, got {type(cfg[table]).__name__}")
        unknown = sorted(set(cfg) - set(RIG_TABLES))  # a misspelt [projecter] was ignored: patterns for 2.2
        if unknown:
            raise InputError(f"{path}: unknown rig file tables {', '.join(f'[{t}]' for t in unknown)} (a rig file has "
                             f"{', '.join(f'[{t}]' for t in RIG_TABLES)})")
        unknown = sorted(set(resp) - PROJECTOR_KEYS)
        if unknown:
            raise InputError(f"{path}: unknown [projector] keys {', '.join(unknown)} (known: {', '.join(sorted(PROJECTOR_KEYS))})")
        if "camera" not in dev or "projector" not in dev:
            raise InputError(f"{path}: [devices] needs camera and projector ids (see `sss devices`)")
        bad = [k for k, v in dev.items() if k not in ("camera", "projector", "turntable", "trigger") or not isinstance(v, str)]
        if bad:
            raise InputError(f"{path}: [devices] takes camera, projector, turntable and trigger device ids (strings), "
                             f"not {', '.join(sorted(bad))}")
        unknown = set(proc) - {"patch", "saturation", "black_level", "white_scale", "median", "bayer"}
        if unknown:
            raise InputError(f"{path}: unknown [processing] keys {sorted(unknown)}")
        if "bayer" in proc:
            from sssphase_core.processing.isp import BAYER_LAYOUTS

            if proc["bayer"] not in BAYER_LAYOUTS:
                raise InputError(f"{path}: [processing] bayer must be one of {', '.join(BAYER_LAYOUTS)}, got {proc['bayer']!r}")
        from sssphase_core.processing.footprints import PATCH_RANGE

        ranges = {"patch": PATCH_RANGE, "saturation": (1e-6, 1e12), "black_level": (0, 1e12), "white_scale": (1e-12, 1e12)}
        for key, (lo, hi) in ranges.items():  # a NaN or negative value failed only after capturing, or wrote NaN JSON
            v = proc.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int | float) or not lo <= v <= hi
                                  or (key == "patch" and not isinstance(v, int))):
                raise InputError(f"{path}: [processing] {key} must be a {'whole ' if key == 'patch' else ''}number in "
                                 f"[{lo:g}, {hi:g}], got {v!r}")
        if isinstance(proc.get("white_scale"), int | float) and proc["white_scale"] < 1:  # raw frames count whole DN
            raise InputError(f"{path}: [processing] white_scale is the DN above black that one linear camera unit gives "
                             f"(a white at 2,300 DN: 2300), got {proc['white_scale']:g}, below one DN: its inverse?")
        if "median" in proc and not isinstance(proc["median"], bool):
            raise InputError(f"{path}: [processing] median must be true or false, got {proc['median']!r}")
        for key, (lo, hi) in (("gamma_rgb", GAMMA_RANGE), ("black_rgb", (0.0, BLACK_LIMIT))):  # per colour, as fitted
            v = resp.get(key)
            if v is not None and not (_numbers(v, lo, hi) and len(v) == 3):
                raise InputError(f"{path}: [projector] {key} must be three numbers in [{lo:g}, {hi:g}], got {v!r}")
        _check_fit_record(path, resp)
        gamma, black = resp.get("gamma"), resp.get("black")
        if gamma is None and "gamma_rgb" in resp:  # the colours' mean, as `sss calibrate projector` writes it
            gamma = sum(resp["gamma_rgb"]) / 3
        if black is None and "black_rgb" in resp:
            black = sum(resp["black_rgb"]) / 3
        if gamma is not None and not (isinstance(gamma, int | float) and not isinstance(gamma, bool) and GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]):
            raise InputError(f"{path}: [projector] gamma must be a number in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}], "
                             f"got {gamma!r}")
        if black is not None and not (isinstance(black, int | float) and not isinstance(black, bool) and 0 <= black < BLACK_LIMIT):
            raise InputError(f"{path}: [projector] black must be a number in [0, {BLACK_LIMIT:g}), got {black!r}")
        options = cfg.get("options", {})
        if all(str(v).startswith("sim:") for v in dev.values()):  # a sim rig: its plugin's options only
            from sssphase_core.sim.rig import SIM_RIG_OPTIONS

            unknown = sorted(set(options) - SIM_RIG_OPTIONS)
            if unknown:  # a misspelt option was ignored: the capture ran with the default
                raise InputError(f"{path}: unknown sim rig [options] {', '.join(unknown)} (known: "
                                 f"{', '.join(sorted(SIM_RIG_OPTIONS))})")
        elif not any(str(v).startswith("sim:") for v in dev.values()):  # the sim plugin reads bare keys; no other
            _check_real_rig_options(path, options, dev.values())
        return cls(dev["camera"], dev["projector"], dev.get("turntable"), dict(options), **proc,
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
    transport: str | None = None  # sim light-transport model (None: the rig's, burley)
    sim_options: dict[str, Any] = field(default_factory=dict)  # more sim rig options (e.g. sim.randomised_rig_options)
    dot_stride: int = 1  # every S-th dot shift along x and y (footprints for 1/S^2 of the pixels; measured needs 1)

    @classmethod
    def from_options(cls, object_name: str, rig: RigSpec, *, views: int = 4, footprints: bool = False,
                     references: tuple[str, ...] | list[str] = (), hdr: bool = False, hdr_exposures: str | None = None,
                     keep_dots: bool = False, keep_unwrap: bool = False, resume: bool = False, out: Path = Path("sessions"),
                     seed: int = 0, preset: str = "cpu", dot_spacing: int | None = None, transport: str | None = None,
                     randomise_rig: bool = False, dot_stride: int = 1, device: str = "cpu", anisotropy: float | None = None,
                     backdrop: float | None = None,
                     on_drawn: Callable[[dict[str, Any]], None] | None = None) -> CaptureRequest:
        """A request from `sss capture`'s options (and a form's: the same names), checked for ``rig`` as
        :meth:`validate` checks it, in the order the options are given. ``hdr_exposures``: comma-separated
        relative exposures (implies ``hdr``; ``hdr``: :data:`DEFAULT_HDR`). ``randomise_rig`` draws the sim rig's
        physics and camera from ``seed`` and the object's name (:func:`sim.randomised_rig_options`), told to
        ``on_drawn`` as soon as drawn. ``device``: where the sim rig renders (``cuda``: on the GPU, the same images);
        ``anisotropy``: the radiative transport's phase-function mean cosine g; ``backdrop``: a matte grey wall that
        many mm behind the sim rig's turntable centre (``sim.RigConfig.backdrop``)."""
        req = cls(object_name, views, footprints, tuple(references), (), keep_dots, keep_unwrap, resume, out, seed,
                  preset, dot_spacing, transport, dot_stride=dot_stride)
        req._check_counts()
        if randomise_rig and rig.is_sim:
            from sssphase_core.sim import randomised_rig_options

            req.sim_options = randomised_rig_options(seed, object_name)
        if req.sim_options and on_drawn is not None:
            on_drawn(req.sim_options)
        if anisotropy is not None:  # the radiative transport's media (refused for any other model, or a real rig)
            from sssphase_core.sim.rig import anisotropy_option

            model = (transport or rig.options.get("transport")) if rig.is_sim else None
            req.sim_options = {**req.sim_options, **anisotropy_option(model, anisotropy)}
        if backdrop is not None:  # a wall behind the sim's objects
            if not rig.is_sim:
                raise InputError("--backdrop puts a wall behind the simulator's objects: it applies to the sim rig only")
            req.sim_options = {**req.sim_options, "backdrop": backdrop}
        if device != "cpu":  # the sim's light transport on a torch device (sssphase_core.sim_accel)
            if not rig.is_sim:
                raise InputError("--device places the simulator's rendering: it applies to the sim rig only")
            from sssphase_core.compute import check_device

            check_device(device)
            req.sim_options = {**req.sim_options, "device": device}
        req.hdr = parse_exposures(hdr_exposures) if hdr_exposures is not None else DEFAULT_HDR if hdr else ()
        req._check_rig(rig, randomise_rig)
        req._check_frames()
        return req

    def validate(self, rig: RigSpec | None = None) -> None:
        """Refuse, in one line, a request that ``rig`` (default: the sim rig) cannot capture, before a daemon
        starts: the name, views, seed, sim rig options, HDR brackets, references, dot spacing and output folder."""
        self._check_counts()
        self._check_rig(rig or RigSpec(), False)
        self._check_frames()

    def _check_counts(self) -> None:
        check_object_name(self.object)
        if self.views < 1:
            raise InputError(f"--views must be >= 1, got {self.views}")
        if not 0 <= self.seed <= MAX_SEED:
            raise InputError(f"--seed must be 0 to {MAX_SEED} (2**63 - 1, what the sim rig takes), got {self.seed}")

    @property
    def own_sim_options(self) -> dict[str, Any]:
        """The sim rig options this capture sets itself (``engine.CAPTURE_FLAGS``: a rig file may only repeat them)."""
        return {"object": self.object, "preset": self.preset, "seed": self.seed, "n_views": self.views}

    def _check_rig(self, rig: RigSpec, randomise_rig: bool) -> None:
        if rig.is_sim:  # an unknown object, preset or transport model is one line, before a daemon starts
            from sssphase_core.capture.engine import check_rig_leaves_capture_options
            from sssphase_core.sim import MAX_VIEWS, get_object, rig_from_options

            if self.views > MAX_VIEWS:
                raise InputError(f"--views: the sim rig's turntable takes at most {MAX_VIEWS} views, got {self.views}")
            check_rig_leaves_capture_options(rig.options, self.own_sim_options)
            get_object(str(rig.options.get("object", self.object)))
            rig_from_options({"preset": self.preset, **rig.options, **self.sim_options,
                              **({"transport": self.transport} if self.transport else {})})
        elif self.transport is not None or randomise_rig:
            flag = "--transport" if self.transport is not None else "--randomise-rig"
            raise InputError(f"{flag} changes the simulator's physics and camera: it applies to the sim rig only")
        if self.hdr and rig.saturation is None and not rig.is_sim:  # (failed mid-view, after the daemon started)
            raise InputError("--hdr merges each frame's exposures below the camera's clipping level: give it in the rig "
                             "file ([processing] saturation, linear at exposure 1; see HARDWARE.md's rig file)")

    def _check_frames(self) -> None:
        from sssphase_core.capture.engine import check_brackets
        from sssphase_core.processing.patterns import (
            REFERENCE_NAMES,
            check_dot_spacing,
            check_dot_stride,
            unknown_pattern,
        )
        from sssphase_core.store.imageio import MAX_FRAME_PIXELS, frame_shape
        from sssphase_core.store.session import check_output_folder

        check_brackets(self.hdr)
        reference_keys(self.references)
        for ref in self.references:
            if ref not in REFERENCE_NAMES:  # an unreadable file or values outside [0, 1]: one line before a daemon starts
                if not Path(ref).is_file():  # a misspelt name, most likely (or a folder, a FIFO)
                    raise InputError(unknown_pattern("--reference", ref))
                h, w = frame_shape(Path(ref))[:2]
                if w * h > MAX_FRAME_PIXELS:
                    raise InputError(f"--reference {ref} is {w}x{h}: larger than any projector (scale it down first)")
                read_pattern(Path(ref), (w, h))  # (its size is checked against the rig's projector by the daemon)
        if self.dot_spacing is not None:  # 0 meant the default, 10^12 exhausted the memory
            check_dot_spacing(self.dot_spacing)
        check_dot_stride(self.dot_stride, self.dot_spacing)
        check_output_folder(self.out)


def parse_exposures(text: str) -> tuple[float, ...]:
    """``--hdr-exposures``: comma-separated relative exposures, e.g. ``"0.25,1,4,16"`` (checked by
    :func:`engine.check_brackets` in :meth:`CaptureRequest.validate`)."""
    items = text.split(",")
    try:
        if not text.strip() or any(not v.strip() for v in items):  # '' or '1,,2': HDR asked, none given
            raise ValueError
        return tuple(float(v) for v in items)
    except ValueError:
        shown = text if len(text) <= 60 else text[:57] + "..."
        raise InputError(f"--hdr-exposures takes comma-separated numbers, e.g. 0.25,1,4,16; got {shown!r}") from None


def _reference_name(path: str) -> str:
    """A reference image file's stem, the name its capture is stored under: checked like an object name."""
    try:
        return check_object_name(Path(path).stem)
    except InputError:
        raise InputError(f"--reference {path!r}: the file name {Path(path).stem!r} cannot name a capture: use "
                         "letters, digits, '_', '-', '.' (it is stored as ref/<name>)") from None


def reference_keys(references: tuple[str, ...] | list[str]) -> list[str]:
    """The session key (``ref/<name>``) each ``--reference`` is stored under: a pattern's name, or an image
    file's stem (checked as a name). Two references of one key would lose a capture: refused."""
    from sssphase_core.processing.patterns import REFERENCE_NAMES

    keys: dict[str, str] = {}
    for r in dict.fromkeys(references):  # a named pattern given twice is captured once
        if r not in REFERENCE_NAMES and _reference_name(r) in REFERENCE_NAMES:  # its truth would be the named one's
            raise InputError(f"--reference {r}: a file named like the pattern {_reference_name(r)!r} would be stored and "
                             "evaluated as that pattern: rename the file")
        key = f"ref/{r if r in REFERENCE_NAMES else _reference_name(r)}"
        if key in keys:
            raise InputError(f"--reference {keys[key]} and {r} would both be stored as {key}: rename the file")
        keys[key] = r
    return list(keys)


def build_frames(req: CaptureRequest, size: tuple[int, int], patch: int,
                 gamma: float | None = None) -> tuple[Any, list[dict[str, Any]], int]:
    """The capture plan and the daemon's frame specs (named references by plan, files as images);
    PSP patterns are pre-distorted for the projector's ``gamma`` (default 2.2)."""
    from sssphase_core.processing.patterns import DEFAULT_GAMMA, REFERENCE_NAMES, capture_plan

    reference_keys(req.references)
    named = [r for r in req.references if r in REFERENCE_NAMES]
    files = [Path(r) for r in req.references if r not in REFERENCE_NAMES]
    spacing = dot_spacing_for(patch) if req.dot_spacing is None else req.dot_spacing
    if req.footprints and spacing < dot_spacing_for(patch) / 2:
        import warnings

        warnings.warn(f"--dot-spacing {spacing} is under half the {dot_spacing_for(patch)} px that {patch} px footprints "
                      f"are spaced by default: each footprint keeps only the light within {spacing / 2:g} projector px "
                      "of its dot (farther light is a neighbouring dot's), so its wider scattering is cut off", stacklevel=2)
    plan = capture_plan(*size, footprints=req.footprints, dot_spacing=spacing,
                        references=("white", "black", *named), hdr_exposures=req.hdr,
                        gamma=DEFAULT_GAMMA if gamma is None else gamma, dot_stride=req.dot_stride)
    frames = json.loads(plan.to_json())["frames"]
    for path in files:
        name = _reference_name(str(path))
        img = read_pattern(path, size, hint="resize it to the projector's size first")
        for e in req.hdr or (1.0,):
            spec_name = f"ref/{name}" if not req.hdr else f"ref/{name}@e{e:g}"
            frames.append({"name": spec_name, "key": f"ref/{name}", "kind": "image", "exposure": e,
                           "params": {"file": path.name, "hdr": len(req.hdr) or None},
                           "image": {"dtype": img.dtype.str, "shape": list(img.shape), "data": img.tobytes()}})
    return plan, frames, spacing


def plan_digest(frames: list[dict[str, Any]]) -> str:
    h = hashlib.sha256()
    for f in frames:
        h.update(json.dumps({k: v for k, v in f.items() if k != "image"}, sort_keys=True).encode())
        if "image" in f:
            h.update(f["image"]["data"])
    return h.hexdigest()
