"""A session relit, its geometry, or its evaluation against reference captures, as every front end runs
them (``sss relight``, ``sss geometry``, ``sss eval relight``, a notebook, a web view): the checks before
any work, the patterns and backend chosen, the footprint caches, the outputs written, each returned as a
result.

Narration and progress go through a :class:`Narrator` (the default says nothing): its ``say`` gets each
line the CLI prints, as it happens; ``bar``, ``task`` and ``status`` frame the long steps. Core imports
neither rich nor typer; the CLI's narrator draws with them.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.learning.runlog import one_version
from sssphase_core.relight.cache import (
    cache_stem,
    footprint_bytes,
    kept,
    saved_if_interrupted,
    view_caches,
)
from sssphase_core.relight.choices import (
    BLENDS,
    MODEL_FREE,
    WIDEN_MEMBERS,
    check_backends,
    needs_checkpoint,
    unused_widen_note,
    uses_decoder,
    widen_for,
)
from sssphase_core.relight.evaluation import (
    aggregate,
    comparison_figure,
    evaluate_view,
    lpips_note,
    metrics_table,
    relight_metrics,
)
from sssphase_core.relight.images import check_image_formats, display_scale, read_pattern, write_images
from sssphase_core.relight.views import finest_psp_period, has_captured_transport, has_references, load_view
from sssphase_core.store.session import Session

if TYPE_CHECKING:  # the work's modules import torch: loaded once the checks have passed
    from sssphase_core.processing.triangulation import StereoCalibration, Triangulated
    from sssphase_core.relight.engine import FootprintSource
    from sssphase_core.relight.transport import DotTransport
    from sssphase_core.relight.views import RelightView

#: ``evaluate_sessions``' backends unless others are named (measured left out where no view has crops).
EVAL_BACKENDS = "none,analytic,measured"


class Narrator:
    """How a run talks to its front end. This one says nothing; the CLI's prints with rich, a notebook
    may collect the lines. Subclass it or give any object with these four methods."""

    def say(self, text: str, warning: str = "") -> None:
        """One line for the user; ``warning``: a part of it worth highlighting."""

    @contextmanager
    def bar(self) -> Iterator[None]:
        """A progress display, open while its tasks (:meth:`task`) run."""
        yield

    def task(self, label: str) -> Callable[[int, int], None]:
        """A task of the open progress display -> its ``progress(done, total)``."""
        return lambda done, total: None

    @contextmanager
    def status(self, label: str) -> Iterator[None]:
        """A step without a count (a spinner)."""
        yield


def choose_views(session: Session, views: str | Sequence[int] | None = None, say: Narrator | None = None) -> list[int]:
    """The complete views ``views`` names (comma-separated text or numbers; empty or None: all), each once,
    checked before any is relit; with all views, ``say`` is told which incomplete ones are left out. A manifest
    without its rig record (another program's, or edited) is read with defaults, with a warning."""
    if "rig" not in session.manifest:  # (`sss validate` names it too)
        from sssphase_core.store.session import RIG_UNKNOWN

        warnings.warn(f"{session.path}: its manifest has no rig record: {RIG_UNKNOWN}", UserWarning, stacklevel=2)
    if not views:
        states = {int(v): session.status(int(v)) for v in session.manifest["views"]}
        left = ", ".join(f"view {v}: {st}" for v, st in sorted(states.items()) if st != "complete")
        if not session.views():  # a capture that was interrupted: nothing to relight, and saying nothing misleads
            raise InputError(f"session {session.path} has no complete view ({left or 'no views'}); "
                             f"`sss validate {session.path}` says more, {session.completes_it()}")
        if left and say is not None:
            say.say(f"{session.name}: left out, not complete ({left}); {session.completes_it()}", warning="left out")
        return session.views()
    try:
        numbers = [int(v) for v in views.split(",") if v.strip()] if isinstance(views, str) else [int(v) for v in views]
    except ValueError:
        raise InputError(f"--views must be comma-separated integers, got {views!r}") from None
    chosen = list(dict.fromkeys(numbers))  # a view named twice runs once
    if not chosen:
        raise InputError(f"--views {views!r} names no view: give comma-separated view numbers, or leave it out for all")
    missing = [v for v in chosen if v not in session.views()]
    if missing:  # before any view is relit
        raise InputError(f"session {session.path} has no complete view {', '.join(map(str, missing))} "
                         f"(complete: {', '.join(map(str, session.views())) or 'none'})")
    return chosen


def same_pattern(pattern: np.ndarray, reference: np.ndarray) -> bool:
    """Whether a pattern (Hp, Wp[, 3]) is the one a session's reference was captured under (within an 8-bit
    step): only then is the relit image scored against that capture, whatever the pattern file is called."""
    a, b = np.asarray(pattern, np.float32), np.asarray(reference, np.float32)
    if a.ndim != b.ndim:
        a, b = (x if x.ndim == 3 else np.repeat(x[..., None], 3, axis=-1) for x in (a, b))
    return a.shape == b.shape and bool(np.abs(a - b).max(initial=0.0) <= 1 / 255)


def lowrank_path(out: Path, session: Session, rv: RelightView, backend: str, checkpoint: Path | str | None,
                 widen: float | None = None, precision: str = "fp32") -> Path:
    """The eigen-footprint cache of a view relit with ``backend`` (all its members and its calibration, whose members
    are stretched ``widen`` x along x, y and both, and softened; its decoder inferring in ``precision``), named as
    :func:`cache_path` names footprint caches."""
    stem = cache_stem(session, rv, backend, checkpoint, precision, uses_decoder(backend))
    return out / "cache" / f"{stem}{f'_w{widen:g}' if widen else ''}_lowrank.npz"


def parse_formats(formats: str | Sequence[str]) -> tuple[str, ...]:
    """``png``, ``exr`` or both (``"png,exr"`` or a sequence), each once, checked (EXR needs its bindings)."""
    items = formats.split(",") if isinstance(formats, str) else list(formats)
    chosen = check_image_formats(tuple(dict.fromkeys(f.strip().lower() for f in items if f.strip())))
    if "exr" in chosen:
        from sssphase_core.store import exr

        if not exr.available():
            raise InputError(f"--format exr: {exr.MISSING}")
    return chosen


def _plugin_takes_checkpoint(backend: str) -> bool:
    """Whether ``backend`` is a plugin's whose factory takes a ``checkpoint`` (its own trained weights)."""
    from sssphase_core.learning.backends import BUILTIN, accepted_options

    return backend not in BUILTIN and "checkpoint" in accepted_options(backend, {"checkpoint": None})


def resize_note(path: str, size: tuple[int, int], mode: str) -> tuple[str, str] | None:
    """``(line, warning)`` when a pattern file was resized (the warning, when ``stretch`` changed its aspect
    ratio), else None."""
    from sssphase_core.store.imageio import shown_shape

    h, w = shown_shape(Path(path))[:2]  # from the file's header (PNG/TIFF, .npy, EXR), turned as its EXIF tag asks
    if (w, h) == size or not mode:
        return None
    line, warning = f"{path}: {w}x{h} -> {size[0]}x{size[1]} ({mode})", ""
    if mode == "stretch" and abs((w / h) / (size[0] / size[1]) - 1) > 0.01:
        warning = f"aspect ratio changed by {100 * abs((w / h) / (size[0] / size[1]) - 1):.0f}%"
        line += f"; {warning} (fit or fill keep it)"
    return line, warning


#: The longest file name most file systems take, in bytes.
NAME_BYTES = 255
#: Bytes an output file adds after the pattern's name: _<backend>_display.png, _<backend>_compare.png (backends
#: of at most 12 characters).
OUTPUT_SUFFIX_BYTES = 26


def resolve_patterns(specs: Sequence[str], rv: RelightView, resize: str = "",
                     narrator: Narrator | None = None) -> tuple[list[str], list[np.ndarray]]:
    """``(names, patterns)`` of the patterns ``specs`` names, in the projector's size: an image file (read,
    ``resize``-d), one of the view's own reference patterns, or a named pattern. Each name is its output
    file's, so two patterns may not share one."""
    from sssphase_core.processing.patterns import REFERENCE_NAMES, reference_pattern, unknown_pattern

    say = narrator or Narrator()
    wp, hp = rv.proj.projector_size
    names, pats = [], []
    for p in specs:
        named = (p in rv.references or p in REFERENCE_NAMES) and p == Path(p).name  # a bare name, as `sss patterns` says
        if named and Path(p).exists():  # a file or folder of that name here does not hide the pattern
            say.say(f"--pattern {p}: the named pattern, not {'the folder' if Path(p).is_dir() else 'the file'} {p} in "
                    f"this folder (give ./{p} for that)")
        if Path(p).is_file() and not named:
            if any(ord(ch) < 32 or ord(ch) == 127 for ch in Path(p).stem):
                raise InputError(f"--pattern {p!r}: its file name holds a control character (a newline, a tab), which "
                                 "would reach the output files' names: rename the file")
            names.append(Path(p).stem)
            pats.append(read_pattern(p, (wp, hp), resize=resize))
            note = resize_note(p, (wp, hp), resize)
            if note:
                say.say(*note)
        elif p in rv.references:  # the session's own reference pattern
            names.append(p)
            pats.append(rv.references[p])
        elif p in REFERENCE_NAMES:
            names.append(p)
            pats.append(reference_pattern(p, wp, hp))
        elif Path(p).is_dir():  # (one with images is relit as a sequence before this)
            from sssphase_core.store.pattern_sequences import FOLDER_SUFFIXES

            raise InputError(f"--pattern {p!r} is a folder with no pattern images in it ({', '.join(FOLDER_SUFFIXES)}: "
                             "a folder of them is relit as the frames of a sequence)")
        else:
            raise InputError(unknown_pattern("--pattern", p))
    twins = sorted({n for n in names if names.count(n) > 1})
    if twins:  # each pattern's name is its output file's
        raise InputError(f"--pattern: two patterns would both be written as {twins[0]!r}: "
                         "rename one (the output files are named by the pattern)")
    # OBJECT_vN_PATTERN_BACKEND_display.png must fit a file name (255 bytes): refused here, not after the footprints
    room = NAME_BYTES - len(f"{rv.object}_v{rv.view}_".encode()) - OUTPUT_SUFFIX_BYTES
    long = next((n for n in names if len(n.encode()) > room), None)
    if long is not None:
        raise InputError(f"--pattern {long[:40]}...: a pattern named with {len(long.encode())} bytes makes its output "
                         f"file names longer than a file name may be ({NAME_BYTES} bytes): rename the file to at most "
                         f"{max(room, 1)} bytes")
    return names, pats


def mix_line(rv: RelightView, backend: str, mix: np.ndarray, stretched: np.ndarray | None = None) -> str:
    """The line that tells a view's calibration: each model's view-wide weights against no scattering, and how they
    split between its members (``stretched``: (4 members, 3 colours) for the first model where the calibration widened
    it, ``relight_view``'s ``widen``: its footprints stretched along x, y and both, and softened)."""
    rows = np.atleast_2d(mix)
    shares = [None] * len(rows) if stretched is None else [np.reshape(stretched, (len(WIDEN_MEMBERS), 3))] + [None] * (len(rows) - 1)
    f = lambda v: " ".join(f"{x:.2f}" for x in v)  # noqa: E731
    split = lambda s: ("stretched along " + ", ".join(f"{a} {f(v)}" for a, v in zip(WIDEN_MEMBERS[:-1], s[:-1], strict=True))  # noqa: E731
                       + f"; softened {f(s[-1])}")
    weights = "; ".join(f"{m} R G B {f(row)}" + (f" ({split(share)})" if share is not None else "")
                        for m, row, share in zip(BLENDS.get(backend, (backend,)), rows, shares, strict=True))
    return (f"{rv.object} view {rv.view}: {backend} footprints calibrated to the view's fringe captures "
            f"(view-wide weights against no scattering: {weights}{'; refined pixel by pixel' if len(rows) == 1 else ''})")


def denoise_line(rv: RelightView, source: DotTransport) -> str:
    """The line that tells which noise mask the captured transport was denoised with, and the others' fit."""
    fit = source.fit
    others = ", ".join(f"{s:g} px {p:.1f} dB" for s, p in fit.items() if s != source.smoothing)
    return (f"{rv.object} view {rv.view}: captured transport denoised with the {source.smoothing:g} px noise mask "
            f"(relights the view's fringe captures at {fit[source.smoothing]:.1f} dB; {others})")


@dataclass
class RelitImage:
    """One relit image written: its files, the fraction of the object above 1.0, its scores against the
    view's reference capture of the same pattern (None without one)."""

    object: str
    view: int
    pattern: str
    paths: list[Path]
    clipped: float
    metrics: dict[str, float] | None = None
    figure: Path | None = None


@dataclass
class RelightResult:
    """What :func:`relight_session` did: the backend it ran (``auto`` resolved), the decoder it read, the
    patterns' names, every image written and each view's calibration weights (None: not calibrated); a pattern
    sequence's (:func:`~sssphase_core.relight.sequence.relight_sequence`) video per view (its frames in the folder of
    the same name) and frame rate."""

    backend: str
    checkpoint: Path | None
    patterns: list[str] = field(default_factory=list)
    images: list[RelitImage] = field(default_factory=list)
    mixes: dict[int, np.ndarray | None] = field(default_factory=dict)
    videos: dict[int, Path] = field(default_factory=dict)
    fps: float | None = None


def widen_line(widths: dict[str, float | None]) -> str | None:
    """The line that says for which backends (``widths``: each one's :func:`~sssphase_core.relight.choices.widen_for`)
    the view calibration may widen the models' footprints, or None where it may for none."""
    by: dict[float, list[str]] = {}
    for backend, widen in widths.items():
        if widen:
            by.setdefault(widen, []).append(backend)
    if not by:
        return None
    def stretched_models(names: list[str]) -> str:  # the first model of each backend: the one stretched
        return " and ".join(sorted({BLENDS.get(n, (n,))[0] for n in names}))

    def others(names: list[str]) -> str:  # a blend's other models join unstretched
        return " (a blend's other models as they are)" if any(n in BLENDS for n in names) else ""

    return "; ".join(f"calibration ({', '.join(names)}): the {stretched_models(names)} footprints join the view's fit "
                     f"stretched {widen:g} x along x, along y and along both, and softened{others(names)}, so that its "
                     "fringes can widen them along either axis or both, soften their core, as well as narrow them"
                     for widen, names in by.items()) + " (--widen 1: the footprints as they are, only narrowed)"


def resolve_backend(backend: str, checkpoint: Path | str | None, narrator: Narrator | None = None
                    ) -> tuple[str, Path | None]:
    """``(backend, checkpoint)`` checked before any work: a run folder's best checkpoint, ``auto`` as the
    best source the user can run (blend with a decoder, else analytic; docs, relighting: blend >= torch on every object
    tried), unknown backends and unreadable decoders refused, an unused checkpoint noted."""
    from sssphase_core.learning.runlog import resolve_checkpoint

    if checkpoint is not None:
        checkpoint = resolve_checkpoint(checkpoint)  # a run folder: its best.pt when it has one
    if backend == "auto":
        backend = "blend" if checkpoint is not None else "analytic"
    check_backends([backend], checkpoint)
    if checkpoint is not None and not uses_decoder(backend) and not _plugin_takes_checkpoint(backend):
        (narrator or Narrator()).say(f"note: --checkpoint is not used by --backend {backend}")
    return backend, None if checkpoint is None else Path(checkpoint)


def relight_backends(backend: str, checkpoint: Path | str | None) -> list[str]:
    """The backends of ``sss relight --backend`` (comma-separated; ``auto`` alone), each known and runnable with
    ``checkpoint``, refused before any work, in order and once each."""
    from sssphase_core.learning.runlog import resolve_checkpoint

    names = list(dict.fromkeys(b.strip() for b in backend.split(",") if b.strip())) or ["auto"]
    if len(names) > 1:
        if "auto" in names:
            raise InputError("--backend auto chooses one backend; name the ones to run instead (e.g. analytic,blend)")
        check_backends(names, None if checkpoint is None else resolve_checkpoint(checkpoint))
    return names


def check_decoder_fits(checkpoint: Path | None, backends: Sequence[str], sessions: Sequence[Session]) -> None:
    """Refuse a decoder whose footprint size is not the sessions' crop size before any work (as training
    does): a paper-preset decoder (K = 90) on a CPU-preset session (K = 32) ran for minutes up to 5.4 GB."""
    if checkpoint is None or not any(uses_decoder(b) for b in backends):
        return
    from sssphase_core.learning.training.checkpoints import checkpoint_preset
    from sssphase_core.relight.views import session_patch

    preset = checkpoint_preset(checkpoint)
    for s in sessions:
        k = session_patch(s.manifest)
        if preset.patch != k:
            raise InputError(f"{checkpoint} is a {preset.name} decoder ({preset.patch}x{preset.patch} footprints) but "
                             f"{s.name} was captured with {k}x{k} crops (its rig's patch): use a decoder trained at "
                             f"that size")


def check_relight_options(out: Path, patterns: Sequence[str], resize: str, formats: str | Sequence[str],
                           device: str, precision: str = "auto") -> tuple[str, ...]:
    """The options of :func:`relight_session` checked, in the order the CLI always checked them."""
    from sssphase_core.compute import check_device, check_precision
    from sssphase_core.store.imageio import RESIZE_MODES
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    chosen = parse_formats(formats)
    if resize and resize not in RESIZE_MODES:  # (read only for pattern files: checked whatever is given)
        raise InputError(f"--resize must be one of {', '.join(RESIZE_MODES)}, got {resize!r}")
    if any(not p.strip() for p in patterns):
        raise InputError("--pattern is empty: give an image file or a named pattern (checkerboard, stripes_x, ...)")
    check_device(device)  # one line before any progress is drawn
    check_precision(precision)
    return chosen


@one_version()  # every view with the checkpoint as the command first read it
def relight_session(session: Path | str | Session, patterns: Sequence[str], *, backend: str = "auto",
                    checkpoint: Path | str | None = None, out: Path | str = Path("relit"),
                    views: str | Sequence[int] | None = "", resize: str = "", chunk: int = 1024, device: str = "cpu",
                    cache: bool = True, formats: str | Sequence[str] = "png", widen: float | None = None,
                    narrator: Narrator | None = None, precision: str = "auto") -> RelightResult:
    """Relight a session's views under ``patterns`` (image files, the session's reference names or named
    patterns) with ``backend`` (``auto``: blend with a ``checkpoint``, else analytic) and write the images
    to ``out`` as ``<object>_v<view>_<pattern>_<backend>.png`` / ``.exr`` (``formats``), with a comparison
    figure and scores wherever the view holds a reference capture of the same pattern. Model footprints
    are cached in ``out/cache`` (``cache``) for later patterns. ``widen``: :func:`relight_view`'s, by default
    :func:`~sssphase_core.relight.choices.widen_for` the backend (1: none). ``precision``: the decoder's inference
    (:func:`~sssphase_core.compute.inference_precision`)."""
    from sssphase_core.store.session import claim_output

    out, say = Path(out), narrator or Narrator()
    chosen_formats = check_relight_options(out, patterns, resize, formats, device, precision)
    auto = backend == "auto"
    backend, ckpt = resolve_backend(backend, checkpoint, say)
    if note := unused_widen_note([backend], widen):
        say.say(note)
    widen = widen_for(backend, widen) if backend not in MODEL_FREE else None
    s = session if isinstance(session, Session) else Session.open(session)
    check_decoder_fits(ckpt, [backend], [s])
    result, pats = RelightResult(backend, ckpt), []
    for v in choose_views(s, views, say):
        rv = load_view(s, v)
        if not pats:
            result.patterns, pats = resolve_patterns(patterns, rv, resize, say)
            claim_output(out, [s])  # images are named by object: another session's of the same object are not replaced
            if auto:  # said once the input is known good
                say.say(f"backend: {backend}" + ("" if ckpt is not None else
                                                 " (no --checkpoint: the analytic model; with a trained decoder's "
                                                 "--checkpoint, the decoder blends in)"))
            if ckpt is not None and uses_decoder(backend):
                from sssphase_core.compute import inference_precision

                precision = inference_precision(device, precision)
                say.say(f"decoder: {ckpt} ({precision} inference)")
            if line := widen_line({backend: widen}):
                say.say(line)
        relit, result.mixes[v] = relight_one(s, rv, pats, backend, ckpt, out, chunk=chunk, device=device,
                                              cache=cache, say=say, widen=widen, precision=precision)
        result.images += write_relit(rv, relit, result.patterns, pats, out, backend, chosen_formats, say)
    return result


def relight_one(s: Session, rv: RelightView, pats: list[np.ndarray], backend: str, checkpoint: Path | None,
                 out: Path, *, chunk: int, device: str, cache: bool, say: Narrator, widen: float | None = None,
                 precision: str = "auto") -> tuple[np.ndarray, np.ndarray | None]:
    """One view relit (its footprints cached unless the source is the captured transport), its calibration
    and denoising told, its caches saved -> (images (P, H, W, 3), calibration weights or None).

    A model's relight also keeps the view's eigen-footprints and calibration (:mod:`~sssphase_core.relight.lowrank`);
    with them cached, later patterns are relit from those alone (seconds at 1080p, where the footprints
    themselves outgrow any cache); with ``widen``, the calibration's eigen-footprints are the first model's members (stretched along x, y and both, softened)."""
    from sssphase_core.compute import inference_precision
    from sssphase_core.processing.projector import emitted_light
    from sssphase_core.relight.backends import domain_line, make_sources
    from sssphase_core.relight.cache import CACHE_BYTES
    from sssphase_core.relight.engine import lit_pixels
    from sssphase_core.relight.lowrank import LowRankTap, load_lowrank, save_lowrank
    from sssphase_core.relight.pipeline import relight_view, split_stretches
    from sssphase_core.relight.transport import DotTransport

    precision = inference_precision(device, precision) if uses_decoder(backend) else "fp32"
    fast = lowrank_path(out, s, rv, backend, checkpoint, widen, precision)
    saved = load_lowrank(fast, rv.proj.mask, widen) if cache and backend not in MODEL_FREE else None
    if saved is not None:
        return _relight_cached(rv, pats, backend, fast, saved, say, widened=bool(widen))
    sources: list[tuple[FootprintSource, int]] = make_sources(backend, rv, checkpoint=checkpoint, device=device,
                                                              precision=precision)
    models = [src for src, _ in sources]
    members = BLENDS.get(backend, (backend,))
    cached = cache and not isinstance(sources[0][0], DotTransport)  # the measured transport is read, not predicted
    valid = None  # the pixels any pattern can light: those the view calibration's PSP patterns light
    if cached and backend not in MODEL_FREE and rv.psp_patterns is not None:
        valid = lit_pixels(rv.proj, emitted_light(rv.psp_patterns, rv.proj.gamma))[0]
    # The footprints themselves are kept when they all fit (the eigen-footprints serve later patterns either way;
    # at 1080p and K = 90 they are ~10 GB, and a partial cache cost a third of the first relight and 2 GB more)
    n_pixels = len(valid) if valid is not None else int(rv.proj.mask.sum())
    size = footprint_bytes(n_pixels, max(k for _, k in sources))
    keep = cached and size <= CACHE_BYTES
    if keep:
        sources = [(c, k) for c, (_, k) in zip(view_caches(out, rv, sources, members, checkpoint), sources, strict=True)]
    caches = [src for src, _ in sources]
    taps = [LowRankTap(src, valid, rv.proj.shape) for src in caches] if valid is not None else []
    if taps:
        sources = [(tap, k) for tap, (_, k) in zip(taps, sources, strict=True)]
    (source, patch), *also = sources
    calibration: list[tuple[np.ndarray, np.ndarray]] = []
    with say.bar(), saved_if_interrupted(caches if keep else ()):  # type: ignore[arg-type]
        progress = say.task(f"{rv.object} view {rv.view}: {backend}")
        relit, mix = relight_view(source, patch, rv, pats, calibrate=backend not in MODEL_FREE, also=also, chunk=chunk,
                                  device=device, progress=progress, calibration=calibration, widen=widen)
    if mix is not None:  # widened, the calibration's own view-wide weights say how they split between its members
        shares = split_stretches(calibration[0][1], bool(widen))[1] if calibration else None
        say.say(mix_line(rv, backend, mix, shares))
    for model, member in zip(models, members, strict=True):
        line = domain_line(rv, member, model)
        if line:
            say.say(line)
    if isinstance(source, DotTransport) and source.fit:  # its noise mask, chosen on the view's fringe captures
        say.say(denoise_line(rv, source))
    for cache_file in caches if keep else ():
        if (line := kept(cache_file.save, cache_file.path)) is not None:  # type: ignore[attr-defined]
            say.say(line, "was not kept")
            break
        if cache_file.uncached:  # type: ignore[attr-defined]
            say.say(f"cache: {cache_file.uncached:,} footprints beyond its memory budget were not kept "  # type: ignore[attr-defined]
                    "(later patterns recompute them)")
    if taps and calibration and all(tap.covers(valid) for tap in taps):  # every pixel went by: any pattern can be relit
        line = kept(lambda: save_lowrank(fast, [tap.result() for tap in taps], *calibration[0], rv.proj.mask, widen=widen), fast)
        if line is not None:
            say.say(line, "was not kept")
        elif not keep:
            say.say(f"cache: the view's {n_pixels:,} footprints ({size / 2**30:.1f} GiB in float16) are more than the cache "
                    f"holds ({CACHE_BYTES / 2**30:.0f} GiB): later patterns are relit from its eigen-footprints alone")
    return relit, mix


def _relight_cached(rv: RelightView, pats: list[np.ndarray], backend: str, path: Path, saved: tuple[Any, ...],
                    say: Narrator, *, widened: bool) -> tuple[np.ndarray, np.ndarray]:
    """A view relit from its cached eigen-footprints and calibration (``saved``: :func:`load_lowrank`'s, its first
    model as its calibration members where ``widened``), told."""
    from sssphase_core.relight.pipeline import relight_lowrank, split_stretches

    members, weights, view_weights, gains, white = saved
    with say.status(f"{rv.object} view {rv.view}: {backend} from its eigen-footprints"):
        relit = relight_lowrank(rv, members, weights, gains, white, pats)
    view_weights, stretched = split_stretches(view_weights, widened)  # as relight_view gives them
    models = members[:1] + members[len(WIDEN_MEMBERS):] if widened else members  # one per model (its members share a rank)
    mix = view_weights[0] if len(view_weights) == 1 else view_weights
    say.say(mix_line(rv, backend, mix, stretched))
    say.say(f"{rv.object} view {rv.view}: relit from its cached eigen-footprints ({path.name}: rank "
            f"{'/'.join(str(m.rank) for m in models)}, {max(m.residual for m in members):.1e} of the footprints' "
            "energy left out); --no-cache computes the footprints again")
    return relit, mix


def write_relit(rv: RelightView, relit: np.ndarray, names: Sequence[str], pats: Sequence[np.ndarray], out: Path,
                backend: str, formats: tuple[str, ...], narrator: Narrator | None = None) -> list[RelitImage]:
    """Write a view's relit images (one display exposure per view: a dim pattern looks dim), each scored
    against the view's reference capture when it was relit under that very pattern."""
    say = narrator or Narrator()
    exposure = display_scale(rv.white)
    if (lost := rv.decoded_warning()) is not None:
        say.say(f"warning: {lost}", warning="warning:")
    written = []
    for name, pat, img in zip(names, pats, relit, strict=True):
        stem = out / f"{rv.object}_v{rv.view}_{name}_{backend}"
        item = RelitImage(rv.object, rv.view, name, write_images(stem, img, formats=formats, scale=exposure),
                          float((img[rv.proj.mask] > 1.0).any(axis=-1).mean()) if rv.proj.mask.any() else 0.0)
        line = f"wrote {', '.join(str(p) for p in item.paths)}"
        if "exr" not in formats and item.clipped > 0:
            share = f"{item.clipped:.1%}" if item.clipped >= 0.001 else "under 0.1%"
            line += f"  ({share} of the object above 1.0 clipped in the PNG: --format exr keeps them)"
        if name in rv.captured and same_pattern(pat, rv.references[name]):
            item.metrics = relight_metrics(img, rv.captured[name], rv.proj.mask)
            item.figure = comparison_figure(rv.captured[name], img, rv.proj.mask, stem.with_name(stem.name + "_compare.png"),
                                            title=f"{rv.object} view {rv.view}, {name}", metrics=item.metrics,
                                            reference_name=rv.reference_name)
            line += (f"  (vs reference: PSNR {item.metrics['psnr']:.2f} dB, SSIM {item.metrics['ssim']:.3f}; side by side "
                     f"in {item.figure})")
        else:  # an earlier run's comparison for another pattern of this name would contradict the image beside it
            stem.with_name(stem.name + "_compare.png").unlink(missing_ok=True)
        say.say(line)
        written.append(item)
    return written


@dataclass
class GeometryView:
    """One view's correspondences for geometry written: the file, the median scattering shift (projector px)
    and, on simulated sessions, the decoded and corrected points' median distance and x bias to the exact
    ones (``exact``: decoded, decoded bias, for geometry, its bias)."""

    object: str
    view: int
    path: Path
    shift: tuple[float, float]
    period: float
    exact: tuple[float, float, float, float] | None = None
    #: the triangulated points (``points.ply``) and how many it holds, where a stereo calibration was known
    cloud: Path | None = None
    n_points: int = 0
    unit: str = ""
    #: the view's figure of the shift (``shift.png``): along the baseline, and in depth where points were made
    figure: Path | None = None
    #: the corrected points' median reprojection error in the projector (px): how well the calibration fits
    reprojection: float = float("nan")
    #: the view's range-image mesh (``mesh.ply``, ``mesh=True``) and its triangles
    mesh: Path | None = None
    n_faces: int = 0
    #: on simulated sessions, the decoded and corrected 3D points' median distance and depth (z) bias to the
    #: exact ones, in the calibration's unit (mm): decoded, its bias, for geometry, its bias
    exact_3d: tuple[float, float, float, float] | None = None


def _check_geometry_backend(backend: str) -> None:
    """Refuse backends that cannot predict the scattering shift, saying why."""
    from sssphase_core.learning.backends import available_backends

    usable = ["exact", *sorted(available_backends())]
    if backend not in (*usable, "measured", "none"):
        raise InputError(f"--backend {backend!r} cannot predict the scattering shift here; use one of {', '.join(usable)}")
    if backend in ("measured", "none"):
        raise InputError(f"--backend {backend} cannot predict the scattering shift: "
                         + ("the dot-grid crops are placed by the decoded correspondences themselves, so they reproduce "
                            "the decoded points (use torch, analytic or exact)" if backend == "measured"
                            else "without scattering there is no shift"))


@one_version()  # every view with the checkpoint as the command first read it
def geometry_session(session: Path | str | Session, *, backend: str = "analytic", checkpoint: Path | str | None = None,
                     out: Path | str = Path("geometry"), views: str | Sequence[int] | None = "", device: str = "cpu",
                     calibration: Path | str | None = None, crop_radius: float | None = None,
                     refine_axis: bool = False, mesh: bool = False, narrator: Narrator | None = None) -> list[GeometryView]:
    """Projector points for 3D of a session's views: the decoded correspondences minus the scattering shift
    predicted from ``backend``'s footprints, written as ``out/<object>/view_NNN/correspondence_for_geometry.npz``
    (xp, yp, xp_decoded, yp_decoded, shift_x, shift_y, mask); scored against the exact points on simulated
    sessions. With a stereo ``calibration`` (an OpenCV file, :func:`~sssphase_core.processing.triangulation.read_calibration`;
    a simulated session's own rig by default) both are triangulated: ``points`` and ``points_decoded`` (H, W, 3) in the
    npz, and the corrected ones as ``points.ply`` beside it, coloured by the white capture. With a turntable axis in the
    calibration, the views together as ``out/<object>/points_merged.ply`` (only the points within ``crop_radius`` of the
    axis, where given; about the axis refined from the views' overlaps with ``refine_axis``). ``mesh``: each view's
    points also as a range-image mesh, ``mesh.ply`` (neighbouring pixels joined, depth steps left open)."""
    from sssphase_core.compute import check_device
    from sssphase_core.learning.runlog import resolve_checkpoint
    from sssphase_core.store.session import check_output_folder, claim_output, refuse_inside_session

    out, say = Path(out), narrator or Narrator()
    check_output_folder(out)
    check_device(device)  # an unknown device is refused here too, not ignored by the model-free backends
    if crop_radius is not None and not (np.isfinite(crop_radius) and crop_radius > 0):
        raise InputError(f"--crop-radius must be a positive distance from the turntable's axis, got {crop_radius!r}")
    _check_geometry_backend(backend)
    s = session if isinstance(session, Session) else Session.open(session)
    refuse_inside_session(out / s.name, what=f"--out {out}: its folder")  # written as OUT/<object>/view_NNN: OUT must not hold the session itself
    period = finest_psp_period(s.manifest.get("plan", {}))
    if period is None:
        raise InputError(f"{session if not isinstance(session, Session) else session.path}: its capture plan has no "
                         "PSP frames, so the fringe period is unknown")
    needs_checkpoint(backend, checkpoint)
    if checkpoint is not None:
        checkpoint = resolve_checkpoint(checkpoint)
        check_decoder_fits(Path(checkpoint), [backend], [s])
    from sssphase_core.sim import session_rig_calibration

    exact_rig = session_rig_calibration(s.manifest.get("rig", {}))  # a simulated session's: evaluation, and the default
    stereo, said = _stereo_calibration(calibration, exact_rig)
    chosen = choose_views(s, views, say)
    say.say(said)  # once the input is known good: a refused run says only why
    claim_output(out, [s])  # once the input is known good: a refused run leaves no folder of its own behind
    from sssphase_core.relight.backends import make_source  # torch: once the views are known
    from sssphase_core.relight.geometry import ENTRY_CENTRED, geometric_correspondence

    done = []
    for v in chosen:
        rv = load_view(s, v)
        source, patch = make_source(backend, rv, checkpoint=checkpoint, device=device)
        with say.status(f"{rv.object} view {v}: predicting the scattering shift ({backend})"):
            geo = geometric_correspondence(source, rv.proj, patch, period,
                                           centred_on="entry" if backend in ENTRY_CENTRED else "decoded")
        done.append(_write_geometry(s, rv, geo, out, period, stereo, exact_rig, say, mesh))
        say.say(_geometry_line(done[-1]))
        if line := _points_line(done[-1]):
            say.say(line)
    if mesh and stereo is None:
        say.say("note: no mesh written: meshing joins the 3D points, which need --calibration")
    if refine_axis and (stereo is None or len(done) < 2):
        say.say("note: the axis was not refined: that needs the 3D points of two or more turntable views")
    merged = None
    if stereo is not None and len(done) > 1:  # a turntable's views: one cloud in the turntable's frame at 0 degrees
        from sssphase_core.relight.merged_points import (
            merge_note,
            merge_views,
            merged_line,
            recorded_angles,
            refinement_lines,
        )

        views = [d.view for d in done]
        if note := merge_note(stereo, views, recorded_angles(s, views)):
            say.say(note)
        else:
            clouds = {d.view: (np.load(d.path)["points"], np.asarray(s.load(d.view, "white"), np.float32)) for d in done}
            with say.status(f"{s.name}: merging the views{' (refining the axis)' if refine_axis else ''}"):
                merged = merge_views(s, clouds, stereo, out, exact_rig, crop_radius=crop_radius, refine=refine_axis,
                                     errors=_recorded_errors(calibration) if refine_axis else None, mesh=mesh,
                                     calibration=calibration)
            if merged is not None:
                notes, line = refinement_lines(merged, stereo.unit), merged_line(merged, stereo.unit or "the calibration's unit")
                for said_line in [*notes, line] if merged.refinement is not None else [line, *notes]:  # (a hint after)
                    say.say(said_line)
    written = {p.name for p in (getattr(merged, "path", None), getattr(merged, "mesh", None)) if p is not None}
    for stale in {"points_merged.ply", "mesh_merged.ply"} - written:  # an earlier run's merge is not this run's
        (out / s.name / stale).unlink(missing_ok=True)
    return done


def _recorded_errors(calibration: Path | str | None) -> dict[str, float] | None:
    """The RMS errors a calibration file recorded (kept where the geometry writes it again), or None."""
    from sssphase_core.capture.stereo_calibration import calibration_entries

    return calibration_entries(calibration)[0] if calibration is not None else None


def _stereo_calibration(calibration: Path | str | None, exact_rig: StereoCalibration | None
                        ) -> tuple[StereoCalibration | None, str]:
    """The stereo calibration to triangulate with (the file given, else a simulated session's ``exact_rig``, else
    None) and the line that says which."""
    from sssphase_core.processing.triangulation import read_calibration

    if calibration is not None:
        return read_calibration(calibration), f"triangulating with the calibration in {calibration}"
    if exact_rig is not None:
        return exact_rig, "triangulating with the simulated rig's exact calibration"
    return None, ("note: no points triangulated: give --calibration FILE, the rig's camera-projector calibration (an "
                  "OpenCV YAML, XML or JSON file with cam_K, cam_kc, proj_K, proj_kc, R, T), for 3D points and points.ply")


def _write_geometry(s: Session, rv: RelightView, geo: Any, out: Path, period: float, stereo: StereoCalibration | None,
                    exact_rig: StereoCalibration | None, say: Narrator, mesh: bool = False) -> GeometryView:
    """Write one view's correspondences for geometry (and, with ``stereo``, their 3D points) and score them
    (simulated sessions: against the exact points, and their 3D points against ``exact_rig``'s surface)."""
    from sssphase_core.store.session import view_dir_name

    shift_x, shift_y = rv.proj.xp - geo.xp, rv.proj.yp - geo.yp
    folder = out / rv.object / view_dir_name(rv.view)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "correspondence_for_geometry.npz"
    from sssphase_core.store.files import atomic_path

    m = rv.proj.mask
    arrays = {"xp": geo.xp, "yp": geo.yp, "xp_decoded": rv.proj.xp, "yp_decoded": rv.proj.yp, "shift_x": shift_x,
              "shift_y": shift_y, "mask": m}
    corrected = None
    if stereo is not None:
        corrected, arrays["points_decoded"] = _triangulated(stereo, rv, geo, say)
        arrays["points"] = corrected.points
    with atomic_path(path, ".npz") as tmp:
        np.savez_compressed(tmp, **arrays)
    done = GeometryView(rv.object, rv.view, path, (float(np.nanmedian(shift_x[m])), float(np.nanmedian(shift_y[m]))), period)
    if stereo is not None and corrected is not None:
        from sssphase_core.store.pointcloud import write_point_cloud

        done.cloud, done.unit, done.reprojection = folder / "points.ply", stereo.unit or "the calibration's unit", corrected.reprojection
        done.n_points = write_point_cloud(done.cloud, arrays["points"], rv.white)
        if mesh:
            from sssphase_core.store.pointcloud import write_range_mesh

            done.mesh = folder / "mesh.ply"
            _, done.n_faces = write_range_mesh(done.mesh, arrays["points"], rv.white)
    for stale in {"points.ply", "mesh.ply"} - {p.name for p in (done.cloud, done.mesh) if p is not None}:
        (folder / stale).unlink(missing_ok=True)  # an earlier run's (another calibration, or --mesh): not this run's
    from sssphase_core.relight.geometry import shift_figure

    done.figure = shift_figure(rv.white, shift_x, m, folder / "shift.png", title=f"{rv.object} view {rv.view}: what "
                               "scattering does to the decoded points", unit=done.unit,
                               depth=None if stereo is None else (arrays["points_decoded"] - arrays["points"])[..., 2])
    if rv.sim is not None and "gt/proj_xy" in s.arrays(rv.view):  # evaluation only: the simulator's exact points
        gt = np.asarray(s.load(rv.view, "gt/proj_xy"), np.float32)
        ok = m & np.isfinite(gt[..., 0])
        scores: list[float] = []
        for xp, yp in ((rv.proj.xp, rv.proj.yp), (geo.xp, geo.yp)):
            scores += [float(np.median(np.hypot(xp - gt[..., 0], yp - gt[..., 1])[ok])), float(np.median((xp - gt[..., 0])[ok]))]
        done.exact = (scores[0], scores[1], scores[2], scores[3])
        from sssphase_core.processing.triangulation import mm_per_unit

        factor = mm_per_unit(stereo) if stereo is not None else None  # (the rig's truth is in mm)
        if factor is not None and exact_rig is not None:  # the truth is the rig's, whichever calibration made the points
            done.exact_3d = _scored_points(exact_rig, gt, ok, factor * arrays["points_decoded"], factor * arrays["points"])
    return done


#: A median reprojection error (projector px) above which triangulated points are said to come from a calibration
#: of another rig, or a pose inverted (X_c = R X_p + T: 1.0 px on the simulated soap) or the devices' matrices swapped
#: (0.9 px): a calibrated rig's is a fraction of a pixel (the simulated rig's exact one 0.02, its focal length 5% off 0.35).
MAX_REPROJECTION_PX = 0.75


def _triangulated(stereo: StereoCalibration, rv: RelightView, geo: Any, say: Narrator) -> tuple[Triangulated, np.ndarray]:
    """The corrected correspondences of a view triangulated and the decoded ones' points (H, W, 3); a calibration
    whose rays mostly meet behind the devices, or miss each other by more than :data:`MAX_REPROJECTION_PX`, is asked
    about in one warning."""
    from sssphase_core.processing.triangulation import triangulate

    corrected = triangulate(stereo, geo.xp, geo.yp, rv.proj.mask)
    decoded = triangulate(stereo, rv.proj.xp, rv.proj.yp, rv.proj.mask)
    lit = int(rv.proj.mask.sum())
    if corrected.behind > 0.5 * lit or corrected.reprojection > MAX_REPROJECTION_PX:
        wrong = (f"{corrected.behind} of {lit} pixels' rays meet behind the camera or the projector"
                 if corrected.behind > 0.5 * lit else
                 f"the camera's and the projector's rays miss each other by {corrected.reprojection:.1f} projector px (median)")
        say.say(f"{rv.object} view {rv.view}: {wrong}: is the calibration this rig's, with the projector's pose as "
                "X_p = R X_c + T?", warning=wrong)
    return corrected, decoded.points


def _scored_points(exact_rig: StereoCalibration, gt: np.ndarray, ok: np.ndarray, decoded: np.ndarray,
                   corrected: np.ndarray) -> tuple[float, float, float, float] | None:
    """Median distance and median depth (z) error of the decoded and corrected points to the surface the exact
    correspondences give with the simulated rig's exact calibration (mm), or None where no pixel has all three."""
    from sssphase_core.processing.triangulation import triangulate

    exact = triangulate(exact_rig, gt[..., 0], gt[..., 1], ok).points
    both = ok & np.isfinite(exact).all(-1) & np.isfinite(decoded).all(-1) & np.isfinite(corrected).all(-1)
    if not both.any():
        return None
    scores: list[float] = []
    for points in (decoded, corrected):
        error = points[both] - exact[both]
        scores += [float(np.median(np.linalg.norm(error, axis=-1))), float(np.median(error[:, 2]))]
    return scores[0], scores[1], scores[2], scores[3]


def _geometry_line(g: GeometryView) -> str:
    line = (f"wrote {g.path}: median shift {g.shift[0]:+.3f} px along x, {g.shift[1]:+.3f} px "
            f"along y (projector px, period {g.period:g})")
    if g.exact is not None:
        line += (f"; against the exact points: decoded {g.exact[0]:.3f} px (bias x {g.exact[1]:+.3f}), "
                 f"for geometry {g.exact[2]:.3f} px (bias x {g.exact[3]:+.3f})")
    return line


def _points_line(g: GeometryView) -> str | None:
    if g.cloud is None:
        return None
    line = (f"wrote {g.cloud}: {g.n_points} points (the corrected correspondences triangulated, {g.unit}; "
            f"median reprojection error {g.reprojection:.3f} projector px)")
    if g.exact_3d is not None:
        line += (f"; against the exact surface: decoded {g.exact_3d[0]:.3f} (depth bias {g.exact_3d[1]:+.3f}), "
                 f"for geometry {g.exact_3d[2]:.3f} (depth bias {g.exact_3d[3]:+.3f}) mm")
    if g.mesh is not None:
        line += f"; and {g.mesh}: {g.n_faces} triangles joining neighbouring pixels"
    return line


@dataclass
class EvaluationResult:
    """What :func:`evaluate_sessions` did: a row per object, view, pattern and backend, the tables, the
    record and its Markdown."""

    rows: list[dict[str, Any]]
    backends: list[str]
    tables: list[Any]
    json: Path
    md: Path


def _eval_backends(backend: str, checkpoint: Path | str | None, say: Narrator) -> tuple[list[str], Path | None]:
    """The backends ``backend`` lists, each once, checked (and the checkpoint resolved) before any work."""
    from sssphase_core.learning.runlog import check_checkpoint_file, resolve_checkpoint

    backends = list(dict.fromkeys(b.strip() for b in backend.split(",") if b.strip()))  # each once
    if not backends:
        raise InputError(f"--backend names no backend (got {backend!r}): give e.g. none,analytic,torch")
    if checkpoint is not None:
        checkpoint = resolve_checkpoint(checkpoint)  # a run folder: its best.pt when it has one
        if not any(map(uses_decoder, backends)):  # (the model was silently not evaluated, the checkpoint not read)
            check_checkpoint_file(checkpoint)  # a typo is refused, not "unused" (check_backends checks a used one)
            say.say(f"note: --checkpoint is read only by torch and blend, which --backend {','.join(backends)} "
                    "does not list: add them to evaluate the model")
    check_backends(backends, checkpoint)
    return backends, None if checkpoint is None else Path(checkpoint)


def _eval_views(found: Sequence[Session], views: str | Sequence[int] | None, backends: list[str], asked: bool,
                say: Narrator) -> None:
    """Every session has views to evaluate, with references, before any work; ``measured`` is left out (or,
    ``asked`` for, refused) where a view holds no dot-grid footprints."""
    bare = []  # views without the dot-grid crops `measured` relights with
    for s in found:
        for v in choose_views(s, views, say):
            if not has_references(s.arrays(v)):
                raise InputError(f"{s.name} view {v} has no reference captures to evaluate against (capture with "
                                 "--reference checkerboard ..., or import ref__<name> frames)")
            if not has_captured_transport(s.arrays(v)):
                bare.append(f"{s.name} view {v}")
    if "measured" in backends and bare:
        if asked:  # refused before any work (it failed after the other backends)
            raise InputError(f"--backend measured: {bare[0]} has no captured footprints (capture with --footprints)")
        backends.remove("measured")
        say.say(f"measured left out: {', '.join(bare[:3])}{' ...' if len(bare) > 3 else ''} holds no dot-grid "
                "footprints (capture with --footprints)")


@one_version()  # every view with the checkpoint as the command first read it
def evaluate_sessions(sessions: Sequence[Path | str], *, backend: str = EVAL_BACKENDS, checkpoint: Path | str | None = None,
                      views: str | Sequence[int] | None = "", out: Path | str = Path("eval_relight"), device: str = "cpu",
                      calibrate: bool = True, cache: bool = True, widen: float | None = None,
                      narrator: Narrator | None = None, precision: str = "auto") -> EvaluationResult:
    """Relight every reference pattern of the sessions (folders, or folders holding sessions) with each of
    ``backend``'s comma-separated backends and tabulate MSE / PSNR / SSIM over objects and views: figures
    and images in ``out``, ``relight_eval.json`` and ``.md``. The default backends leave ``measured`` out
    where a view holds no dot-grid footprints. Model footprints are cached in ``out/cache`` (``cache``),
    started from those the checkpoint's training cached when its check relit the same view. ``precision``: the
    decoder's inference (:func:`~sssphase_core.compute.inference_precision`)."""
    from sssphase_core.compute import check_device, check_precision, inference_precision
    from sssphase_core.store.results import write_report
    from sssphase_core.store.session import by_object, check_output_folder, claim_output, find_sessions

    out, say = Path(out), narrator or Narrator()
    check_output_folder(out)
    backends, checkpoint = _eval_backends(backend, checkpoint, say)
    if not calibrate:  # both act through the view calibration (a blend failed at its first view, --widen did nothing)
        if blends := [b for b in backends if b in BLENDS]:
            raise InputError(f"--no-calibrate: {', '.join(blends)} weights its members by the view calibration, so it "
                             "needs it: leave out --no-calibrate or that backend")
        if widen is not None and widen != 1:
            raise InputError(f"--widen {widen:g} stretches footprints within the view calibration, which "
                             "--no-calibrate turns off: give one or the other")
    if note := unused_widen_note(backends, widen):
        say.say(note)
    check_device(device)  # one line before any progress is drawn
    check_precision(precision)
    found = find_sessions(list(sessions))  # a missing folder is one line before any progress is drawn
    by_object(found, purpose="their results would share names; evaluate them with separate --out folders")
    check_decoder_fits(checkpoint, backends, found)
    _eval_views(found, views, backends, backend != EVAL_BACKENDS, say)
    claim_output(out, found)  # figures are named by object: another session's of the same object are not replaced
    if checkpoint is not None and any(uses_decoder(b) for b in backends):
        precision = inference_precision(device, precision)
        say.say(f"torch backend: {checkpoint} ({precision} inference)")
    widths = {b: widen_for(b, widen) if calibrate and b not in MODEL_FREE else None for b in backends}
    if line := widen_line(widths):
        say.say(line)
    rows: list[dict[str, Any]] = []
    with say.bar():
        for s in found:
            for v in choose_views(s, views):
                rv = load_view(s, v)
                if (lost := rv.decoded_warning()) is not None:  # once per view, not per backend
                    warnings.warn(lost, UserWarning, stacklevel=2)
                for b in backends:
                    rows += evaluate_view(rv, b, out, checkpoint=checkpoint, device=device, calibrate=calibrate,
                                          cache=cache, widen=widen, precision=precision,
                                          progress=say.task(f"{rv.object} view {v}: {b}"))
    tables = [metrics_table(rows), metrics_table(rows, by=("object", "backend"), title="Relighting per object")]
    result = EvaluationResult(rows, backends, tables, out / "relight_eval.json", out / "relight_eval.md")
    seen = None  # views the decoder was trained on, or of its training objects, scored here
    if checkpoint is not None and any(uses_decoder(b) for b in backends):
        from sssphase_core.relight.evaluation import training_overlap

        seen = training_overlap(checkpoint, [(r["object"], r["view"]) for r in rows])
        if seen:  # in the Markdown file as on the screen
            tables[0].note = f"{tables[0].note}\n\n{seen}".strip()
    write_report({"rows": rows, "aggregate": aggregate(rows), "lpips": lpips_note(), "widen": widths,
                  "training_overlap": seen}, tables, result.json, md=result.md,
                 title="Relighting against reference captures")
    say.say(tables[0].markdown())
    for r in dict.fromkeys((r["object"], r["view"], r["backend"], r["footprints_from_cache"]) for r in rows
                           if r.get("footprints_from_cache")):
        say.say(f"{r[0]} view {r[1]}: {r[2]} read {r[3]:.0%} of its footprints from {out / 'cache'} (kept by an earlier "
                "evaluation, relight or training check of this view and checkpoint): its seconds are not the model's "
                "run time (--no-cache predicts them all)")
    if calibrate:  # a model relit without the view calibration is worth a word: it scores several dB lower
        for obj, view, b in dict.fromkeys((r["object"], r["view"], r["backend"]) for r in rows
                                          if r["backend"] not in MODEL_FREE and "mix" not in r):
            say.say(f"note: {obj} view {view}: {b} is not calibrated to the view (the projector patterns of its "
                    "PSP captures are unknown): the model alone")
    say.say(f"wrote {result.json} and {result.md}")
    return result
