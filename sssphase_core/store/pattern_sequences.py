"""Pattern sequences: a video (MP4, MOV, AVI, MKV, WebM; read with OpenCV's FFmpeg), an animated image (GIF, APNG,
multi-page TIFF; Pillow) or a folder of pattern images (their names' natural order), as a projector plays it, one
pattern per frame.

:func:`open_sequence` reads the header only (frame size and count, frame rate) and refuses, before any frame is
decoded, a file that is not a sequence, far larger than the projector, or longer than :data:`MAX_FRAMES`;
:meth:`PatternSequence.frames` then decodes one frame at a time, each as :func:`~sssphase_core.store.imageio.read_pattern`
reads a still: values in [0, 1] (8-bit codes / 255), brought to the projector's size by ``resize``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import InputError

#: File suffixes read as videos (OpenCV's FFmpeg backend).
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg")
#: Suffixes of images that may hold several frames (Pillow).
ANIMATED_SUFFIXES = (".gif", ".png", ".apng", ".tif", ".tiff", ".webp")
#: The longest sequence relit (an hour at 25 frames/s).
MAX_FRAMES = 90_000
#: The frame rate written where a file gives none (a folder of images).
DEFAULT_FPS = 25.0
#: The files of a folder sequence that are frames (read as ``sss relight`` reads a still pattern); others are ignored.
FOLDER_SUFFIXES = (".png", ".tif", ".tiff", ".exr", ".npy", ".jpg", ".jpeg", ".bmp")


@dataclass
class PatternSequence:
    """A sequence file's header: ``count`` frames of ``size`` (W, H) at ``fps``, and how they are brought to the
    projector's ``projector_size`` (``resize``: fit, fill, stretch or "" for none)."""

    path: Path
    count: int
    fps: float
    size: tuple[int, int]
    projector_size: tuple[int, int]
    resize: str = ""
    video: bool = True
    #: a folder sequence's frame files, in order (None: a video or an animated image)
    files: list[Path] | None = None

    @property
    def name(self) -> str:
        return self.path.stem

    def frames(self, start: int = 0) -> Iterator[tuple[int, np.ndarray]]:
        """``(index, pattern)`` from frame ``start`` on, each (Hp, Wp, 3) float32 in [0, 1]. A video frame that does
        not decode ends the sequence early (a video's header may count more frames than it holds); an animated image's
        frame that does not decode, or is of another size than its first, is refused in one line (the frames before
        it stay relit)."""
        if self.files is not None:
            yield from self._folder_frames(start)
            return
        read = self._video_frames if self.video else self._image_frames
        for index, rgb in read(start):
            yield index, self._fitted(rgb)

    def _folder_frames(self, start: int) -> Iterator[tuple[int, np.ndarray]]:
        from sssphase_core.store.imageio import read_pattern

        for index, path in enumerate(self.files or []):
            if index >= start:
                pattern = read_pattern(path, self.projector_size, resize=self.resize)
                yield index, np.repeat(pattern[..., None], 3, -1) if pattern.ndim == 2 else pattern

    def _video_frames(self, start: int) -> Iterator[tuple[int, np.ndarray]]:
        import cv2

        capture = cv2.VideoCapture(str(self.path))
        try:
            for index in range(self.count):
                ok = capture.grab()
                if not ok:
                    return
                if index < start:
                    continue
                ok, bgr = capture.retrieve()
                if not ok or bgr is None:
                    return
                yield index, np.ascontiguousarray(bgr[..., ::-1]) if bgr.ndim == 3 else np.repeat(bgr[..., None], 3, -1)
        finally:
            capture.release()

    def _image_frames(self, start: int) -> Iterator[tuple[int, np.ndarray]]:
        from PIL import Image, ImageSequence

        with Image.open(self.path) as img:
            frames = ImageSequence.Iterator(img)
            for index in range(self.count):
                try:
                    frame = next(frames)
                    if frame.size != self.size:  # (a TIFF page's own header: before it is decoded)
                        raise InputError(f"--pattern {self.path}: frame {index + 1} is {frame.size[0]}x{frame.size[1]} "
                                         f"but the first is {self.size[0]}x{self.size[1]}: the frames of a sequence "
                                         "share one size")
                    if index < start:
                        continue
                    rgb = _frame_values(frame, self.path, index)
                except StopIteration:
                    return
                except InputError:
                    raise
                except (OSError, SyntaxError, ValueError, EOFError, Image.DecompressionBombError) as exc:
                    raise InputError(f"--pattern {self.path}: frame {index + 1} of {self.count} does not decode "
                                     f"({str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__}): the "
                                     "file is damaged or cut short") from None
                yield index, rgb

    def _fitted(self, rgb: np.ndarray) -> np.ndarray:
        """A frame (H, W, 3), 8-bit codes (a video's) or float32 values in [0, 1] (an animated image's) -> the
        projector's pattern (Hp, Wp, 3) float32 in [0, 1]."""
        from PIL import Image

        from sssphase_core.store.imageio import _resized

        if rgb.shape[1::-1] != self.projector_size:
            if not self.resize:  # (a stream whose frames change size part-way; the header's were checked)
                raise InputError(f"--pattern {self.path}: a frame is {rgb.shape[1]}x{rgb.shape[0]} but the projector is "
                                 f"{self.projector_size[0]}x{self.projector_size[1]} (pass --resize fit, fill or stretch)")
            if rgb.dtype == np.uint8:
                rgb = np.asarray(_resized(Image.fromarray(rgb), self.projector_size, self.resize))
            else:
                rgb = np.stack([np.asarray(_resized(Image.fromarray(np.ascontiguousarray(rgb[..., c])), self.projector_size,
                                                    self.resize)) for c in range(3)], axis=-1)
        return rgb.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else np.clip(rgb, 0, 1).astype(np.float32)


