"""Pattern sequences relit for the page in the background (a video or an animated image uploaded to ``sss view``):
each a :class:`SequenceJob` whose progress the page polls, run by ``sss relight``'s own sequence runner
(:func:`~sssphase_core.relight.sequence.relight_sequence`) on the view's relight thread."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

from sssphase_core.errors import SssError
from sssphase_core.relight.runner import Narrator

log = logging.getLogger("sssphase.view")

#: Sequence relights whose progress and frames the view keeps (the oldest finished are forgotten first).
MAX_JOBS = 20


@dataclass
class SequenceJob:
    """A sequence relit for the page: ``status`` waiting, running, done, failed or stopped (``error`` says why), the
    ``step`` under way (the first frame's footprints, then the frames) and its count ``done`` of ``total``, and once
    done the URLs of its display ``frames`` (in order), its ``video`` and ``fps``."""

    id: str
    upload: str = ""  # the uploaded sequence's name (kept while the job runs)
    status: str = "waiting"
    step: str = ""
    done: int = 0
    total: int = 0
    fps: float = 25.0
    frames: list[str] = field(default_factory=list)
    video: str | None = None
    error: str = ""
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0
    #: asked to stop (the page's stop button): the relight stops at its next progress report, its frames kept
    stop: bool = False

    @property
    def finished(self) -> bool:
        return self.status in ("done", "failed", "stopped")


class JobNotes(Narrator):
    """The relight's lines for the page (not its "wrote ..." lines: the page shows the frames) and its progress."""

    def __init__(self, job: SequenceJob) -> None:
        self.job = job

    def say(self, text: str, warning: str = "") -> None:
        if not text.startswith("wrote "):
            self.job.notes.append(text)

    def task(self, label: str) -> Any:
        def progress(done: int, total: int) -> None:
            self.job.step, self.job.done, self.job.total = label, done, total
            if self.job.stop:
                raise Stopped(f"stopped at {done} of {total} ({label}): the frames relit so far are kept, and relighting "
                              "the same video again relights only the rest")
        return progress


class Stopped(SssError):
    """A sequence relight the page asked to stop."""


def run_sequence_job(job: SequenceJob, relight: Any, view: int, files_url: str) -> None:
    """Run ``relight(narrator) -> RelightResult`` (of one ``view``) for ``job`` and record its outcome; the frames'
    URLs are ``files_url/<folder>/<frame>`` and the video's ``files_url/<folder>.mp4``. An :class:`SssError` is the
    job's one-line error; anything else is logged with its stack and named as an internal error."""
    job.status, started = "running", time.perf_counter()
    try:
        result = relight(JobNotes(job))
        video = result.videos[view]
        folder = video.with_suffix("")
        frames = sorted(folder.glob("*_display.png"))
        job.frames = [f"{files_url}/{folder.name}/{f.name}" for f in frames]
        job.video = f"{files_url}/{video.name}"
        job.done = job.total = len(frames)
        job.fps = result.fps or job.fps
        job.status = "done"
    except Stopped as exc:
        job.error, job.status = str(exc), "stopped"
    except SssError as exc:
        job.error, job.status = str(exc), "failed"
    except Exception as exc:  # noqa: BLE001 (the page gets one line; the log keeps the stack)
        log.exception("relighting a sequence failed")
        job.error, job.status = f"relighting failed: {type(exc).__name__}: {exc} (the server's log has the details)", "failed"
    finally:
        job.seconds = time.perf_counter() - started


def forget_old_jobs(jobs: dict[str, SequenceJob]) -> None:
    """Keep at most :data:`MAX_JOBS`: the oldest finished ones go (a running one is kept)."""
    finished = [key for key, job in jobs.items() if job.finished]  # (insertion order: oldest first)
    for key in finished[: max(0, len(jobs) - MAX_JOBS)]:
        del jobs[key]
