"""Relighting under a pattern sequence: a video, an animated image or a folder of images played by the projector,
relit frame by frame (``sss relight SESSION --pattern clip.mp4``).

A view's first frames compute its footprints as any relight does and keep its eigen-footprints
(:mod:`~sssphase_core.relight.lowrank`); every later frame is relit from those alone, a few filters per colour, so
a sequence costs one footprint pass and then a fraction of a second per frame at the CPU preset. Frames are
relit in chunks that fit :data:`CHUNK_BYTES` and written as they come, into
``OUT/<object>_v<view>_<name>_<backend>/`` (16-bit linear PNG or EXR, and a display PNG each); the display frames
are then joined into ``OUT/<object>_v<view>_<name>_<backend>.mp4`` at the sequence's frame rate. An interrupted run
keeps its frames, and the same command again relights only the missing ones (the folder's ``sequence.json``
records what they were relit with; other settings are refused rather than mixed in).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.relight.choices import MODEL_FREE, uses_decoder, widen_for
from sssphase_core.relight.runner import (
    NAME_BYTES,
    OUTPUT_SUFFIX_BYTES,
    Narrator,
    RelightResult,
    check_decoder_fits,
    check_relight_options,
    choose_views,
    relight_one,
    resolve_backend,
    widen_line,
    write_relit,
)
from sssphase_core.relight.views import RelightView, load_view
from sssphase_core.store.pattern_sequences import MAX_FRAMES, PatternSequence, open_sequence
from sssphase_core.store.session import Session

#: The relit frames held in memory at once (float32; at least one frame, at most :data:`MAX_CHUNK_FRAMES`: an
#: interrupted run loses at most the chunk it was in).
CHUNK_BYTES, MAX_CHUNK_FRAMES = 256 << 20, 32
#: The record of what a folder's frames were relit with.
RECORD = "sequence.json"


class _Quiet(Narrator):
    """Says nothing but warnings: the lines a chunk repeats (the calibration, "wrote ...") once per frame."""

    def __init__(self, say: Narrator) -> None:
        self.outer, self.warned = say, set()

    def say(self, text: str, warning: str = "") -> None:
        if warning and text not in self.warned:
            self.warned.add(text)
            self.outer.say(text, warning)


def check_sequence_name(sequence: PatternSequence, rv: RelightView) -> None:
    """Refuse a sequence whose name would make its output files' names unusable: a control character, or longer
    than a file name may be with the object, view, frame number and backend around it."""
    name = sequence.name
    if any(ord(ch) < 32 or ord(ch) == 127 for ch in name):
        raise InputError(f"--pattern {str(sequence.path)!r}: its name holds a control character (a newline, a tab), which "
                         "would reach the output files' names: rename it")
    room = NAME_BYTES - len(f"{rv.object}_v{rv.view}_".encode()) - len(b"-000000") - OUTPUT_SUFFIX_BYTES
    if len(name.encode()) > room:
        raise InputError(f"--pattern {name[:40]}...: a sequence named with {len(name.encode())} bytes makes its output "
                         f"file names longer than a file name may be ({NAME_BYTES} bytes): rename it to at most "
                         f"{max(room, 1)} bytes")


def frame_name(sequence: PatternSequence, index: int) -> str:
    """The pattern name of frame ``index``: the files' ``<object>_v<view>_<name>-000123_<backend>``."""
    return f"{sequence.name}-{index:06d}"


def _record(session: Session, view: int, sequence: PatternSequence, backend: str, checkpoint: Path | None,
            widen: float | None, formats: tuple[str, ...]) -> dict:
    stats = [f.stat() for f in (sequence.files if sequence.files is not None else [sequence.path])]
    return {"written_by": "sssphase", "session": str(session.path.resolve()), "view": view, "backend": backend,
            "checkpoint": str(checkpoint.resolve()) if checkpoint else None, "widen": widen, "formats": list(formats),
            "pattern": {"file": str(sequence.path.resolve()), "bytes": sum(st.st_size for st in stats),
                        "mtime_ns": max(st.st_mtime_ns for st in stats), "frames": sequence.count,
                        "resize": sequence.resize}}


