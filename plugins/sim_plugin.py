"""Built-in ``sim`` device plugin: a camera, a projector and a turntable sharing one simulated scene.

It behaves like hardware: a camera exposure sees the pattern that was *on screen* when the exposure
started (``Projector.show(confirm=False)`` followed at once by a grab sees the previous image, as on
a real rig); frames carry a sequence number, a device-clock timestamp (simulated: each frame takes
``frame_period_s * exposure``) and the exposure. Noise is drawn from a generator seeded by
``(seed, view, pattern tag, exposure)`` so a re-captured frame is bit-identical (resumable sessions).

Rig options (all optional): ``object`` (catalogue name, default "apple"), ``preset`` ("cpu"|"paper"),
``seed``, ``n_views``, ``view``, ``latency_s`` (projector), ``frame_period_s``, ``realtime`` (sleep
for the simulated times), ``projector_gamma`` / ``projector_black`` (a projector response other than
the preset's, for calibration), ``transport`` (``burley``, ``directional_dipole`` or ``radiative``; ``anisotropy``, the radiative media's phase-function g),
``backdrop`` (mm: a matte grey wall that far behind the turntable centre, facing the camera), ``mfp_skew`` (the
objects' red mean free paths times it, their blue ones over it: materials of other spectral shapes), the camera's
``lens_blur`` (px), ``read_noise`` (e-), ``white_fraction`` (exposure) and ``demosaic`` (``malvar`` or
``opencv``, or ``none`` for a three-chip camera without a colour filter array; see ``sim.rig.with_camera``),
``raw`` (Bayer frames; not for a three-chip camera), ``device`` (``cpu``, or ``cuda[:N]``: the light transport
on a GPU, ``sssphase_core.sim_accel``, the same images; ``auto``: the GPU where torch sees one, else ``cpu``),
and fault injection for tests: ``fail_at_frame`` (the camera raises at that grab), ``disconnect_at_frame`` (the camera is gone from that grab on, as an
unplugged USB camera: every later call raises until the rig is opened again), ``stall_at_frame`` (that grab
never returns), ``garbage_at_frame`` (that frame is half as tall and NaN), ``grab_delay_s`` (slow frames) and
``frame_timeout_s`` (how long the camera declares a frame may take: the daemon waits no less for a grab). Options nobody reads are refused
by name (``check_options``).
The ``sim:bench-camera`` streams one fixed frame (``shape``, ``dtype``) for throughput benchmarks.

Like a DLP projector's pattern-sequence mode, ``SimProjector.preload`` takes the upcoming patterns
(lazily, as ``(tag, render)`` pairs); the scene then renders them noise-free in batches of
``RENDER_BATCH`` (one light-transport pass per batch instead of one per frame) and each camera
exposure only adds sensor noise to the cached image of the pattern on screen.
"""

from __future__ import annotations

import threading
import time
import zlib
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import numpy as np

from sssphase_core.errors import InputError
from sssphase_plugins.drivers import DeviceError, DeviceInfo, Frame, ShowReceipt, check_pattern
from sssphase_plugins.hookspecs import hookimpl

PLUGIN = "sim"
CAMERA_ID, BENCH_CAMERA_ID = "sim:camera0", "sim:bench-camera"
PROJECTOR_ID, TURNTABLE_ID = "sim:projector0", "sim:turntable0"
#: Preloaded patterns rendered together (they share one footprint pass): at most this many, and at most
#: RENDER_BATCH_BYTES of rendered images (the splat canvas and its copies scale with it: 32 frames of
#: 1080p RGB took the daemon to 4.3 GB; 10 keep it near 2 GB). The CPU preset still batches 32.
RENDER_BATCH = 32
RENDER_BATCH_BYTES = 256 * 2**20


def _sim():
    """The simulator module, imported only when a sim device is opened (numpy only, no torch)."""
    from sssphase_core import sim

    return sim


def _number(options: Mapping[str, Any], name: str, default: float, lo: float, hi: float, kind: type) -> Any:
    """Option ``name`` as ``kind`` within [lo, hi]; a client's wrong value is an InputError (bad_args), not a crash."""
    value = options.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or (kind is int and value != int(value)):
        raise InputError(f"sim option {name} must be {'an integer' if kind is int else 'a number'}, got {value!r}")
    if not lo <= value <= hi:  # NaN fails too
        shown = f"[{int(lo):,}, {int(hi):,}]" if kind is int else f"[{lo:g}, {hi:g}]"
        raise InputError(f"sim option {name} must be in {shown}, got {value!r}")
    return kind(value)


