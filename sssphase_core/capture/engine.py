"""The daemon loop (:func:`run_capture`): opens the rig, moves the turntable, asks the daemon for each
view's frames and hands them to the view processor as they arrive; a view that fails or is interrupted
is marked so and aborted, never half-written. The client is anything with ``call`` and ``capture``
(:class:`ClientLike`), so this module never imports ZeroMQ."""

from __future__ import annotations

import contextlib
import errno
import itertools
import json
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

from sssphase_core import __version__
from sssphase_core.capture.plan import CaptureRequest, RigSpec, build_frames, plan_digest
from sssphase_core.capture.processing import FrameLike, ViewProcessor, write_sim_ground_truth
from sssphase_core.errors import DataError, InputError
from sssphase_core.store.locks import session_lock
from sssphase_core.store.session import Session, check_object_name

Progress = Callable[[int, int, int], None]  # (view, frames done, frames total)


class ClientLike(Protocol):
    def call(self, op: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]: ...

    def capture(self, rig: str, frames: list[dict[str, Any]], deadline_s: float | None = None) -> Iterable[FrameLike]: ...


MAX_BRACKETS = 8

#: Seconds between the pings that keep a rig open while the user turns the object by hand (a daemon closes a
#: rig whose client it has not heard from for 5 minutes; a prompt left waiting lost the rig and the capture).
KEEPALIVE_S = 30.0


@contextlib.contextmanager
def _keeping_rig_open(client: ClientLike) -> Iterator[None]:
    """Ping the daemon from a thread while the block waits for the user (the main thread sends nothing then)."""
    import threading

    stop = threading.Event()

    def beat() -> None:
        while not stop.wait(KEEPALIVE_S):
            try:
                client.call("ping", timeout_s=5.0)
            except Exception:  # a daemon that went away is reported by the next capture request
                return

    thread = threading.Thread(target=beat, name="sss-keep-rig", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


#: The shortest relative HDR exposure: a thousandth of the base exposure (a daemon refuses exposures under a
#: microsecond, which 1e-9 of a second-long base gave, after the session was begun).
MIN_BRACKET = 1e-3


#: The widest step between neighbouring HDR exposures (0.001,1 merges well; 0.01,256 and 0.001,64 did not).
MAX_BRACKET_STEP = 1024


def check_brackets(exposures: tuple[float, ...]) -> None:
    """HDR brackets: none, or 2 to ``MAX_BRACKETS`` distinct finite relative exposures in [``MIN_BRACKET``, 256]."""
    if not exposures:
        return
    ok = all(isinstance(e, int | float) and MIN_BRACKET <= e <= 256 for e in exposures)  # NaN fails too
    if not ok or not 2 <= len(exposures) <= MAX_BRACKETS or len(set(exposures)) != len(exposures):
        shown = ", ".join(f"{e:g}" for e in exposures[:MAX_BRACKETS + 1]) + (", ..." if len(exposures) > MAX_BRACKETS + 1 else "")
        raise InputError(f"HDR exposures must be 2 to {MAX_BRACKETS} distinct numbers in [{MIN_BRACKET:g}, 256], got "
                         f"{len(exposures)}: {shown}")
    ordered = sorted(exposures)
    for short, long in itertools.pairwise(ordered):
        if long / short > MAX_BRACKET_STEP:  # 0.001,64: where the long frame clips only the short one's noise is left
            raise InputError(f"HDR exposures {short:g} and {long:g} are {long / short:.0f}x apart: where the longer clips, "
                             f"the merge has only the shorter frame's noise, scaled {long / short:.0f}x (a session of "
                             f"noise); put brackets at most {MAX_BRACKET_STEP}x apart (add ones between)")


#: The sim rig options `sss capture` sets from its own options (--object, --preset, --seed, --views).
CAPTURE_FLAGS = {"object": "--object", "preset": "--preset", "seed": "--seed", "n_views": "--views"}


def check_rig_leaves_capture_options(rig_options: dict[str, Any], own: dict[str, Any]) -> None:
    """A rig file's ``[options]`` may repeat what the capture sets (``own``: :data:`CAPTURE_FLAGS`), not change it,
    and may not set ``view`` (the turntable's): its value had won, and a session named apple held an orange."""
    clash = [k for k in CAPTURE_FLAGS if k in rig_options and rig_options[k] != own[k]]
    if clash or "view" in rig_options:
        said = [f"{k} = {rig_options[k]!r} (the capture's {CAPTURE_FLAGS[k]} gives {own[k]!r})" for k in clash]
        said += ["view (the turntable sets it)"] if "view" in rig_options else []
        raise InputError(f"the rig file's [options] set {'; '.join(said)}: `sss capture` sets these itself; remove "
                         "them from the rig file")


#: The errors of a session store that cannot take more (zarr names no file): said with the session and --resume.
WRITE_FAILURES = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EIO}


