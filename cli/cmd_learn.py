"""`sss train pretrain|decoder`, `sss eval knn|footprints`, `sss viz pca`: the learning commands.

Data come from the simulated rig (default: ``--source sim``); patches are cached under ``--cache``.
Each train/eval command parses its options and calls one runner of
:mod:`sssphase_core.reporting.learning_runs`, which says what it does through the :class:`Report` made here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from sssphase_cli.progress import step_bar
from sssphase_cli.run_config import ConfigOpt, run_config_file
from sssphase_core.learning.inputs import DEFAULT_CACHE, Report

console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)

ObjectsOpt = Annotated[str, typer.Option("--objects", help="Comma-separated object names (default: the paper's split).")]
ViewsOpt = Annotated[str | None, typer.Option("--views", help="Comma-separated view indices (with --sessions, default: "
                                                "every complete view).")]
CacheOpt = Annotated[Path, typer.Option("--cache", help="Folder caching simulated views (.npz).")]
SessionsOpt = Annotated[
    Path | None, typer.Option("--sessions", help="Folder of captured sessions (one per object), or one session folder, "
                              "to use instead of the simulator.")
]
MAX_SEED = 2**32 - 1  # numpy's and torch's seeds take it; the loop derives per-step seeds from it
NViewsOpt = Annotated[int, typer.Option(min=1, help="Turntable views per object (simulator).")]
DeterministicOpt = Annotated[bool, typer.Option(
    help="CUDA: deterministic kernels, so a resumed run ends with exactly an uninterrupted run's weights (`sss bench "
         "gpu` measures the cost; the docs' paper-scale page gives an H200's: SimSiam resumed exactly without them, the decoder did "
         "not); the CPU's kernels always are.")]
SeedOpt = Annotated[int, typer.Option(min=0, max=MAX_SEED, help="Random seed (sampling, augmentations, weights): the "
                                      "same seed and inputs give the same run.")]
EpochsOpt = Annotated[int, typer.Option(min=1, max=100_000, help="Passes over the sampled patches.")]
PixelsOpt = Annotated[int, typer.Option(min=1, help="Surface pixels sampled per view.")]
RigOpt = Annotated[str, typer.Option(help="Simulated rig preset when no --sessions are given (cpu: K=32, paper: K=90; "
                                     "`sss rigs`).")]
DeviceOpt = Annotated[str, typer.Option(help="Where to train: auto (a GPU where torch sees one, else cpu), cpu, cuda "
                                        "or cuda:N.")]
BatchOpt = Annotated[int, typer.Option(min=1, help="Patches per step.")]
ResumeOpt = Annotated[bool, typer.Option(help="Continue from out/last.pt when present (--no-resume starts afresh "
                                         "into an empty --out).")]
CkptEveryOpt = Annotated[int, typer.Option(min=0, help="Steps between mid-epoch checkpoints (0: epoch ends only).")]
TimeLimitOpt = Annotated[float | None, typer.Option(
    "--time-limit", min=0.001, help="Seconds this run may train: it stops at the last epoch end that fits (its "
    "schedule stays sized to --epochs; rerun to continue).")]
ResultOpt = Annotated[Path | None, typer.Option(help="JSON output (a .md table is written next to it).")]
EncoderOpt = Annotated[Path | None, typer.Option("--encoder", help="Pretraining checkpoint (run folder or .pt).")]
EndToEndOpt = Annotated[bool, typer.Option("--end-to-end", help="No --encoder: train encoder and decoder together "
                                           "from random weights (the supervised U-Net baseline, no SSL).")]
ValViewsOpt = Annotated[str | None, typer.Option(help="Held-out views of the same objects for validation (with "
                                                 "--sessions, default: each session's last view when it has two or more; "
                                                 "\"\" for none).")]
HeadOpt = Annotated[str, typer.Option(help="reciprocal (energy from the PSP patch x learned shape) or direct (the paper's head).")]
AuxClassesOpt = Annotated[int, typer.Option(help="0: none; else an auxiliary material-classification head with this many "
                                            "classes (>= 2, more than the largest material label).")]
LearnGainOpt = Annotated[bool, typer.Option("--learn-gain", help="Reciprocal head: also learn a per-colour energy "
                                            "gain (default: energy from reciprocity alone).")]
CaptureModelOpt = Annotated[bool, typer.Option(help="Compare each predicted footprint with its captured crop as the "
                                               "crop recorded it (moved to where its dot lit the surface, then the "
                                               "camera's Bayer sampling and demosaicing), so the decoder predicts the "
                                               "light entering at the pixel (--no-capture-model: the crops are the "
                                               "targets, blurred by both).")]
CameraAugmentOpt = Annotated[float, typer.Option(min=0.0, max=1.0, help="Show the decoder each PSP patch as "
                                                 "another camera would have recorded it, each step with this "
                                                 "probability: Bayer resampling and demosaicing, lens blur, noise, a "
                                                 "response error on the fringes (0: as captured).")]
CheckSessionsOpt = Annotated[list[Path] | None, typer.Option(
    "--check-sessions", help="Sessions with reference captures (e.g. captured with --reference checkerboard) on "
    "which the trained model is relit against the none and analytic baselines; repeatable. Default: --sessions.")]
CompareOpt = Annotated[list[str] | None, typer.Option("--compare", help="NAME=PATH: another decoder run in the table "
                                                     "(repeat; e.g. unet=runs/dec_e2e from --end-to-end).")]
#: how the runners' marked words look (``Report.style`` kinds)
STYLES = {"strong": "bold", "note": "yellow", "warning": "bold yellow", "done": "green"}


def _report() -> Report:
    """The runners' lines printed, their long steps as spinners and training steps as progress bars."""
    return Report(say=console.print, status=console.status, steps=lambda: step_bar(console),
                  style=lambda text, kind: f"[{STYLES[kind]}]{text}[/]")


