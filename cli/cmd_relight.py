"""`sss relight`, `sss eval relight`, `sss demo`, `sss bench relight`, `sss bench stability`."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from sssphase_core.errors import InputError

console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)

BackendOpt = Annotated[str, typer.Option("--backend", help="torch, analytic, blend (torch and analytic weighted by how well they relight the view's own fringe captures; needs --checkpoint), measured (the session's captured dot-grid footprints), none, or exact (simulated sessions only: the simulator's ground truth, for evaluation).")]
CheckpointOpt = Annotated[Path | None, typer.Option("--checkpoint", help="Decoder checkpoint for the torch backend.")]


def _progress():
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console)


#: `sss eval relight`'s backends unless --backend names others (measured left out where no view has crops);
#: the same as ``sssphase_core.relight.runner.EVAL_BACKENDS`` (the CLI does not import core at start-up).
EVAL_BACKENDS = "none,analytic,measured"

SessionArg = Annotated[Path, typer.Argument(help="Session folder (one object).")]
PatternOpt = Annotated[list[str], typer.Option("--pattern", help="Pattern image (PNG/TIFF, float TIFF/EXR or a .npy array of values in [0, 1]) or a named pattern (checkerboard, stripes_x, ...); repeat. A video (MP4, MOV, AVI, MKV, WebM), an animated GIF/PNG or a folder of images is relit frame by frame, on its own.")]
RelightBackendOpt = Annotated[str, typer.Option("--backend", help="auto (blend with --checkpoint, else analytic), torch, "
                                                "analytic, blend (torch and analytic weighted pixel by pixel by how well they "
                                                "relight the view's own fringe captures; needs --checkpoint), measured (the "
                                                "session's captured light transport), none, or exact (simulated sessions "
                                                "only: the simulator's ground truth, for evaluation); comma-separated for "
                                                "several, each written beside the others.")]
GeometryBackendOpt = Annotated[str, typer.Option("--backend", help="torch (with --checkpoint), analytic, or exact (simulated sessions: the simulator's footprints, evaluation only).")]
EvalBackendOpt = Annotated[str, typer.Option("--backend", help="Comma-separated backends (none, analytic, torch, blend, measured, exact); by default measured only where the views hold dot-grid footprints.")]
OutOpt = Annotated[Path, typer.Option("--out", help="Output folder.")]
EvalOutOpt = Annotated[Path, typer.Option("--out", help="Output folder (figures, relight_eval.json / .md).")]
ViewsOpt = Annotated[str, typer.Option(help="Comma-separated views (default: all).")]
ResizeOpt = Annotated[str, typer.Option("--resize", help="Bring patterns of another size to the projector's: fit "
                                        "(keep the aspect ratio, pad with black), fill (keep it, crop) or stretch.")]
ChunkOpt = Annotated[int, typer.Option(min=1, help="Pixels per footprint/splat chunk.")]
DeviceOpt = Annotated[str, typer.Option(help="cpu, cuda or cuda:N: where the models compute their footprints (the "
                                        "decoder, the analytic model and its parts of the decoder's) and the splat "
                                        "runs; on a GPU the footprints stay there.")]
PrecisionOpt = Annotated[str, typer.Option(help="The decoder's inference: auto (bf16 where the device computes it "
                                           "natively: CUDA GPUs from Ampere, CPUs with AVX512-BF16 or AMX; else "
                                           "fp32), fp32 or bf16.")]
CacheOpt = Annotated[bool, typer.Option(help="Keep predicted footprints in OUT/cache (float16) for later patterns.")]
EvalCacheOpt = Annotated[bool, typer.Option(help="Keep the models' footprints in OUT/cache (float16) for the next evaluation; "
                                            "start from those `sss train decoder --check-sessions` kept for the same view and checkpoint.")]
FormatOpt = Annotated[str, typer.Option("--format", help="png (16-bit linear, clips at 1.0), exr (float32 "
                                        "linear, unclipped) or png,exr.")]
def _widen_range(value: float | None) -> float | None:
    """Refuse a stretch that is not a number from 1 to 4 in words that say so (NaN fails typer's bounds as 'above 4')."""
    if value is None:
        return None
    from sssphase_core.relight.choices import WIDEN_MAX

    if not 1.0 <= value <= WIDEN_MAX:
        raise typer.BadParameter(f"{value!r} is not a stretch from 1 to {WIDEN_MAX:g} (1: the footprints as they are)")
    return value


WidenOpt = Annotated[float | None, typer.Option(callback=_widen_range, help="Let the view calibration also widen the model's "
                                               "footprints (a blend's decoder's): they join its fit stretched this many times along x, along "
                                               "y and along both, and softened at their own width, and the view's own "
                                               "fringes weigh the four (default: 1.3 "
                                               "for backends that run the decoder, 1 for the others; 1: the footprints "
                                               "as they are, only narrowed).")]
CalibrateOpt = Annotated[bool, typer.Option(help="Mix a model's footprints with no scattering by the weight that relights "
                                            "the view's own fringe captures best (--no-calibrate: the model alone).")]


class _Narrator:
    """The runner's narration (``sssphase_core.relight.runner.Narrator``) on this console: lines printed as
    they come (the warning part in yellow), progress bars and spinners drawn with rich."""

    def __init__(self) -> None:
        self._bar = None

    def say(self, text: str, warning: str = "") -> None:
        console.print(text.replace(warning, f"[yellow]{warning}[/]", 1) if warning else text)

    @contextmanager
    def bar(self) -> Iterator[None]:
        with _progress() as self._bar:
            yield
        self._bar = None

    def task(self, label: str):
        bar = self._bar
        task = bar.add_task(label, total=None)
        return lambda done, total: bar.update(task, completed=done, total=total)

    def status(self, label: str):
        return console.status(label)


def relight_cmd(
    session: SessionArg,
    pattern: PatternOpt,
    backend: RelightBackendOpt = "auto",
    checkpoint: CheckpointOpt = None,
    out: OutOpt = Path("relit"),
    views: ViewsOpt = "",
    resize: ResizeOpt = "",
    chunk: ChunkOpt = 1024,
    device: DeviceOpt = "cpu",
    cache: CacheOpt = True,
    image_format: FormatOpt = "png",
    widen: WidenOpt = None,
    precision: PrecisionOpt = "auto",
) -> None:
    """Relight a captured object under new projector patterns (several patterns share one footprint pass), or under
    every frame of a video or an animated image (frames and an MP4 per view; an interrupted run resumes)."""
    from sssphase_core.errors import InputError
    from sssphase_core.processing.patterns import REFERENCE_NAMES
    from sssphase_core.relight.choices import uses_decoder
    from sssphase_core.relight.runner import relight_backends, relight_session
    from sssphase_core.relight.sequence import relight_sequence
    from sssphase_core.store.pattern_sequences import is_sequence

    names = relight_backends(backend, checkpoint)  # every name checked before any work
    sequences = [p for p in pattern if p not in REFERENCE_NAMES and is_sequence(p)]  # (a folder named like a named pattern does not hide it)
    if sequences and len(pattern) > 1:
        raise InputError(f"--pattern {sequences[0]} is a sequence of frames (a video, an animated image or a folder of "
                         "images): relight it on its own, one --pattern per run")
    for name in names:  # (a listed backend without the decoder is not told that the checkpoint is unused)
        own = checkpoint if len(names) == 1 or uses_decoder(name) else None
        run = relight_sequence if sequences else relight_session
        run(session, sequences[0] if sequences else pattern, backend=name, checkpoint=own, out=out, views=views,
            resize=resize, chunk=chunk, device=device, cache=cache, formats=image_format, widen=widen, narrator=_Narrator(),
            precision=precision)


def geometry_cmd(
    session: SessionArg,
    backend: GeometryBackendOpt = "analytic",
    checkpoint: CheckpointOpt = None,
    out: OutOpt = Path("geometry"),
    views: ViewsOpt = "",
    device: DeviceOpt = "cpu",
    calibration: Annotated[Path | None, typer.Option(help="The rig's camera-projector calibration, an OpenCV YAML, XML "
                                                     "or JSON file (cam_K, cam_kc, proj_K, proj_kc, R, T as "
                                                     "projector-camera calibration writes them, or K1, D1, K2, D2, R, "
                                                     "T), to triangulate 3D points (default: a simulated session's "
                                                     "own rig).")] = None,
    crop_radius: Annotated[float | None, typer.Option(help="Merge only the points within this distance of the "
                                                      "turntable's axis (the calibration's unit): a wall or a rig behind "
                                                      "the object is left out of points_merged.ply.")] = None,
    refine_axis: Annotated[bool, typer.Option("--refine-axis", help="Refine the turntable's axis from the views' own "
                                              "overlaps before merging (a point-to-plane ICP that moves only the axis); "
                                              "where they pin it down, the merge is about it and "
                                              "OUT/<object>/calibration_refined.yml is written with it.")] = False,
    mesh: Annotated[bool, typer.Option("--mesh", help="Also write each view's points as a range-image mesh, "
                                       "mesh.ply (neighbouring pixels joined into triangles, depth steps left "
                                       "open).")] = False,
) -> None:
    """Projector points for 3D: the decoded correspondences minus the shift that subsurface scattering
    gives them (light re-emerges displaced), predicted from the backend's footprints, and the 3D points.

    Writes OUT/<object>/view_NNN/correspondence_for_geometry.npz: xp, yp (for triangulation), the
    decoded xp_decoded, yp_decoded (where light re-emerges: what relighting uses), shift_x, shift_y
    and mask. With a calibration (a simulated session has its own), also points and points_decoded
    (H x W x 3, the calibration's unit) and points.ply, the corrected points coloured by the white
    capture; shift.png shows the shift (and in depth, with a calibration). On a simulated session both
    are also scored against the exact ones.
    Only footprints that carry the skew of oblique incidence remove the bias along the baseline; the
    analytic model's are radially symmetric and correct silhouettes and material edges only."""
    from sssphase_core.relight.runner import geometry_session

    geometry_session(session, backend=backend, checkpoint=checkpoint, out=out, views=views, device=device,
                     calibration=calibration, crop_radius=crop_radius, refine_axis=refine_axis, mesh=mesh,
                     narrator=_Narrator())


def eval_relight(
    sessions: Annotated[list[Path], typer.Argument(help="Session folders, or folders holding sessions.")],
    backend: EvalBackendOpt = EVAL_BACKENDS,
    checkpoint: CheckpointOpt = None,
    views: ViewsOpt = "",
    out: EvalOutOpt = Path("eval_relight"),
    device: str = "cpu",
    calibrate: CalibrateOpt = True,
    cache: EvalCacheOpt = True,
    widen: WidenOpt = None,
    precision: PrecisionOpt = "auto",
) -> None:
    """Relight every reference pattern of the sessions and tabulate MSE / PSNR / SSIM over objects and views."""
    from sssphase_core.errors import InputError
    from sssphase_core.relight.runner import evaluate_sessions

    if out.suffix.lower() in (".json", ".md") and not out.is_dir():  # (it made a folder named X.json)
        raise InputError(f"--out {out}: sss eval relight writes a folder (its figures, relight_eval.json and "
                         f"relight_eval.md): give a folder name, e.g. {out.with_suffix('')}")
    evaluate_sessions(sessions, backend=backend, checkpoint=checkpoint, views=views, out=out, device=device,
                      calibrate=calibrate, cache=cache, widen=widen, narrator=_Narrator(), precision=precision)


def _names(text: str, option: str) -> tuple[str, ...]:
    """Comma-separated names, each once; one line when they name nothing (``,`` had run every case, or none)."""
    from sssphase_core.learning.inputs import parse_names

    names = tuple(parse_names(text, ()))
    if not names:
        raise InputError(f"{option} {text!r} names nothing: give comma-separated names")
    return names


def bench_relight(
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md and .png written next to it).")] = Path("bench_relight.json"),
    objects: Annotated[str, typer.Option(help="Comma-separated simulated objects.")] = "soap",
    checkpoint: CheckpointOpt = None,
    backends: Annotated[str, typer.Option(help="Comma-separated backends (torch and blend need --checkpoint).")] = "none,analytic,exact,torch,blend",
    radii: Annotated[str, typer.Option(help="Footprint truncation radii (px).")] = "4,8",
    chunks: Annotated[str, typer.Option(help="Chunk sizes besides the default 1024.")] = "256,4096",
    repeats: Annotated[int, typer.Option(min=1, help="Timed runs of each configuration.")] = 3,
) -> None:
    """Relit PSNR against run time per backend, radius, chunk and precision; cost vs lit fraction; splat FLOP/s."""
    from sssphase_core.learning.inputs import parse_ints

    chosen = _names(backends, "--backends")
    if checkpoint is None and not set(chosen) - {"torch", "blend"}:
        raise InputError(f"--backends {backends} needs --checkpoint (a decoder run): nothing else is left to measure")
    radii_px, chunk_sizes = tuple(parse_ints(radii, "--radii")), tuple(parse_ints(chunks, "--chunks"))
    from sssphase_core.bench import relight_bench  # torch: after the options are read
    with console.status("benchmarking") as st:
        res = relight_bench.run(out, objects=tuple(o for o in objects.split(",") if o), checkpoint=checkpoint,
                                backends=chosen, radii=radii_px, chunks=chunk_sizes,
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
    backend: Annotated[str, typer.Option("--backend", help="Comma-separated backends to relight with: none, analytic, "
                                         "measured, torch (needs --decoder), blend (torch and analytic weighted by how "
                                         "well they relight the view's own fringe captures; needs --decoder) or exact "
                                         "(simulated sessions only).")] = "none,analytic,measured,torch",
) -> None:
    """The demo's HTML report for your own sessions and runs: relit vs reference vs difference, tables, error
    against run time, kNN, PCA."""
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    from sssphase_core.errors import InputError
    from sssphase_core.learning.runlog import check_checkpoint_file, resolve_checkpoint
    from sssphase_core.relight.choices import check_backends, uses_decoder
    from sssphase_core.store.session import find_sessions

    backends = tuple(dict.fromkeys(b.strip() for b in backend.split(",") if b.strip()))
    decoder = resolve_checkpoint(decoder) if decoder else None
    pretrain = resolve_checkpoint(pretrain) if pretrain else None
    # as `sss eval relight`: unknown backends and unreadable checkpoints are one line before any work, and
    # before torch is imported where the file alone shows it (without --decoder the torch rows are left out,
    # as the default backends list them)
    blends = [b for b in backends if b != "torch" and uses_decoder(b)]
    if decoder is None and blends:
        raise InputError(f"the {blends[0]} backend blends the decoder in: it needs --decoder (a run of `sss train decoder`)")
    for ckpt in (pretrain, decoder):
        if ckpt is not None:
            check_checkpoint_file(ckpt)
    checked = [b for b in backends if b != "torch" or decoder is not None]
    check_backends(checked, decoder)  # loads the decoder when a backend runs it
    from sssphase_core.reporting.demo import run_report

    for ckpt in (pretrain, None if any(map(uses_decoder, checked)) else decoder):
        if ckpt is not None:
            from sssphase_core.learning.training.checkpoints import load_checkpoint  # torch: only now

            kind = load_checkpoint(ckpt).get("kind")  # raises DataError naming what the file is
            if ckpt == pretrain and kind not in (None, "pretrain"):  # its options were tabled as pretraining's
                raise InputError(f"--pretrain {ckpt} is a {kind} checkpoint: give the run of `sss train pretrain`"
                                 + (" (and this one as --decoder)" if kind == "decoder" else ""))
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