def _claim_folder(folder: Path, record: dict) -> None:
    """Make ``folder`` this sequence's: new, or holding frames relit with the very same ``record`` (resumed);
    refused in one line where it holds anything else."""
    path = folder / RECORD
    if folder.exists() and any(folder.iterdir()):
        try:
            held = json.loads(path.read_text())
        except (OSError, ValueError):
            raise InputError(f"{folder} holds files that no relight of this sequence wrote (no readable {RECORD}): "
                             "choose another --out") from None
        if held != record:
            differs = sorted(k for k in set(held) | set(record) if held.get(k) != record.get(k)) if isinstance(held, dict) else ["all"]
            raise InputError(f"{folder} holds frames relit with other settings ({', '.join(differs)} differ): remove the "
                             "folder to relight them again, or choose another --out")
        return
    folder.mkdir(parents=True, exist_ok=True)
    from sssphase_core.store.files import write_bytes

    write_bytes(path, json.dumps(record, indent=1).encode())


def _done(folder: Path, rv: RelightView, sequence: PatternSequence, backend: str) -> set[int]:
    """The frames already relit into ``folder`` (their display PNG, written last, is there)."""
    prefix, suffix = f"{rv.object}_v{rv.view}_{sequence.name}-", f"_{backend}_display.png"
    done = set()
    for p in folder.glob(f"*{suffix}"):
        number = p.name[len(prefix):-len(suffix)] if p.name.startswith(prefix) else ""
        if number.isdigit():
            done.add(int(number))
    return done


def _chunks(sequence: PatternSequence, skip: set[int], size: int, first: int) -> Iterator[list[tuple[int, np.ndarray]]]:
    """The frames not in ``skip``, ``first`` of them and then ``size`` at a time."""
    chunk: list[tuple[int, np.ndarray]] = []
    for index, pattern in sequence.frames():
        if index in skip:
            continue
        chunk.append((index, pattern))
        if len(chunk) == first:
            yield chunk
            chunk, first = [], size
    if chunk:
        yield chunk


def write_video(frames: list[Path], path: Path, fps: float) -> Path:
    """The display PNGs ``frames`` joined into an MPEG-4 video at ``fps``, written under a temporary name and
    renamed once complete."""
    import cv2

    from sssphase_core.store.files import atomic_path

    first = cv2.imread(str(frames[0]))
    if first is None:
        raise InputError(f"{frames[0]} cannot be read: remove it and relight again to remake it")
    h, w = first.shape[:2]
    with atomic_path(path, ".mp4") as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
        if not writer.isOpened():
            raise InputError(f"cannot write the video {path}: OpenCV's FFmpeg has no MPEG-4 encoder here")
        try:
            for frame in frames:
                image = cv2.imread(str(frame))
                if image is None or image.shape[:2] != (h, w):
                    raise InputError(f"{frame} cannot be read: remove it and relight again to remake it")
                writer.write(image)
        finally:
            writer.release()
    return path


def relight_sequence(session: Path | str | Session, pattern: Path | str, *, backend: str = "auto",
                     checkpoint: Path | str | None = None, out: Path | str = Path("relit"),
                     views: str | list[int] | None = "", resize: str = "", chunk: int = 1024, device: str = "cpu",
                     cache: bool = True, formats: str = "png", widen: float | None = None,
                     narrator: Narrator | None = None, precision: str = "auto",
                     max_frames: int | None = None) -> RelightResult:
    """Relight a session's views under every frame of the sequence ``pattern`` (a video or an animated image) with
    ``backend`` (as :func:`~sssphase_core.relight.runner.relight_session`), writing each view's frames and its video.
    ``cache``: a model backend's later frames come from the view's eigen-footprints, which need it. ``max_frames``:
    a front end's own limit below :data:`~sssphase_core.store.pattern_sequences.MAX_FRAMES` (a web page's upload)."""
    from sssphase_core.store.session import claim_output

    out, say = Path(out), narrator or Narrator()
    chosen_formats = check_relight_options(out, [str(pattern)], resize, formats, device, precision)
    backend, ckpt = resolve_backend(backend, checkpoint, say)
    if not cache and backend not in MODEL_FREE:
        raise InputError("a pattern sequence is relit from the view's eigen-footprints, computed on its first frames and "
                         "kept in OUT/cache: leave out --no-cache (remove OUT/cache to compute them again)")
    widen = widen_for(backend, widen) if backend not in MODEL_FREE else None
    s = session if isinstance(session, Session) else Session.open(session)
    check_decoder_fits(ckpt, [backend], [s])
    result = RelightResult(backend, ckpt)
    for v in choose_views(s, views, say):
        rv = load_view(s, v)
        sequence = open_sequence(pattern, rv.proj.projector_size, resize)
        if max_frames is not None and sequence.count > max_frames:
            raise InputError(f"--pattern {pattern} holds {sequence.count:,} frames, more than the {max_frames:,} relit "
                             f"here: `sss relight SESSION --pattern FILE` takes up to {MAX_FRAMES:,}")
        check_sequence_name(sequence, rv)
        if not result.patterns:
            claim_output(out, [s])
            say.say(f"{sequence.path.name}: {sequence.count:,} frames of {sequence.size[0]}x{sequence.size[1]} at "
                    f"{sequence.fps:g} frames/s; backend {backend}" + (f", decoder {ckpt}" if ckpt and uses_decoder(backend) else ""))
            if line := widen_line({backend: widen}):
                say.say(line)
        result.patterns = [sequence.name]
        _relight_view_sequence(s, rv, sequence, backend, ckpt, out, chosen_formats, chunk=chunk, device=device,
                               cache=cache, widen=widen, say=say, result=result, precision=precision)
    return result