def _flag(options: Mapping[str, Any], name: str) -> bool:
    """Option ``name`` as true or false (a string such as "false" had counted as true)."""
    value = options.get(name, False)
    if not isinstance(value, bool):
        raise InputError(f"sim option {name} must be true or false, got {value!r}")
    return value


def _transport_factory(device: Any):
    """The rig option ``device``: where the light transport computes (``cpu``: numpy, no torch imported;
    ``cuda[:N]``: torch, ``sssphase_core.sim_accel``; ``auto``: a GPU torch sees, else numpy); a device this
    process cannot use is refused. None: the numpy path."""
    if not isinstance(device, str):
        raise InputError(f"sim option device must be a string (cpu, cuda, cuda:N or auto), got {device!r}")
    from sssphase_core.compute import renders_on_torch

    if not renders_on_torch(device):
        return None
    from sssphase_core.sim_accel import transport_factory

    return transport_factory(device)


class SimRigState:
    """State shared by the sim devices of one rig: scene, shown pattern, turntable, device clock."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        sim = _sim()
        self.object_name = str(options.get("object", "apple"))
        self.obj = sim.get_object(self.object_name)  # UnknownObjectError lists the catalogue
        self.rig = sim.rig_from_options(options)  # an unknown preset, transport or out-of-range value is an InputError
        self.seed = _number(options, "seed", 0, 0, 2**63 - 1, int)
        self.n_views = _number(options, "n_views", 4, 1, sim.MAX_VIEWS, int)
        self.view = _number(options, "view", 0, 0, 2**31, int) % self.n_views
        self.latency_ns = int(_number(options, "latency_s", 1 / 60, 0.0, 60.0, float) * 1e9)
        self.frame_period_ns = int(_number(options, "frame_period_s", 1 / 30, 1e-6, 60.0, float) * 1e9)
        self.realtime = _flag(options, "realtime")
        self.transport_factory = _transport_factory(options.get("device", "cpu"))
        self.sensor = None  # the camera's sensor on the same device (sim_accel.DeviceSensor), where it applies
        if self.transport_factory is not None:
            from sssphase_core.sim_accel import DeviceSensor

            if DeviceSensor.handles(self.rig.sensor):
                self.sensor = DeviceSensor(str(options["device"]))
        self.clock_ns = 0
        self.shown: list[tuple[int, np.ndarray, str, int]] = []  # (on_screen_ns, image, tag, frame_id)
        self._scene = None
        self._scene_view = -1
        self.sequence: list[tuple[str, Callable[[], np.ndarray]]] = []  # preloaded (tag, pattern)
        self.rendered: dict[str, np.ndarray] = {}  # tag -> noise-free image of the current view

    @property
    def projector_size(self) -> tuple[int, int]:
        return projector_size(self.rig)

    @property
    def scene(self):
        if self._scene_view != self.view:
            self._scene = _sim().SimScene(self.obj, rig=self.rig, view=self.view, n_views=self.n_views, seed=self.seed,
                                          transport_factory=self.transport_factory)
            self._scene_view = self.view
            self.rendered.clear()
        return self._scene

    def render(self, pattern: np.ndarray, tag: str) -> np.ndarray:
        """Noise-free image of ``pattern``; preloaded patterns are rendered in batches and cached."""
        scene = self.scene
        if tag in self.rendered:
            return self.rendered[tag]
        index = next((i for i, (t, _) in enumerate(self.sequence) if t == tag), None)
        if index is None:
            return scene.render(pattern[None])[0]
        h, w = scene.shape
        size = max(1, min(RENDER_BATCH, RENDER_BATCH_BYTES // (h * w * 3 * 4)))
        batch, self.sequence = self.sequence[index:index + size], self.sequence[index + size:]
        self.rendered = {}  # the previous batch is not needed any more: free it before rendering the next
        patterns = [make() for _, make in batch]
        if any(p.ndim == 3 for p in patterns):  # a colour image in the batch: render every pattern as RGB
            patterns = [np.repeat(p[..., None], 3, axis=-1) if p.ndim == 2 else p for p in patterns]
        images = scene.render(np.stack(patterns))
        self.rendered = {t: img for (t, _), img in zip(batch, images, strict=True)}  # this batch only
        return self.rendered[tag]

    def capture(self, pattern: np.ndarray, tag: str, rng: np.random.Generator, exposure: float, raw: bool) -> np.ndarray:
        """What ``SimScene.capture`` returns for this pattern, from the (cached) noise-free image."""
        image = self.render(pattern, tag)[None]
        if self.sensor is not None:
            return self.sensor.sense(image, self.rig.sensor, rng, exposure, raw)[0]
        return self.scene.sense(image, rng, exposure, raw)[0]

    def advance(self, ns: int) -> None:
        self.clock_ns += ns
        if self.realtime:
            time.sleep(ns / 1e9)

    def visible_pattern(self) -> tuple[np.ndarray | None, str, int]:
        """The image on screen at the current device time (None before the first show)."""
        on = [s for s in self.shown if s[0] <= self.clock_ns]
        if not on:
            return None, "", -1
        _, image, tag, frame_id = on[-1]
        self.shown = [s for s in self.shown if s[0] >= on[-1][0]]  # keep the visible one and pending ones
        return image, tag, frame_id


def projector_size(rig: Any) -> tuple[int, int]:
    """(width, height) of a sim rig's projector."""
    return int(rig.projector.width), int(rig.projector.height)