def run_capture(client: ClientLike, req: CaptureRequest, rig: RigSpec | None = None, *,
                progress: Progress | None = None, ask_move: Callable[[int, float], None] | None = None) -> Session:
    """Capture ``req.views`` views of ``req.object`` into ``req.out/<object>`` (resuming if asked)."""
    check_object_name(req.object)
    if req.views < 1:
        raise InputError(f"--views must be >= 1, got {req.views}")
    check_brackets(req.hdr)
    rig = rig or RigSpec()
    options = dict(rig.options)
    if rig.is_sim:
        check_rig_leaves_capture_options(options, req.own_sim_options)
        options = {**req.own_sim_options, **options, **req.sim_options}
        if req.transport is not None:
            options["transport"] = req.transport
    with session_lock(Path(req.out), req.object):
        opened = client.call("open_rig", camera=rig.camera, projector=rig.projector, turntable=rig.turntable,
                             trigger=rig.trigger, options=options)
        try:
            return _capture_views(client, req, rig, options, opened, progress, ask_move)
        except OSError as exc:
            if exc.errno not in WRITE_FAILURES:
                raise
            raise DataError(f"cannot write the session {Path(req.out) / req.object}: {exc.strerror or exc} (the views "
                            "captured so far are kept: make room, then continue with --resume)") from None
        finally:
            try:
                client.call("close_rig", timeout_s=2.0, rig=opened["rig"])
            except Exception:  # the daemon may be gone (that is what the caller is told about)
                pass


def _check_resumable(session: Session, digest: str, n_views: int, rig_record: dict[str, Any]) -> None:
    """Refuse to resume ``session`` with another capture plan, view count or rig (before anything of it changes)."""
    if session.manifest.get("plan_digest") != digest or session.manifest.get("n_views") != n_views:
        raise InputError(f"{session.path} was captured with a different plan or view count: resume with the same options")
    from sssphase_core.sim.rig import COMPUTE_OPTIONS, FAULT_OPTIONS

    before, now = (json.loads(json.dumps(r, default=str)) for r in (session.manifest.get("rig", {}), rig_record))
    for r in (before, now):  # a fault injected into the sim devices (a camera that fails, then comes back), or the
        if isinstance(r.get("options"), dict):  # sim computing on a GPU, is no other rig
            r["options"] = {k: v for k, v in r["options"].items() if k not in FAULT_OPTIONS | COMPUTE_OPTIONS}
    changed = sorted({k for k in set(before) | set(now) if before.get(k) != now.get(k)})
    if changed:  # the new views would be captured on another rig (another seed, transport, camera) than the first
        raise InputError(f"{session.path} was captured with other rig settings ({', '.join(changed)} differ): "
                         "resume with the same --rig, --seed, --transport, --anisotropy and --preset, or capture into a new --out")


def _capture_views(client: ClientLike, req: CaptureRequest, rig: RigSpec, options: dict[str, Any],
                   opened: dict[str, Any], progress: Progress | None,
                   ask_move: Callable[[int, float], None] | None) -> Session:
    size = tuple(opened["projector_size"])
    camera_isp = None  # how the camera made its colour frames, when known (raw frames: ViewProcessor knows)
    if rig.is_sim:
        from sssphase_core.sim import rig_from_options

        preset = rig_from_options(options)  # the preset with the session's camera options (exposure)
        rig.patch = rig.patch or preset.patch
        rig.saturation = rig.saturation or preset.sensor.saturation(1.0)
        camera_isp = None if preset.sensor.three_chip else {  # a three-chip camera has no Bayer pipeline
            "demosaic": preset.sensor.demosaic, "median": preset.sensor.isp_median, "bayer": "RGGB"}
    if req.footprints and rig.patch is None:
        raise InputError("footprints need the crop size: set [processing] patch in the rig file")
    plan, frames, spacing = build_frames(req, size, rig.patch or 32, rig.gamma)
    digest = plan_digest(frames)
    rig_record = {**asdict(rig), "options": options}
    session = Session.create(req.out, req.object, resume=req.resume,
                             check_resume=lambda s: _check_resumable(s, digest, req.views, rig_record),
                             n_views=req.views, plan_digest=digest, rig=rig_record, devices=opened["devices"],
                             plugins=opened["plugins"], software={"sssphase": __version__},
                             plan=json.loads(plan.to_json()), reference_files=list(dict.fromkeys(f["params"]["file"] for f in frames if f["kind"] == "image")))
    n_dots = len({f["key"] for f in frames if f["kind"] == "dots"})  # dot-grid images kept (one per bracket set)
    for view in range(req.views):
        if session.status(view) == "complete":
            continue
        angle = 360.0 * view / req.views
        if rig.turntable:
            client.call("move", rig=opened["rig"], angle=angle)
        elif ask_move is not None:
            with _keeping_rig_open(client):
                ask_move(view, angle)
        writer = session.begin_view(view)
        try:
            proc = ViewProcessor(writer, plan, spacing, rig.patch or 32, rig, req, n_dots, camera_isp)
            deadline = getattr(client, "timeout_s", None)  # a device call that takes longer fails the view, naming it
            for i, (frame, spec) in enumerate(zip(client.capture(opened["rig"], frames, deadline_s=deadline), frames,
                                                  strict=False)):
                proc.add(frame, spec)
                if progress:
                    progress(view, i + 1, len(frames))
            proc.check_light()
            info = proc.finish()
            if rig.is_sim:
                write_sim_ground_truth(writer, req, view, frames, options)
        except BaseException:
            writer.abort()
            session.set_view(view, {"status": "interrupted"})
            raise
        writer.commit({"angle": angle, "frames": len(frames), **info})
        coverage = info.get("coverage", {})
        if coverage and not coverage.get("VALID"):  # "complete" and valid, with nothing in it to learn or relight
            causes = ", ".join(f"{k.lower().replace('_', ' ')} {v}" for k, v in coverage.items() if v)
            warnings.warn(f"{session.path} view {view}: no camera pixel decoded ({causes}): is the projector on and in "
                          "focus, the exposure right, the object in view? (the view is kept as captured: once the "
                          "rig is right, capture again into a new --out)", stacklevel=2)
    return session
