"""The acquisition daemon: owns the devices and serves them over ZeroMQ.

One ROUTER control socket answers every request from the main thread (it never blocks on a
device for long); each capture runs in a job thread that drives the rig's projector and camera and
pushes frames on the job's own PUSH socket, and device discovery in a thread of its own, whose reply the
main thread sends. Any request from a client counts as its heartbeat; a job
whose client stops heartbeating is cancelled so a dead client never stalls the daemon. A device
error ends that job with a clear error (in the stream's end message and in ``job``) and the daemon
keeps serving. Malformed, oversized, wrong-version or unauthenticated requests get an error reply
(or are dropped by ZeroMQ) and never reach a handler.
"""

from __future__ import annotations

import contextlib
import functools
import hmac
import itertools
import logging
import operator
import os
import queue
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zmq

from sssphase_core.errors import SssError
from sssphase_core.processing.patterns import frame_params_problem
from sssphase_daemon import protocol, security
from sssphase_daemon.frames import ClientGone, FrameSender, Preview, bind, configure_curve_server
from sssphase_daemon.guard import ConnectionGuard
from sssphase_daemon.protocol import ProtocolError
from sssphase_plugins import manager
from sssphase_plugins.drivers import (
    DeviceError,
    PreloadingProjector,
    ShowReceipt,
    TriggeredCamera,
    plain_meta,
)

log = logging.getLogger("sssphase.daemon")
MAX_FRAMES_PER_JOB = 200_000
MAX_OPEN_RIGS = 16  # each may hold a simulated scene or a camera: a client cannot open thousands
MAX_RUNNING_JOBS = 32  # each holds a thread and a stream socket: thousands exhausted ZeroMQ's sockets and threads
HEAVY_MODULES = ("torch", "depthai", "hid", "usb", "serial")  # a sim-only daemon must load none of these
FRAME_KINDS = ("psp", "white", "black", "level", "dots", "ref", "image")
#: How long one device call of a job may take unless the request says (``deadline_s``) or the camera
#: declares itself slower (``frame_timeout_s``, e.g. the simulator at the paper preset).
DEFAULT_DEADLINE_S = 600.0
MAX_DEADLINE_S = 86400.0

#: Seconds ``close_rig``'s reply waits for the rig's devices to close (the clients ask with a 2 s timeout); a device
#: still closing then closes in the background, and cannot be opened again until its close returns.
CLOSE_REPLY_S = 1.5
#: Seconds after which a device's close() that has not returned is logged, naming the device.
CLOSE_WARN_S = 5.0
#: Seconds ``open_rig`` waits for a device of a rig being closed to finish closing before it says which hangs.
CLOSING_WAIT_S = 5.0
#: Seconds between two looks at the authorised clients' keys (a client key copied there is admitted without a restart).
AUTHORIZED_CHECK_S = 2.0
#: Seconds a rig's close at shutdown waits for a device call under way (a grab waiting for its frame).
SHUTDOWN_CALL_WAIT_S = 5.0

#: Seconds an ``open_rig`` may take (a camera's boot, a USB enumeration) before the client is told which device
#: hangs; the daemon serves other requests meanwhile.
#: ``$SSS_OPEN_TIMEOUT_S`` overrides it (read when the daemon starts).
OPEN_TIMEOUT_S = 25.0


def _error_reply(rid: Any, exc: BaseException) -> bytes:
    """The protocol's error reply for what a handler raised (a plugin's sys.exit() is logged: it ended the daemon
    without a line in its log)."""
    if isinstance(exc, ProtocolError):
        return protocol.reply_error(rid, exc.code, str(exc))
    if isinstance(exc, DeviceError):
        return protocol.reply_error(rid, protocol.DEVICE, str(exc))
    if isinstance(exc, (KeyError, ValueError, TypeError)):
        return protocol.reply_error(rid, protocol.BAD_ARGS, f"{type(exc).__name__}: {exc}"[:500])
    if isinstance(exc, SystemExit):
        log.exception("a device plugin called sys.exit(%s)", exc.code)
        return protocol.reply_error(rid, protocol.DEVICE, f"a device plugin called sys.exit({exc.code!r})")
    log.exception("handler failed")
    return protocol.reply_error(rid, protocol.INTERNAL, _exception_line(exc)[:500])


def _id_arg(args: dict, name: str) -> str | None:
    """A request's ``rig`` or ``job`` id: a string, or absent (None); anything else is refused naming the argument
    (a list was "bad_args: TypeError: unhashable type: 'list'")."""
    value = args.get(name)
    if value is not None and not isinstance(value, str):
        raise ProtocolError(protocol.BAD_ARGS, f"{name} must be a {name} id (a string), not {type(value).__name__}")
    return value


def _exception_line(exc: BaseException) -> str:
    """``RuntimeError: grab exploded`` (``MemoryError: (no message)`` when it says nothing), on one line."""
    text = " ".join(str(exc).split())[:300]
    return f"{type(exc).__name__}: {text or '(no message)'}"


class DeviceStalled(DeviceError):
    """A device call did not return within the job's deadline: the rig is closed and dropped."""


@dataclass
class Rig:
    """Opened devices used together; ``shared`` lets one plugin's devices share state (the sim scene)."""

    id: str
    owner: bytes
    devices: dict[str, Any]
    options: dict[str, Any]
    lock: threading.Lock = field(default_factory=threading.Lock)
    orphaned: bool = False  # a job of it lost its client's heartbeats while the client itself was silent too
    closing: str = ""  # the device whose close() is under way (named while it hangs)
    closing_since: float = 0.0  # (time.monotonic())

    def close_after_its_call(self, wait_s: float, closed: Callable[[str], None] | None = None) -> bool:
        """:meth:`close` once the device call under way (it holds ``self.lock``) has ended, waiting ``wait_s`` at most
        (0: not at all), then regardless; True when a call was still under way. Closing a camera under a grab of
        another thread aborted the daemon inside pylon."""
        ended = self.lock.acquire(timeout=wait_s) if wait_s > 0 else self.lock.acquire(False)
        try:
            self.close(closed)
        finally:
            if ended:
                self.lock.release()
        return not ended

    def close(self, closed: Callable[[str], None] | None = None) -> None:
        """Close the devices and drop them: finished jobs keep their rig for ``status``, not its devices
        (a sim rig's scene is ~120 MB). ``closed(device_id)`` is called as each device's close() returns; one
        that has not returned after :data:`CLOSE_WARN_S` is logged by name (its plugin hangs in close())."""
        for driver in self.devices.values():
            device_id = _device_id(driver)
            self.closing, self.closing_since = device_id, time.monotonic()
            warn = threading.Timer(CLOSE_WARN_S, log.warning, ("%s: close() has not returned within %g s (its plugin "
                                   "hangs): it cannot be opened again until it does", device_id, CLOSE_WARN_S))
            warn.daemon = True
            warn.start()
            t0 = time.monotonic()
            try:
                driver.close()
            except BaseException as exc:  # noqa: BLE001  (a plugin's sys.exit() too) closing must not take the daemon down
                log.warning("closing %s failed: %s", device_id, _exception_line(exc))
            finally:
                warn.cancel()
                if time.monotonic() - t0 > CLOSE_WARN_S:
                    log.info("%s closed after %.1f s", device_id, time.monotonic() - t0)
                if closed is not None:
                    closed(device_id)
        self.devices, self.closing = {}, ""
        _return_freed_memory()


def _device_id(driver: Any) -> str:
    """A driver's device id (its ``info`` was checked when it was opened)."""
    return str(getattr(getattr(driver, "info", None), "id", "?"))