def _relight_view_sequence(s: Session, rv: RelightView, sequence: PatternSequence, backend: str, ckpt: Path | None,
                           out: Path, formats: tuple[str, ...], *, chunk: int, device: str, cache: bool,
                           widen: float | None, say: Narrator, result: RelightResult, precision: str) -> None:
    """One view's frames relit (those not already in its folder) and its video written, the folder locked meanwhile
    (two runs into one folder would relight the same frames and write the video twice at once)."""
    from sssphase_core.store.locks import folder_lock

    folder = out / f"{rv.object}_v{rv.view}_{sequence.name}_{backend}"
    with folder_lock(folder, f"{folder} is being relit by {{holder}} (another `sss relight` of this sequence): wait for "
                             "it, or choose another --out"):
        _relight_frames(s, rv, sequence, backend, ckpt, out, folder, formats, chunk=chunk, device=device, cache=cache,
                        widen=widen, say=say, result=result, precision=precision)


def _relight_frames(s: Session, rv: RelightView, sequence: PatternSequence, backend: str, ckpt: Path | None,
                    out: Path, folder: Path, formats: tuple[str, ...], *, chunk: int, device: str, cache: bool,
                    widen: float | None, say: Narrator, result: RelightResult, precision: str) -> None:
    _claim_folder(folder, _record(s, rv.view, sequence, backend, ckpt, widen, formats))
    done = _done(folder, rv, sequence, backend)
    if done:
        rest = "relighting the rest" if len(done) < sequence.count else "none left to relight"
        say.say(f"{rv.object} view {rv.view}: {len(done):,} of {sequence.count:,} frames already relit in {folder}: "
                f"{rest}")
    h, w = rv.white.shape[:2]
    per_chunk = max(1, min(MAX_CHUNK_FRAMES, CHUNK_BYTES // (h * w * 3 * 4)))
    quiet = _Quiet(say)
    # a model's first frame computes the footprints and keeps the eigen-footprints the rest are relit from (a full
    # pass costs as much per pattern as per footprint); model-free backends splat every chunk
    chunks = _chunks(sequence, done, per_chunk, per_chunk if backend in MODEL_FREE else 1)
    count = len(done)

    def relight(frames: list[tuple[int, np.ndarray]], told: Narrator) -> None:
        nonlocal count
        names, pats = [frame_name(sequence, i) for i, _ in frames], [p for _, p in frames]
        relit, result.mixes[rv.view] = relight_one(s, rv, pats, backend, ckpt, out, chunk=chunk, device=device,
                                                    cache=cache, say=told, widen=widen, precision=precision)
        result.images.extend(write_relit(rv, relit, names, pats, folder, backend, formats, quiet))
        count += len(frames)

    if not done:  # the first chunk computes the footprints with its own progress, and says how it calibrated
        first = next(chunks, None)
        if first is not None:
            relight(first, say)
    with say.bar():  # then the frames from the eigen-footprints
        progress = say.task(f"{rv.object} view {rv.view}: {sequence.name}")
        progress(count, sequence.count)
        for frames in chunks:
            relight(frames, quiet)
            progress(count, sequence.count)
    displays = sorted(folder.glob(f"{rv.object}_v{rv.view}_{sequence.name}-*_{backend}_display.png"))
    if not displays:
        raise InputError(f"--pattern {sequence.path}: no frame could be decoded")
    video = write_video(displays, out / f"{folder.name}.mp4", sequence.fps)
    result.videos[rv.view], result.fps = video, sequence.fps
    say.say(f"wrote {len(displays):,} frames to {folder} and the video {video} ({sequence.fps:g} frames/s)")
