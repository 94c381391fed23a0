"""`sss relight`, `sss eval relight`, `sss demo`, `sss bench relight`, `sss bench stability`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console

if TYPE_CHECKING:
    import numpy as np

    from sssphase_core.store.session import Session

console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)

BackendOpt = Annotated[str, typer.Option("--backend", help="torch, analytic, blend (torch and analytic weighted by how well they relight the view's own fringe captures; needs --checkpoint), measured (the session's captured dot-grid footprints), none, or exact (simulated sessions only: the simulator's ground truth, for evaluation).")]
CheckpointOpt = Annotated[Path | None, typer.Option("--checkpoint", help="Decoder checkpoint for the torch backend.")]


def _progress():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console)


#: `sss eval relight`'s backends unless --backend names others (measured left out where no view has crops).
EVAL_BACKENDS = "none,analytic,measured"


def _views(session, views: str) -> list[int]:
    from sssphase_core.errors import InputError

    if not views:
        if not session.views():  # a capture that was interrupted: nothing to relight, and saying nothing misleads
            states = ", ".join(f"view {v}: {session.status(int(v))}" for v in sorted(session.manifest["views"], key=int))
            raise InputError(f"session {session.path} has no complete view ({states or 'no views'}); "
                             f"`sss validate {session.path}` says more, `sss capture ... --resume` completes it")
        return session.views()
    try:
        chosen = list(dict.fromkeys(int(v) for v in views.split(",") if v.strip()))  # a view named twice runs once
    except ValueError:
        raise InputError(f"--views must be comma-separated integers, got {views!r}") from None
    if not chosen:
        raise InputError(f"--views {views!r} names no view: give comma-separated view numbers, or leave it out for all")
    missing = [v for v in chosen if v not in session.views()]
    if missing:  # before any view is relit
        raise InputError(f"session {session.path} has no complete view {', '.join(map(str, missing))} "
                         f"(complete: {', '.join(map(str, session.views())) or 'none'})")
    return chosen


def _same_pattern(pattern: np.ndarray, reference: np.ndarray) -> bool:
    """Whether a pattern (Hp, Wp[, 3]) is the one a session's reference was captured under (within an 8-bit
    step): only then is the relit image scored against that capture, whatever the pattern file is called."""
    import numpy as np

    a, b = np.asarray(pattern, np.float32), np.asarray(reference, np.float32)
    if a.ndim != b.ndim:
        a, b = (x if x.ndim == 3 else np.repeat(x[..., None], 3, axis=-1) for x in (a, b))
    return a.shape == b.shape and bool(np.abs(a - b).max(initial=0.0) <= 1 / 255)


def _model_tag(checkpoint: Path | None) -> str:
    """Short digest of the checkpoint path and modification time: a retrained model gets a new cache."""
    import hashlib

    key = "none" if checkpoint is None else f"{Path(checkpoint).resolve()}:{Path(checkpoint).stat().st_mtime_ns}"
    return hashlib.sha256(key.encode()).hexdigest()[:10]


def _view_tag(session: Session, view: int) -> str:
    """Short digest of a view's array checksums (the manifest's): footprints cached for one session's view
    are never read for another session's (the same object name imported again, another session relit into
    the same --out)."""
    import hashlib
    import json

    arrays = session.manifest.get("views", {}).get(str(view), {}).get("arrays", {})
    key = json.dumps({name: a.get("checksum") for name, a in sorted(arrays.items())}, sort_keys=True)
    return hashlib.sha256(f"{session.path.resolve()}:{key}".encode()).hexdigest()[:10]


def _say_resize(path: str, size: tuple[int, int], mode: str) -> None:
    """One line when a pattern was resized, with a warning when ``stretch`` changed its aspect ratio."""
    from sssphase_core.store.imageio import frame_shape

    h, w = frame_shape(Path(path))[:2]  # from the file's header (PNG/TIFF, .npy, EXR)
    if (w, h) == size or not mode:
        return
    line = f"{path}: {w}x{h} -> {size[0]}x{size[1]} ({mode})"
    if mode == "stretch" and abs((w / h) / (size[0] / size[1]) - 1) > 0.01:
        line += f"; [yellow]aspect ratio changed by {100 * abs((w / h) / (size[0] / size[1]) - 1):.0f}%[/] (fit or fill keep it)"
    console.print(line)


def relight_cmd(
    session: Annotated[Path, typer.Argument(help="Session folder (one object).")],
    pattern: Annotated[list[str], typer.Option("--pattern", help="Pattern image (PNG/TIFF, float TIFF/EXR or a .npy array of values in [0, 1]) or a named pattern (checkerboard, stripes_x, ...); repeat.")],
    backend: Annotated[str, typer.Option("--backend", help="auto (blend with --checkpoint, else analytic), torch, "
                                         "analytic, blend (torch and analytic weighted pixel by pixel by how well they "
                                         "relight the view's own fringe captures; needs --checkpoint), measured (the "
                                         "session's captured light transport), none, or exact (simulated sessions "
                                         "only: the simulator's ground truth, for evaluation).")] = "auto",
    checkpoint: CheckpointOpt = None,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("relit"),
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
    resize: Annotated[str, typer.Option("--resize", help="Bring patterns of another size to the projector's: fit "
                                        "(keep the aspect ratio, pad with black), fill (keep it, crop) or stretch.")] = "",
    chunk: Annotated[int, typer.Option(min=1, help="Pixels per footprint/splat chunk.")] = 1024,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
    cache: Annotated[bool, typer.Option(help="Keep predicted footprints in OUT/cache (float16) for later patterns.")] = True,
    image_format: Annotated[str, typer.Option("--format", help="png (16-bit linear, clips at 1.0), exr (float32 "
                                              "linear, unclipped) or png,exr.")] = "png",
) -> None:
    """Relight a captured object under new projector patterns (several patterns share one footprint pass)."""
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    import numpy as np

    from sssphase_core.compute import compute_device
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import resolve_checkpoint
    from sssphase_core.processing.patterns import REFERENCE_NAMES, reference_pattern
    from sssphase_core.relight import (
        BLENDS,
        MODEL_FREE,
        DotTransport,
        FootprintCache,
        check_image_formats,
        load_view,
        make_sources,
        read_pattern,
        relight_view,
        write_images,
    )
    from sssphase_core.relight.backends import check_backends, uses_decoder
    from sssphase_core.relight.evaluation import comparison_figure, relight_metrics
    from sssphase_core.relight.images import display_scale
    from sssphase_core.store.session import Session, claim_output

    formats = check_image_formats(tuple(dict.fromkeys(f.strip().lower() for f in image_format.split(",") if f.strip())))
    if "exr" in formats:
        from sssphase_core.store import exr

        if not exr.available():
            raise InputError(f"--format exr: {exr.MISSING}")
    from sssphase_core.store.imageio import RESIZE_MODES

    if resize and resize not in RESIZE_MODES:  # (read only for pattern files: checked whatever is given)
        raise InputError(f"--resize must be one of {', '.join(RESIZE_MODES)}, got {resize!r}")
    if any(not p.strip() for p in pattern):
        raise InputError("--pattern is empty: give an image file or a named pattern (checkerboard, stripes_x, ...)")
    compute_device(device)  # one line before any progress is drawn
    if checkpoint is not None:
        checkpoint = resolve_checkpoint(checkpoint)  # a run folder: its best.pt when it has one
    auto = backend == "auto"  # the best measured source the user can run (README: blend >= torch on every object tried)
    if auto:
        backend = "blend" if checkpoint is not None else "analytic"
    check_backends([backend], checkpoint)
    if checkpoint is not None and not uses_decoder(backend):
        console.print(f"note: --checkpoint is not used by --backend {backend}")
    s = Session.open(session)
    names, pats = [], []
    for v in _views(s, views):
        rv = load_view(s, v)
        if not pats:
            wp, hp = rv.proj.projector_size
            for p in pattern:
                if Path(p).is_file():  # (a folder named like a pattern does not hide the pattern)
                    names.append(Path(p).stem)
                    pats.append(read_pattern(p, (wp, hp), resize=resize))
                    _say_resize(p, (wp, hp), resize)
                elif p in rv.references:  # the session's own reference pattern
                    names.append(p)
                    pats.append(rv.references[p])
                elif p in REFERENCE_NAMES:
                    names.append(p)
                    pats.append(reference_pattern(p, wp, hp))
                else:
                    raise InputError(f"--pattern {p!r} is neither an image file nor one of {', '.join(REFERENCE_NAMES)}")
            twins = sorted({n for n in names if names.count(n) > 1})
            if twins:  # each pattern's name is its output file's
                raise InputError(f"--pattern: two patterns would both be written as {twins[0]!r}: "
                                 "rename one (the output files are named by the pattern)")
            claim_output(out, [s])  # images are named by object: another session's of the same object are not replaced
            if auto:  # said once the input is known good
                console.print(f"backend: {backend}" + ("" if checkpoint is not None else
                                                        " (no --checkpoint: the analytic model; a trained decoder blends in)"))
            if checkpoint is not None and uses_decoder(backend):
                console.print(f"decoder: {checkpoint}")
        sources = make_sources(backend, rv, checkpoint=checkpoint, device=device)
        cached = cache and not isinstance(sources[0][0], DotTransport)  # the measured transport is read, not predicted
        if cached:
            members = BLENDS.get(backend, (backend,))
            sources = [(FootprintCache(src, out / "cache" / f"{rv.object}_v{v}_{_view_tag(s, v)}_{m}_{_model_tag(checkpoint if m == 'torch' else None)}.npz",
                                       rv.proj.shape, k), k) for (src, k), m in zip(sources, members, strict=True)]
        (source, patch), *also = sources
        with _progress() as bar:
            task = bar.add_task(f"{rv.object} view {v}: {backend}", total=None)
            relit, mix = relight_view(source, patch, rv, pats, calibrate=backend not in MODEL_FREE, also=also, chunk=chunk,
                                      device=device, progress=lambda done, total, task=task: bar.update(task, completed=done, total=total))
        if mix is not None:
            weights = "; ".join(f"{m} R G B {' '.join(f'{x:.2f}' for x in row)}"
                                for m, row in zip(BLENDS.get(backend, (backend,)), np.atleast_2d(mix), strict=True))
            console.print(f"{rv.object} view {v}: {backend} footprints calibrated to the view's fringe captures "
                          f"(view-wide weights against no scattering: {weights}"
                          f"{'; refined pixel by pixel' if len(np.atleast_2d(mix)) == 1 else ''})")
        fit = getattr(source, "fit", None)  # the captured transport's noise mask, chosen on the view's fringe captures
        if fit:
            others = ", ".join(f"{s:g} px {p:.1f} dB" for s, p in fit.items() if s != source.smoothing)  # type: ignore[attr-defined]
            console.print(f"{rv.object} view {v}: captured transport denoised with the {source.smoothing:g} px noise mask "  # type: ignore[attr-defined]
                          f"(relights the view's fringe captures at {fit[source.smoothing]:.1f} dB; {others})")  # type: ignore[attr-defined]
        for cache_file, _ in sources if cached else ():
            cache_file.save()
            if cache_file.uncached:
                console.print(f"cache: {cache_file.uncached:,} footprints beyond its memory budget were not kept "
                              "(later patterns recompute them)")
        exposure = display_scale(rv.white)  # the display PNGs of a view share its white's: a dim pattern looks dim
        for name, img in zip(names, relit, strict=True):
            stem = out / f"{rv.object}_v{v}_{name}_{backend}"
            paths = write_images(stem, img, formats=formats, scale=exposure)
            line = f"wrote {', '.join(str(p) for p in paths)}"
            clipped = float((img[rv.proj.mask] > 1.0).any(axis=-1).mean()) if rv.proj.mask.any() else 0.0
            if "exr" not in formats and clipped > 0:
                line += f"  ({clipped:.1%} of the object above 1.0 clipped in the PNG: --format exr keeps them)"
            if name in rv.captured and _same_pattern(pats[names.index(name)], rv.references[name]):
                met = relight_metrics(img, rv.captured[name], rv.proj.mask)
                comparison_figure(rv.captured[name], img, rv.proj.mask, stem.with_name(stem.name + "_compare.png"),
                                  title=f"{rv.object} view {v}, {name}", metrics=met)
                line += f"  (vs reference: PSNR {met['psnr']:.2f} dB, SSIM {met['ssim']:.3f})"
            console.print(line)


def geometry_cmd(
    session: Annotated[Path, typer.Argument(help="Session folder (one object).")],
    backend: Annotated[str, typer.Option("--backend", help="torch (with --checkpoint), analytic, or exact (simulated sessions: the simulator's footprints, evaluation only).")] = "analytic",
    checkpoint: CheckpointOpt = None,
    out: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("geometry"),
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cpu",
) -> None:
    """Projector points for 3D: the decoded correspondences minus the shift that subsurface scattering
    gives them (light re-emerges displaced), predicted from the backend's footprints.

    Writes OUT/<object>/view_NNN/correspondence_for_geometry.npz: xp, yp (for triangulation), the
    decoded xp_decoded, yp_decoded (where light re-emerges: what relighting uses), shift_x, shift_y
    and mask. On a simulated session both maps are also scored against the exact correspondences.
    Only footprints that carry the skew of oblique incidence remove the bias along the baseline; the
    analytic model's are radially symmetric and correct silhouettes and material edges only."""
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    import numpy as np

    from sssphase_core.compute import compute_device
    from sssphase_core.errors import InputError
    from sssphase_core.learning.backends import available_backends
    from sssphase_core.learning.training import resolve_checkpoint
    from sssphase_core.relight import finest_psp_period, geometric_correspondence, load_view, make_source
    from sssphase_core.store.session import Session, claim_output, refuse_inside_session, view_dir_name

    compute_device(device)  # an unknown device is refused here too, not ignored by the model-free backends
    usable = ["exact", *sorted(available_backends())]
    if backend not in (*usable, "measured", "none"):
        raise InputError(f"--backend {backend!r} cannot predict the scattering shift here; use one of {', '.join(usable)}")
    if backend in ("measured", "none"):
        raise InputError(f"--backend {backend} cannot predict the scattering shift: "
                         + ("the dot-grid crops are placed by the decoded correspondences themselves, so they reproduce "
                            "the decoded points (use torch, analytic or exact)" if backend == "measured"
                            else "without scattering there is no shift"))
    s = Session.open(session)
    refuse_inside_session(out / s.name, what=f"--out {out}: its folder")  # written as OUT/<object>/view_NNN: OUT must not hold the session itself
    claim_output(out, [s])
    period = finest_psp_period(s.manifest.get("plan", {}))
    if period is None:
        raise InputError(f"{session}: its capture plan has no PSP frames, so the fringe period is unknown")
    if checkpoint is not None:
        checkpoint = resolve_checkpoint(checkpoint)
    for v in _views(s, views):
        rv = load_view(s, v)
        source, patch = make_source(backend, rv, checkpoint=checkpoint, device=device)
        with console.status(f"{rv.object} view {v}: predicting the scattering shift ({backend})"):
            geo = geometric_correspondence(source, rv.proj, patch, period)
        shift_x, shift_y = rv.proj.xp - geo.xp, rv.proj.yp - geo.yp
        folder = out / rv.object / view_dir_name(v)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / "correspondence_for_geometry.npz"
        np.savez_compressed(path, xp=geo.xp, yp=geo.yp, xp_decoded=rv.proj.xp, yp_decoded=rv.proj.yp,
                            shift_x=shift_x, shift_y=shift_y, mask=rv.proj.mask)
        m = rv.proj.mask
        line = (f"wrote {path}: median shift {np.nanmedian(shift_x[m]):+.3f} px along x, {np.nanmedian(shift_y[m]):+.3f} px "
                f"along y (projector px, period {period:g})")
        if rv.sim is not None and "gt/proj_xy" in s.arrays(v):  # evaluation only: the simulator's exact points
            gt = np.asarray(s.load(v, "gt/proj_xy"), np.float32)
            ok = m & np.isfinite(gt[..., 0])
            scores = []
            for xp, yp in ((rv.proj.xp, rv.proj.yp), (geo.xp, geo.yp)):
                scores += [float(np.median(np.hypot(xp - gt[..., 0], yp - gt[..., 1])[ok])), float(np.median((xp - gt[..., 0])[ok]))]
            line += (f"; against the exact points: decoded {scores[0]:.3f} px (bias x {scores[1]:+.3f}), "
                     f"for geometry {scores[2]:.3f} px (bias x {scores[3]:+.3f})")
        console.print(line)


