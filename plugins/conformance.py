"""The device conformance checks, for a plugin's own test suite: ``check_driver(kind, make)``.

Every driver sssphase ships is held to these (``tests/devices/test_dev_conformance.py``); a third-party plugin
runs the same from its repository, against a fake of its hardware library::

    from sssphase_plugins.conformance import check_driver

    def test_my_camera_follows_the_protocol():
        check_driver("camera", lambda: MyProvider(sdk=FakeSdk()).open("acme:0", {}, {}))

``make()`` opens one driver as the daemon does (through the provider). A failed check raises
:class:`ConformanceError` (an ``AssertionError``) saying which rule the driver broke. No test framework is needed.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from typing import Any

import numpy as np

from sssphase_plugins.drivers import (
    DEVICE_KINDS,
    Camera,
    DeviceError,
    DeviceInfo,
    Frame,
    PreloadingProjector,
    Projector,
    ShowReceipt,
    Trigger,
    Turntable,
    plain_meta,
)

PROTOCOLS: dict[str, type] = {"camera": Camera, "projector": Projector, "trigger": Trigger, "turntable": Turntable}


class ConformanceError(AssertionError):
    """A driver broke one of the protocol's rules (the message says which)."""


def _require(ok: object, rule: str) -> None:
    if not ok:
        raise ConformanceError(rule)


def _refuses(call: Callable[[], object], rule: str) -> None:
    """``call()`` must raise :class:`DeviceError` (any other outcome breaks ``rule``)."""
    try:
        call()
    except DeviceError:
        return
    except Exception as exc:  # noqa: BLE001  (the wrong exception is the finding)
        raise ConformanceError(f"{rule}: it raised {type(exc).__name__} ({exc}), not DeviceError") from None
    raise ConformanceError(f"{rule}: it raised nothing")


def check_identity(driver: Any, kind: str) -> None:
    """The driver follows ``kind``'s protocol and says who it is: a :class:`DeviceInfo` of that kind, an id
    ``<plugin>:<serial>`` and a model."""
    _require(kind in PROTOCOLS, f"kind must be one of {', '.join(DEVICE_KINDS)}, got {kind!r}")
    _require(isinstance(driver, PROTOCOLS[kind]), f"{type(driver).__name__} lacks a method of the {kind} protocol")
    info = getattr(driver, "info", None)
    _require(isinstance(info, DeviceInfo), f"driver.info is a {type(info).__name__}, not a DeviceInfo")
    _require(info.kind == kind, f"driver.info.kind is {info.kind!r}, not {kind!r}")
    _require(info.id.startswith(info.plugin + ":"), f"the id {info.id!r} does not start with its plugin {info.plugin!r}:")
    _require(bool(info.model), f"{info.id}: driver.info.model is empty")


def check_camera(camera: Any) -> None:
    """Exposures at or below 0 refused with DeviceError; ``grab()`` and ``stream(2)`` give :class:`Frame` records of
    one shape, (H, W) or (H, W, 3), finite, exposure above 0, sequence numbers distinct and rising, timestamps in
    order."""
    check_identity(camera, "camera")
    who = camera.info.id
    _refuses(lambda: camera.configure(exposure=0.0), f"{who}: configure(exposure=0) must raise DeviceError")
    _refuses(lambda: camera.configure(exposure=-1.0), f"{who}: configure(exposure=-1) must raise DeviceError")
    camera.configure(exposure=1.0)
    frames = [camera.grab(), *list(camera.stream(2))]
    _require(len(frames) == 3, f"{who}: stream(2) gave {len(frames) - 1} frames")
    for f in frames:
        _require(isinstance(f, Frame), f"{who}: a frame is a {type(f).__name__}, not a Frame")
        _require(isinstance(f.data, np.ndarray), f"{who}: Frame.data is a {type(f.data).__name__}, not an ndarray")
        _require(f.data.ndim == 2 or (f.data.ndim == 3 and f.data.shape[2] == 3),
                 f"{who}: a frame is (H, W) raw or (H, W, 3) RGB, got {f.data.shape}")
        _require(f.data.size and np.isfinite(f.data.astype(np.float64)).all(), f"{who}: a frame is empty or not finite")
        _require(f.exposure > 0, f"{who}: Frame.exposure must be above 0, got {f.exposure}")
        _require(f.data.dtype.kind in "iu" or f.data.ndim == 3,
                 f"{who}: an (H, W) frame is a raw Bayer mosaic of integer codes, got {f.data.dtype} (a mono camera "
                 "sends (H, W, 3), its grey in each channel)")
        try:
            plain_meta(f.meta, f"{who}: a frame")  # what the daemon sends in every frame's header
        except DeviceError as exc:
            raise ConformanceError(str(exc)) from None
        for name in ("sequence", "timestamp_ns"):
            try:
                operator.index(getattr(f, name))
            except TypeError:
                raise ConformanceError(f"{who}: Frame.{name} is {getattr(f, name)!r}, not a whole number") from None
    sequences = [f.sequence for f in frames]
    _require(sequences == sorted(set(sequences)), f"{who}: sequence numbers must be distinct and rising, got {sequences}")
    stamps = [f.timestamp_ns for f in frames]
    _require(stamps == sorted(stamps), f"{who}: timestamps must not go back, got {stamps}")
    _require(len({f.data.shape for f in frames}) == 1, f"{who}: frames of one camera share one shape")