def _png_out(out: Path, example: str, *also: Path) -> None:
    """Refuse a figure's ``--out`` that is no .png file name (a folder became FOLDER.png and 'x.txt' failed after
    all the work), that lies inside a session, or that (or a companion figure in ``also``) would replace a file
    sssphase did not write, before any work."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.files import ours_to_replace
    from sssphase_core.store.session import refuse_inside_session

    if out.is_dir() or out.suffix.lower() != ".png":
        raise InputError(f"--out {out}: give a .png file name (e.g. {out / example if out.is_dir() else out.with_suffix('.png')})")
    refuse_inside_session(out.parent, f"--out {out}: its folder")
    ours_to_replace(out, "--out")
    for path in also:
        ours_to_replace(path, f"--out {out}: its companion figure")


def _check_result_file(out: Path | None) -> None:
    """Refuse, before any work, a result file inside a session or on its own Markdown twin."""
    if out is not None:
        from sssphase_core.bench.output import check_result_paths

        check_result_paths(out, out.with_suffix(".md"))


def _write(out: Path | None, payload: dict, markdown: str) -> None:
    _check_result_file(out)
    console.print(markdown)
    if out is not None:
        from sssphase_core.store.results import write_result_files

        write_result_files(payload, out, out.with_suffix(".md"), markdown)
        console.print(f"wrote {out} and {out.with_suffix('.md')}")


# --- train -------------------------------------------------------------------------------------------


def train_pretrain(
    ctx: typer.Context,
    config: ConfigOpt = None,
    out: Annotated[Path, typer.Option("--out", help="Run folder (checkpoint last.pt, metrics.jsonl).")] = Path("runs/pretrain"),
    preset: Annotated[str, typer.Option(help="Model preset: lite or paper.")] = "lite",
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    n_views: NViewsOpt = 4,
    rig: Annotated[str, typer.Option(help="Simulated rig preset (cpu: K=32, paper: K=90).")] = "cpu",
    pixels_per_view: Annotated[int, typer.Option(min=1, help="Surface pixels sampled per view.")] = 2000,
    epochs: EpochsOpt = 10,
    batch_size: Annotated[int, typer.Option(min=1, help="Patches per step (at least 2: SimSiam's BatchNorm).")] = 64,
    lr: Annotated[float, typer.Option(help="Learning rate (SGD with momentum; warmup, then cosine decay).")] = 0.05,
    warmup_epochs: Annotated[float, typer.Option(help="Epochs of linear learning-rate warmup (>= 0), then cosine decay.")] = 2.0,
    augment: Annotated[str, typer.Option(help="psp (weak/strong PSP set) or imagenet (baseline).")] = "psp",
    fix_pred_lr: Annotated[bool, typer.Option(help="Keep the predictor at the base lr (no schedule).")] = True,
    decorrelate: Annotated[float, typer.Option(help="Weight of the projections' decorrelation term against "
                                               "dimensional collapse (>= 0; 0: SimSiam alone).")] = 1.0,
    phase_shift: Annotated[bool, typer.Option(help="The psp strong view also moves the fringes by a random phase "
                                              "(ours; --no-phase-shift: the paper's set alone).")] = True,
    knn_monitor: Annotated[int, typer.Option(min=0, help="Training patches in the per-epoch kNN monitor (0: off).")] = 2000,
    seed: SeedOpt = 0,
    ckpt_every: CkptEveryOpt = 50,
    time_limit: TimeLimitOpt = None,
    device: DeviceOpt = "auto",
    deterministic: DeterministicOpt = False,
    resume: Annotated[bool, typer.Option(help="Continue from out/last.pt when present.")] = True,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """SimSiam pretraining of the encoder on PSP patches of the training objects (resumable)."""
    from sssphase_core.reporting.learning_runs import PretrainOptions, run_pretrain

    opts = PretrainOptions(
        out=out, preset=preset, objects=objects, views=views, n_views=n_views, rig=rig, pixels_per_view=pixels_per_view,
        epochs=epochs, batch_size=batch_size, lr=lr, warmup_epochs=warmup_epochs, augment=augment,
        fix_pred_lr=fix_pred_lr, decorrelate=decorrelate, phase_shift=phase_shift, knn_monitor=knn_monitor, seed=seed, ckpt_every=ckpt_every, time_limit=time_limit,
        device=device, deterministic=deterministic, resume=resume, cache=cache, sessions=sessions)
    run_pretrain(opts, _report(), config_file=run_config_file(ctx))


def train_decoder(
    ctx: typer.Context,
    config: ConfigOpt = None,
    encoder: EncoderOpt = None,
    end_to_end: EndToEndOpt = False,
    preset: Annotated[str, typer.Option(help="Model preset of an --end-to-end run (lite or paper).")] = "lite",
    out: Annotated[Path, typer.Option("--out", help="Run folder.")] = Path("runs/decoder"),
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    val_views: ValViewsOpt = None,
    n_views: NViewsOpt = 4,
    rig: RigOpt = "cpu",
    pixels_per_view: PixelsOpt = 2000,
    noisy_targets: Annotated[bool, typer.Option(help="Add capture noise to the footprint targets.")] = False,
    epochs: EpochsOpt = 10,
    batch_size: BatchOpt = 32,
    lr: Annotated[float, typer.Option(help="Learning rate (Adam).")] = 1e-3,
    head: HeadOpt = "reciprocal",
    aux_classes: AuxClassesOpt = 0,
    learn_gain: LearnGainOpt = False,
    capture_model: CaptureModelOpt = True,
    camera_augment: CameraAugmentOpt = 0.0,
    seed: SeedOpt = 0,
    ckpt_every: CkptEveryOpt = 50,
    time_limit: TimeLimitOpt = None,
    device: DeviceOpt = "auto",
    deterministic: DeterministicOpt = True,
    resume: ResumeOpt = True,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
    check_sessions: CheckSessionsOpt = None,
) -> None:
    """Fit the footprint decoder with the SBH loss on the frozen encoder, or end-to-end (resumable)."""
    from sssphase_core.reporting.learning_runs import DecoderOptions, run_decoder

    given = getattr(ctx.get_parameter_source("preset"), "name", "")  # typed on the command line (not a default/config)
    opts = DecoderOptions(
        encoder=encoder, end_to_end=end_to_end, preset=preset, preset_given=given in ("COMMANDLINE", "ENVIRONMENT"),
        out=out, objects=objects, views=views, val_views=val_views, n_views=n_views, rig=rig,
        pixels_per_view=pixels_per_view, noisy_targets=noisy_targets, epochs=epochs, batch_size=batch_size, lr=lr,
        head=head, aux_classes=aux_classes, learn_gain=learn_gain, capture_model=capture_model,
        camera_augment=camera_augment, seed=seed,
        ckpt_every=ckpt_every, time_limit=time_limit, device=device, deterministic=deterministic, resume=resume,
        cache=cache, sessions=sessions, check_sessions=check_sessions)
    run_decoder(opts, _report(), config_file=run_config_file(ctx))


# --- eval --------------------------------------------------------------------------------------------


def eval_knn(
    checkpoint: Annotated[list[str], typer.Option("--checkpoint", help="NAME=PATH (repeat to compare, e.g. psp=... imagenet=...).")],
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    n_views: NViewsOpt = 4,
    rig: RigOpt = "cpu",
    pixels_per_view: PixelsOpt = 1000,
    k: Annotated[str, typer.Option(help="Neighbours; a comma list adds a sweep (the table uses the first).")] = "20",
    vote: Annotated[str, typer.Option(help="majority or weighted.")] = "majority",
    label: Annotated[str, typer.Option(help="object (the paper's Table 2) or material.")] = "object",
    seed: Annotated[int, typer.Option(min=0, max=MAX_SEED, help="Pixel sampling seed (use one the encoder was not "
                                      "trained on for new patches).")] = 1,
    out: ResultOpt = None,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """kNN accuracy of frozen embeddings with view-level leave-one-out (cosine similarity)."""
    from sssphase_core.reporting.learning_runs import KnnOptions, evaluate_knn

    _check_result_file(out)
    result = evaluate_knn(KnnOptions(checkpoints=checkpoint, objects=objects, views=views, n_views=n_views, rig=rig,
                                     pixels_per_view=pixels_per_view, k=k, vote=vote, label=label, seed=seed,
                                     cache=cache, sessions=sessions), _report())
    _write(out, result.payload, result.markdown())


def eval_footprints(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Decoder checkpoint (run folder or .pt).")],
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    n_views: NViewsOpt = 4,
    rig: RigOpt = "cpu",
    pixels_per_view: PixelsOpt = 500,
    baseline: Annotated[str, typer.Option(help="Backend to compare with ('' for none).")] = "analytic",
    compare: CompareOpt = None,
    seed: SeedOpt = 2,
    plots: Annotated[Path | None, typer.Option(help="Folder for footprint profile plots (one per object).")] = None,
    out: ResultOpt = None,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
    precision: Annotated[str, typer.Option(help="The decoders' inference: auto (bf16 where the device computes it "
                                                "natively), fp32 or bf16.")] = "auto",
) -> None:
    """MSE, PSNR (data range 1) and SSIM (data range = GT peak) per object, like the paper's Table 1."""
    from sssphase_core.reporting.learning_runs import FootprintOptions, evaluate_footprints

    _check_result_file(out)
    result = evaluate_footprints(FootprintOptions(
        checkpoint=checkpoint, objects=objects, views=views, n_views=n_views, rig=rig, pixels_per_view=pixels_per_view,
        baseline=baseline, compare=compare, seed=seed, plots=plots, cache=cache, sessions=sessions, precision=precision),
        _report())
    _write(out, result.payload, result.markdown())