#: The largest frame the bench camera makes (a 10^6 x 10^6 one replied `internal: MemoryError`).
MAX_FRAME_BYTES = 1 << 30


def check_options(options: Mapping[str, Any]) -> None:
    """Refuse a sim option nobody reads, by name (a misspelt one was ignored: the rig ran with the default);
    tables (``[options.<plugin>]``) belong to other plugins of the rig."""
    from sssphase_core.sim.rig import SIM_RIG_OPTIONS

    unknown = sorted(k for k, v in options.items() if k not in SIM_RIG_OPTIONS and not isinstance(v, Mapping))
    if unknown:
        raise InputError(f"unknown sim option(s) {', '.join(map(str, unknown))[:200]} (known: {', '.join(sorted(SIM_RIG_OPTIONS))})")


def _bench(shared: dict[str, Any], options: Mapping[str, Any]) -> SimRigState:
    if "sim_bench" not in shared:
        shared["sim_bench"] = SimRigState(options)
    return shared["sim_bench"]


class SimCamera:
    def __init__(self, bench: SimRigState, options: Mapping[str, Any]) -> None:
        self.info = DeviceInfo(CAMERA_ID, "camera", PLUGIN, "simulated camera", "camera0")
        theirs = sorted({"shape", "dtype"} & set(options))  # accepted, ignored and recorded in the session as if used
        if theirs:
            raise InputError(f"sim option {', '.join(theirs)} is the sim:bench-camera's: {CAMERA_ID} renders the rig "
                             "preset's frames (choose their size with the preset)")
        self.bench = bench
        self.exposure = 1.0
        self.gain = 1.0
        self.raw = _flag(options, "raw")
        if self.raw and bench.rig.sensor.three_chip:
            raise DeviceError("a three-chip sim camera (demosaic none) has no raw Bayer frames: leave out the raw option")
        fault = lambda name: _number(options, name, -1, -1, 2**31, int)  # noqa: E731  # a frame number, -1: never
        self.fail_at = fault("fail_at_frame")
        self.disconnect_at = fault("disconnect_at_frame")  # gone from that grab on (unplugged)
        self.delay_s = _number(options, "grab_delay_s", 0.0, 0.0, 3600.0, float)
        self.stall_at = fault("stall_at_frame")  # that grab never returns (a hung camera)
        self.grabbing = threading.Lock()  # as a driver does, close waits for a grab in flight (for ever, when it hangs)
        self.garbage_at = fault("garbage_at_frame")  # that frame is not a frame of this camera
        self.sequence = 0
        w, h = bench.rig.camera.width, bench.rig.camera.height
        #: how long a frame may take to render (the daemon's deadline is no shorter): 30 s at the CPU preset's
        #: 256 x 192, in proportion at larger cameras (a batch of 1080p frames takes minutes on 2 cores). A view's
        #: first grab builds its scene and renders a batch of patterns: over 10 s on a loaded 2-core machine
        self.frame_timeout_s = _number(options, "frame_timeout_s", 30.0 * max(1.0, w * h / (256 * 192)), 1.0, 86400.0,
                                       float)

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        if exposure is not None:
            if not exposure > 0:
                raise DeviceError(f"exposure must be positive, got {exposure}")
            self.exposure = float(exposure)
        if gain is not None:
            if not gain > 0:  # (a factor: a camera's 0 dB is 1 here)
                raise DeviceError(f"the sim camera's gain is a factor on the signal and must be positive, got {gain:g}")
            self.gain = float(gain)
        if pixel_format is not None:
            if pixel_format not in ("rgb32f", "bayer16"):
                raise DeviceError(f"sim camera formats are rgb32f and bayer16, not {pixel_format!r}")
            if pixel_format == "bayer16" and self.bench.rig.sensor.three_chip:
                raise DeviceError("a three-chip sim camera (demosaic none) has no raw Bayer frames (bayer16)")
            self.raw = pixel_format == "bayer16"

    def grab(self, timeout_s: float = 5.0) -> Frame:
        with self.grabbing:
            return self._grab()

    def _grab(self) -> Frame:
        if 0 <= self.disconnect_at <= self.sequence:
            raise DeviceError(f"{self.info.id}: the camera is disconnected (simulated at frame {self.disconnect_at}): "
                              "reconnect it and resume the capture")
        if self.sequence == self.fail_at:
            raise DeviceError(f"{self.info.id}: simulated sensor failure at frame {self.sequence}")
        if self.delay_s:
            time.sleep(self.delay_s)
        if self.sequence == self.stall_at:
            time.sleep(24 * 3600)  # as a camera whose driver hangs: only the daemon's deadline gets past it
        b = self.bench
        image, tag, frame_id = b.visible_pattern()
        w, h = b.projector_size
        pattern = np.zeros((h, w), np.float32) if image is None else image
        key = [b.seed, b.view, zlib.crc32(tag.encode()), int(np.float64(self.exposure).view(np.uint64) & 0xFFFFFFFF)]
        rng = np.random.default_rng(key)
        data = b.capture(pattern, tag, rng, self.exposure * self.gain, self.raw)
        if not self.raw and self.gain != 1.0:  # as a camera's gain: the frame brighter, clipping at a lower light level
            data = data * np.float32(self.gain)  # (the sensor developed it in units of exposure x gain)
        if self.sequence == self.garbage_at:  # a corrupted transfer: half the rows, NaN where pixels were
            data = np.full((data.shape[0] // 2, *data.shape[1:]), np.nan, np.float32)
        frame = Frame(np.ascontiguousarray(data), self.sequence, b.clock_ns, self.exposure,
                      {"pattern_tag": tag, "pattern_frame_id": frame_id, "view": b.view, "gain": self.gain})
        self.sequence += 1
        b.advance(int(b.frame_period_ns * max(self.exposure, 1.0)))
        return frame

    def stream(self, count: int) -> Iterator[Frame]:
        return (self.grab() for _ in range(count))

    def wait_frame(self, timeout_s: float = 5.0) -> Frame:
        """The frame of a hardware trigger pulse: the sim exposes when asked, as a triggered sensor does
        on the pulse (a rig with a trigger device, e.g. a serial board, fires it just before)."""
        return self.grab(timeout_s)

    def close(self) -> None:
        with self.grabbing:
            pass


class SimProjector:
    def __init__(self, bench: SimRigState) -> None:
        self.info = DeviceInfo(PROJECTOR_ID, "projector", PLUGIN, "simulated projector", "projector0")
        self.bench = bench
        self.frame_id = 0

    @property
    def resolution(self) -> tuple[int, int]:
        return self.bench.projector_size

    def show(self, image: np.ndarray, *, tag: str = "", confirm: bool = True) -> ShowReceipt:
        image = check_pattern(image, self.resolution, self.info.id)
        b = self.bench
        self.frame_id += 1
        on_screen = b.clock_ns + b.latency_ns
        b.shown.append((on_screen, image, tag, self.frame_id))
        if confirm:
            b.advance(on_screen - b.clock_ns)
        return ShowReceipt(self.frame_id, tag, on_screen)

    def preload(self, sequence: list[tuple[str, Callable[[], np.ndarray]]]) -> None:
        """Announce the coming patterns (tag, render function) in display order."""
        self.bench.sequence = list(sequence)
        self.bench.rendered.clear()

    def close(self) -> None:
        pass


class SimTurntable:
    def __init__(self, bench: SimRigState) -> None:
        self.info = DeviceInfo(TURNTABLE_ID, "turntable", PLUGIN, "simulated turntable", "turntable0")
        self.bench = bench

    @property
    def angle(self) -> float:
        return 360.0 * self.bench.view / self.bench.n_views

    def move_to(self, angle_deg: float) -> float:
        step = 360.0 / self.bench.n_views
        self.bench.view = int(round(float(angle_deg) / step)) % self.bench.n_views
        self.bench.advance(int(0.5e9))
        return self.angle

    def close(self) -> None:
        pass


class BenchCamera:
    """Streams one fixed frame as fast as the consumer takes it (daemon throughput benchmark)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        self.info = DeviceInfo(BENCH_CAMERA_ID, "camera", PLUGIN, "fixed-frame benchmark camera", "bench-camera")
        given = options.get("shape", (1080, 1920, 3))
        if not isinstance(given, list | tuple) or not all(isinstance(s, int) and not isinstance(s, bool) for s in given):
            raise InputError(f"bench camera shape must be a list of 1 to 3 integers ([H, W] or [H, W, C]), "
                             f"got {str(given)[:40]!r}")
        shape = tuple(given)
        rng = np.random.default_rng(_number(options, "seed", 0, 0, 2**63 - 1, int))  # (-1 was a device error)
        try:
            dtype = np.dtype(str(options.get("dtype", "uint16")))
        except TypeError:
            raise InputError(f"bench camera dtype {str(options.get('dtype'))[:40]!r} is not a numpy type") from None
        if dtype.kind not in "biuf":  # an object array's bytes would be pointers into the daemon
            raise InputError(f"bench camera dtype must be numeric, got {dtype.str}")
        if not (1 <= len(shape) <= 3 and all(s > 0 for s in shape)) or np.prod(shape, dtype=np.float64) * 8 > MAX_FRAME_BYTES:
            raise InputError(f"bench camera shape {shape} is not a frame of at most {MAX_FRAME_BYTES >> 20} MiB "
                             "(refused before allocating it)")
        top = min(65535, int(np.finfo(dtype).max) if dtype.kind == "f" else int(np.iinfo(dtype).max) if dtype.kind in "iu" else 1)
        self.data = rng.integers(0, top, size=shape, dtype=np.uint16, endpoint=True).astype(dtype)  # (float16: finite)
        self.sequence = 0

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        pass

    def grab(self, timeout_s: float = 5.0) -> Frame:
        self.sequence += 1
        return Frame(self.data, self.sequence - 1, time.monotonic_ns(), 1.0, {})

    def stream(self, count: int) -> Iterator[Frame]:
        return (self.grab() for _ in range(count))

    def close(self) -> None:
        pass


class _Provider:
    """One provider per kind; discovery is static (no I/O), opening builds the shared bench."""

    def __init__(self, kind: str, ids: tuple[str, ...], models: tuple[str, ...]) -> None:
        self.kind = kind
        self.ids, self.models = ids, models

    def discover(self) -> list[DeviceInfo]:
        return [DeviceInfo(i, self.kind, PLUGIN, m, i.split(":")[1]) for i, m in zip(self.ids, self.models, strict=True)]

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]):
        if device_id not in self.ids:
            raise DeviceError(f"the sim plugin has no {self.kind} {device_id!r}")
        check_options(options)
        if device_id == BENCH_CAMERA_ID:
            return BenchCamera(options)
        bench = _bench(shared, options)
        return {"camera": lambda: SimCamera(bench, options), "projector": lambda: SimProjector(bench),
                "turntable": lambda: SimTurntable(bench)}[self.kind]()


@hookimpl
def sssphase_cameras() -> list[_Provider]:
    return [_Provider("camera", (CAMERA_ID, BENCH_CAMERA_ID), ("simulated camera", "fixed-frame benchmark camera"))]


@hookimpl
def sssphase_projectors() -> list[_Provider]:
    return [_Provider("projector", (PROJECTOR_ID,), ("simulated projector",))]


@hookimpl
def sssphase_turntables() -> list[_Provider]:
    return [_Provider("turntable", (TURNTABLE_ID,), ("simulated turntable",))]