def check_projector(projector: Any) -> None:
    """A positive integer resolution; ``show`` of grey and RGB patterns returns :class:`ShowReceipt` records with the
    tag, rising frame ids and on-screen times; patterns of another shape refused with DeviceError; a
    :class:`PreloadingProjector` shows a preloaded pattern."""
    check_identity(projector, "projector")
    who = projector.info.id
    w, h = projector.resolution
    # plain ints: the daemon converts numpy integers, but a plugin's own clients may not
    _require(type(w) is int and type(h) is int and w > 0 and h > 0,
             f"{who}: resolution must be two positive ints, got {(w, h)}")
    ramp = np.broadcast_to(np.linspace(0, 1, w, dtype=np.float32), (h, w))
    first = projector.show(ramp, tag="grey")
    second = projector.show(np.zeros((h, w, 3), np.float32), tag="rgb")
    _require(isinstance(first, ShowReceipt) and isinstance(second, ShowReceipt),
             f"{who}: show() must return a ShowReceipt, got {type(first).__name__}")
    _require((first.tag, second.tag) == ("grey", "rgb"), f"{who}: a receipt carries its pattern's tag")
    _require(second.frame_id > first.frame_id and second.on_screen_ns >= first.on_screen_ns,
             f"{who}: receipts' frame ids must rise and their on-screen times not go back")
    for wrong in (np.zeros((h + 1, w), np.float32), np.zeros((h, w, 4), np.float32), np.zeros(w, np.float32)):
        _refuses(lambda wrong=wrong: projector.show(wrong), f"{who}: show() of a {wrong.shape} pattern must raise "
                                                             "DeviceError (check_pattern does it)")
    if isinstance(projector, PreloadingProjector):
        projector.preload([("a", lambda: np.ones((h, w), np.float32))])
        _require(projector.show(np.ones((h, w), np.float32), tag="a").tag == "a", f"{who}: a preloaded pattern's tag")


def check_trigger(trigger: Any) -> None:
    """``fire()`` returns integer device timestamps, distinct and rising."""
    check_identity(trigger, "trigger")
    stamps = [trigger.fire() for _ in range(3)]
    _require(all(isinstance(t, int) for t in stamps) and stamps == sorted(set(stamps)),
             f"{trigger.info.id}: fire() returns integer timestamps, distinct and rising, got {stamps}")


def check_turntable(turntable: Any) -> None:
    """``move_to`` returns the angle reached, ``angle`` reads it, and angles are taken modulo a turn."""
    check_identity(turntable, "turntable")
    who = turntable.info.id
    reached = turntable.move_to(90.0)
    _require(math.isclose(reached, 90.0, abs_tol=0.01), f"{who}: move_to(90) returned {reached}")
    _require(math.isclose(turntable.angle, 90.0, abs_tol=0.01), f"{who}: angle reads {turntable.angle} after move_to(90)")
    turned = turntable.move_to(450.0) % 360
    _require(math.isclose(turned, 90.0, abs_tol=0.01), f"{who}: move_to(450) is 90 modulo a turn, got {turned}")


CHECKS: dict[str, Callable[[Any], None]] = {"camera": check_camera, "projector": check_projector,
                                            "trigger": check_trigger, "turntable": check_turntable}


def check_driver(kind: str, make: Callable[[], Any]) -> None:
    """Open a driver with ``make()``, hold it to ``kind``'s checks, close it, and check that closing it again,
    and closing a fresh one twice, is harmless."""
    if kind not in CHECKS:
        raise ConformanceError(f"kind must be one of {', '.join(CHECKS)}, got {kind!r}")
    driver = make()
    try:
        CHECKS[kind](driver)
    finally:
        driver.close()
    driver.close()
    fresh = make()
    fresh.close()
    fresh.close()
