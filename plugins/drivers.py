"""Typed driver protocols that device plugins implement, and the records they exchange.

A plugin's hooks return :class:`DeviceProvider` objects; the daemon (never the hook call) asks a
provider to ``discover()`` its devices, each with a stable ID, and to ``open()`` one of them. The
driver objects it returns follow the small protocols below. Drivers raise :class:`DeviceError` for
device failures; the daemon turns it into a clear error for the client and keeps serving.
"""

from __future__ import annotations

import datetime
import enum
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

DeviceKind = Literal["camera", "projector", "trigger", "turntable"]
DEVICE_KINDS: tuple[DeviceKind, ...] = ("camera", "projector", "trigger", "turntable")


class DeviceError(RuntimeError):
    """A device failed (disconnected, timed out, refused a setting)."""


class DeviceNotFound(DeviceError):
    """Discovery found no device of this kind (none plugged in, or its library is not installed): an
    answer to report, not a failure. The message says why and starts with "no device"."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason if reason.startswith("no device") else f"no device: {reason}")


@dataclass(frozen=True)
class DeviceInfo:
    """One discovered device. ``id`` is stable across runs (e.g. ``plugin:serial``)."""

    id: str
    kind: DeviceKind
    plugin: str
    model: str
    serial: str = ""


@dataclass
class Frame:
    """A camera frame with its metadata; ``data`` is (H, W, 3) or (H, W) (raw Bayer)."""

    data: np.ndarray
    sequence: int
    timestamp_ns: int
    exposure: float
    meta: dict[str, Any] = field(default_factory=dict)


#: How many values a frame's metadata may hold in all (it rides in every frame's header).
MAX_META_VALUES = 1000


def plain_meta(meta: Any, where: str) -> dict[str, Any]:
    """A driver's ``Frame.meta`` as the plain values a header carries: numpy scalars and small arrays become
    numbers and lists, dates ISO text, paths and enums their text or value. Anything else (an object, a large
    array) raises :class:`DeviceError` naming its key: msgpack failed on it with a bare TypeError."""
    count = 0

    def plain(value: Any, key: str, depth: int) -> Any:
        nonlocal count
        count += 1
        if count > MAX_META_VALUES or depth > 8:
            raise DeviceError(f"{where}: its meta holds more than {MAX_META_VALUES} values or nests deeper than 8 "
                              f"(at {key!r}): keep a frame's metadata small")
        if isinstance(value, np.generic | np.ndarray) and np.asarray(value).dtype.kind in "biuf" \
                and np.asarray(value).size <= 64:
            value = np.asarray(value).tolist()
        if isinstance(value, enum.Enum):
            value = value.value
        if value is None or isinstance(value, bool | str | bytes) or (isinstance(value, int) and -2**63 <= value < 2**64):
            return value
        if isinstance(value, float):
            return value
        if isinstance(value, datetime.date | datetime.time):
            return value.isoformat()
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        if isinstance(value, list | tuple):
            return [plain(v, f"{key}[{i}]", depth + 1) for i, v in enumerate(value)]
        if isinstance(value, dict) and all(isinstance(k, str) for k in value):
            return {k: plain(v, f"{key}.{k}" if key else k, depth + 1) for k, v in value.items()}
        what = (f"an array of {np.asarray(value).size} {np.asarray(value).dtype} values (64 numbers at most)"
                if isinstance(value, np.ndarray | np.generic) else "an integer beyond 64 bits" if isinstance(value, int)
                else "a table whose keys are not all text" if isinstance(value, dict)
                else f"of type {type(value).__qualname__}")
        raise DeviceError(f"{where}: its meta[{key!r}] is {what}, which a frame's header cannot carry: give numbers, "
                          "text, lists or tables of them")

    if not isinstance(meta, dict):
        raise DeviceError(f"{where}: its meta must be a dict of names to values, got {type(meta).__qualname__}")
    return plain(meta, "", 0)


@dataclass(frozen=True)
class ShowReceipt:
    """Confirmation that a projector image is on screen (``on_screen_ns`` on the device clock)."""

    frame_id: int
    tag: str
    on_screen_ns: int


def check_pattern(image: np.ndarray, resolution: tuple[int, int], device_id: str) -> np.ndarray:
    """A pattern for :meth:`Projector.show` as float32 ``(H, W)`` or ``(H, W, 3)`` of the projector's
    ``resolution`` (width, height); anything else raises :class:`DeviceError` naming both shapes."""
    w, h = resolution
    img = np.asarray(image, np.float32)
    if img.ndim not in (2, 3) or img.shape[:2] != (h, w) or (img.ndim == 3 and img.shape[2] != 3):
        raise DeviceError(f"{device_id}: a pattern is (H, W) or (H, W, 3) of the projector's {w}x{h}, "
                          f"got shape {img.shape}")
    return img


@runtime_checkable
class Camera(Protocol):
    info: DeviceInfo

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        """Set exposure (relative to the rig's reference exposure), gain and output format."""

    def grab(self, timeout_s: float = 5.0) -> Frame:
        """Trigger one exposure and return the frame (software trigger). The daemon calls it without
        ``timeout_s``: the driver's own wait applies, covering the exposure. A camera whose frames may take
        longer than a client's deadline declares a ``frame_timeout_s`` attribute (seconds), which the daemon's
        watchdog then allows. ``Frame.meta`` holds plain values (numbers, text, lists, tables)."""

    def stream(self, count: int) -> Any:
        """Free-running acquisition: an iterator of ``count`` frames."""

    def close(self) -> None: ...


@runtime_checkable
class Projector(Protocol):
    info: DeviceInfo

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) in projector pixels."""

    def show(self, image: np.ndarray, *, tag: str = "", confirm: bool = True) -> ShowReceipt:
        """Display a pattern (float values in [0, 1]); with ``confirm`` return once it is on screen."""

    def close(self) -> None: ...


@runtime_checkable
class PreloadingProjector(Projector, Protocol):
    """A projector that takes the coming patterns in advance (optional: the daemon calls ``preload``
    before a capture when the projector has it)."""

    def preload(self, sequence: list[tuple[str, Callable[[], np.ndarray]]]) -> None:
        """The capture's patterns as ``(tag, render)`` in display order (pattern-sequence memory of DLP
        projectors; batch rendering in the sim). ``show`` is still called for each, in that order."""


@runtime_checkable
class TriggeredCamera(Camera, Protocol):
    """A camera that exposes on an external pulse: a rig with a ``trigger`` device needs one. Per frame
    the daemon shows the pattern, fires the trigger, then takes the frame with ``wait_frame``."""

    def wait_frame(self, timeout_s: float = 5.0) -> Frame:
        """The frame exposed by the trigger pulse just fired (raise ``DeviceError`` if none comes)."""


@runtime_checkable
class Trigger(Protocol):
    info: DeviceInfo

    def fire(self) -> int:
        """Emit one trigger pulse; returns the device timestamp in ns."""

    def close(self) -> None: ...


@runtime_checkable
class Turntable(Protocol):
    info: DeviceInfo

    @property
    def angle(self) -> float:
        """Current angle in degrees."""

    def move_to(self, angle_deg: float) -> float:
        """Move and return the reached angle once settled."""

    def close(self) -> None: ...


Driver = Camera | Projector | Trigger | Turntable


@runtime_checkable
class DeviceProvider(Protocol):
    """What hooks return: cheap to build; device I/O happens only in ``discover`` and ``open``."""

    kind: DeviceKind

    def discover(self) -> list[DeviceInfo]: ...

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> Driver:
        """Open a device. ``shared`` is one dict per rig, so devices of one plugin can share state."""