@functools.cache
def _libc() -> Any:
    """The C library, loaded once (None where it cannot be)."""
    import ctypes
    import ctypes.util

    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim`` (None where the C library has none)."""
    return getattr(_libc(), "malloc_trim", None)


#: glibc's ``mallopt`` parameter for the most heap arenas (``M_ARENA_MAX`` in malloc.h).
M_ARENA_MAX = -8


def limit_malloc_arenas(arenas: int = 2) -> bool:
    """Let the process's threads share ``arenas`` glibc heap arenas (8 per core by default), unless
    ``$MALLOC_ARENA_MAX`` says otherwise; call it before threads start. A daemon's job threads, one per capture and
    stream, each freed into an arena of its own what no later thread reused: under `sss bench soak` (crashing
    clients, streams, a capture every 20 cycles) resident memory rose from 86 to 241 MB over 600 cycles, and stays
    at 80 MB with two arenas. -> whether the limit was set."""
    mallopt = getattr(_libc(), "mallopt", None)
    if mallopt is None or os.environ.get("MALLOC_ARENA_MAX"):
        return False
    return bool(mallopt(M_ARENA_MAX, arenas))


def _return_freed_memory() -> None:
    """Give the heap's free pages back to the system (glibc ``malloc_trim``): a closed rig's scene (~6 MB at
    the CPU preset) was freed into the arenas of the job threads that rendered it, and a long-running
    daemon's resident memory kept it."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _close_all(devices: dict[str, Any]) -> None:
    """Close every driver, each whatever the others do (a failing close must not leave the rest open)."""
    for driver in devices.values():
        try:
            driver.close()
        except Exception as exc:
            log.warning("closing a device failed: %s", exc)
    devices.clear()


@dataclass
class Job:
    id: str
    owner: bytes
    rig: Rig
    endpoint: str
    total: int
    sent: int = 0
    state: str = "running"  # running | done | failed | cancelled
    error: dict[str, str] | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    started: float = field(default_factory=time.time)
    last_beat: float = field(default_factory=time.monotonic)
    deadline_s: float = DEFAULT_DEADLINE_S  # the longest one device call may take
    doing: str = "the rig"  # the device call under way (named when it stalls)
    last_stamp: tuple[int, int] | None = None  # the previous frame's (sequence, timestamp_ns): a stale buffer repeats it

    def summary(self) -> dict[str, Any]:
        return {"job": self.id, "rig": self.rig.id, "state": self.state, "sent": self.sent, "total": self.total,
                "error": self.error, "started": self.started}


def _raise_fd_limit(target: int = 65536) -> None:
    """Raise the soft open-file limit toward the hard one: each client connection is a descriptor."""
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        want = target if hard == resource.RLIM_INFINITY else min(hard, target)
        if soft != resource.RLIM_INFINITY and soft < want:
            resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))
    except (ImportError, ValueError, OSError):  # not on this platform, or not allowed: keep the limit
        pass


def _pattern_for(spec: dict[str, Any]) -> np.ndarray:
    """Render the projector image of one requested frame (an uploaded image or a planned pattern)."""
    if spec["kind"] == "image":
        img = spec["image"]
        return protocol.decode_frame(img, img["data"]).astype(np.float32)
    from sssphase_core.processing.patterns import PlannedFrame

    return PlannedFrame(spec["key"], spec["kind"], dict(spec["params"]), float(spec["exposure"])).pattern()


def _image_problem(img: dict[str, Any]) -> str | None:
    """What is wrong with an uploaded projector image (``{"dtype", "shape", "data"}``), or None: it is
    decoded when the job runs, so a bad one is refused with the request, not as an internal error later."""
    try:
        arr = protocol.decode_frame(img, img["data"])
    except ProtocolError as exc:
        return str(exc)
    except (KeyError, TypeError, ValueError) as exc:
        return f"the image needs dtype, shape and data ({type(exc).__name__}: {str(exc)[:80]})"
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (1, 3)) or not arr.size:
        return f"the image must be (H, W) or (H, W, 3), got {arr.shape}"
    if arr.dtype.kind not in "fiu":
        return f"the image must hold numbers (light in [0, 1]), got {arr.dtype}"
    values = arr.astype(np.float32, copy=False)
    if not np.isfinite(values).all() or values.min() < 0 or values.max() > 1:  # (it failed as the camera's fault)
        return "the image must hold light in [0, 1] (0 black, 1 the projector's full white), got values outside it"
    return None


#: a turntable angle in degrees (ten turns either way); beyond it float angles lose whole degrees
MAX_ANGLE = 3600.0
#: a frame's exposure, relative to the rig's own (1.0): HDR brackets span a few powers of two; beyond these
#: bounds (or NaN/inf) a driver's arithmetic breaks.
MIN_EXPOSURE, MAX_EXPOSURE = 1e-6, 1e6
#: The most frames one ``stream`` request may ask for.
MAX_STREAM_FRAMES = 10_000_000
#: a frame's camera gain (the driver's own unit, e.g. dB or a factor), when the frame names one
MAX_GAIN = 1e3


def _check_frames(frames: Any) -> list[dict[str, Any]]:
    if not isinstance(frames, list) or not 0 < len(frames) <= MAX_FRAMES_PER_JOB:
        raise ProtocolError(protocol.BAD_ARGS, f"frames must be a list of 1..{MAX_FRAMES_PER_JOB} frame specs")
    for f in frames:
        problem = _frame_spec_problem(f)
        if problem:
            raise ProtocolError(protocol.BAD_ARGS, f"bad frame spec {str(f)[:120]}: {problem}")
        gain = f.get("gain")
        if gain is not None and (isinstance(gain, bool) or not isinstance(gain, int | float) or not 0 <= gain <= MAX_GAIN):
            raise ProtocolError(protocol.BAD_ARGS, f"frame {f['name'][:60]!r}: gain must be a number in [0, {MAX_GAIN:g}], "
                                                   f"got {str(gain)[:40]}")
        problem = _image_problem(f["image"]) if f["kind"] == "image" else frame_params_problem(f["kind"], f.get("params", {}))
        if problem:
            raise ProtocolError(protocol.BAD_ARGS, f"frame {f['name'][:60]!r}: {problem}")
        f.setdefault("key", f["name"])
        f.setdefault("params", {})
        f.setdefault("exposure", 1.0)
    return frames


def _frame_spec_problem(f: Any) -> str | None:
    """What is wrong with one frame spec's fields (the first found, named), or None."""
    if not isinstance(f, dict):
        return f"a frame spec is a table of name, kind, params, exposure, got {type(f).__name__}"
    if not isinstance(f.get("name"), str):
        return "name must be text"
    if f.get("kind") not in FRAME_KINDS:
        return f"kind must be one of {', '.join(FRAME_KINDS)}, got {str(f.get('kind'))[:40]!r}"
    if not isinstance(f.get("params", {}), dict):
        return "params must be a table"
    exposure = f.get("exposure", 1.0)
    if isinstance(exposure, bool) or not isinstance(exposure, int | float) or not MIN_EXPOSURE <= exposure <= MAX_EXPOSURE:
        return f"exposure must be a number from {MIN_EXPOSURE:g} to {MAX_EXPOSURE:g}, got {str(exposure)[:40]}"
    if f["kind"] == "image" and not isinstance(f.get("image"), dict):
        return "a frame of kind image needs image: {dtype, shape, data}"
    return None


def projector_size(projector: Any) -> list[int]:
    """The projector's ``resolution`` as [width, height] of plain positive integers (numpy integers converted);
    anything else is a :class:`DeviceError` naming it (numpy values failed the reply and left its rig held)."""
    got = getattr(projector, "resolution", None)
    try:
        w, h = got  # type: ignore[misc]
        size = [operator.index(w), operator.index(h)]
    except Exception:  # noqa: BLE001  (a driver's value of any type)
        raise DeviceError(f"{projector.info.id}: its resolution must be (width, height) in whole pixels, got "
                          f"{str(got)[:60]}") from None
    if min(size) <= 0:
        raise DeviceError(f"{projector.info.id}: its resolution must be positive, got {size[0]}x{size[1]}")
    return size


