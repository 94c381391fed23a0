"""The rig as the live view sees it: one daemon rig, one frame or one PSP set at a time.

:class:`LiveRig` owns a client of the local daemon (started as ``sss capture`` starts one when none runs)
and a rig opened on it; :meth:`LiveRig.frame` projects a pattern and returns the developed frame with its
statistics, :meth:`LiveRig.decode` captures one PSP set and decodes it. What they compute is
``sssphase_core.capture.live``'s; this module only runs it against the daemon, from a worker thread.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sssphase_core.capture.live import (
    FrameStats,
    LiveDecode,
    decode_set,
    develop_live,
    frame_stats,
    pattern_spec,
    psp_set,
)
from sssphase_core.capture.plan import RigSpec

#: A device call of the live view that takes longer fails with the device named on the page (the daemon
#: allows no less than the camera declares: the simulator at the paper preset takes minutes).
LIVE_DEADLINE_S = 30.0


@dataclass
class LiveSettings:
    """What the page asked for: the pattern on the projector, the exposure, live decode on or off."""

    pattern: str = "white"
    exposure: float = 1.0
    gain: float | None = None  # the camera's gain in its driver's unit (None: as the rig opened it)
    psp_frame: int = 0
    decode: bool = False
    image: np.ndarray | None = field(default=None, repr=False)  # an uploaded pattern at the projector's size


@dataclass
class LiveFrame:
    image: np.ndarray  # (H, W, 3) linear, in units of the reference exposure; times the exposure: on the sensor
    stats: FrameStats
    sequence: int
    requested_s: float  # host time (time.time) the frame was asked for
    received_s: float  # ... and arrived from the daemon
    exposure: float = 1.0


class LiveRig:
    """A rig opened on the local daemon for live use (its devices are the rig file's, else the sim rig's)."""

    def __init__(self, rig: RigSpec | None = None) -> None:
        self.rig = rig or RigSpec()
        self.lock = threading.Lock()  # one daemon job at a time
        self._stack = contextlib.ExitStack()
        self.client: Any = None
        self.rig_id: str | None = None
        self.projector_size: tuple[int, int] = (0, 0)
        self.sequence = 0
        self.last: LiveFrame | None = None  # the latest frame, for the page's pixel probe

    def open(self) -> None:
        from sssphase_daemon.client import local_client

        if self.rig_id is not None:
            return
        self.client = self._stack.enter_context(local_client())
        opened = self.client.call("open_rig", camera=self.rig.camera, projector=self.rig.projector, turntable=None,
                                  options=dict(self.rig.options))
        self.rig_id, self.projector_size = opened["rig"], tuple(opened["projector_size"])

    def close(self) -> None:
        with self.lock:
            if self.rig_id is not None and self.client is not None:
                with contextlib.suppress(Exception):
                    self.client.call("close_rig", timeout_s=2.0, rig=self.rig_id)
            self._forget()

    def _forget(self) -> None:
        """Drop the client and its rig: the next frame connects and opens the rig again."""
        self.rig_id, self.client = None, None
        with contextlib.suppress(Exception):  # (a daemon this started and that is gone: nothing left to stop)
            self._stack.close()
        self._stack = contextlib.ExitStack()

    @contextlib.contextmanager
    def _reconnecting(self) -> Iterator[None]:
        """Forget the daemon when a call shows it gone, restarted (its token changed) or its rig closed, so that the
        next frame connects anew: without this the live view showed "missing or wrong token" until restarted."""
        from sssphase_daemon import protocol
        from sssphase_daemon.client import DaemonError, DaemonUnavailable

        try:
            yield
        except DaemonUnavailable:
            self._forget()
            raise
        except DaemonError as exc:
            if exc.code in (protocol.UNAUTHENTICATED, protocol.NOT_FOUND, protocol.CLIENT_TIMEOUT):
                self._forget()
            raise

    def frame(self, settings: LiveSettings) -> LiveFrame:
        """Project ``settings``' pattern and take one frame through the daemon."""
        with self.lock, self._reconnecting():
            self.open()
            spec = pattern_spec(settings.pattern, self.projector_size, exposure=settings.exposure,
                                psp_frame=settings.psp_frame, image=settings.image, gain=settings.gain)
            asked = time.time()
            (received,) = list(self.client.capture(self.rig_id, [spec], deadline_s=LIVE_DEADLINE_S))
            got = time.time()
            image = develop_live(received, self.rig)  # linear, in units of the reference exposure (as captures are)
            self.sequence += 1
            self.last = LiveFrame(image, frame_stats(image * np.float32(settings.exposure)), self.sequence, asked, got,
                                  settings.exposure)
            return self.last

    def decode(self, settings: LiveSettings) -> tuple[LiveDecode, np.ndarray, float]:
        """Capture one PSP set (and white, black) and decode it -> (decode, white image, seconds)."""
        with self.lock, self._reconnecting():
            self.open()
            t0 = time.perf_counter()
            specs = [{**s, "exposure": float(settings.exposure), **({} if settings.gain is None else {"gain": settings.gain})}
                     for s in psp_set(self.projector_size, self.rig.gamma)]
            images = {f.header["name"]: develop_live(f, self.rig)
                      for f in self.client.capture(self.rig_id, specs, deadline_s=LIVE_DEADLINE_S)}
            bayer = self.rig.bayer if self.rig.is_sim else None
            result = decode_set(images, self.projector_size, bayer)
            return result, images["white"], time.perf_counter() - t0
