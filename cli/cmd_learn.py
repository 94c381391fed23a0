"""`sss train pretrain|decoder`, `sss eval knn|footprints`, `sss viz pca`: the learning commands.

Data come from the simulated rig (default: ``--source sim``); patches are cached under ``--cache``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from sssphase_cli.progress import step_bar
from sssphase_cli.run_config import ConfigOpt, check_run_config, save_run_config

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
         "gpu` measures the cost; the README gives an H200's: SimSiam resumed exactly without them, the decoder did "
         "not); the CPU's kernels always are.")]
DEFAULT_CACHE = Path(".sss_cache")


MAX_LR = 10.0  # SimSiam's SGD rate is 0.05 x batch/256 (0.8 at batch 4096); Adam's 1e-3


def _check_lr(lr: float) -> None:
    """A learning rate is a finite number > 0 (NaN or a negative one would fail or diverge after the first step)
    and at most :data:`MAX_LR` (above it, a run diverges, or, with the decoder's bounded heads, silently learns nothing)."""
    import math

    from sssphase_core.errors import InputError

    if not (math.isfinite(lr) and lr > 0):
        raise InputError(f"--lr must be a finite number > 0, got {lr}")
    if lr > MAX_LR:
        raise InputError(f"--lr must be at most {MAX_LR:g}, got {lr:g} (defaults: 0.05 for pretraining, 1e-3 for the decoder)")


def _check_batch(batch_size: int, ds, what: str) -> None:
    """Before the run's folder is written: at least one whole batch (the loop drops a last, partial one)."""
    if len(ds) < batch_size:
        from sssphase_core.errors import InputError

        raise InputError(f"--batch-size {batch_size} is more than the {len(ds)} {what}: lower it, or sample more "
                         "--pixels-per-view / views")


def _check_out(ctx: typer.Context, out: Path, kind: str, resume: bool) -> bool:
    """Before any data is read: refuse an ``out`` that is a session or holds another kind of run, or a run
    resumed with options that shaped it changed. True when the run will resume from ``out``."""
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import check_run_folder
    from sssphase_core.store.session import MANIFEST, check_output_folder

    check_output_folder(out)  # not inside a session (a view folder)
    if out.is_dir() and any((child / MANIFEST).is_file() for child in out.iterdir() if child.is_dir()):
        raise InputError(f"--out {out} holds sessions: give the run a folder of its own (e.g. runs/{kind})")
    resuming = check_run_folder(out, kind) is not None and resume
    check_run_config(ctx, out, resuming=resuming)
    return resuming


def _names(text: str, default: tuple[str, ...]) -> list[str]:
    """Comma-separated names, each once (``apple,apple`` read the session twice and skewed kNN's accuracies)."""
    return list(dict.fromkeys(t.strip() for t in text.split(",") if t.strip())) if text else list(default)


def _png_out(out: Path, example: str) -> None:
    """Refuse a figure's ``--out`` that is no .png file name (a folder became FOLDER.png and 'x.txt' failed after
    all the work) or that lies inside a session, before any work."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import refuse_inside_session

    if out.is_dir() or out.suffix.lower() != ".png":
        raise InputError(f"--out {out}: give a .png file name (e.g. {out / example if out.is_dir() else out.with_suffix('.png')})")
    refuse_inside_session(out.parent, f"--out {out}: its folder")


def _ints(text: str, option: str = "--views") -> list[int]:
    from sssphase_core.errors import InputError

    try:
        return [int(t) for t in text.split(",") if t.strip()]
    except ValueError as exc:
        raise InputError(f"{option} expects comma-separated integers, got {text!r}") from exc


def _chosen(views: str | None, sim_default: str, sessions: Path | None) -> list[int] | None:
    """The --views given, else every complete view of the sessions (None), else the simulator's default views."""
    if views is not None:
        return list(dict.fromkeys(_ints(views)))  # a view named twice is read once (it trained twice as often)
    return None if sessions is not None else _ints(sim_default)


def _used_views(views: str | None, vds) -> str:
    """The --views as given, or the views that were read (the sessions' own), for tables and JSON."""
    return views if views is not None else ",".join(map(str, sorted({v.view for v in vds})))


def _views(objects: list[str], views: list[int] | dict[str, list[int]] | None, *, n_views: int, rig: str,
           pixels: int | None, footprints: bool, seed: int, cache: Path, noisy: bool = False, sessions: Path | None = None,
           role: str = "data"):
    """Views from captured sessions (``--sessions``; ``views`` None: every complete view, or per object) or else
    rendered by the simulator."""
    if sessions is not None:
        from sssphase_core.learning.data import session_views

        with console.status(f"reading sessions under {sessions}"):
            vds = session_views(sessions, objects or None, views or None, pixels_per_view=pixels, footprints=footprints,
                                seed=seed)
        if not vds:
            from sssphase_core.errors import InputError

            why = "" if Path(sessions).is_dir() else " (a file, not a folder)" if Path(sessions).exists() else " (no such folder)"
            raise InputError(f"no complete session views under {sessions}{why}")
        console.print(f"{role}: captured sessions under {sessions}: {_describe(vds)}")
        return vds
    from sssphase_core.learning.data import simulate_views

    wanted = sorted({v for vs in (views.values() if isinstance(views, dict) else [views or []]) for v in vs})
    if wanted and wanted[-1] >= n_views:  # view 0 was simulated before "view must be in [0, 1)"
        from sssphase_core.errors import InputError

        raise InputError(f"views {','.join(map(str, wanted))} need --n-views above {wanted[-1]} (the turntable's views "
                         f"per object; it is {n_views}): pass --views within 0..{n_views - 1} or raise --n-views")
    with console.status(f"simulating {len(objects)} object(s) x {len(views)} view(s) (cached in {cache})"):
        vds = simulate_views(objects, views, n_views=n_views, rig=rig, pixels_per_view=pixels, footprints=footprints,
                             noisy_footprints=noisy, seed=seed, cache_dir=cache)
    console.print(f"{role}: the simulated rig ({rig} preset{', exact footprints' if footprints and not noisy else ''}): "
                  f"{_describe(vds)}; pass --sessions DIR to use your own captures")
    return vds


def _describe(vds) -> str:
    views: dict[str, list[int]] = {}
    for v in vds:
        views.setdefault(v.object, []).append(v.view)
    return "; ".join(f"{o} view {','.join(map(str, vs))}" for o, vs in views.items())


def _objects(vds) -> list[str]:
    return list(dict.fromkeys(v.object for v in vds))


def _check_result_file(out: Path | None) -> None:
    """Refuse, before any work, a result file inside a session or on its own Markdown twin."""
    if out is not None:
        from sssphase_core.bench.output import check_result_paths

        check_result_paths(out, out.with_suffix(".md"))


def _write(out: Path | None, payload: dict, markdown: str) -> None:
    _check_result_file(out)
    console.print(markdown)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(payload, indent=2))
        out.with_suffix(".md").write_text(markdown + "\n")
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
    epochs: Annotated[int, typer.Option(min=1, max=100_000)] = 10,
    batch_size: Annotated[int, typer.Option(min=1, help="Patches per step (at least 2: SimSiam's BatchNorm).")] = 64,
    lr: float = 0.05,
    warmup_epochs: Annotated[float, typer.Option(help="Epochs of linear learning-rate warmup (>= 0), then cosine decay.")] = 2.0,
    augment: Annotated[str, typer.Option(help="psp (weak/strong PSP set) or imagenet (baseline).")] = "psp",
    fix_pred_lr: Annotated[bool, typer.Option(help="Keep the predictor at the base lr (no schedule).")] = True,
    knn_monitor: Annotated[int, typer.Option(min=0, help="Training patches in the per-epoch kNN monitor (0: off).")] = 2000,
    seed: Annotated[int, typer.Option(min=0, max=MAX_SEED)] = 0,
    ckpt_every: Annotated[int, typer.Option(min=0, help="Steps between mid-epoch checkpoints (0: epoch ends only).")] = 50,
    device: str = "auto",
    deterministic: DeterministicOpt = False,
    resume: Annotated[bool, typer.Option(help="Continue from out/last.pt when present.")] = True,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """SimSiam pretraining of the encoder on PSP patches of the training objects (resumable)."""
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.models import get_preset
    from sssphase_core.learning.runlog import read_rows
    from sssphase_core.learning.training import METRICS, PretrainConfig, _knn_monitor_indices, pretrain
    from sssphase_core.learning.training.pretrain import check_pretrain_options
    from sssphase_core.reporting.figures import plot_metric_vs_time
    from sssphase_core.sim import TRAIN_OBJECTS

    _check_lr(lr)
    check_pretrain_options(batch_size, warmup_epochs, augment)
    p = get_preset(preset)
    resuming = _check_out(ctx, out, "pretrain", resume)
    names = _names(objects, () if sessions else TRAIN_OBJECTS)
    vds = _views(names, _chosen(views, "0,1,2,3", sessions), n_views=n_views, rig=rig, pixels=pixels_per_view,
                 footprints=False, seed=seed, cache=cache, sessions=sessions)
    names = names or _objects(vds)
    ds = PatchDataset(vds, p.patch, names)
    _check_batch(batch_size, ds, "training patches")
    if knn_monitor and _knn_monitor_indices(ds, knn_monitor, seed) is None:
        console.print("note: the kNN monitor is off: it needs two views (leave one view out) and two objects (a "
                      "one-object vote is always right)")
    if warmup_epochs >= epochs:
        console.print(f"[yellow]note:[/] --warmup-epochs {warmup_epochs:g} is not shorter than --epochs {epochs}: the "
                      f"learning rate rises for the whole run, to about {epochs / warmup_epochs:.2g} x --lr, and never decays")
    cfg = PretrainConfig(epochs=epochs, batch_size=batch_size, seed=seed, ckpt_every=ckpt_every, device=device, preset=preset,
                         deterministic=deterministic, lr=lr, warmup_epochs=warmup_epochs, fix_pred_lr=fix_pred_lr, augment=augment, knn_monitor=knn_monitor)
    console.print(f"pretraining [bold]{preset}[/] on {len(ds)} patches of {', '.join(names)} -> {out} "
                  f"(options in {save_run_config(ctx, out, resuming=resuming)})")
    with step_bar(console) as progress:
        path = pretrain(cfg, ds, out, resume=resume, progress=progress)
    _print_final(out / METRICS, ("loss", "knn_acc", "eff_rank"), "knn_acc")
    rows = [r for r in read_rows(out / METRICS) if "knn_acc" in r]
    if rows:
        plot_metric_vs_time(out / METRICS, "knn_acc", out / "knn_vs_time.png", log=False, chance=1 / len(names),
                            ylabel="kNN accuracy (fraction, training patches)",
                            title=f"kNN monitor against run time ({len(names)} objects)")
        trail = ", ".join(f"{100 * r['knn_acc']:.1f}" for r in rows)
        console.print(f"kNN monitor (% per epoch, training patches): {trail}; plot {out / 'knn_vs_time.png'}")
    console.print(f"[green]done[/]: {path}")