def _check_pattern_sizes(frames: list[dict[str, Any]], projector: Any) -> None:
    """Refuse, with the request, a frame whose pattern is not the projector's size: it was rendered in the job
    before the projector refused it (a 16384 x 16384 pattern kept 1 GB of the daemon's memory per request)."""
    w, h = projector_size(projector)
    for f in frames:
        shape = f["image"]["shape"] if f["kind"] == "image" else (f["params"]["height"], f["params"]["width"])
        if (int(shape[1]), int(shape[0])) != (w, h):
            raise ProtocolError(protocol.BAD_ARGS, f"frame {f['name'][:60]!r} is {shape[1]}x{shape[0]}, but the projector "
                                                   f"{projector.info.id} shows {w}x{h}")


def _check_receipt(receipt: Any, tag: str, who: str) -> None:
    """A projector's answer to ``show(..., tag=tag)``: a :class:`ShowReceipt` of that pattern (a driver that returned
    None, or the receipt of another pattern, went unnoticed: the camera was exposed whatever was on screen)."""
    if not isinstance(receipt, ShowReceipt):
        raise DeviceError(f"{who}: show() of pattern {tag[:60]!r} came back as {type(receipt).__name__}, not a "
                          "sssphase_plugins.api.ShowReceipt: a projector confirms each pattern it shows, "
                          "ShowReceipt(frame_id, tag, on_screen_ns)")
    if receipt.tag != tag:
        raise DeviceError(f"{who}: show() of pattern {tag[:60]!r} confirmed pattern {str(receipt.tag)[:60]!r}: the "
                          "projector shows another pattern than the one asked for (a receipt carries the tag it was given)")


def _check_frame(job: Job, name: str, frame: Any, first: tuple[tuple[int, ...], str] | None) -> tuple[tuple[int, ...], str]:
    """A frame a driver delivered, checked before it is sent: an array of numbers of the job's first frame's
    shape and type, finite where it is float (a corrupted transfer is a device error naming the frame, not
    a session damaged downstream). Returns the job's (shape, dtype)."""
    camera = job.rig.devices.get("camera")
    who = camera.info.id if camera is not None else "the camera"
    if not hasattr(frame, "meta") or not hasattr(frame, "timestamp_ns"):  # (an ndarray's .data is its memoryview)
        raise DeviceError(f"{who}: frame {name[:60]!r} came back as {type(frame).__module__}.{type(frame).__qualname__}, "
                          "not a sssphase_plugins.api.Frame: its driver must return Frame(data, sequence, timestamp_ns, "
                          "exposure, meta)")
    frame.meta = plain_meta(frame.meta, f"{who}: frame {name[:60]!r}")
    for field_name in ("sequence", "timestamp_ns"):  # (a text timestamp failed the next frame's header, blamed on its grab)
        try:
            setattr(frame, field_name, operator.index(getattr(frame, field_name)))
        except TypeError:
            raise DeviceError(f"{who}: frame {name[:60]!r} has {field_name} {str(getattr(frame, field_name))[:40]!r} "
                              f"of type {type(getattr(frame, field_name)).__name__}: a whole number") from None
    exposure = getattr(frame, "exposure", None)
    if isinstance(exposure, bool) or not isinstance(exposure, int | float | np.number) or not float(exposure) > 0:
        raise DeviceError(f"{who}: frame {name[:60]!r} has exposure {str(exposure)[:40]!r}: a number above 0")
    frame.exposure = float(exposure)
    stamp = (frame.sequence, frame.timestamp_ns)
    if stamp == job.last_stamp:  # the same buffer delivered again: every later frame the same image
        raise DeviceError(f"{who}: frame {name[:60]!r} repeats the previous frame's sequence {stamp[0]} and timestamp "
                          f"{stamp[1]}: a stale buffer, or a fault of its driver")
    job.last_stamp = stamp
    data = getattr(frame, "data", None)
    if not isinstance(data, np.ndarray) or data.dtype.kind not in "biuf" or data.ndim not in (2, 3) or not data.size:
        raise DeviceError(f"{who}: frame {name[:60]!r} is not an image array ({type(data).__name__} "
                          f"{getattr(data, 'shape', '')}): a corrupted transfer or a fault of its driver")
    seen = (tuple(data.shape), data.dtype.str)
    if first is not None and seen != first:
        raise DeviceError(f"{who}: frame {name[:60]!r} is {seen[0]} {seen[1]}, the job's first frame was {first[0]} "
                          f"{first[1]}: a corrupted transfer or a fault of its driver")
    if data.dtype.kind == "f" and not np.isfinite(data).all():
        raise DeviceError(f"{who}: frame {name[:60]!r} holds NaN or infinite values: a corrupted transfer or a fault of its driver")
    return first or seen


def _deadline(args: dict, rig: Rig) -> float:
    """The longest one device call of a job may take: the request's ``deadline_s`` (a client's timeout), but
    no less than the camera says its frames can take (``frame_timeout_s``: the simulator at the paper preset)."""
    given = args.get("deadline_s", DEFAULT_DEADLINE_S)
    if isinstance(given, bool) or not isinstance(given, int | float) or not 0 < given <= MAX_DEADLINE_S:
        raise ProtocolError(protocol.BAD_ARGS, f"deadline_s must be a number of seconds in (0, {MAX_DEADLINE_S:g}], "
                                               f"got {str(given)[:40]}")
    declared = getattr(rig.devices.get("camera"), "frame_timeout_s", 0.0)
    return max(float(given), float(declared) if isinstance(declared, int | float) else 0.0)


