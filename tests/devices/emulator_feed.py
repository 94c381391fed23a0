"""A test rig's projector that feeds pylon's camera emulator (loaded into a daemon through ``SSS_PLUGINS``).

``feed:projector0`` is the simulated projector, and for every pattern it shows it writes what the sim
camera would record of it, as raw Bayer at the sensor's bit depth, to the file the emulated Basler camera
streams (``[options.feed] image_file``, the same path as ``[options.basler] image_file``): 16-bit PNG,
``value << (16 - bit_depth)``, which the emulator turns back into the value exactly. The Basler plugin is
then software-triggered and runs unchanged; the capture goes through pylon's grab engine, buffers and
pixel formats. Written atomically (a temporary file renamed over it), so the emulator never reads half a
frame. Exposure stays the rig's reference (the feed renders at exposure 1: no HDR brackets).

``$SSS_FEED_LOSE_FRAME_AT=N`` in the daemon's environment removes the file instead of writing frame N of a
rig (counted from 0): the emulator then fails that grab, as a camera does whose frame is lost on the cable
(an environment variable, not a rig option, so that the capture resumes with the same rig).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_plugins.api import DeviceError, DeviceInfo, ShowReceipt, hookimpl, plugin_options

PLUGIN = "feed"
PROJECTOR_ID = "feed:projector0"


class FeedProjector:
    """The sim projector, writing the sim camera's raw frame of each shown pattern for the emulator."""

    def __init__(self, options: Mapping[str, Any], shared: dict[str, Any]) -> None:
        import cv2  # noqa: F401  (fail here, not at the first frame)

        from sssphase_plugins.sim_plugin import SimCamera, SimProjector, _bench

        feed = plugin_options(options, PLUGIN)
        if "image_file" not in feed:
            raise DeviceError(f"{PROJECTOR_ID}: set [options.feed] image_file (the emulated camera's image file)")
        self.path = Path(str(feed["image_file"]))
        bench = _bench(shared, options)  # the rig's sim scene: the sim turntable turns it
        self.sim, self.camera = SimProjector(bench), SimCamera(bench, {"raw": True})
        self.bits = bench.rig.sensor.bit_depth
        self.info = DeviceInfo(PROJECTOR_ID, "projector", PLUGIN, "sim projector feeding pylon's camera emulator", "projector0")
        self.frames = 0
        self.lose_at = int(os.environ.get("SSS_FEED_LOSE_FRAME_AT", "-1"))

    @property
    def resolution(self) -> tuple[int, int]:
        return self.sim.resolution

    def preload(self, sequence: list[tuple[str, Callable[[], np.ndarray]]]) -> None:
        self.sim.preload(sequence)

    def show(self, image: np.ndarray, *, tag: str = "", confirm: bool = True) -> ShowReceipt:
        import cv2

        receipt = self.sim.show(image, tag=tag, confirm=True)  # on screen now: the sim camera sees it
        self.frames += 1
        if self.frames - 1 == self.lose_at:
            self.path.unlink(missing_ok=True)
            return receipt
        raw = self.camera.grab().data  # (H, W) uint16 Bayer, the sensor's DN
        tmp = self.path.with_name(f".{self.path.stem}.tmp.png")
        if not cv2.imwrite(str(tmp), (raw.astype(np.uint16) << np.uint16(16 - self.bits))):
            raise DeviceError(f"{PROJECTOR_ID}: cannot write {tmp}")
        os.replace(tmp, self.path)
        return receipt

    def close(self) -> None:
        pass


class FeedProvider:
    kind = "projector"

    def discover(self) -> list[DeviceInfo]:
        return [DeviceInfo(PROJECTOR_ID, "projector", PLUGIN, "sim projector feeding pylon's camera emulator", "projector0")]

    def open(self, device_id: str, options: Mapping[str, Any], shared: dict[str, Any]) -> FeedProjector:
        if device_id != PROJECTOR_ID:
            raise DeviceError(f"the feed plugin has no projector {device_id!r}")
        return FeedProjector(options, shared)


@hookimpl
def sssphase_projectors() -> list[FeedProvider]:
    return [FeedProvider()]
