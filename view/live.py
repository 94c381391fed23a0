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
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sssphase_core.capture.live import (
    CLIP_FRACTION,
    FrameStats,
    LiveDecode,
    decode_set,
    develop_live,
    frame_stats,
    pattern_spec,
    psp_set,
    sensor_full_scale,
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
    changed_by: int = 0  # the live page that set these last (0: none yet)


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
        self.full_scale = sensor_full_scale(self.rig)  # where the camera clips, on the sensor
        self.lock = threading.Lock()  # one daemon job at a time
        self._stack = contextlib.ExitStack()
        self.client: Any = None
        self.rig_id: str | None = None
        self.projector_size: tuple[int, int] = (0, 0)
        self.sequence = 0
        self.last: LiveFrame | None = None  # the latest frame, for the page's pixel probe
        self.opened_gain: float | None = None  # the camera's gain as the rig opened it (its frames say, where they do)
        self.gain_set = False  # whether the page has set the gain since

    def open(self) -> None:
        from sssphase_daemon.client import local_client

        if self.rig_id is not None:
            return
        try:
            self.client = self._stack.enter_context(local_client())
            opened = self.client.call("open_rig", camera=self.rig.camera, projector=self.rig.projector, turntable=None,
                                      options=dict(self.rig.options))
        except BaseException:  # (a client left in the stack would be opened again beside it by the next frame)
            self._forget()
            raise
        self.rig_id, self.projector_size = opened["rig"], tuple(opened["projector_size"])

    def close(self) -> None:
        with self.lock:
            self._close_rig()

    def _close_rig(self) -> None:
        if self.rig_id is not None and self.client is not None:
            with contextlib.suppress(Exception):
                self.client.call("close_rig", timeout_s=2.0, rig=self.rig_id)
        self._forget()

    def _forget(self) -> None:
        """Drop the client and its rig: the next frame connects and opens the rig again."""
        self.rig_id, self.client = None, None
        self.opened_gain, self.gain_set = None, False  # (opened again, the camera has the rig file's gain)
        with contextlib.suppress(Exception):  # (a daemon this started and that is gone: nothing left to stop)
            self._stack.close()
        self._stack = contextlib.ExitStack()

    def _capture(self, specs: list[dict[str, Any]]) -> list[Any]:
        """The frames of ``specs`` through the daemon, the rig opened first. A daemon gone, restarted (its token
        changed) or that closed the rig is forgotten, so that the next call connects anew; one restarted or that
        closed the rig is tried again at once (the page saw "missing or wrong token" while it reconnected)."""
        from sssphase_daemon import protocol
        from sssphase_daemon.client import DaemonError, DaemonUnavailable

        for attempt in range(2):
            try:
                self.open()
                return list(self.client.capture(self.rig_id, specs, deadline_s=LIVE_DEADLINE_S))
            except DaemonUnavailable:
                self._forget()
                raise
            except DaemonError as exc:
                if exc.code not in (protocol.UNAUTHENTICATED, protocol.NOT_FOUND, protocol.CLIENT_TIMEOUT):
                    raise
                self._forget()
                if attempt or exc.code == protocol.CLIENT_TIMEOUT:
                    raise
        raise AssertionError("unreachable")

    def _gain(self, settings: LiveSettings) -> float | None:
        """The gain to send with the next frames: the page's, else (the field emptied after a gain was set) the
        camera's gain as the rig opened it; a camera that does not say its gain is opened again instead."""
        if settings.gain is not None:
            self.gain_set = True
            return settings.gain
        if not self.gain_set:
            return None
        self.gain_set = False
        if self.opened_gain is None:
            self._close_rig()  # (opened again with the rig file's options)
        return self.opened_gain

    def _note_gain(self, frame: Any) -> None:
        gain = frame.header.get("meta", {}).get("gain")
        if not self.gain_set and self.opened_gain is None and isinstance(gain, int | float):
            self.opened_gain = float(gain)

    def frame(self, settings: LiveSettings) -> LiveFrame:
        """Project ``settings``' pattern and take one frame through the daemon."""
        with self.lock:
            gain = self._gain(settings)
            self.open()
            spec = pattern_spec(settings.pattern, self.projector_size, exposure=settings.exposure,
                                psp_frame=settings.psp_frame, image=settings.image, gain=gain)
            asked = time.time()
            (received,) = self._capture([spec])
            got = time.time()
            self._note_gain(received)
            image = develop_live(received, self.rig)  # linear, in units of the reference exposure (as captures are)
            self.sequence += 1
            stats = frame_stats(image * np.float32(settings.exposure), self.full_scale)
            self.last = LiveFrame(image, stats, self.sequence, asked, got, settings.exposure)
            return self.last

    def decode(self, settings: LiveSettings) -> tuple[LiveDecode, np.ndarray, float]:
        """Capture one PSP set (and white, black) and decode it -> (decode, white image, seconds); a pixel clipped in
        some PSP frame is ``SATURATED``."""
        with self.lock:
            gain = self._gain(settings)
            self.open()
            t0 = time.perf_counter()
            specs = [{**s, "exposure": float(settings.exposure), **({} if gain is None else {"gain": gain})}
                     for s in psp_set(self.projector_size, self.rig.gamma)]
            frames = self._capture(specs)
            self._note_gain(frames[0])
            images = {f.header["name"]: develop_live(f, self.rig) for f in frames}
            bayer = self.rig.bayer if self.rig.is_sim else None
            clip = CLIP_FRACTION * self.full_scale / float(settings.exposure)  # (the developed images' units)
            result = decode_set(images, self.projector_size, bayer, saturation=clip)
            return result, images["white"], time.perf_counter() - t0