# --- viz ---------------------------------------------------------------------------------------------


def viz_pca(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Encoder checkpoint (pretraining or decoder run).")],
    objects: Annotated[str, typer.Option(help="Comma-separated objects shown side by side (default: every session "
                                         "under --sessions, else the simulator's soap and shovel).")] = "",
    view: Annotated[int, typer.Option(min=0, help="The view of each object shown.")] = 0,
    n_views: NViewsOpt = 4,
    rig: RigOpt = "cpu",
    stride: Annotated[int, typer.Option(min=1, help="Embed every stride-th pixel in x and y.")] = 2,
    out: Annotated[Path, typer.Option(help="PNG output.")] = Path("pca_rgb.png"),
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """PCA-RGB map: joint PCA of the patch embeddings of the images shown, first 3 components as RGB."""
    from sssphase_core.learning.inputs import ViewOptions
    from sssphase_core.reporting.learning_runs import pca_figure

    _png_out(out, "pca_rgb.png")
    data = ViewOptions(n_views=n_views, rig=rig, seed=0, cache=cache, sessions=sessions)
    vds = pca_figure(checkpoint, objects, view, data, stride, out, _report())
    console.print(f"wrote {out} ({', '.join(v.object for v in vds)}, view {view})")


def viz_footprints(
    session: Annotated[Path, typer.Argument(help="Session folder (captured with --footprints for the 'captured' row).")],
    backend: Annotated[str, typer.Option(help="Comma-separated rows: captured (the session's dot-grid crops), torch, "
                                         "analytic, exact (sim sessions), none.")] = "captured,analytic",
    checkpoint: Annotated[Path | None, typer.Option(help="Decoder checkpoint for the torch row.")] = None,
    view: Annotated[int, typer.Option(min=0, help="The session's view whose footprints are shown.")] = 0,
    pixels: Annotated[int, typer.Option(min=1, max=16, help="Pixels shown (spread over the object).")] = 6,
    out: Annotated[Path, typer.Option(help="PNG output (profiles in <out>_profiles.png).")] = Path("footprints.png"),
) -> None:
    """Footprints at a few pixels, one row per source (log scale), and their centre-row profiles."""
    from sssphase_core.reporting.learning_runs import footprint_figures, profiles_path

    _png_out(out, "footprints.png", profiles_path(out))
    fig = footprint_figures(session, view, backend, out=out, pixels=pixels, checkpoint=checkpoint, report=_report())
    console.print(f"wrote {fig.figure} and {fig.profiles} ({', '.join(fig.rows)} at {len(fig.pixels)} pixels of "
                  f"{fig.session} view {view})")


def bench_learn(
    out: Annotated[Path, typer.Option(help="JSON output.")] = Path("bench_learn.json"),
    md: Annotated[Path | None, typer.Option(help="Markdown table output.")] = None,
    repeats: Annotated[int, typer.Option(min=1, help="Timed runs of each measurement.")] = 3,
    device: Annotated[str, typer.Option(help="cpu, cuda or cuda:N (auto: CUDA when torch sees one)")] = "cpu",
) -> None:
    """Throughput (patches/s) of the lite and paper presets, inference and training, ratio to paper."""
    from sssphase_core.bench.output import check_result_paths
    from sssphase_core.compute import check_device

    check_device(device)  # one line before any work (it was torch's own error after the timing began)
    check_result_paths(out, md)
    from sssphase_core.bench.learn_bench import learn_bench
    from sssphase_core.bench.output import machine_info, write_bench_report

    results, tables = learn_bench(repeats=repeats, device=device, status=console.status)
    write_bench_report({"machine": machine_info(), "device": device, "results": results}, tables, out, md,
                       title="sss bench learn")
    for table in tables:
        console.print(table.markdown())


def bench_gpu(
    out: Annotated[Path, typer.Option(help="JSON output (a Markdown table is written next to it).")] = Path("benchmarks/gpu.json"),
    device: Annotated[str, typer.Option(help="auto (CUDA when torch sees one), cuda, cuda:N or cpu (plumbing)")] = "auto",
    preset: Annotated[str, typer.Option(help="model preset (paper, lite, ...)")] = "paper",
    steps: Annotated[int, typer.Option(help="training steps of each stage")] = 200,
    batch: Annotated[int, typer.Option(min=1, help="patches per step")] = 32,
    epochs: Annotated[int, typer.Option(min=1, help="epochs the steps are split into (one loss figure each)")] = 4,
    md: Annotated[Path | None, typer.Option(help="Markdown output (default: next to --out)")] = None,
) -> None:
    """The GPU path: paper-preset training with mixed precision, CPU/GPU agreement, relighting, NCCL DDP."""
    from sssphase_cli.output import write_result
    from sssphase_core.compute import check_device

    check_device(device)  # one line before any work (and before torch is imported)
    from sssphase_core.bench.gpu_bench import markdown, run
    from sssphase_core.learning.models import get_preset

    get_preset(preset)  # an unknown preset is one line before any work

    with console.status("sss bench gpu") as status:
        result = run(out, device=device, preset=preset, steps=steps, batch=batch, epochs=epochs,
                     progress=lambda stage: status.update(f"sss bench gpu: {stage}"))
    write_result(console, out, md, result, markdown(result))


def register(groups: dict[str, typer.Typer]) -> None:
    groups["bench"].command("learn")(bench_learn)
    groups["bench"].command("gpu")(bench_gpu)
    groups["train"].command("pretrain")(train_pretrain)
    groups["train"].command("decoder")(train_decoder)
    groups["eval"].command("knn")(eval_knn)
    groups["eval"].command("footprints")(eval_footprints)
    groups["viz"].command("pca")(viz_pca)
    groups["viz"].command("footprints")(viz_footprints)