def bench_geometry(
    sessions: Annotated[list[Path], typer.Argument(help="Simulated sessions (e.g. `sss capture --transport directional_dipole`).")],
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_geometry.json"),
    backends: Annotated[str, typer.Option(help="Comma-separated backends (torch needs --checkpoint).")] = "exact,analytic",
    checkpoint: CheckpointOpt = None,
) -> None:
    """Correspondences for geometry (`sss geometry`) per backend against the simulator's exact points."""
    from sssphase_core.bench import geometry_bench
    from sssphase_core.store.session import find_sessions

    with console.status("scoring correspondences for geometry") as st:
        geometry_bench.run(find_sessions(sessions), out, _names(backends, "--backends"),
                           checkpoint, progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    console.print(f"wrote {out} and {out.with_suffix('.md')}")


def bench_axis(
    sessions: Annotated[list[Path], typer.Argument(help="Simulated turntable sessions (`sss capture --object soap --views 4`).")],
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_axis.json"),
    tilt: Annotated[float, typer.Option(help="Degrees the axis is turned by (about the camera's axis).")] = 3.0,
    move: Annotated[float, typer.Option(help="How far the axis is moved along x (the calibration's unit).")] = 8.0,
    backends: Annotated[str, typer.Option(help="Comma-separated backends whose scattering shift is taken out of the "
                                          "points (as sss geometry --backend).")] = "exact,analytic",
    views: ViewsOpt = "",
) -> None:
    """The turntable's axis refined from the views' overlaps (`sss geometry --refine-axis`) against the merge about
    the rig's own axis and one turned and moved, scored against the simulator's exact surface."""
    from sssphase_core.bench import axis_bench
    from sssphase_core.store.session import find_sessions

    with console.status("refining turntable axes") as st:
        axis_bench.run(find_sessions(sessions), out, tilt, move, _names(backends, "--backends"), views=views,
                       progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    console.print(f"wrote {out} and {out.with_suffix('.md')}")


def bench_stability(
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_stability.json"),
    cases: Annotated[str, typer.Option(help="Comma-separated cases (default: all).")] = "",
    checkpoint: CheckpointOpt = None,
    backends: Annotated[str, typer.Option(help="Comma-separated backends (torch and blend need --checkpoint).")] = "none,analytic,exact,torch,blend",
) -> None:
    """Extreme materials, saturation, low light and grazing views: no NaN/inf, error per case."""
    chosen_cases, chosen = list(_names(cases, "--cases")) if cases else None, _names(backends, "--backends")
    from sssphase_core.bench import stability_bench  # torch: after the options are read

    with console.status("stability sweep") as st:
        res = stability_bench.run(out, cases=chosen_cases, checkpoint=checkpoint, backends=chosen,
                                  progress=lambda m: st.update(m))
    console.print(out.with_suffix(".md").read_text())
    if res["non_finite"]:
        raise typer.Exit(1)


def bench_relight_cache(
    session: Annotated[Path, typer.Argument(help="A session view with reference patterns or any named one.")],
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_relight_cache.json"),
    backend: Annotated[str, typer.Option(help="A model backend: analytic, torch or blend.")] = "analytic",
    checkpoint: CheckpointOpt = None,
    view: Annotated[int, typer.Option(min=0, help="The view to relight.")] = 0,
    first: Annotated[str, typer.Option(help="The first relight's pattern (computes the footprints).")] = "checkerboard",
    new: Annotated[str, typer.Option(help="The later pattern, from the cache and from scratch.")] = "stripes_y",
    frames: Annotated[int, typer.Option(min=2, max=10_000, help="Frames of the clip relit as a sequence.")] = 100,
) -> None:
    """A new pattern relit from a view's cached eigen-footprints against the full relight: seconds, peak RSS,
    agreement (three `sss relight` processes); and a clip relit as a sequence, its cost per frame."""
    from sssphase_core.bench import relight_cache_bench
    from sssphase_core.errors import InputError

    if backend not in ("analytic", "torch", "blend"):
        raise InputError(f"--backend {backend}: the eigen-footprint cache is kept for the model backends "
                         "(analytic, torch, blend)")
    if first == new:  # the "new" pattern would be the one the first relight made: nothing new to time
        raise InputError(f"--new {new} is the --first pattern: give another pattern to relight from the cache")
    with console.status("four relights (cold, cached, full, a sequence)"):
        relight_cache_bench.run(session, out, backend=backend, checkpoint=checkpoint, view=view, first=first, new=new,
                                frames=frames)
    console.print(out.with_suffix(".md").read_text())


def bench_gap(
    sessions: Annotated[list[Path], typer.Argument(help="Simulated sessions (or folders of them) captured with a --reference.")],
    checkpoint: CheckpointOpt = None,
    backend: Annotated[str, typer.Option(help="The model backend whose gap to the exact footprints is decomposed.")] = "torch",
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
    out: Annotated[Path, typer.Option("--out", help="JSON output (.md written next to it).")] = Path("bench_gap.json"),
    calibrate: Annotated[bool, typer.Option(help="The model's footprints mixed with no scattering by its view-wide "
                                            "calibration weight (footprints, not images: without the widening, per-pixel "
                                            "weights and white-consistent gain `sss relight` adds; --no-calibrate: the "
                                            "model alone).")] = True,
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
    transport: Annotated[str | None, typer.Option(help="sim light transport: burley (default), directional_dipole (footprints skewed by the incidence direction) or radiative (random-walk profiles, no diffusion approximation).")] = None,
    training_rigs: Annotated[str, typer.Option(help="The training objects' sim rigs: nominal, camera (each object its own randomised camera and projector: response, lens blur, noise, exposure, demosaicing) or randomised (the transport model drawn too); the unseen objects always on the nominal rig.")] = "nominal",
    three_chip: Annotated[bool, typer.Option("--three-chip", help="Capture every object with a three-chip sim camera (every pixel sees R, G and B: nothing is demosaiced; the sim option demosaic = \"none\").")] = False,
) -> None:
    """The user's path on the simulated rig: capture sessions through the daemon, pretrain and fit the decoder
    from them, relight unseen objects, evaluate, report (resumable)."""
    from sssphase_cli.progress import step_bar
    from sssphase_core.reporting.demo import check_demo_options, run_demo
    from sssphase_daemon.client import local_client

    def log(message: str) -> None:
        console.print(message, markup=False, highlight=False)

    check_demo_options(out, preset, transport, training_rigs)  # before a daemon is started for them
    with local_client(on_start=lambda pid: log(f"started a local daemon (pid {pid})"),
                      on_stop=lambda pid: log(f"stopped the local daemon (pid {pid})"),
                      on_left=lambda pid: log(f"left the local daemon (pid {pid}) running: another client is using it "
                                              "(`sss daemon stop` ends it)")) as client:
        with step_bar(console) as progress:
            report = run_demo(out, client, preset=preset, fresh=fresh, log=log, progress=progress, transport=transport,
                              training_rigs=training_rigs, three_chip=three_chip)
    console.print(f"[green]report[/]: {report}")


def register(groups: dict[str, typer.Typer]) -> None:
    groups["root"].command("relight")(relight_cmd)
    groups["root"].command("geometry")(geometry_cmd)
    groups["root"].command("demo")(demo)
    groups["eval"].command("relight")(eval_relight)
    groups["bench"].command("relight")(bench_relight)
    groups["bench"].command("stability")(bench_stability)
    groups["bench"].command("relight-cache")(bench_relight_cache)
    groups["bench"].command("store")(bench_store)
    groups["bench"].command("geometry")(bench_geometry)
    groups["bench"].command("axis")(bench_axis)
    groups["bench"].command("gap")(bench_gap)
    groups["root"].command("report")(report)