def train_decoder(
    ctx: typer.Context,
    config: ConfigOpt = None,
    encoder: Annotated[Path | None, typer.Option("--encoder", help="Pretraining checkpoint (run folder or .pt).")] = None,
    end_to_end: Annotated[bool, typer.Option("--end-to-end", help="No --encoder: train encoder and decoder together "
                                             "from random weights (the supervised U-Net baseline, no SSL).")] = False,
    preset: Annotated[str, typer.Option(help="Model preset of an --end-to-end run (lite or paper).")] = "lite",
    out: Annotated[Path, typer.Option("--out", help="Run folder.")] = Path("runs/decoder"),
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    val_views: Annotated[str | None, typer.Option(help="Held-out views of the same objects for validation (with "
                                                  "--sessions, default: each session's last view when it has two or more; "
                                                  "\"\" for none).")] = None,
    n_views: NViewsOpt = 4,
    rig: str = "cpu",
    pixels_per_view: Annotated[int, typer.Option(min=1)] = 2000,
    noisy_targets: Annotated[bool, typer.Option(help="Add capture noise to the footprint targets.")] = False,
    epochs: Annotated[int, typer.Option(min=1, max=100_000)] = 10,
    batch_size: Annotated[int, typer.Option(min=1)] = 32,
    lr: float = 1e-3,
    head: Annotated[str, typer.Option(help="reciprocal (energy from the PSP patch x learned shape) or direct (the paper's head).")] = "reciprocal",
    aux_classes: Annotated[int, typer.Option(help="0: none; else an auxiliary material-classification head with this many "
                                             "classes (>= 2, more than the largest material label).")] = 0,
    learn_gain: Annotated[bool, typer.Option("--learn-gain", help="Reciprocal head: also learn a per-colour energy "
                                             "gain (default: energy from reciprocity alone).")] = False,
    capture_model: Annotated[bool, typer.Option(help="Compare each predicted footprint with its captured crop as the "
                                                "crop recorded it (moved to where its dot lit the surface, then the "
                                                "camera's Bayer sampling and demosaicing), so the decoder predicts the "
                                                "light entering at the pixel (--no-capture-model: the crops are the "
                                                "targets, blurred by both).")] = True,
    seed: Annotated[int, typer.Option(min=0, max=MAX_SEED)] = 0,
    ckpt_every: Annotated[int, typer.Option(min=0, help="Steps between mid-epoch checkpoints (0: epoch ends only).")] = 50,
    device: str = "auto",
    deterministic: DeterministicOpt = True,
    resume: bool = True,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
    check_sessions: Annotated[list[Path] | None, typer.Option(
        "--check-sessions", help="Sessions with reference captures (e.g. captured with --reference checkerboard) on "
        "which the trained model is relit against the none and analytic baselines; repeatable. Default: --sessions.")] = None,
) -> None:
    """Fit the footprint decoder with the SBH loss on the frozen encoder, or end-to-end (resumable)."""
    from sssphase_core.errors import InputError
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.models.decoder import HEADS
    from sssphase_core.learning.training import METRICS, DecoderConfig, decoder_patch
    from sssphase_core.learning.training import train_decoder as fit
    from sssphase_core.learning.training.decoder import check_aux_classes
    from sssphase_core.reporting.figures import plot_metric_vs_time
    from sssphase_core.sim import TRAIN_OBJECTS

    _check_lr(lr)
    check_aux_classes(aux_classes)
    if head not in HEADS:
        raise InputError(f"unknown decoder head {head!r}; choose one of {', '.join(HEADS)}")
    if (encoder is None) == (not end_to_end):
        raise InputError("give either --encoder PATH (a pretraining run; the paper's method) or --end-to-end (the "
                         "supervised baseline without SSL), not both or neither")
    given = getattr(ctx.get_parameter_source("preset"), "name", "")  # typed on the command line (not a default/config)
    if encoder is not None and given in ("COMMANDLINE", "ENVIRONMENT"):
        raise InputError("--preset sets the model of an --end-to-end run; with --encoder the decoder takes the encoder's "
                         "preset (it was ignored, and config.toml recorded the wrong one)")
    patch = decoder_patch(None if end_to_end else encoder, preset)
    resuming = _check_out(ctx, out, "decoder", resume)
    names = _names(objects, () if sessions else TRAIN_OBJECTS)
    kw = dict(n_views=n_views, rig=rig, pixels=pixels_per_view, footprints=True, seed=seed, cache=cache, noisy=noisy_targets,
              sessions=sessions)
    train_views, held = _chosen(views, "0,1,2", sessions), _chosen(val_views, "3", sessions)
    if sessions is not None and held is None:  # the default: each session's last view held out, when it has two
        from sssphase_core.learning.data import held_out_split

        split_train, split_val = held_out_split(sessions, names or None)
        if train_views is None:
            train_views, held = (split_train, split_val) if any(split_val.values()) else (None, [])
        else:  # the views given train; a last view that is not among them validates
            left = {o: [v for v in vs if v not in train_views] for o, vs in split_val.items()}
            held = left if any(left.values()) else []
    if check_sessions:  # a typo here was found only after the whole training
        from sssphase_core.store.session import find_sessions

        find_sessions(check_sessions)
    train_vds = _views(names, train_views, **kw)
    val_vds = _views(names, held, role="validation (held out)", **kw) if held else []
    both = sorted({(v.object, v.view) for v in train_vds} & {(v.object, v.view) for v in val_vds})
    if both:  # it was labelled "held out" and chose best.pt
        raise InputError(f"--val-views: {', '.join(f'{o} view {v}' for o, v in both)} "
                         f"{'is also a training view' if len(both) == 1 else 'are also training views'}; validation views "
                         "must be held out")
    names = names or _objects([*train_vds, *val_vds])
    ds = PatchDataset(train_vds, patch, names, with_targets=True)
    val = PatchDataset(val_vds, patch, names, with_targets=True) if val_vds else None
    _check_batch(batch_size, ds, "training footprints")
    check_aux_classes(aux_classes, ds)
    cfg = DecoderConfig(epochs=epochs, batch_size=batch_size, seed=seed, ckpt_every=ckpt_every, device=device, lr=lr,
                        deterministic=deterministic, head=head, aux_classes=aux_classes, preset=preset, learn_gain=learn_gain,
                        capture_model=capture_model)
    what = f"encoder and decoder end-to-end ({preset})" if end_to_end else "the decoder"
    console.print(f"training {what} on {len(ds)} footprints of {', '.join(names)} -> {out} "
                  f"(options in {save_run_config(ctx, out, resuming=resuming)})")
    with step_bar(console) as progress:
        path = fit(cfg, encoder, ds, out, val=val, resume=resume, progress=progress)
    if val is not None:
        plot_metric_vs_time(out / METRICS, ("loss", "val_loss"), out / "error_vs_time.png", log=False,
                            ylabel="SBH loss", right=("val_psnr",),
                            right_label="validation footprint PSNR (dB)", title="decoder error against run time")
        console.print(f"validation error against run time: {out / 'error_vs_time.png'}")
    _print_final(out / METRICS, ("val_loss", "val_psnr"), "val_loss")
    console.print(f"[green]done[/]: {path}")
    held_out = sorted({vd.view for vd in val_vds}) if sessions and not check_sessions else []  # the held-out views
    _check_against_baselines(out, check_sessions or ([sessions] if sessions else []), held_out or None, device)