def eval_relight(
    sessions: Annotated[list[Path], typer.Argument(help="Session folders, or folders holding sessions.")],
    backend: Annotated[str, typer.Option("--backend", help="Comma-separated backends (none, analytic, torch, blend, measured, exact); by default measured only where the views hold dot-grid footprints.")] = EVAL_BACKENDS,
    checkpoint: CheckpointOpt = None,
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
    out: Annotated[Path, typer.Option("--out", help="Output folder (figures, relight_eval.json / .md).")] = Path("eval_relight"),
    device: str = "cpu",
    calibrate: Annotated[bool, typer.Option(help="Mix a model's footprints with no scattering by the weight that relights "
                                            "the view's own fringe captures best (--no-calibrate: the model alone).")] = True,
) -> None:
    """Relight every reference pattern of the sessions and tabulate MSE / PSNR / SSIM over objects and views."""
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    from sssphase_core.bench.output import write_bench_report
    from sssphase_core.compute import compute_device
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import resolve_checkpoint
    from sssphase_core.relight import load_view
    from sssphase_core.relight.backends import MODEL_FREE, check_backends, uses_decoder
    from sssphase_core.relight.evaluation import aggregate, evaluate_view, lpips_note, metrics_table
    from sssphase_core.relight.views import has_captured_transport, has_references
    from sssphase_core.store.session import by_object, claim_output, find_sessions

    backends = list(dict.fromkeys(b.strip() for b in backend.split(",") if b.strip()))  # each once
    if not backends:
        raise InputError(f"--backend names no backend (got {backend!r}): give e.g. none,analytic,torch")
    if checkpoint is not None:
        checkpoint = resolve_checkpoint(checkpoint)  # a run folder: its best.pt when it has one
        if not any(map(uses_decoder, backends)):  # (the model was silently not evaluated, the checkpoint not read)
            console.print(f"note: --checkpoint is read only by torch and blend, which --backend {','.join(backends)} "
                          "does not list: add them to evaluate the model")
    check_backends(backends, checkpoint)
    compute_device(device)  # one line before any progress is drawn
    rows, found = [], find_sessions(sessions)  # a missing folder is one line before any progress is drawn
    by_object(found, purpose="their results would share names; evaluate them with separate --out folders")
    bare = []  # views without the dot-grid crops `measured` relights with
    for s in found:  # every session has views to evaluate, with references, before any work
        for v in _views(s, views):
            if not has_references(s.arrays(v)):
                raise InputError(f"{s.name} view {v} has no reference captures to evaluate against (capture with "
                                 "--reference checkerboard ...)")
            if not has_captured_transport(s.arrays(v)):
                bare.append(f"{s.name} view {v}")
    if "measured" in backends and bare:
        if backend != EVAL_BACKENDS:  # asked for: refused before any work (it failed after the other backends)
            raise InputError(f"--backend measured: {bare[0]} has no captured footprints (capture with --footprints)")
        backends.remove("measured")
        console.print(f"measured left out: {', '.join(bare[:3])}{' ...' if len(bare) > 3 else ''} holds no dot-grid "
                      "footprints (capture with --footprints)")
    claim_output(out, found)  # figures are named by object: another session's of the same object are not replaced
    if checkpoint is not None and any(uses_decoder(b) for b in backends):
        console.print(f"torch backend: {checkpoint}")
    with _progress() as bar:
        for s in found:
            for v in _views(s, views):
                rv = load_view(s, v)
                for b in backends:
                    task = bar.add_task(f"{rv.object} view {v}: {b}", total=None)
                    rows += evaluate_view(rv, b, out, checkpoint=checkpoint, device=device, calibrate=calibrate,
                                          progress=lambda d, t, task=task: bar.update(task, completed=d, total=t))
    table = metrics_table(rows)
    per_object = metrics_table(rows, by=("object", "backend"), title="Relighting per object")
    write_bench_report({"rows": rows, "aggregate": aggregate(rows), "lpips": lpips_note()}, [table, per_object],
                 out / "relight_eval.json", md=out / "relight_eval.md", title="Relighting against reference captures")
    console.print(table.markdown())
    if calibrate:  # a model relit without the view calibration is worth a word: it scores several dB lower
        for obj, view, b in dict.fromkeys((r["object"], r["view"], r["backend"]) for r in rows
                                          if r["backend"] not in MODEL_FREE and "mix" not in r):
            console.print(f"note: {obj} view {view}: {b} is not calibrated to the view (the projector patterns of its "
                          "PSP captures are unknown): the model alone")
    console.print(f"wrote {out / 'relight_eval.json'} and {out / 'relight_eval.md'}")