class Daemon:
    """Serve the control socket until ``shutdown``; see the module docstring."""

    def __init__(self, endpoint: str | None = None, *, token: str | None = None, curve_dir: Path | None = None,
                 preview: str | None = None, client_timeout_s: float = 10.0,
                 max_message_bytes: int = protocol.DEFAULT_MAX_MESSAGE_BYTES, state_file: Path | None = None,
                 exit_when_idle_s: float | None = None) -> None:
        """``exit_when_idle_s``: stop once no rig is open, no job runs and no client has been heard from for this
        long (a daemon a capture started for itself: a capture interrupted or killed left it running for ever)."""
        from sssphase_core.settings import env_seconds

        self.exit_when_idle_s = exit_when_idle_s
        self.open_timeout_s = env_seconds("SSS_OPEN_TIMEOUT_S", OPEN_TIMEOUT_S)  # checked before anything is bound
        manager.discovery_timeout_s()  # (SSS_DISCOVERY_TIMEOUT_S too: said at start, not at the first `sss devices`)
        self.started_at = time.monotonic()
        self.endpoint = endpoint or security.default_endpoint()
        for what in (e for e in (self.endpoint, preview) if e):
            if (problem := security.endpoint_problem(what)) is not None:
                raise ValueError(problem)
        problem = security.endpoint_collision(self.endpoint, preview, state_file)
        if problem:
            raise ValueError(problem)
        running = security.read_state(state_file) if state_file is not None else None
        if running is not None and running.pid != os.getpid() and security.is_daemon_process(running.pid):
            raise PermissionError(f"another daemon (pid {running.pid}) is serving {running.endpoint}; stop it first")
        for what in (e for e in (self.endpoint, preview) if e):  # `sss daemon start` checks these too; systemd not
            problem = security.ipc_path_problem(what)  # (ZeroMQ would unlink a user's file at an ipc path)
            if problem:
                raise PermissionError(problem)
        problem = security.state_file_problem(state_file) if state_file is not None else None
        if problem:
            raise PermissionError(problem)
        self.curve: tuple[bytes, bytes] | None = None
        self.curve_dir = curve_dir.resolve() if curve_dir is not None else None
        self.ctx = zmq.Context()
        self.auth = None
        if not security.is_local(self.endpoint) or curve_dir is not None:
            if curve_dir is None:
                raise PermissionError(f"binding {self.endpoint} (not loopback/ipc) requires CURVE keys: run "
                                      "`sss daemon keys` and pass --curve-dir")
            from zmq.auth.thread import ThreadAuthenticator

            self.curve = security.server_keys(curve_dir)
            self.auth = ThreadAuthenticator(self.ctx)
            self.auth.start()
            self.auth.configure_curve(domain="*", location=str(curve_dir / security.AUTHORIZED))
        self.authorized = self._authorized_keys()
        self.authorized_checked = time.monotonic()
        self.token = token or security.new_token()
        if self.auth is None:  # frame streams authenticate with the token (ZeroMQ PLAIN), so no other local
            from zmq.auth.thread import (
                ThreadAuthenticator,  # process can connect to a job's port and take frames
            )

            self.auth = ThreadAuthenticator(self.ctx)
            self.auth.start()
            self.auth.configure_plain(domain="*", passwords={security.STREAM_USER: self.token})
        self.max_bytes = max_message_bytes
        self.client_timeout = client_timeout_s
        self.rig_idle_s = max(300.0, 10 * client_timeout_s)  # a rig outlives pauses between views
        _raise_fd_limit()
        self.control = self.ctx.socket(zmq.ROUTER)
        self.control.linger = 0
        # (bind() drops a peer that does not complete the ZeroMQ handshake within frames.HANDSHAKE_MS)
        self.control.setsockopt(zmq.MAXMSGSIZE, max_message_bytes + 4096)
        self.control.setsockopt(zmq.ROUTER_MANDATORY, 0)
        configure_curve_server(self.control, self.curve)
        if preview and not security.is_local(preview) and self.curve is None:
            raise PermissionError(f"the preview {preview} is not loopback/ipc: like the control socket it needs CURVE "
                                  "keys (`sss daemon keys`, --curve-dir)")
        # held until close(): a daemon started at the same moment found no state file either (the check above);
        # taken before anything is removed or bound (the other's socket, its port)
        self.state_lock = None
        try:
            self.state_lock = security.hold_state_lock(state_file) if state_file is not None else None
            security.remove_ipc_socket(self.endpoint)  # a dead daemon's socket; nothing else is ever removed
            self.endpoint = bind(self.control, self.endpoint, self.curve)
            # over TCP, a peer's connections that never authenticate are limited (its oldest closed beyond 16)
            self.guard = ConnectionGuard(self.control) if self.endpoint.startswith("tcp://") else None
            self.preview = Preview(self.ctx, preview, self.curve, token=self.token) if preview else None
        except BaseException:  # (another daemon's lock, an address in use) nothing of this one is left behind
            if self.state_lock is not None and state_file is not None:
                security.release_state_lock(self.state_lock, state_file)
            if self.auth is not None:
                self.auth.stop()
            self.ctx.destroy(linger=0)
            raise
        self.pm = manager.get_plugin_manager()
        self.rigs: dict[str, Rig] = {}
        self.closed_rigs: dict[str, str] = {}  # rig id -> why the daemon closed it (the latest 256)
        self.jobs: dict[str, Job] = {}
        self.last_seen: dict[bytes, float] = {}
        self.lock = threading.Lock()
        # device discovery (plugins' USB/serial enumeration, seconds or more) runs off the main thread, one
        # at a time (plugins need not be thread-safe); its replies wait here for the main thread to send
        self.discovery_lock = threading.Lock()
        self.discovery_waiters: list[tuple[bytes, list[bytes], Any]] | None = None
        self.answering = 0  # open_rig and close_rig requests being answered from their threads
        self.closing: dict[str, Rig] = {}  # device id -> the rig closing it, until its close() returns
        self.replies: queue.SimpleQueue[list[bytes]] = queue.SimpleQueue()
        self.running = True
        self.started = time.time()
        self.counter = itertools.count()
        self.state_file = state_file
        self.handlers: dict[str, Callable[[bytes, dict[str, Any]], Any]] = {
            "hello": self._hello, "ping": self._ping, "heartbeat": self._heartbeat,  # devices: _discover_for
            "plugins": self._plugins, "status": self._status, "open_rig": self._open_rig,  # close_rig: _close_rig
            "move": self._move, "capture": self._capture, "stream": self._stream,
            "job": self._job, "cancel": self._cancel, "shutdown": self._shutdown,
        }

    # ---- lifecycle -------------------------------------------------------------------------
    def write_state(self) -> Path:
        from sssphase_core import __version__

        state = security.DaemonState(self.endpoint, self.token, os.getpid(), __version__, self.started,
                                     self.preview.endpoint if self.preview else "",
                                     str(self.curve_dir) if self.curve_dir is not None else "")
        return security.write_state(state, self.state_file)

    def serve_forever(self) -> None:
        poller = zmq.Poller()
        poller.register(self.control, zmq.POLLIN)
        try:
            while self.running:
                if poller.poll(200 if self.discovery_waiters is None and not self.answering else 20):
                    frames = self.control.recv_multipart(copy=False)
                    self._handle([f.bytes for f in frames], fd=frames[-1].get(zmq.SRCFD) if self.guard else None)
                self._send_replies()
                self._reap()
                self._reload_authorized()
                if self.exit_when_idle_s is not None and self.idle_s() > self.exit_when_idle_s:
                    log.info("idle for %.0f s (no rig, job or client): exiting", self.idle_s())
                    self.running = False
        finally:
            self.close()

    def _authorized_keys(self) -> tuple[tuple[str, int], ...]:
        """(name, mtime) of the authorised clients' public keys (none without CURVE)."""
        if self.curve_dir is None:
            return ()
        keys = sorted((self.curve_dir / security.AUTHORIZED).glob("*.key"))
        return tuple((path.name, path.stat().st_mtime_ns) for path in keys if path.is_file())

    def _reload_authorized(self) -> None:
        """Every :data:`AUTHORIZED_CHECK_S`, read the authorised clients' keys again when they changed: a client key
        copied there (or removed) took effect only at a restart, which changed the token every connection folder
        holds. Connections already made stay."""
        if self.curve_dir is None or time.monotonic() - self.authorized_checked < AUTHORIZED_CHECK_S:
            return
        self.authorized_checked = time.monotonic()
        try:
            keys = self._authorized_keys()
            if keys == self.authorized:
                return
            self.auth.configure_curve(domain="*", location=str(self.curve_dir / security.AUTHORIZED))
        except (OSError, ValueError) as exc:  # a key file half-copied: read again at the next check
            log.warning("authorised clients not read again: %s", _exception_line(exc))
            return
        self.authorized = keys
        log.info("authorised clients read again: %d key(s) in %s", len(keys), self.curve_dir / security.AUTHORIZED)

    def close(self) -> None:
        for job in list(self.jobs.values()):
            job.cancel.set()
        for job_thread in [t for t in threading.enumerate() if t.name.startswith("sss-job-")]:
            job_thread.join(timeout=5)

        def close_after_its_call(rig: Rig) -> None:  # (a cancelled job's grab waiting for its frame ends first)
            if rig.close_after_its_call(SHUTDOWN_CALL_WAIT_S):
                log.warning("rig %s: a device call did not end within %g s; closed regardless", rig.id,
                            SHUTDOWN_CALL_WAIT_S)

        closing = [threading.Thread(target=close_after_its_call, args=(rig,), name=f"sss-close-{rig.id}", daemon=True)
                   for rig in self.rigs.values()]
        for thread in closing:  # a device that hangs in close (a stalled camera) must not keep the daemon alive
            thread.start()
        for thread in closing:
            thread.join(timeout=SHUTDOWN_CALL_WAIT_S + 5)
            if thread.is_alive():
                log.warning("%s: a device did not close within %g s; exiting without it", thread.name,
                            SHUTDOWN_CALL_WAIT_S + 5)
        self.rigs.clear()
        if self.preview:
            self.preview.close()
        if self.guard is not None:
            self.guard.close()
        self.control.close(linger=0)
        if self.auth:
            self.auth.stop()
        self.ctx.term()
        security.remove_ipc_socket(self.endpoint)
        if self.state_file is not None:
            self.state_file.unlink(missing_ok=True)
        if self.state_lock is not None and self.state_file is not None:  # (after the state file is gone)
            security.release_state_lock(self.state_lock, self.state_file)

    def idle_s(self) -> float:
        """Seconds since the daemon last had an open rig, a running job or a request (0 while it has)."""
        with self.lock:
            if self.rigs or any(j.state == "running" for j in self.jobs.values()):
                return 0.0
            last = max(self.last_seen.values(), default=self.started_at)
        return time.monotonic() - max(last, self.started_at)

    def _alive(self, owner: bytes, timeout: float | None = None) -> bool:
        return time.monotonic() - self.last_seen.get(owner, 0.0) < (timeout or self.client_timeout)

    def _reap(self) -> None:
        """Cancel jobs whose heartbeats stopped (dead client); close long-idle rigs; forget old jobs."""
        now = time.monotonic()
        taken_back: list[Rig] = []
        with self.lock:
            for job in self.jobs.values():  # running, or finished but not yet acknowledged
                if not job.cancel.is_set() and now - job.last_beat > self.client_timeout:
                    log.warning("job %s: no heartbeat for %.1f s, cancelling", job.id, now - job.last_beat)
                    job.error = job.error or {  # what a client that was only slow is told by `job`
                        "code": protocol.CLIENT_TIMEOUT,
                        "message": f"the daemon cancelled the capture: no heartbeat from its client for "
                                   f"{now - job.last_beat:.1f} s (the daemon's --client-timeout is {self.client_timeout:g} s)"}
                    job.cancel.set()
                    job.rig.orphaned = not self._alive(job.rig.owner)  # the client died (a crashed process)
            busy = {j.rig.id for j in self.jobs.values() if j.state == "running"}
            for rid, rig in list(self.rigs.items()):
                if rid in busy:
                    continue
                if not self._alive(rig.owner, self.rig_idle_s):
                    taken_back.append(self._forget_rig(rig, f"its client was silent for {self.rig_idle_s:g} s"))
                elif rig.orphaned and not self._alive(rig.owner):
                    taken_back.append(self._forget_rig(
                        rig, f"its client stopped heartbeating its capture for {self.client_timeout:g} s"))
            finished = [j for j in self.jobs.values() if j.state != "running" and j.cancel.is_set()]
            for job in sorted(finished, key=lambda j: j.started)[:-64]:
                del self.jobs[job.id]
            stale = [c for c in self.last_seen if not self._alive(c) and time.monotonic() - self.last_seen[c] > 600]
            for c in stale:
                del self.last_seen[c]
        for rig in taken_back:  # (a cancelled job's device call may still hold it, or its close hang)
            self._close_in_background(rig)

    def _close_in_background(self, rig: Rig, *, lock_wait_s: float = 0.0,
                             then: Callable[[bool], None] | None = None) -> None:
        """Close ``rig`` (already taken out of ``self.rigs``) in a thread of its own: a plugin whose close() hung
        held the main thread, and the daemon answered no one again ("runs but does not answer"). The close waits
        up to ``lock_wait_s`` for a device call of the rig under way (a cancelled job's, on a stalled device), then
        closes regardless; ``then(under_way)`` is called once every device has closed. Until its close() returns a
        device is in ``self.closing``: ``open_rig`` waits a little for it, then names the device that hangs.
        Takes ``self.lock``."""
        with self.lock:
            for driver in rig.devices.values():
                self.closing[_device_id(driver)] = rig

        def closed(device_id: str) -> None:
            with self.lock:
                if self.closing.get(device_id) is rig:
                    del self.closing[device_id]

        def run() -> None:
            under_way = rig.close_after_its_call(lock_wait_s, closed)
            if then is not None:
                then(under_way)

        threading.Thread(target=run, name=f"sss-close-{rig.id}", daemon=True).start()

    def _wait_until_closed(self, ids: Iterable[str], doing: dict[str, str]) -> None:
        """Wait (at most :data:`CLOSING_WAIT_S`) for those of ``ids`` that a closed rig is still closing; refuse one
        whose close() has not returned by then, naming the device that hangs (opening a device its plugin is still
        closing fails or hangs in the driver, where nobody can say why). Simulated devices are shared: not waited for."""
        deadline = time.monotonic() + min(CLOSING_WAIT_S, 0.5 * self.open_timeout_s)
        for device_id in ids:
            if device_id.partition(":")[0] == "sim":
                continue
            while (rig := self.closing.get(device_id)) is not None:
                if time.monotonic() > deadline:
                    hung, since = rig.closing or device_id, time.monotonic() - rig.closing_since
                    raise ProtocolError(protocol.BUSY, f"{device_id} is still closing: the close() of {hung} has not "
                                        f"returned for {since:.0f} s (its plugin hangs), and it cannot be opened again "
                                        "until it does: check the device, or restart the daemon")
                doing["what"] = f"{device_id} (waiting for its close)"
                time.sleep(0.02)

    def _forget_rig(self, rig: Rig, why: str) -> Rig:
        """Take a rig back from its client (the caller closes it) and remember ``why``, for the client that comes
        back to it (a paused notebook) to be told. Holds ``self.lock``."""
        log.info("rig %s closed: %s", rig.id, why)
        del self.rigs[rig.id]
        self.closed_rigs[rig.id] = why
        while len(self.closed_rigs) > 256:
            del self.closed_rigs[next(iter(self.closed_rigs))]
        return rig

    def _room_for_a_rig(self) -> list[Rig]:
        """At :data:`MAX_OPEN_RIGS`, take back (-> to be closed) the idle rig whose client was heard from longest
        ago, when that client is silent for longer than the client timeout (crashed between captures); else refuse.
        Holds ``self.lock``."""
        if len(self.rigs) < MAX_OPEN_RIGS:
            return []
        busy = {j.rig.id for j in self.jobs.values() if j.state == "running"}
        idle = [r for r in self.rigs.values() if r.id not in busy and not self._alive(r.owner)]
        if not idle:
            raise ProtocolError(protocol.BUSY, f"{len(self.rigs)} rigs are open (at most {MAX_OPEN_RIGS}), each "
                                "capturing or of a client heard from within the client timeout: close one first")
        oldest = min(idle, key=lambda r: self.last_seen.get(r.owner, 0.0))
        silent = time.monotonic() - self.last_seen.get(oldest.owner, 0.0)
        return [self._forget_rig(oldest, f"{MAX_OPEN_RIGS} rigs were open and its client had been silent for "
                                         f"{silent:.0f} s")]

    # ---- request dispatch ------------------------------------------------------------------
    def _handle(self, parts: list[bytes], fd: int | None = None) -> None:
        """Answer one request; ``fd``: the descriptor it came on (its connection is proven once it gives the token)."""
        if len(parts) < 2 or any(p for p in parts[1:-1]):
            return  # not an envelope we can answer: drop
        identity, envelope, payload = parts[0], parts[1:-1], parts[-1]
        rid: Any = None
        try:
            req = protocol.parse_request(payload, self.max_bytes)
            rid = req.id
            if not hmac.compare_digest(req.token.encode(), self.token.encode()):
                raise ProtocolError(protocol.UNAUTHENTICATED, "missing or wrong token (read it from the daemon state file)")
            if self.guard is not None:
                self.guard.proven(fd)
            self.last_seen[identity] = time.monotonic()
            if req.op == "devices":  # answered when discovery is done; the control socket keeps serving
                self._discover_for(identity, envelope, rid)
                return
            if req.op == "open_rig":  # a plugin may hang in open(): answered from a thread, with a deadline
                self._open_in_thread(identity, envelope, rid, req.args)
                return
            if req.op == "close_rig":  # or in close(): answered from the close's thread, with a deadline
                self._close_rig(identity, envelope, rid, req.args)
                return
            result = self.handlers[req.op](identity, req.args)
            reply = protocol.reply_ok(rid, result)
        except Exception as exc:  # the daemon keeps serving whatever a handler does
            reply = _error_reply(getattr(exc, "rid", rid), exc)
        except SystemExit as exc:
            reply = _error_reply(rid, exc)
        try:
            self.control.send_multipart([identity, *envelope, reply], flags=zmq.NOBLOCK)
        except zmq.ZMQError:
            pass  # the client went away

    # ---- handlers --------------------------------------------------------------------------
    def _hello(self, client: bytes, args: dict) -> dict:
        from sssphase_core import __version__

        return {"protocol": protocol.PROTOCOL_VERSION, "version": __version__, "pid": os.getpid(),
                "endpoint": self.endpoint, "preview": self.preview.endpoint if self.preview else "",
                "client_timeout_s": self.client_timeout}

    def _ping(self, client: bytes, args: dict) -> dict:
        return {"time": time.time()}

    def _heartbeat(self, client: bytes, args: dict) -> dict:
        job = self.jobs.get(_id_arg(args, "job"))
        if job is not None:
            job.last_beat = time.monotonic()
        return {"time": time.time(), "job": job.state if job else None}

    def _devices(self) -> dict:
        """Every plugin's devices and discovery errors (device I/O: run on the discovery thread)."""
        with self.discovery_lock:
            devices, errors = manager.discover_devices(self.pm)
        return {"devices": [asdict(d) for d in devices], "errors": errors}

    def _open_in_thread(self, identity: bytes, envelope: list[bytes], rid: Any, args: dict) -> None:
        """Answer ``open_rig`` from a thread of its own: a plugin that hung in its hook or in open() held the main
        thread, so no client was answered and the daemon could not be stopped. Past ``open_timeout_s`` the
        client is told which device hangs; a rig opened after that is closed again."""
        answered, guard = [False], threading.Lock()
        doing = {"what": "the rig"}

        def answer(reply: bytes) -> bool:
            with guard:
                if answered[0]:
                    return False
                answered[0] = True
            self.replies.put([identity, *envelope, reply])
            return True

        def work() -> None:
            opened: dict | None = None
            try:
                opened = self._open_rig(identity, args, doing)
                reply = protocol.reply_ok(rid, opened)
            except SystemExit as exc:  # named with the call under way (it said "a device plugin" alone)
                log.exception("open_rig: %s: a device plugin called sys.exit(%s)", doing["what"], exc.code)
                reply = protocol.reply_error(rid, protocol.DEVICE,
                                             f"{doing['what']}: a device plugin called sys.exit({exc.code!r})")
            except BaseException as exc:  # noqa: BLE001  (a plugin's CancelledError too)
                reply = _error_reply(rid, exc)
            finally:
                with self.lock:
                    self.answering -= 1
            if not answer(reply) and opened is not None:  # the client was told it hung: nobody holds this rig
                with self.lock:
                    late = self.rigs.pop(opened["rig"], None)
                if late is not None:
                    self._close_in_background(late)

        def late() -> None:
            if answer(protocol.reply_error(rid, protocol.DEVICE, f"{doing['what']} did not return within "
                                           f"{self.open_timeout_s:g} s: its plugin hangs (the daemon keeps serving other "
                                           "devices; check the device, or restart the daemon)")):
                log.error("open_rig: %s did not return within %g s", doing["what"], self.open_timeout_s)

        with self.lock:
            self.answering += 1
        timer = threading.Timer(self.open_timeout_s, late)
        timer.daemon = True
        timer.start()
        threading.Thread(target=lambda: (work(), timer.cancel()), name="sss-open-rig", daemon=True).start()

    def _discover_for(self, identity: bytes, envelope: list[bytes], rid: Any) -> None:
        """Answer a ``devices`` request from a discovery thread: a slow plugin (a USB bus that takes
        seconds to enumerate) held the main thread, so heartbeats went unanswered and running captures
        were cancelled. Requests that arrive while one discovery runs share its result."""
        with self.lock:
            start = self.discovery_waiters is None
            self.discovery_waiters = [*(self.discovery_waiters or []), (identity, envelope, rid)]
        if start:
            threading.Thread(target=self._discovery_thread, name="sss-discovery", daemon=True).start()

    def _discovery_thread(self) -> None:
        try:
            result: Any = self._devices()
        except BaseException as exc:  # a plugin's sys.exit() too: the waiting clients get an error, not silence
            log.exception("device discovery failed")
            result = exc
        with self.lock:
            waiters, self.discovery_waiters = self.discovery_waiters or [], None
        for identity, envelope, rid in waiters:
            reply = (protocol.reply_ok(rid, result) if not isinstance(result, BaseException) else
                     protocol.reply_error(rid, protocol.INTERNAL, f"device discovery failed: {type(result).__name__}: {result}"[:500]))
            self.replies.put([identity, *envelope, reply])

    def _send_replies(self) -> None:
        """Send the replies made off the main thread (ZeroMQ sockets belong to one thread)."""
        while True:
            try:
                parts = self.replies.get_nowait()
            except queue.Empty:
                return
            try:
                self.control.send_multipart(parts, flags=zmq.NOBLOCK)
            except zmq.ZMQError:
                pass  # the client went away

    def _plugins(self, client: bytes, args: dict) -> dict:
        return {"plugins": [asdict(r) for r in manager.plugin_records(self.pm)]}

    def _status(self, client: bytes, args: dict) -> dict:
        with self.lock:
            return {"pid": os.getpid(), "uptime_s": time.time() - self.started, "endpoint": self.endpoint,
                    "rigs": [{"rig": r.id, "devices": {k: d.info.id for k, d in r.devices.items()},
                              "client_alive": self._alive(r.owner)} for r in self.rigs.values()],
                    "jobs": [j.summary() for j in self.jobs.values()],
                    "clients": sum(self._alive(c) for c in self.last_seen),
                    "heavy_modules": [m for m in HEAVY_MODULES if m in sys.modules]}

    def _open_rig(self, client: bytes, args: dict, doing: dict[str, str] | None = None) -> dict:
        """Open the devices ``args`` names as one rig of ``client``; ``doing["what"]``: the call under way."""
        doing = {} if doing is None else doing
        options = args.get("options", {})
        wanted = {k: args[k] for k in ("camera", "projector", "trigger", "turntable") if args.get(k)}
        if "camera" not in wanted or not isinstance(options, dict) or not all(isinstance(v, str) for v in wanted.values()):
            raise ProtocolError(protocol.BAD_ARGS, "open_rig needs a camera device id (string) and an options map")
        try:  # (no device of the rig is opened for options no plugin would read)
            manager.check_rig_options(options, wanted.values(), self.pm)
        except SssError as exc:
            raise ProtocolError(protocol.BAD_ARGS, str(exc)) from None
        with self.lock:
            stale = self._room_for_a_rig() + self._claim_devices(wanted.values())
        for rig in stale:
            self._close_in_background(rig)
        self._wait_until_closed(wanted.values(), doing)
        shared: dict[str, Any] = {}
        devices: dict[str, Any] = {}
        device_id = "the rig"
        try:
            for kind, device_id in wanted.items():
                doing["what"] = f"the plugins' hooks or discover() (finding {device_id})"
                if not self.discovery_lock.acquire(timeout=0.8 * self.open_timeout_s):  # not while discovery asks the plugins
                    raise ProtocolError(protocol.DEVICE, f"finding {device_id}: another request's device discovery has "
                                        f"not returned for {0.8 * self.open_timeout_s:g} s (a plugin hangs): restart the daemon")
                try:
                    provider = manager.find_provider(device_id, self.pm, kind=kind)
                except KeyError as exc:
                    raise ProtocolError(protocol.NOT_FOUND, str(exc.args[0])) from None
                finally:
                    self.discovery_lock.release()
                doing["what"] = f"{device_id} (open)"
                driver = provider.open(device_id, options, shared)
                if not (callable(getattr(driver, "close", None)) and hasattr(driver, "info")):
                    _close_all(devices)  # (an AttributeError on 'close' named no plugin, and left the others open)
                    raise ProtocolError(protocol.DEVICE, f"open() of the plugin of {device_id} returned "
                                        f"{type(driver).__name__}, not a {kind} driver")
                devices[kind] = driver
                said = getattr(driver.info, "id", None)
                if said != device_id:  # (held under another id, the device was not refused to a second client)
                    raise ProtocolError(protocol.DEVICE, f"open() of {device_id} returned a driver whose info.id is "
                                        f"{str(said)[:60]!r}: a driver describes the device it was opened as "
                                        "(DeviceInfo with that id)")
        except BaseException as exc:  # a plugin's sys.exit() too: the devices opened so far are closed
            _close_all(devices)
            if isinstance(exc, SssError):
                raise ProtocolError(protocol.BAD_ARGS, str(exc)) from None
            if isinstance(exc, Exception) and not isinstance(exc, ProtocolError):  # a driver's own error: name it
                log.exception("open_rig: the plugin of %s failed", device_id)
                raise ProtocolError(protocol.DEVICE, f"{device_id} (open): {_exception_line(exc)}") from None
            raise
        if "trigger" in devices and not isinstance(devices["camera"], TriggeredCamera):
            for d in devices.values():
                d.close()
            raise ProtocolError(protocol.BAD_ARGS, f"camera {wanted['camera']} cannot expose on a hardware trigger "
                                "(its driver has no wait_frame): open the rig without the trigger")
        rig = Rig(uuid.uuid4().hex[:12], client, devices, options)
        try:  # a driver that breaks here must not hold a rig slot
            info = {k: asdict(d.info) for k, d in devices.items()}
            projector = devices.get("projector")
            versions = {r.name: r.version for r in manager.plugin_records(self.pm)}
            reply = {"rig": rig.id, "devices": info, "projector_size": projector_size(projector) if projector else None,
                     "plugins": {d["plugin"]: versions.get(d["plugin"], "?") for d in info.values()}}
            try:
                protocol.pack(reply)  # (a numpy number in a driver's info failed the reply after the rig was held)
            except (TypeError, ValueError, OverflowError) as exc:
                raise DeviceError(f"the drivers of {', '.join(d.info.id for d in devices.values())} describe themselves "
                                  f"with values a reply cannot carry ({exc}): DeviceInfo fields are text") from None
        except Exception:
            for d in devices.values():
                d.close()
            raise
        with self.lock:
            self.rigs[rig.id] = rig
        return reply

    def _claim_devices(self, ids: Iterable[str]) -> list[Rig]:
        """Refuse a device another open rig holds (two captures drove one camera's exposure and grabs: brackets
        of both mixed without a word); a rig whose client is gone and that runs no job is stale: taken out and
        returned to be closed. Simulated devices (``sim:``) are virtual and may be shared. Holds ``self.lock``."""
        stale: list[Rig] = []
        for device_id in ids:
            if device_id.partition(":")[0] == "sim":
                continue
            holder = next((r for r in self.rigs.values() if r not in stale
                           and any(d.info.id == device_id for d in r.devices.values())), None)
            if holder is None:
                continue
            running = any(j.rig is holder and j.state == "running" for j in self.jobs.values())
            if running or self._alive(holder.owner):
                raise ProtocolError(protocol.BUSY, f"{device_id} is in use by rig {holder.id} of another client"
                                    f"{' (a capture is running)' if running else ''}: wait until it closes the rig, "
                                    "or stop that command")
            stale.append(holder)
            del self.rigs[holder.id]
        return stale

    def _get_rig(self, args: dict) -> Rig:
        rig = self.rigs.get(_id_arg(args, "rig"))
        if rig is None:
            why = self.closed_rigs.get(_id_arg(args, "rig"))
            raise ProtocolError(protocol.NOT_FOUND, f"no open rig {str(args.get('rig'))[:40]!r}"
                                + (f": the daemon closed it ({why}); open the rig again" if why else ""))
        return rig

    def _close_rig(self, identity: bytes, envelope: list[bytes], rid: Any, args: dict) -> None:
        """Take the rig back and answer ``close_rig`` from its close's thread once its devices have closed, or after
        :data:`CLOSE_REPLY_S` saying they close in the background: a plugin whose close() hung held the main
        thread, and the daemon answered no one again. A rig that is capturing is refused (raised here)."""
        rig = self._get_rig(args)
        with self.lock:
            if any(j.rig is rig and j.state == "running" and not j.cancel.is_set() for j in self.jobs.values()):
                raise ProtocolError(protocol.BUSY, f"rig {rig.id} is capturing; cancel the job first")
            self.rigs.pop(rig.id, None)
            self.answering += 1
        answered, guard = [False], threading.Lock()

        def answer(result: dict[str, Any]) -> None:
            with guard:
                if answered[0]:
                    return
                answered[0] = True
            self.replies.put([identity, *envelope, protocol.reply_ok(rid, result)])
            with self.lock:
                self.answering -= 1

        def closed(under_way: bool) -> None:
            timer.cancel()
            answer({"closed": rig.id, **({"note": "a device call was still under way: its devices close in the "
                                                  "background"} if under_way else {})})

        def late() -> None:
            hung = rig.closing or "a device"
            log.warning("close_rig %s: %s did not close within %g s; it closes in the background", rig.id, hung,
                        CLOSE_REPLY_S)
            answer({"closed": rig.id, "note": f"{hung} did not close within {CLOSE_REPLY_S:g} s: its devices close in "
                                              "the background (it cannot be opened again until its close returns)"})

        timer = threading.Timer(CLOSE_REPLY_S, late)
        timer.daemon = True
        timer.start()
        self._close_in_background(rig, lock_wait_s=1.0, then=closed)

    def _move(self, client: bytes, args: dict) -> dict:
        rig = self._get_rig(args)
        table = rig.devices.get("turntable")
        if table is None:
            raise ProtocolError(protocol.NOT_FOUND, "this rig has no turntable")
        angle = args.get("angle")
        if isinstance(angle, bool) or not isinstance(angle, int | float) or not abs(angle) <= MAX_ANGLE:
            raise ProtocolError(protocol.BAD_ARGS, f"move needs an angle in degrees within ±{MAX_ANGLE:g}, got {str(angle)[:40]}")
        if not rig.lock.acquire(timeout=1.0):
            raise ProtocolError(protocol.BUSY, f"rig {rig.id} is capturing")
        try:
            return {"angle": table.move_to(float(angle))}
        finally:
            rig.lock.release()

    def _start_job(self, client: bytes, rig: Rig, total: int, frames: Callable[[Job], Iterator[tuple[str, Any]]],
                   args: dict) -> dict:
        deadline = _deadline(args, rig)
        with self.lock:
            running = sum(j.state == "running" for j in self.jobs.values())
        if running >= MAX_RUNNING_JOBS:
            raise ProtocolError(protocol.BUSY, f"{running} capture jobs are running (at most {MAX_RUNNING_JOBS}): read or "
                                "cancel one first")
        job_id = f"{next(self.counter)}-{uuid.uuid4().hex[:8]}"
        sender = FrameSender(self.ctx, security.stream_endpoint(self.endpoint, job_id), self.curve,
                             plain=self.curve is None)
        job = Job(job_id, client, rig, sender.endpoint, total, deadline_s=deadline)
        with self.lock:
            self.jobs[job_id] = job
        threading.Thread(target=self._run_job, args=(job, sender, frames), name=f"sss-job-{job_id}", daemon=True).start()
        return {"job": job_id, "endpoint": sender.endpoint, "frames": total}

    def _capture(self, client: bytes, args: dict) -> dict:
        rig = self._get_rig(args)
        frames = _check_frames(args.get("frames"))
        if "projector" not in rig.devices:
            raise ProtocolError(protocol.BAD_ARGS, "capture needs a rig with a projector (use 'stream' otherwise)")
        _check_pattern_sizes(frames, rig.devices["projector"])

        def run(job: Job) -> Iterator[tuple[str, Any]]:
            camera, projector, trigger = rig.devices["camera"], rig.devices["projector"], rig.devices.get("trigger")
            if isinstance(projector, PreloadingProjector):
                projector.preload([(spec["name"], functools.partial(_pattern_for, spec)) for spec in frames])
            for spec in frames:
                job.doing = f"{projector.info.id} (show {spec['name'][:60]})"
                _check_receipt(projector.show(_pattern_for(spec), tag=spec["name"], confirm=True), spec["name"],
                               projector.info.id)
                job.doing = f"{camera.info.id} (configure)"
                camera.configure(exposure=float(spec["exposure"]),
                                 **({"gain": float(spec["gain"])} if spec.get("gain") is not None else {}))
                job.doing = f"{camera.info.id} (grab {spec['name'][:60]})"
                if trigger is None:  # software trigger
                    yield spec["name"], camera.grab()
                    continue
                job.doing = f"{trigger.info.id} (fire)"
                fired_ns = trigger.fire()  # the pulse exposes the camera (checked at open_rig: TriggeredCamera)
                job.doing = f"{camera.info.id} (wait for the triggered frame)"
                frame = camera.wait_frame()
                frame.meta["trigger_ns"] = fired_ns
                yield spec["name"], frame

        return self._start_job(client, rig, len(frames), run, args)

    def _stream(self, client: bytes, args: dict) -> dict:
        rig = self._get_rig(args)
        count = args.get("count")
        if isinstance(count, bool) or not isinstance(count, int) or not 0 < count <= MAX_STREAM_FRAMES:
            raise ProtocolError(protocol.BAD_ARGS, f"stream needs a frame count, a whole number from 1 to "
                                                   f"{MAX_STREAM_FRAMES:,}, got {str(count)[:40]}")

        def run(job: Job) -> Iterator[tuple[str, Any]]:
            job.doing = f"{rig.devices['camera'].info.id} (stream)"
            for i, frame in enumerate(rig.devices["camera"].stream(count)):  # (_check_frame: is it a Frame?)
                yield f"stream/{getattr(frame, 'sequence', i)}", frame

        return self._start_job(client, rig, count, run, args)

    def _run_job(self, job: Job, sender: FrameSender, frames: Callable[[Job], Iterator[tuple[str, Any]]]) -> None:
        def alive() -> bool:
            return not job.cancel.is_set()

        first: tuple[tuple[int, ...], str] | None = None
        try:
            for name, frame in self._within_deadline(job, frames):
                first = _check_frame(job, name, frame, first)
                header = protocol.frame_header(job.id, job.sent, name, frame.data, frame.timestamp_ns,
                                               frame.exposure, frame.meta)
                sender.send_frame(header, frame.data, alive)
                if self.preview:
                    self.preview.publish(job.id, job.sent, name, frame.data)
                job.sent += 1
            job.state = "done"
        except ClientGone:
            job.state = "cancelled"
        except DeviceStalled as exc:  # the rig is dropped: its devices are closed in the background (they may hang)
            log.error("job %s: %s", job.id, exc)
            job.state, job.error = "failed", {"code": protocol.DEVICE, "message": str(exc)}
            with self.lock:
                self.rigs.pop(job.rig.id, None)
            self._close_in_background(job.rig)
        except DeviceError as exc:
            job.state, job.error = "failed", {"code": protocol.DEVICE, "message": str(exc)}
        except SssError as exc:
            job.state, job.error = "failed", {"code": protocol.BAD_ARGS, "message": str(exc)}
        except SystemExit as exc:  # a plugin's sys.exit() ended the job's thread: the job hung "running" for ever
            log.exception("job %s: a device plugin called sys.exit(%s)", job.id, exc.code)
            job.state, job.error = "failed", {"code": protocol.DEVICE,
                                              "message": f"{job.doing}: a device plugin called sys.exit({exc.code!r})"}
        except Exception as exc:  # a driver's own error (or ours): named with the device call under way
            log.exception("job %s failed", job.id)
            job.state, job.error = "failed", {"code": protocol.DEVICE if job.doing != "the rig" else protocol.INTERNAL,
                                              "message": f"{job.doing}: {_exception_line(exc)}"}
        except BaseException as exc:  # noqa: BLE001  (a driver's KeyboardInterrupt or asyncio's CancelledError
            # ended the job's thread without an end message: the capture waited for ever, the daemon never stopped)
            log.exception("job %s: a device plugin raised %s", job.id, type(exc).__name__)
            job.state, job.error = "failed", {"code": protocol.DEVICE, "message": f"{job.doing}: {_exception_line(exc)}"}
        try:
            if job.state != "cancelled":
                sender.send_end(protocol.end_header(job.id, job.sent, job.error),
                                lambda: not job.cancel.is_set() and self.running)
                # keep the queued frames deliverable until the client acknowledges the end or dies
                while self.running and not job.cancel.wait(0.1):
                    pass
        except ClientGone:
            pass
        finally:
            sender.close()

    def _within_deadline(self, job: Job, frames: Callable[[Job], Iterator[tuple[str, Any]]]) -> Iterator[tuple[str, Any]]:
        """``frames(job)``'s items, its device calls made in a thread of their own (holding the rig's lock):
        a call that takes longer than ``job.deadline_s`` raises :class:`DeviceStalled` naming it, and a cancel
        takes effect within 0.1 s however long the device takes (the call itself cannot be interrupted: its
        thread stops at the next item)."""
        items: queue.Queue = queue.Queue(maxsize=2)
        stop = threading.Event()

        def put(entry: tuple[str, Any]) -> bool:
            while not stop.is_set():
                try:
                    items.put(entry, timeout=0.1)
                    return True
                except queue.Full:
                    continue
            return False

        def produce() -> None:
            try:
                with job.rig.lock, contextlib.closing(frames(job)) as items_of_job:  # (its cleanup under the lock)
                    for item in items_of_job:
                        if not put(("item", item)):
                            return
                put(("end", None))
            except BaseException as exc:  # (a plugin's sys.exit() too) handed to the job thread
                put(("error", exc))

        threading.Thread(target=produce, name=f"sss-device-{job.id}", daemon=True).start()
        since = time.monotonic()
        try:
            while True:
                if job.cancel.is_set() or not self.running:
                    raise ClientGone("job cancelled")
                try:
                    kind, value = items.get(timeout=0.1)
                except queue.Empty:
                    if time.monotonic() - since > job.deadline_s:
                        raise DeviceStalled(f"{job.doing} did not answer within {job.deadline_s:g} s (stalled or "
                                            "disconnected): the rig was closed; check the device, then open the rig "
                                            "again (a capture continues with --resume)") from None
                    continue
                if kind == "end":
                    return
                if kind == "error":
                    raise value
                yield value
                since = time.monotonic()
        finally:
            stop.set()

    def _job(self, client: bytes, args: dict) -> dict:
        job = self.jobs.get(_id_arg(args, "job"))
        if job is None:
            raise ProtocolError(protocol.NOT_FOUND, f"no job {str(args.get('job'))[:40]!r}")
        return job.summary()

    def _cancel(self, client: bytes, args: dict) -> dict:
        job = self.jobs.get(_id_arg(args, "job"))
        if job is not None:
            job.cancel.set()
        return {"cancelled": job is not None}

    def _shutdown(self, client: bytes, args: dict) -> dict:
        self.running = False
        return {"stopping": True}