def _print_final(metrics: Path, names: tuple[str, ...], monitored: str) -> None:
    """The last epoch's figures and the epoch kept in best.pt."""
    from sssphase_core.learning.runlog import read_rows
    from sssphase_core.learning.training import BEST

    rows = read_rows(metrics)
    if not rows:
        return
    last = rows[-1]
    figures = ", ".join(f"{n} {last[n]:.4g}" for n in names if n in last)
    if figures:
        console.print(f"final (epoch {last['epoch']}): {figures}")
    best = last.get("best_epoch")
    if best is not None:
        row = next(r for r in rows if r["epoch"] == best)
        console.print(f"best {monitored} at epoch {best} ({row[monitored]:.4g}): {metrics.parent / BEST} "
                      "(what backends load from this run folder)")


def _check_against_baselines(run: Path, roots: list[Path], views: list[int] | None, device: str) -> None:
    """Relight held-out views with reference captures by the new model and the none/analytic baselines."""
    from sssphase_core.relight.evaluation import baseline_check
    from sssphase_core.store.session import find_sessions

    if not roots:
        console.print("no --check-sessions: relighting against the baselines was not checked")
        return
    if device == "auto":
        from sssphase_core.learning.training import init_distributed

        device = str(init_distributed(device).device)
    with console.status("relighting held-out views against the none and analytic baselines"):
        res = baseline_check(find_sessions(roots), run, run / "check", views=views, device=device)
    if not res["views"]:
        console.print(f"[yellow]not checked:[/] no view of {', '.join(map(str, roots))} has reference captures "
                      "(capture one with --reference checkerboard and pass it as --check-sessions)")
        return
    where = ", ".join(f"{o} view {v}" for o, v in res["views"])
    figures = ", ".join(f"{b} {psnr:.2f} dB" for b, psnr in res["mean_psnr"].items())
    console.print(f"relit PSNR on {where}: {figures}")
    for b in res["losing_to"]:
        console.print(f"[bold yellow]warning:[/] the model relights worse than the {b} baseline "
                      f"({res['mean_psnr']['torch']:.2f} < {res['mean_psnr'][b]:.2f} dB): prefer the baseline, or train on more data")