def bench_relight(
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md and .png written next to it).")] = Path("bench_relight.json"),
    objects: Annotated[str, typer.Option(help="Comma-separated simulated objects.")] = "soap",
    checkpoint: CheckpointOpt = None,
    backends: Annotated[str, typer.Option(help="Comma-separated backends.")] = "none,analytic,exact,torch",
    radii: Annotated[str, typer.Option(help="Footprint truncation radii (px).")] = "4,8",
    chunks: Annotated[str, typer.Option(help="Chunk sizes besides the default 1024.")] = "256,4096",
    repeats: int = 3,
) -> None:
    """Relit PSNR against run time per backend, radius, chunk and precision; cost vs lit fraction; splat FLOP/s."""
    from sssphase_core.bench import relight_bench

    ints = lambda t: tuple(int(x) for x in t.split(",") if x.strip())  # noqa: E731
    with console.status("benchmarking") as st:
        res = relight_bench.run(out, objects=tuple(o for o in objects.split(",") if o), checkpoint=checkpoint,
                                backends=tuple(b for b in backends.split(",") if b), radii=ints(radii), chunks=ints(chunks),
                                repeats=repeats, progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    console.print(f"wrote {out}, {out.with_suffix('.md')} and {res['figure']}")


def report(
    sessions: Annotated[list[Path], typer.Argument(help="Test sessions (or folders of them) with reference captures.")],
    out: Annotated[Path, typer.Option("--out", help="Report folder (index.html and img/).")] = Path("report"),
    train_sessions: Annotated[Path | None, typer.Option(help="Folder of training sessions (for the kNN table).")] = None,
    pretrain: Annotated[Path | None, typer.Option(help="Pretraining run or checkpoint (kNN table, PCA maps).")] = None,
    decoder: Annotated[Path | None, typer.Option(help="Decoder run or checkpoint (the torch rows).")] = None,
    view: Annotated[int, typer.Option(help="The view of each test session to relight.")] = 0,
    backend: BackendOpt = "none,analytic,measured,torch",
) -> None:
    """The demo's HTML report for your own sessions and runs: relit vs reference vs difference, tables, error
    against run time, kNN, PCA."""
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import resolve_checkpoint
    from sssphase_core.learning.training.checkpoints import load_checkpoint
    from sssphase_core.relight.backends import check_backends, uses_decoder
    from sssphase_core.reporting.demo import run_report
    from sssphase_core.store.session import find_sessions

    backends = tuple(dict.fromkeys(b.strip() for b in backend.split(",") if b.strip()))
    decoder = resolve_checkpoint(decoder) if decoder else None
    pretrain = resolve_checkpoint(pretrain) if pretrain else None
    # as `sss eval relight`: unknown backends and unreadable checkpoints are one line before any work (without
    # --decoder the torch rows are left out, as the default backends list them)
    blends = [b for b in backends if b != "torch" and uses_decoder(b)]
    if decoder is None and blends:
        raise InputError(f"the {blends[0]} backend blends the decoder in: it needs --decoder (a run of `sss train decoder`)")
    checked = [b for b in backends if b != "torch" or decoder is not None]
    check_backends(checked, decoder)  # loads the decoder when a backend runs it
    for ckpt in (pretrain, None if any(map(uses_decoder, checked)) else decoder):
        if ckpt is not None:
            load_checkpoint(ckpt)  # raises DataError naming what the file is
    path = run_report(out, find_sessions(sessions), train_sessions=train_sessions, pretrain=pretrain,
                      decoder=decoder, view=view, backends=backends,
                      log=lambda m: console.print(m, markup=False, highlight=False))
    console.print(f"wrote {path}")


def bench_store(
    sessions: Annotated[list[Path], typer.Argument(help="Sessions captured with --footprints --keep-dots and a --reference.")],
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_store.json"),
) -> None:
    """Bytes per stored footprint against float32 and the relit PSNR change the compact store causes."""
    from sssphase_core.bench import store_bench
    from sssphase_core.store.session import find_sessions

    with console.status("measuring the footprint store") as st:
        store_bench.run(find_sessions(sessions), out, progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    console.print(f"wrote {out} and {out.with_suffix('.md')}")


def bench_stability(
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_stability.json"),
    cases: Annotated[str, typer.Option(help="Comma-separated cases (default: all).")] = "",
    checkpoint: CheckpointOpt = None,
    backends: Annotated[str, typer.Option(help="Comma-separated backends.")] = "none,analytic,exact,torch",
) -> None:
    """Extreme materials, saturation, low light and grazing views: no NaN/inf, error per case."""
    from sssphase_core.bench import stability_bench

    with console.status("stability sweep") as st:
        res = stability_bench.run(out, cases=[c for c in cases.split(",") if c] or None, checkpoint=checkpoint,
                                  backends=tuple(b for b in backends.split(",") if b), progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    if res["non_finite"]:
        raise typer.Exit(1)


def bench_gap(
    sessions: Annotated[list[Path], typer.Argument(help="Simulated sessions (or folders of them) captured with a --reference.")],
    checkpoint: CheckpointOpt = None,
    backend: Annotated[str, typer.Option(help="The model backend whose gap to the exact footprints is decomposed.")] = "torch",
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_gap.json"),
    calibrate: Annotated[bool, typer.Option(help="The model as relighting uses it, mixed with no scattering by its "
                                            "view calibration (--no-calibrate: the model alone).")] = True,
) -> None:
    """What separates a model's relighting from the exact footprints': energy, shape, centre, angular detail,
    silhouettes (simulated sessions; the exact footprints serve evaluation only)."""
    from sssphase_core.bench import gap_bench
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import find_sessions

    try:
        chosen = [int(v) for v in views.split(",") if v.strip()] or None
    except ValueError:
        raise InputError(f"--views must be comma-separated integers, got {views!r}") from None
    with console.status("decomposing the gap") as st:
        gap_bench.run(find_sessions(sessions), out, checkpoint=checkpoint, backend=backend, views=chosen,
                      calibrate=calibrate, progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    console.print(f"wrote {out} and {out.with_suffix('.md')}")


def demo(
    out: Annotated[Path, typer.Option("--out", help="Demo folder (resumable: finished steps are skipped).")] = Path("demo"),
    preset: Annotated[str, typer.Option(help="lite (minutes on 2 CPU cores) or tiny (tests).")] = "lite",
    fresh: Annotated[bool, typer.Option("--fresh", help="Redo every step.")] = False,
    transport: Annotated[str | None, typer.Option(help="sim light transport: burley (default) or directional_dipole (footprints skewed by the incidence direction).")] = None,
    randomise_rig: Annotated[bool, typer.Option(help="Capture each training object on its own randomised sim rig (projector response, lens blur, noise, exposure, demosaicing, transport model); the unseen objects on the nominal rig.")] = False,
    three_chip: Annotated[bool, typer.Option("--three-chip", help="Capture every object with a three-chip sim camera (every pixel sees R, G and B: nothing is demosaiced; the sim option demosaic = \"none\").")] = False,
) -> None:
    """The user's path on the simulated rig: capture sessions through the daemon, pretrain and fit the decoder
    from them, relight unseen objects, evaluate, report (resumable)."""
    from sssphase_cli.progress import step_bar
    from sssphase_core.reporting.demo import run_demo
    from sssphase_daemon.client import local_client

    def log(message: str) -> None:
        console.print(message, markup=False, highlight=False)

    with local_client(on_start=lambda pid: log(f"started a local daemon with the sim rig (pid {pid})"),
                      on_stop=lambda pid: log(f"stopped the local daemon (pid {pid})"),
                      on_left=lambda pid: log(f"left the local daemon (pid {pid}) running: another client is using it "
                                              "(`sss daemon stop` ends it)")) as client:
        with step_bar(console) as progress:
            report = run_demo(out, client, preset=preset, fresh=fresh, log=log, progress=progress, transport=transport,
                              randomise_rig=randomise_rig, three_chip=three_chip)
    console.print(f"[green]report[/]: {report}")


def register(groups: dict[str, typer.Typer]) -> None:
    groups["root"].command("relight")(relight_cmd)
    groups["root"].command("geometry")(geometry_cmd)
    groups["root"].command("demo")(demo)
    groups["eval"].command("relight")(eval_relight)
    groups["bench"].command("relight")(bench_relight)
    groups["bench"].command("stability")(bench_stability)
    groups["bench"].command("store")(bench_store)
    groups["bench"].command("gap")(bench_gap)
    groups["root"].command("report")(report)
