"""The capture engine: runs the capture plan per view through a daemon client and streams frames into
core processing as they arrive (PSP decoding, dot-grid footprint extraction), writing a session.

The client is passed in (anything with ``call(op, **args) -> dict`` and ``capture(rig, frames)``
yielding frames with ``name``, ``data`` and ``header``; see ``sssphase_daemon.client``), so this
module never imports ZeroMQ. Raw dot-grid frames are kept only on request. A view is written
atomically when complete, so an interrupted capture (Ctrl-C, a dead daemon, a full disk) resumes at
the first incomplete view; sim frames are seeded per (view, pattern), so a resumed capture is
bit-identical to an uninterrupted one.

One job per module, in the order frames flow: :mod:`~sssphase_core.capture.plan` (what to capture),
:mod:`~sssphase_core.capture.engine` (the daemon loop), :mod:`~sssphase_core.capture.processing` (frames
into a view: the one code path that writes views) and :mod:`~sssphase_core.capture.importer` (frames of
another rig through the same processing).
"""

from sssphase_core.capture.engine import ClientLike, Progress, run_capture
from sssphase_core.capture.importer import IMAGE_SUFFIXES, import_folder
from sssphase_core.capture.plan import (
    DEFAULT_HDR,
    DOT_SPACING_PER_PATCH,
    CaptureRequest,
    RigSpec,
    build_frames,
    dot_spacing_for,
    plan_digest,
)
from sssphase_core.capture.processing import (
    CropStream,
    FrameLike,
    ViewProcessor,
    develop_frame,
    write_sim_ground_truth,
)

__all__ = [
    "DEFAULT_HDR", "DOT_SPACING_PER_PATCH", "IMAGE_SUFFIXES", "CaptureRequest", "ClientLike", "CropStream", "FrameLike",
    "Progress", "RigSpec", "ViewProcessor", "build_frames", "develop_frame", "dot_spacing_for", "import_folder",
    "plan_digest", "run_capture", "write_sim_ground_truth",
]
