"""Example third-party sssphase device plugin: a synthetic test-pattern camera.

A plugin module implements the device hooks with the ``hookimpl`` marker, importing only from the
public API ``sssphase_plugins.api``; each hook returns cheap provider objects, and device I/O happens
only in ``discover()`` and ``open()``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from sssphase_plugins.api import DeviceError, DeviceInfo, Frame, hookimpl, plugin_options

__version__ = "0.1.0"
PLUGIN = "example"
CAMERA_ID = f"{PLUGIN}:testpattern0"
#: The settings of its ``[options.example]`` table and their kinds: an unknown one (a misspelt ``widht``) or one of
#: the wrong type is refused by name when the camera opens.
OPTIONS = {"width": "count", "height": "count"}


def colour_bars(width: int, height: int, phase: float) -> np.ndarray:
    """Eight vertical colour bars times a horizontal gradient that moves with ``phase``; float32 RGB."""
    bars = np.array([[1, 1, 1], [1, 1, 0], [0, 1, 1], [0, 1, 0], [1, 0, 1], [1, 0, 0], [0, 0, 1], [0, 0, 0]], np.float32)
    colour = bars[(np.arange(width) * 8) // width]  # (W, 3)
    ramp = 0.25 + 0.75 * (0.5 + 0.5 * np.cos(2 * np.pi * (np.arange(height) / height + phase)))
    return (ramp[:, None, None] * colour[None]).astype(np.float32)


class PatternCamera:
    def __init__(self, options: Mapping[str, Any]) -> None:
        self.info = DeviceInfo(CAMERA_ID, "camera", PLUGIN, "synthetic test-pattern camera", "testpattern0")
        self.width, self.height = int(options.get("width", 320)), int(options.get("height", 240))
        self.exposure, self.gain = 1.0, 1.0
        self.sequence = 0

    def configure(self, *, exposure: float | None = None, gain: float | None = None,
                  pixel_format: str | None = None) -> None:
        if exposure is not None:
            if not exposure > 0:
                raise DeviceError(f"exposure must be positive, got {exposure}")
            self.exposure = float(exposure)
        if gain is not None:
            self.gain = float(gain)
        if pixel_format not in (None, "rgb32f"):
            raise DeviceError(f"{CAMERA_ID} only delivers rgb32f, not {pixel_format!r}")

    def grab(self, timeout_s: float = 5.0) -> Frame:
        image = np.minimum(colour_bars(self.width, self.height, self.sequence / 30) * self.exposure * self.gain, 1.0)
        frame = Frame(image, self.sequence, time.monotonic_ns(), self.exposure, {"source": "test pattern"})
        self.sequence += 1
        return frame

    def stream(self, count: int) -> Iterator[Frame]:
        return (self.grab() for _ in range(count))

    def close(self) -> None:
        pass


class PatternProvider:
    kind = "camera"

    def discover(self) -> list[DeviceInfo]:
        return [DeviceInfo(CAMERA_ID, "camera", PLUGIN, "synthetic test-pattern camera", "testpattern0")]

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> PatternCamera:
        if device_id != CAMERA_ID:
            raise DeviceError(f"the example plugin has no camera {device_id!r}")
        return PatternCamera(plugin_options(options, PLUGIN, OPTIONS, device_id))


@hookimpl
def sssphase_cameras() -> list[PatternProvider]:
    return [PatternProvider()]