# --- eval --------------------------------------------------------------------------------------------


def eval_knn(
    checkpoint: Annotated[list[str], typer.Option("--checkpoint", help="NAME=PATH (repeat to compare, e.g. psp=... imagenet=...).")],
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    n_views: NViewsOpt = 4,
    rig: str = "cpu",
    pixels_per_view: Annotated[int, typer.Option(min=1)] = 1000,
    k: Annotated[str, typer.Option(help="Neighbours; a comma list adds a sweep (the table uses the first).")] = "20",
    vote: Annotated[str, typer.Option(help="majority or weighted.")] = "majority",
    label: Annotated[str, typer.Option(help="object (the paper's Table 2) or material.")] = "object",
    seed: Annotated[int, typer.Option(min=0, max=MAX_SEED, help="Pixel sampling seed (use one the encoder was not "
                                      "trained on for new patches).")] = 1,
    out: Annotated[Path | None, typer.Option(help="JSON output (a .md table is written next to it).")] = None,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """kNN accuracy of frozen embeddings with view-level leave-one-out (cosine similarity)."""
    import numpy as np

    from sssphase_core.errors import InputError

    _check_result_file(out)
    from sssphase_core.learning.evaluation import knn_of_views, knn_tables
    from sssphase_core.learning.training import load_encoder
    from sssphase_core.sim import MATERIAL_NAMES, TRAIN_OBJECTS

    pairs = [c.split("=", 1) if "=" in c else (Path(c).stem if Path(c).suffix else Path(c).name, c) for c in checkpoint]
    from sssphase_core.store.session import NAME_RE

    names_given = [n for n, _ in pairs]
    for (name, _), item in zip(pairs, checkpoint, strict=True):  # a column each: one name, plain
        if not NAME_RE.fullmatch(name) or names_given.count(name) > 1:
            raise InputError(f"--checkpoint takes NAME=PATH (or PATH) with a distinct name of letters, digits, '_', "
                             f"'-', '.', got {item!r}")
    runs = dict(pairs)
    missing = [path for path in runs.values() if not Path(path).exists()]
    if missing:  # before any view is read or simulated
        raise InputError(f"no checkpoint at {missing[0]} (a pretraining run folder or its .pt file)")
    names = _names(objects, () if sessions else TRAIN_OBJECTS)
    if label not in ("object", "material"):
        raise InputError(f"--label must be object or material, got {label!r}")
    ks = _ints(k, "--k")
    if not ks or min(ks) < 1:
        raise InputError(f"--k needs one or more positive integers, got {k!r}")
    vds = _views(names, _chosen(views, "0,1,2,3", sessions), n_views=n_views, rig=rig, pixels=pixels_per_view,
                 footprints=False, seed=seed, cache=cache, sessions=sessions)
    names = names or _objects(vds)
    n_patches = sum(len(v.pixels) for v in vds)
    classes = (set(v.object for v in vds) if label == "object"
               else {int(m) for v in vds for m in np.unique(v.materials) if m >= 0})
    if len(classes) < 2:  # every patch would get the one label: 100% that measures nothing
        raise InputError(f"kNN by {label} needs two or more {label}s to tell apart; the views read hold "
                         + (f"only {', '.join(map(str, sorted(classes)))}" if classes else "no material labels (sessions "
                            "without ground truth: use --label object)"))
    per_view: dict[int, int] = {}
    for v in vds:  # leave-one-view-out: the patches of one view index are the queries, the others the database
        per_view[v.view] = per_view.get(v.view, 0) + len(v.pixels)
    database = n_patches - max(per_view.values())
    if max(ks) >= database:  # (it was clamped to the database in silence and reported as given)
        raise InputError(f"--k {max(ks)} is not smaller than the {database} patches of the smallest leave-one-view-out "
                         f"database ({n_patches} read, {max(per_view.values())} of them in one view): every patch would "
                         "get the majority label; lower --k or raise --pixels-per-view")
    results = {}
    for run, path in runs.items():
        with console.status(f"embedding {sum(len(v.pixels) for v in vds)} patches with {run}"):
            sweep = knn_of_views(load_encoder(path), vds, names, label=label, material_names=list(MATERIAL_NAMES),
                                 ks=ks, vote=vote)
        res = sweep[ks[0]]
        res["overall_by_k"] = {kk: r["overall"] for kk, r in sweep.items()}
        results[run] = res
    used = _used_views(views, vds)
    tables = knn_tables(results, label=label, ks=ks, vote=vote, views=used)
    _write(out, {"k": ks[0], "vote": vote, "label": label, "views": used, "results": results},
           "\n".join(t.markdown() for t in tables))


def eval_footprints(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Decoder checkpoint (run folder or .pt).")],
    objects: ObjectsOpt = "",
    views: ViewsOpt = None,
    n_views: NViewsOpt = 4,
    rig: str = "cpu",
    pixels_per_view: Annotated[int, typer.Option(min=1)] = 500,
    baseline: Annotated[str, typer.Option(help="Backend to compare with ('' for none).")] = "analytic",
    compare: Annotated[list[str] | None, typer.Option("--compare", help="NAME=PATH: another decoder run in the table "
                                                      "(repeat; e.g. unet=runs/dec_e2e from --end-to-end).")] = None,
    seed: Annotated[int, typer.Option(min=0, max=MAX_SEED)] = 2,
    plots: Annotated[Path | None, typer.Option(help="Folder for footprint profile plots (one per object).")] = None,
    out: Annotated[Path | None, typer.Option(help="JSON output (a .md table is written next to it).")] = None,
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """MSE, PSNR (data range 1) and SSIM (data range = GT peak) per object, like the paper's Table 1."""
    _check_result_file(out)
    if plots is not None:
        from sssphase_core.store.session import check_output_folder

        check_output_folder(plots, "--plots")
    import numpy as np

    from sssphase_core.errors import DataError, InputError
    from sssphase_core.learning.backends import get_backend
    from sssphase_core.learning.evaluation import footprint_metrics, footprint_table, summarise
    from sssphase_core.reporting.figures import plot_profiles
    from sssphase_core.sim import UNSEEN_OBJECTS, rig_preset

    names = _names(objects, () if sessions else UNSEEN_OBJECTS)
    from sssphase_core.store.session import NAME_RE

    others = [item.partition("=") for item in compare or []]
    for (name, sep, _), item in zip(others, compare or [], strict=True):  # NAME names output files
        if not sep or not NAME_RE.fullmatch(name) or name in ("torch", baseline) or [o[0] for o in others].count(name) > 1:
            raise InputError(f"--compare takes NAME=PATH with a new name of letters, digits, '_', '-', '.', got {item!r}")
    backends = {"torch": get_backend("torch", checkpoint=checkpoint)}  # checked before any data is read
    backends.update({name: get_backend("torch", checkpoint=path) for name, _, path in others})
    if baseline == "torch":  # the model itself (it said "pass checkpoint=... or call fit()" after reading the data)
        raise InputError("--baseline torch is the model --checkpoint gives; compare another decoder with --compare "
                         "NAME=RUN, or choose a baseline that is no decoder (analytic, or '' for none)")
    vds = _views(names, _chosen(views, "0", sessions), n_views=n_views, rig=rig, pixels=pixels_per_view, footprints=True, seed=seed,
                 cache=cache, sessions=sessions)
    names = names or _objects(vds)
    if baseline:
        patch = backends["torch"].patch
        opts = {"patch": patch, "black": rig_preset(rig).projector.black} if baseline == "analytic" else {}
        backends[baseline] = get_backend(baseline, **opts)
    from sssphase_core.relight.evaluation import lpips_note

    console.print(lpips_note())
    results: dict[str, dict[str, dict[str, float]]] = {}
    for obj in names:
        obj_views = [v for v in vds if v.object == obj]
        gt = np.concatenate([np.asarray(v.footprints) for v in obj_views])
        bad = int(np.count_nonzero(~np.isfinite(gt).all(axis=(1, 2, 3))))
        if bad:  # the table read NaN (and its JSON was no JSON)
            raise DataError(f"{bad} of the {len(gt)} sampled footprint crops of {obj} hold NaN or infinite values: the "
                            "session's footprint crops are corrupt (a capture never stores them)")
        results[obj] = {}
        preds = {}
        for bname, be in backends.items():
            with console.status(f"{bname}: predicting {len(gt)} footprints of {obj}"):
                preds[bname] = np.concatenate([be.predict_footprints((v.psp, v.pixels)) for v in obj_views])
            results[obj][bname] = summarise(footprint_metrics(preds[bname], gt))
        if plots is not None:
            plots.mkdir(parents=True, exist_ok=True)
            i = int(np.argmax(gt.sum(axis=(1, 2, 3))))
            for bname, pred in preds.items():
                plot_profiles(gt[i], pred[i], plots / f"{obj}_{bname}.png", title=f"{obj}: {bname}")
    note = ("PSNR: data range 1 (white reference = 1.0); SSIM: 11x11 Gaussian window, data range = each GT footprint's peak; "
            f"{lpips_note()}.")
    used = _used_views(views, vds)
    _write(out, {"objects": names, "views": used, "results": results, "note": note},
           footprint_table(results, views=used, note=note).markdown())


# --- viz ---------------------------------------------------------------------------------------------


def viz_pca(
    checkpoint: Annotated[Path, typer.Option("--checkpoint", help="Encoder checkpoint (pretraining or decoder run).")],
    objects: Annotated[str, typer.Option(help="Comma-separated objects shown side by side (default: every session "
                                         "under --sessions, else the simulator's soap and shovel).")] = "",
    view: Annotated[int, typer.Option(min=0)] = 0,
    n_views: NViewsOpt = 4,
    rig: str = "cpu",
    stride: Annotated[int, typer.Option(min=1, help="Embed every stride-th pixel in x and y.")] = 2,
    out: Annotated[Path, typer.Option(help="PNG output.")] = Path("pca_rgb.png"),
    cache: CacheOpt = DEFAULT_CACHE,
    sessions: SessionsOpt = None,
) -> None:
    """PCA-RGB map: joint PCA of the patch embeddings of the images shown, first 3 components as RGB."""
    from sssphase_core.learning.evaluation import PCA_TITLE, pca_maps
    from sssphase_core.learning.training import load_encoder
    from sssphase_core.reporting.figures import panels_figure

    _png_out(out, "pca_rgb.png")
    enc = load_encoder(checkpoint)
    names = _names(objects, () if sessions else ("soap", "shovel"))
    vds = _views(names, [view], n_views=n_views, rig=rig, pixels=None, footprints=False, seed=0, cache=cache,
                 sessions=sessions)
    with console.status(f"embedding one pixel in {stride} along x and y of {len(vds)} view(s)"):
        maps = pca_maps(enc, [(v.psp, v.pixels) for v in vds], stride)
    panels_figure(out, maps, [f"{v.object}, view {v.view}" for v in vds], f"{PCA_TITLE} (one pixel in {stride} along x and y)")
    console.print(f"wrote {out} ({', '.join(v.object for v in vds)}, view {view})")


def viz_footprints(
    session: Annotated[Path, typer.Argument(help="Session folder (captured with --footprints for the 'captured' row).")],
    backend: Annotated[str, typer.Option(help="Comma-separated rows: captured (the session's dot-grid crops), torch, "
                                         "analytic, exact (sim sessions), none.")] = "captured,analytic",
    checkpoint: Annotated[Path | None, typer.Option(help="Decoder checkpoint for the torch row.")] = None,
    view: int = 0,
    pixels: Annotated[int, typer.Option(min=1, max=16, help="Pixels shown (spread over the object).")] = 6,
    out: Annotated[Path, typer.Option(help="PNG output (profiles in <out>_profiles.png).")] = Path("footprints.png"),
) -> None:
    """Footprints at a few pixels, one row per source (log scale), and their centre-row profiles."""
    import numpy as np

    from sssphase_core.errors import InputError
    from sssphase_core.relight import load_view
    from sssphase_core.relight.evaluation import footprints_at
    from sssphase_core.reporting.figures import grid_figure, profiles_figure
    from sssphase_core.store.session import Session

    _png_out(out, "footprints.png")
    s = Session.open(session)
    rv = load_view(s, view)
    rows = [b.strip() for b in backend.split(",") if b.strip()]
    if not rows:
        raise InputError(f"--backend names no row (got {backend!r}): e.g. captured,analytic")
    if "captured" in rows and "footprints/pixels" in s.arrays(view):
        candidates = np.asarray(s.load(view, "footprints/pixels"), np.int64)
    else:
        if "captured" in rows:
            if rows == ["captured"]:
                raise InputError(f"{session} view {view} has no captured footprints (capture with --footprints)")
            console.print(f"note: {session} view {view} has no captured footprints: that row is left out")
        rows = [r for r in rows if r != "captured"]
        candidates = np.argwhere(rv.proj.mask)
    chosen = candidates[np.linspace(0, len(candidates) - 1, pixels + 2)[1:-1].astype(int)]
    fps = footprints_at(rv, chosen, rows, checkpoint=checkpoint)
    luminance = {name: f.mean(axis=-1) for name, f in fps.items()}
    peak = np.maximum(next(iter(luminance.values())).max(axis=(1, 2)), 1e-12)  # each column's first-row peak
    grid = [[np.log10(np.maximum(luminance[name][i], 1e-30) / peak[i]) for i in range(len(chosen))] for name in rows]
    titles = [f"({y}, {x})" for y, x in chosen]
    grid_figure(out, grid, rows, titles, f"{s.name}, view {view}: footprints at pixels (row, col), mean of RGB",
                units=f"log10 intensity / {rows[0]} peak", vmin=-4, vmax=0.3)
    k = next(iter(luminance.values())).shape[1]
    profiles = out.with_name(out.stem + "_profiles.png")
    profiles_figure(profiles, {name: lum[:, k // 2, :] for name, lum in luminance.items()}, titles,
                    f"{s.name}, view {view}: centre-row profiles", xlabel="offset (camera px)",
                    ylabel="linear camera units")
    console.print(f"wrote {out} and {profiles} ({', '.join(rows)} at {len(chosen)} pixels of {s.name} view {view})")


def bench_learn(
    out: Annotated[Path, typer.Option(help="JSON output.")] = Path("bench_learn.json"),
    md: Annotated[Path | None, typer.Option(help="Markdown table output.")] = None,
    repeats: int = 3,
    device: str = "cpu",
) -> None:
    """Throughput (patches/s) of the lite and paper presets, inference and training, ratio to paper."""
    from sssphase_core.bench.learn_bench import loader_throughput, measure_throughput
    from sssphase_core.bench.output import Table, machine_info, write_bench_report

    batches = {"paper": 8, "lite": 64}
    results = {}
    for name, batch in batches.items():
        with console.status(f"measuring the {name} preset (batch {batch})"):
            results[name] = {"batch": batch, **measure_throughput(name, batch=batch, repeats=repeats, device=device),
                             **loader_throughput(name, batch=batch, repeats=repeats)}
    base = results["paper"]
    table = Table("Learning throughput (patches/s); baseline: the paper preset, same run",
                  ["preset", "batch", "encoder params", "decoder params", "inference", "x paper", "SimSiam step", "x paper"])
    loader = Table("Training loader against the model (patches/s, same run): PSP patches cropped from a view stack in "
                   "memory, footprint targets streamed from a chunked store on disk",
                   ["preset", "camera", "K", "loader, PSP only", "loader, with targets", "SimSiam step",
                    "loader / SimSiam step", "loader / inference"])
    for name, r in results.items():
        table.rows.append([name, r["batch"], f"{r['encoder_params'] / 1e6:.2f}M", f"{r['decoder_params'] / 1e6:.2f}M",
                           r["infer_patches_s"], r["infer_patches_s"] / base["infer_patches_s"],
                           r["train_patches_s"], r["train_patches_s"] / base["train_patches_s"]])
        loader.rows.append([name, r["camera"], r["patch"], r["loader_psp_patches_s"], r["loader_patches_s"], r["train_patches_s"],
                            r["loader_patches_s"] / r["train_patches_s"], r["loader_patches_s"] / r["infer_patches_s"]])
    write_bench_report({"machine": machine_info(), "device": device, "results": results}, [table, loader], out, md,
                 title="sss bench learn")
    console.print(table.markdown())
    console.print(loader.markdown())


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