def _frame_values(frame: Any, path: Path, index: int) -> np.ndarray:
    """One decoded frame of an animated image or a multi-page TIFF -> (H, W, 3) float32 in [0, 1], read as a still
    pattern is (16-bit codes / 65535, floats as they are, alpha as opacity over black): through Pillow's RGB they
    were clipped to 8 bits (a 16-bit mid-grey relit as full white, a float one as black)."""
    from sssphase_core.store.imageio import _light_modes, _pil_pattern_values

    values = _pil_pattern_values(_light_modes(frame, path), f"{path} (frame {index + 1})")
    return np.repeat(values[..., None], 3, -1) if values.ndim == 2 else values


def is_sequence(path: Path | str) -> bool:
    """Whether ``path`` is a file to be read as a sequence: a video by its suffix, or an image holding more than
    one frame (an animated GIF or PNG, a multi-page TIFF); a still image is not."""
    path = Path(path)
    if path.is_dir():
        return bool(folder_frames(path))
    if not path.is_file():
        return False
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return True
    if suffix not in ANIMATED_SUFFIXES:
        return False
    from PIL import Image

    from sssphase_core.store.imageio import header_read

    try:
        with header_read(), Image.open(path) as img:  # the header (and, for a GIF, a scan of its frames' headers)
            return getattr(img, "n_frames", 1) > 1
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError):
        return False  # read as a still, which says what is wrong with it


def folder_frames(folder: Path) -> list[Path]:
    """A folder's frame files (:data:`FOLDER_SUFFIXES`, not hidden) in their names' natural order (frame2 before
    frame10)."""
    import re

    def natural(p: Path) -> list[Any]:
        return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]

    try:
        files = [p for p in folder.iterdir() if p.suffix.lower() in FOLDER_SUFFIXES and not p.name.startswith(".")
                 and p.is_file()]
    except OSError:
        return []
    return sorted(files, key=natural)


def open_sequence(path: Path | str, projector_size: tuple[int, int], resize: str = "") -> PatternSequence:
    """The header of the sequence at ``path`` checked against a ``projector_size`` (W, H) projector: frames of the
    projector's size unless ``resize``, at most 64 MP with it (4x the projector without); 1 to :data:`MAX_FRAMES`
    frames. Refused in one line naming the file and the problem."""
    from sssphase_core.store.files import check_input_file
    from sssphase_core.store.imageio import RESIZE_MODES, _max_pattern_pixels

    path = Path(path)
    if resize and resize not in RESIZE_MODES:
        raise InputError(f"--resize must be one of {', '.join(RESIZE_MODES)}, got {resize!r}")
    if path.is_dir():
        return _open_folder(path, projector_size, resize)
    check_input_file(path, "pattern")
    video = path.suffix.lower() in VIDEO_SUFFIXES
    count, fps, size = sequence_header(path)
    wp, hp = projector_size
    if count < 1:
        raise InputError(f"--pattern {path}: no frame could be read from it")
    if count > MAX_FRAMES:
        raise InputError(f"--pattern {path} holds {count:,} frames, more than the {MAX_FRAMES:,} relit at once: cut it "
                         "into parts")
    if size[0] * size[1] > _max_pattern_pixels(wp, hp, resize):
        raise InputError(f"--pattern {path}: its frames are {size[0]}x{size[1]}, far larger than the {wp}x{hp} projector: "
                         f"refused without decoding them (scale it down first{'' if resize else ', or pass --resize'})")
    if size != (wp, hp) and not resize:
        raise InputError(f"--pattern {path}: its frames are {size[0]}x{size[1]} but the projector is {wp}x{hp} "
                         "(pass --resize fit, fill or stretch)")
    if not (np.isfinite(fps) and 0.1 <= fps <= 1000):
        fps = DEFAULT_FPS
    return PatternSequence(path, count, float(fps), size, (wp, hp), resize, video)


def sequence_header(path: Path | str) -> tuple[int, float, tuple[int, int]]:
    """A sequence file's (frame count, frames per second, (W, H)) from its header, refused in one line when it does not
    read (a front end checks an upload with it before keeping it)."""
    path = Path(path)
    return _video_header(path) if path.suffix.lower() in VIDEO_SUFFIXES else _image_header(path)


def _video_header(path: Path) -> tuple[int, float, tuple[int, int]]:
    import cv2

    from sssphase_core.store.imageio import native_stderr_silenced

    with native_stderr_silenced():  # FFmpeg's own complaints about a damaged file; the line below says it
        capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise InputError(f"--pattern {path}: not a video OpenCV's FFmpeg can read")
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        capture.release()
    if size[0] < 1 or size[1] < 1:
        raise InputError(f"--pattern {path}: not a video OpenCV's FFmpeg can read (no frame size)")
    return count, fps, size


def _image_header(path: Path) -> tuple[int, float, tuple[int, int]]:
    from PIL import Image

    from sssphase_core.store.imageio import header_read

    try:
        with header_read(), Image.open(path) as img:
            count, size = int(getattr(img, "n_frames", 1)), img.size
            duration = img.info.get("duration")  # ms per frame (GIF, APNG)
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise InputError(f"cannot read pattern {path}: {exc}") from None
    fps = 1000.0 / duration if isinstance(duration, int | float) and duration > 0 else DEFAULT_FPS
    return count, fps, size


def _open_folder(folder: Path, projector_size: tuple[int, int], resize: str) -> PatternSequence:
    """A folder of pattern images as a sequence; its first frame read now, so that a frame size or format the others
    share is refused before any work."""
    from sssphase_core.store.imageio import read_pattern

    files = folder_frames(folder)
    if not files:
        raise InputError(f"--pattern {folder}: a folder with no pattern images ({', '.join(FOLDER_SUFFIXES)})")
    if len(files) > MAX_FRAMES:
        raise InputError(f"--pattern {folder} holds {len(files):,} frames, more than the {MAX_FRAMES:,} relit at once: "
                         "split it")
    from sssphase_core.store.imageio import frame_shape

    sizes = {f: frame_shape(f)[:2] for f in files}  # from the headers: a frame of another size refused before any work
    other = next((f for f in files if sizes[f] != sizes[files[0]]), None)
    if other is not None:
        (h0, w0), (h1, w1) = sizes[files[0]], sizes[other]
        raise InputError(f"--pattern {folder}: {other.name} is {w1}x{h1} but {files[0].name} is {w0}x{h0}: the frames of "
                         "a sequence share one size")
    first = read_pattern(files[0], projector_size, resize=resize)
    return PatternSequence(folder, len(files), DEFAULT_FPS, (first.shape[1], first.shape[0]), projector_size, resize,
                           video=False, files=files)
