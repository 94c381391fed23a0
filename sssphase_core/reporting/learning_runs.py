"""The learning commands' session-level runners: ``sss train pretrain|decoder`` and ``sss eval knn|footprints``
are one call each here, so the CLI, a notebook or a web view run the same code.

Each runner checks its options before any work, reads the data (``learning.inputs.load_views``: captured
sessions or the simulator), says what it does through a :class:`~sssphase_core.learning.inputs.Report`
and returns what it made (a checkpoint and the run's figures, or the evaluation's results and tables)::

    from sssphase_core.reporting.learning_runs import PretrainOptions, run_pretrain
    run_pretrain(PretrainOptions(out=Path("runs/pre"), epochs=2, sessions=Path("sessions")))
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from sssphase_core.compute import check_device
from sssphase_core.errors import DataError, InputError
from sssphase_core.learning.inputs import (
    DECODER_HEADS,
    Report,
    RunConfigFile,
    ViewOptions,
    check_aux_class_count,
    check_batch,
    check_lr,
    check_pretrain_options,
    check_run_out,
    chosen_views,
    decoder_view_choice,
    load_views,
    parse_ints,
    parse_names,
    training_data_from_sessions,
    used_views,
    view_objects,
)
from sssphase_core.tables import Table

# --- training ----------------------------------------------------------------------------------------


@dataclass(kw_only=True)
class TrainOptions(ViewOptions):
    """What both trainings share (a run folder ``out``, resumed from its checkpoint with ``resume``)."""

    out: Path
    preset: str = "lite"
    epochs: int = 10
    batch_size: int = 64
    lr: float = 0.05
    ckpt_every: int = 50
    time_limit: float | None = None  # seconds this call may train (LoopConfig.time_limit_s)
    device: str = "auto"
    deterministic: bool = False
    resume: bool = True


@dataclass(kw_only=True)
class PretrainOptions(TrainOptions):
    """``sss train pretrain``'s options (SimSiam on the training objects' PSP patches)."""

    out: Path = Path("runs/pretrain")
    warmup_epochs: float = 2.0
    augment: str = "psp"
    fix_pred_lr: bool = True
    knn_monitor: int = 2000
    decorrelate: float = 1.0
    phase_shift: bool = True


@dataclass(kw_only=True)
class DecoderOptions(TrainOptions):
    """``sss train decoder``'s options: on the frozen ``encoder`` (a pretraining run), or ``end_to_end``.
    ``preset_given``: the preset was chosen (not a default), which only an end-to-end run may do."""

    out: Path = Path("runs/decoder")
    encoder: Path | None = None
    end_to_end: bool = False
    preset_given: bool = False
    val_views: str | Sequence[int] | None = None
    noisy_targets: bool = False
    batch_size: int = 32
    lr: float = 1e-3
    head: str = "reciprocal"
    aux_classes: int = 0
    learn_gain: bool = False
    capture_model: bool = True
    camera_augment: float = 0.0
    deterministic: bool = True
    check_sessions: Sequence[Path] | None = None


@dataclass
class TrainResult:
    """A finished run: its checkpoint, its metrics rows and the figures it drew."""

    checkpoint: Path
    rows: list[dict[str, Any]]
    figures: list[Path] = field(default_factory=list)
    baselines: dict[str, Any] | None = None  # the decoder's relighting check (``baseline_check``), when one ran


def final_lines(metrics: Path, names: Sequence[str], monitored: str) -> list[str]:
    """The last epoch's figures and the epoch kept in best.pt, as lines."""
    from sssphase_core.learning.runlog import read_rows
    from sssphase_core.learning.training import BEST

    rows = read_rows(metrics)
    if not rows:
        return []
    last, lines = rows[-1], []
    figures = ", ".join(f"{n} {last[n]:.4g}" for n in names if n in last)
    if figures:
        lines.append(f"final (epoch {last['epoch']}): {figures}")
    best = last.get("best_epoch")
    if best is not None:
        row = next(r for r in rows if r["epoch"] == best)
        lines.append(f"best {monitored} at epoch {best} ({row[monitored]:.4g}): {metrics.parent / BEST} "
                     "(what backends load from this run folder)")
    return lines


def _header(report: Report, text: str, out: Path, config_file: RunConfigFile | None, resuming: bool) -> None:
    saved = f" (options in {config_file.save(out, resuming)})" if config_file is not None else ""
    report.say(f"{text} -> {out}{saved}")
    if resuming:  # (a resumed run said nothing: only a progress bar that did not start at 0 told)
        from sssphase_core.learning.training import CHECKPOINT, load_checkpoint

        loop = load_checkpoint(out / CHECKPOINT, mmap=True).get("loop", {})
        done, into = int(loop.get("epoch", 0)), int(loop.get("step_in_epoch", 0))
        report.say(f"{report.style('note:', 'note')} resuming from {out / CHECKPOINT}: {done} epoch{'s' * (done != 1)} "
                   f"done, {into} step{'s' * (into != 1)} into the next (--no-resume starts again)")


@contextmanager
def _saying_where_it_stopped(report: Report) -> Iterator[None]:
    """Say where a training asked to stop (Ctrl-C, SIGTERM) saved its checkpoint, then let the interrupt go on."""
    from sssphase_core.learning.training import TrainingStopped

    try:
        yield
    except TrainingStopped as stopped:
        report.say(f"{report.style('note:', 'note')} {stopped}: the same command continues from it")
        raise


def one_training_per_folder(run: Callable[..., TrainResult]) -> Callable[..., TrainResult]:
    """``run(opts, ...)`` holding a lock on ``opts.out`` (:func:`~sssphase_core.store.locks.folder_lock`): two trainings
    into one run folder both ran to the end, the second's checkpoints over the first's (torchrun: its rank 0 holds
    it for the group)."""
    import functools

    @functools.wraps(run)
    def locked(opts: Any, *args: Any, **kwargs: Any) -> TrainResult:
        if int(os.environ.get("RANK", "0") or 0) != 0:
            return run(opts, *args, **kwargs)
        from sssphase_core.store.locks import folder_lock

        with folder_lock(Path(opts.out), f"run folder {opts.out} is being trained by {{holder}}: wait for it to end, "
                         "or give another --out"):
            return run(opts, *args, **kwargs)

    return locked


@one_training_per_folder
def run_pretrain(opts: PretrainOptions, report: Report = Report(), *,
                 config_file: RunConfigFile | None = None) -> TrainResult:
    """SimSiam pretraining of the encoder on PSP patches of the training objects (resumable); draws
    ``knn_vs_time.png`` when the kNN monitor ran."""
    check_lr(opts.lr)  # before torch is imported (2 s): a mistyped option is answered at once
    check_pretrain_options(opts.batch_size, opts.warmup_epochs, opts.augment, opts.decorrelate)
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.models import get_preset
    from sssphase_core.learning.runlog import read_rows
    from sssphase_core.learning.training import METRICS, PretrainConfig, knn_monitor_indices, pretrain
    from sssphase_core.sim import TRAIN_OBJECTS

    p = get_preset(opts.preset)
    check_device(opts.device)  # before anything is written: a refused run left --device in config.toml
    resuming = check_run_out(opts.out, "pretrain", opts.resume, config_file, opts.epochs)
    names = parse_names(opts.objects, () if opts.sessions else TRAIN_OBJECTS)
    vds = load_views(names, chosen_views(opts.views, "0,1,2,3", opts.sessions), opts, footprints=False, report=report)
    names = names or view_objects(vds)
    ds = PatchDataset(vds, p.patch, names)
    check_batch(opts.batch_size, ds, "training patches")
    if opts.knn_monitor and knn_monitor_indices(ds, opts.knn_monitor, opts.seed) is None:
        report.say(f"{report.style('note:', 'note')} the kNN monitor is off: it leaves one view out, so it needs two "
                   "objects each seen in two or more views (an object's only view left out leaves nothing of it to "
                   "match, and a one-object vote is always right)")
    if opts.warmup_epochs >= opts.epochs:
        report.say(f"{report.style('note:', 'note')} --warmup-epochs {opts.warmup_epochs:g} is not shorter than --epochs "
                   f"{opts.epochs}: the learning rate rises for the whole run, to about {opts.epochs / opts.warmup_epochs:.2g}"
                   " x --lr, and never decays")
    cfg = PretrainConfig(epochs=opts.epochs, batch_size=opts.batch_size, seed=opts.seed, ckpt_every=opts.ckpt_every,
                         time_limit_s=opts.time_limit, device=opts.device, preset=opts.preset,
                         deterministic=opts.deterministic, lr=opts.lr,
                         warmup_epochs=opts.warmup_epochs, fix_pred_lr=opts.fix_pred_lr, augment=opts.augment,
                         knn_monitor=opts.knn_monitor, decorrelate=opts.decorrelate, phase_shift=opts.phase_shift)
    _header(report, f"pretraining {report.style(opts.preset, 'strong')} on {len(ds)} patches of {', '.join(names)}",
            opts.out, config_file, resuming)
    with _saying_where_it_stopped(report), report.training() as progress:
        path = pretrain(cfg, ds, opts.out, resume=opts.resume, progress=progress)
    result = TrainResult(path, read_rows(opts.out / METRICS))
    _say_if_stopped(result, opts, report)
    for line in final_lines(opts.out / METRICS, ("loss", "knn_acc", "eff_rank"), "knn_acc"):
        report.say(line)
    _knn_trail(opts.out, result, len(names), report)
    report.say(f"{report.style('done', 'done')}: {path}")
    return result


def _say_if_stopped(result: TrainResult, opts: TrainOptions, report: Report) -> None:
    """Say when ``--time-limit`` ended the run before its last epoch (a rerun continues it)."""
    done = max((int(r["epoch"]) for r in result.rows if "epoch" in r), default=0)
    if opts.time_limit is not None and done < opts.epochs:
        report.say(f"{report.style('note:', 'note')} stopped after epoch {done} of {opts.epochs}: another would pass "
                   f"--time-limit {opts.time_limit:g} s (rerun the command to continue from {opts.out / 'last.pt'})")


def _knn_trail(out: Path, result: TrainResult, n_objects: int, report: Report) -> None:
    """The kNN monitor's accuracy per epoch, plotted against run time and said."""
    from sssphase_core.learning.training import METRICS
    from sssphase_core.reporting.figures import plot_metric_vs_time

    rows = [r for r in result.rows if "knn_acc" in r]
    if not rows:
        return
    initial = rows[0].get("knn_initial")
    plot = out / "knn_vs_time.png"
    plot_metric_vs_time(out / METRICS, "knn_acc", plot, log=False, chance=1 / n_objects,
                        ylabel="kNN accuracy (fraction, training patches)",
                        title=f"kNN monitor against run time ({n_objects} objects)",
                        reference=None if initial is None else ("initial encoder", initial))
    result.figures.append(plot)
    trail = ", ".join(f"{100 * r['knn_acc']:.1f}" for r in rows)
    start = "" if initial is None else f"initial encoder {100 * initial:.1f} -> "
    report.say(f"kNN monitor (% per epoch, training patches): {start}{trail}; plot {plot}")
    best = max(r["knn_acc"] for r in rows)
    if initial is not None and best < initial:
        report.say(f"{report.style('warning:', 'warning')} pretraining never raised the kNN monitor above the encoder's "
                   f"random initialisation ({100 * best:.1f}% at best against {100 * initial:.1f}%): its features "
                   "separate the objects less than random ones; train longer or on more patches (--epochs, "
                   "--pixels-per-view), or lower --lr")


def _check_decoder_options(opts: DecoderOptions) -> int:
    """Refuse, before any data is read (and all but the encoder's preset before torch is imported), what no
    decoder run can be; the run's patch size."""
    check_lr(opts.lr)
    check_aux_class_count(opts.aux_classes)
    if opts.head not in DECODER_HEADS:
        raise InputError(f"unknown decoder head {opts.head!r}; choose one of {', '.join(DECODER_HEADS)}")
    if (opts.encoder is None) == (not opts.end_to_end):
        raise InputError("give either --encoder PATH (a pretraining run; the paper's method) or --end-to-end (the "
                         "supervised baseline without SSL), not both or neither")
    if opts.encoder is not None and opts.preset_given:
        raise InputError("--preset sets the model of an --end-to-end run; with --encoder the decoder takes the encoder's "
                         "preset (it was ignored, and config.toml recorded the wrong one)")
    from sssphase_core.learning.training import decoder_patch

    return decoder_patch(None if opts.end_to_end else opts.encoder, opts.preset)


@one_training_per_folder
def run_decoder(opts: DecoderOptions, report: Report = Report(), *,
                config_file: RunConfigFile | None = None) -> TrainResult:
    """Fit the footprint decoder with the SBH loss on the frozen encoder, or end-to-end (resumable); then
    relight the ``check_sessions`` (default: ``sessions``) against the none and analytic baselines."""
    patch = _check_decoder_options(opts)
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.runlog import read_rows
    from sssphase_core.learning.training import METRICS, DecoderConfig, train_decoder
    from sssphase_core.learning.training.decoder import check_aux_classes
    from sssphase_core.sim import TRAIN_OBJECTS

    check_device(opts.device)  # before anything is written: a refused run left --device in config.toml
    resuming = check_run_out(opts.out, "decoder", opts.resume, config_file, opts.epochs)
    if opts.encoder is not None:
        from sssphase_core.learning.training import load_checkpoint

        encoder = load_checkpoint(opts.encoder, mmap=True)
        if encoder.get("kind") == "decoder":  # it was taken without a word
            report.say(f"{report.style('note:', 'note')} --encoder {opts.encoder} is a decoder run: its encoder is "
                       "used, frozen; the paper's method starts from a pretraining run (`sss train pretrain`)")
        from sssphase_core.learning.runlog import CHECKPOINT

        # how far the run got is its last.pt's, not its best.pt's (the best kNN may come before the last epoch)
        latest = Path(opts.encoder) / CHECKPOINT if Path(opts.encoder).is_dir() else Path(opts.encoder).with_name(CHECKPOINT)
        progress = load_checkpoint(latest, mmap=True) if latest.is_file() else encoder
        done, planned = int(progress.get("loop", {}).get("epoch", 0)), int(progress.get("config", {}).get("epochs", 0))
        if encoder.get("kind") == "pretrain" and done < planned:  # an interrupted pretraining's last.pt, taken in silence
            report.say(f"{report.style('warning:', 'warning')} --encoder {opts.encoder} is from an unfinished "
                       f"pretraining ({done} of its {planned} epochs done): the same `sss train pretrain` command finishes it; "
                       "the decoder learns from the encoder it is given")
    names = parse_names(opts.objects, () if opts.sessions else TRAIN_OBJECTS)
    choice = decoder_view_choice(names, opts.views, opts.val_views, opts.sessions)
    if opts.check_sessions:  # a typo, or a damaged chunk, here was found only after the whole training
        from sssphase_core.store.session import find_sessions

        for s in find_sessions(opts.check_sessions):
            damage = [p for p in s.validate() if "not captured completely" not in p]
            if damage:
                raise DataError(f"--check-sessions: session {s.path} is damaged ({damage[0]}; `sss validate {s.path}` "
                                "lists every problem): repair or leave it out before the training")
    train_vds, val_vds = training_data_from_sessions(names, opts, choice, noisy=opts.noisy_targets, report=report)
    names = names or view_objects([*train_vds, *val_vds])
    ds = PatchDataset(train_vds, patch, names, with_targets=True)
    val = PatchDataset(val_vds, patch, names, with_targets=True) if val_vds else None
    check_batch(opts.batch_size, ds, "training footprints")
    check_aux_classes(opts.aux_classes, ds)
    cfg = DecoderConfig(epochs=opts.epochs, batch_size=opts.batch_size, seed=opts.seed, ckpt_every=opts.ckpt_every,
                        time_limit_s=opts.time_limit, device=opts.device, lr=opts.lr, deterministic=opts.deterministic,
                        head=opts.head,
                        aux_classes=opts.aux_classes, preset=opts.preset, learn_gain=opts.learn_gain,
                        capture_model=opts.capture_model, camera_augment=opts.camera_augment)
    what = f"encoder and decoder end-to-end ({opts.preset})" if opts.end_to_end else "the decoder"
    _header(report, f"training {what} on {len(ds)} footprints of {', '.join(names)}", opts.out, config_file, resuming)
    with _saying_where_it_stopped(report), report.training() as progress:
        path = train_decoder(cfg, opts.encoder, ds, opts.out, val=val, resume=opts.resume, progress=progress)
    result = TrainResult(path, read_rows(opts.out / METRICS))
    _say_if_stopped(result, opts, report)
    if val is not None:
        result.figures.append(_validation_plot(opts.out))
        report.say(f"validation error against run time: {result.figures[-1]}")
    for line in final_lines(opts.out / METRICS, ("val_loss", "val_psnr"), "val_loss"):
        report.say(line)
    report.say(f"{report.style('done', 'done')}: {path}")
    held_out = sorted({vd.view for vd in val_vds}) if opts.sessions and not opts.check_sessions else []
    roots = list(opts.check_sessions or ([opts.sessions] if opts.sessions else []))
    result.baselines = check_against_baselines(opts.out, roots, held_out or None, opts.device, report)
    return result


def _validation_plot(out: Path) -> Path:
    from sssphase_core.learning.training import METRICS
    from sssphase_core.reporting.figures import plot_metric_vs_time

    plot_metric_vs_time(out / METRICS, ("loss", "val_loss"), out / "error_vs_time.png", log=False,
                        ylabel="SBH loss", right=("val_psnr",),
                        right_label="validation footprint PSNR (dB)", title="decoder error against run time",
                        right_span=1.0)
    return out / "error_vs_time.png"


def check_against_baselines(run: Path, roots: Sequence[Path], views: list[int] | None, device: str,
                            report: Report = Report()) -> dict[str, Any] | None:
    """Relight the views of ``roots`` with reference captures by the run's model and the none/analytic
    baselines (``relight.evaluation.baseline_check``; None: no ``roots``); says the mean PSNRs and warns when
    the model loses to a baseline."""
    from sssphase_core.relight.cache import CHECK_FOLDER
    from sssphase_core.relight.evaluation import baseline_check
    from sssphase_core.store.session import find_sessions

    if not roots:
        report.say("no --check-sessions: relighting against the baselines was not checked")
        return None
    if device == "auto":
        from sssphase_core.learning.training import init_distributed

        device = str(init_distributed(device).device)
    with report.busy("relighting held-out views against the none and analytic baselines"):
        res = baseline_check(find_sessions(roots), run, run / CHECK_FOLDER, views=views, device=device)
    if not res["views"]:
        report.say(f"{report.style('not checked:', 'note')} no view of {', '.join(map(str, roots))} has reference "
                   "captures (capture one with --reference checkerboard and pass it as --check-sessions)")
        return res
    where = ", ".join(f"{o} view {v}" for o, v in res["views"])
    figures = ", ".join(f"{b} {psnr:.2f} dB" for b, psnr in res["mean_psnr"].items())
    report.say(f"relit PSNR on {where}: {figures}")
    from sssphase_core.relight.evaluation import training_overlap

    if seen := training_overlap(run, res["views"], held_out=views is None):  # held-out views: what `views` asked for
        report.say(seen)
    for b in res["losing_to"]:
        report.say(f"{report.style('warning:', 'warning')} the model relights worse than the {b} baseline "
                   f"({res['mean_psnr']['torch']:.2f} < {res['mean_psnr'][b]:.2f} dB): prefer the baseline, or train on more data")
    return res


# --- evaluation --------------------------------------------------------------------------------------


@dataclass
class Evaluation:
    """An evaluation's results (``payload``, the JSON written) and its tables."""

    payload: dict[str, Any]
    tables: list[Table]

    def markdown(self) -> str:
        return "\n".join(t.markdown() for t in self.tables)


@dataclass(kw_only=True)
class KnnOptions(ViewOptions):
    """``sss eval knn``'s options: ``checkpoints`` are ``NAME=PATH`` or ``PATH`` (named by its file or folder)."""

    checkpoints: Sequence[str]
    pixels_per_view: int = 1000
    k: str | Sequence[int] = "20"
    vote: str = "majority"
    label: str = "object"
    seed: int = 1


def named_checkpoints(items: Sequence[str]) -> dict[str, str]:
    """``NAME=PATH`` (or ``PATH``, named by its stem or folder) -> ``{name: path}``: one column each, named
    plainly and once; every path must exist (checked before any view is read or simulated)."""
    from sssphase_core.store.session import NAME_RE

    pairs = [c.split("=", 1) if "=" in c else (Path(c).stem if Path(c).suffix else Path(c).name, c) for c in items]
    names_given = [n for n, _ in pairs]
    for (name, path), item in zip(pairs, items, strict=True):
        if names_given.count(name) > 1:
            raise InputError(f"--checkpoint takes NAME=PATH (or PATH) with a distinct name for each run: the name "
                             f"{name!r} is given twice")
        if not NAME_RE.fullmatch(name) or not path:  # "psp=" had loaded ./last.pt
            raise InputError(f"--checkpoint takes NAME=PATH (or PATH) with a distinct name of letters, digits, '_', "
                             f"'-', '.' and a path, got {item!r}")
    runs = dict(pairs)
    missing = [path for path in runs.values() if not Path(path).exists()]
    if missing:
        raise InputError(f"no checkpoint at {missing[0]} (a pretraining run folder or its .pt file)")
    return runs


def _check_knn_data(vds: Sequence[Any], label: str, ks: Sequence[int]) -> None:
    """Two classes to tell apart, and a k below the smallest leave-one-view-out database."""
    import numpy as np

    n_patches = sum(len(v.pixels) for v in vds)
    seen = {(c, v.view) for v in vds
            for c in ([v.object] if label == "object" else [int(m) for m in np.unique(v.materials) if m >= 0])}
    classes = {c for c, _ in seen}
    if len(classes) < 2:  # every patch would get the one label: 100% that measures nothing
        raise InputError(f"kNN by {label} needs two or more {label}s to tell apart; the views read hold "
                         + (f"only {', '.join(map(str, sorted(classes)))}" if classes else "no material labels (sessions "
                            "without ground truth: use --label object)"))
    scored = sorted({c for c in classes if sum(1 for cc, _ in seen if cc == c) > 1}, key=str)
    if len(scored) < 2 and len({v for _, v in seen}) > 1:  # the held-out view of a one-view class has none of it to match
        raise InputError(f"kNN leaves one view out, so it scores only {label}s seen in two or more views, and needs two "
                         f"of them to tell apart; of the views read, {' and '.join(map(str, scored)) or 'none'} has two or more: capture "
                         "more views (`sss capture --views 2`) or pass --views with views every object has")
    per_view: dict[int, int] = {}
    for v in vds:  # leave-one-view-out: the patches of one view index are the queries, the others the database
        per_view[v.view] = per_view.get(v.view, 0) + len(v.pixels)
    database = n_patches - max(per_view.values())
    if len(per_view) == 1:  # nothing to leave one view out of: the database is empty whatever --k
        raise InputError(f"kNN leaves one view out: the views read are all view {next(iter(per_view))}, so no patch has "
                         "another view to be compared with; evaluate sessions of two or more views (`sss capture "
                         "--views 2`) or pass --views with two views")
    if max(ks) >= database:  # (it was clamped to the database in silence and reported as given)
        raise InputError(f"--k {max(ks)} is not smaller than the {database} patches of the smallest leave-one-view-out "
                         f"database ({n_patches} read, {max(per_view.values())} of them in one view): every patch would "
                         "get the majority label; lower --k or raise --pixels-per-view")


def evaluate_knn(opts: KnnOptions, report: Report = Report()) -> Evaluation:
    """kNN accuracy of frozen embeddings with view-level leave-one-out (cosine similarity), one column per
    checkpoint; the first k makes the table, the others a sweep."""
    from sssphase_core.sim import MATERIAL_NAMES, TRAIN_OBJECTS

    runs = named_checkpoints(opts.checkpoints)
    names = parse_names(opts.objects, () if opts.sessions else TRAIN_OBJECTS)
    if opts.label not in ("object", "material"):
        raise InputError(f"--label must be object or material, got {opts.label!r}")
    ks = parse_ints(opts.k, "--k") if isinstance(opts.k, str) else [int(k) for k in opts.k]
    ks = list(dict.fromkeys(ks))  # each once: "5,5" printed its sweep row twice
    if not ks or min(ks) < 1:
        raise InputError(f"--k needs one or more positive integers, got {opts.k!r}")
    vds = load_views(names, chosen_views(opts.views, "0,1,2,3", opts.sessions), opts, footprints=False, report=report)
    names = names or view_objects(vds)
    _check_knn_data(vds, opts.label, ks)
    from sssphase_core.learning.evaluation import (  # (torch: once the input is known good)
        knn_of_views,
        knn_tables,
    )
    from sssphase_core.learning.training import load_encoder

    results = {}
    for run, path in runs.items():
        with report.busy(f"embedding {sum(len(v.pixels) for v in vds)} patches with {run}"):
            sweep = knn_of_views(load_encoder(path), vds, names, label=opts.label, material_names=list(MATERIAL_NAMES),
                                 ks=ks, vote=opts.vote)
        res = sweep[ks[0]]
        res["overall_by_k"] = {kk: r["overall"] for kk, r in sweep.items()}
        results[run] = res
    used = used_views(opts.views, vds)
    tables = knn_tables(results, label=opts.label, ks=ks, vote=opts.vote, views=used)
    return Evaluation({"k": ks[0], "vote": opts.vote, "label": opts.label, "views": used, "results": results}, tables)


@dataclass(kw_only=True)
class FootprintOptions(ViewOptions):
    """``sss eval footprints``'s options: the decoder ``checkpoint``, ``compare`` (``NAME=PATH`` decoder runs),
    a ``baseline`` backend ('' for none), a folder of profile ``plots`` and the decoders' inference ``precision``."""

    checkpoint: Path
    pixels_per_view: int = 500
    baseline: str = "analytic"
    compare: Sequence[str] | None = None
    seed: int = 2
    plots: Path | None = None
    precision: str = "auto"


def _footprint_backends(opts: FootprintOptions) -> dict[str, Any]:
    """The model, the --compare decoders (checked before any data is read); the baseline is added later."""
    from sssphase_core.learning.backends import get_backend
    from sssphase_core.store.session import NAME_RE

    others = [item.partition("=") for item in opts.compare or []]
    for (name, sep, path), item in zip(others, opts.compare or [], strict=True):  # NAME names output files
        if [o[0] for o in others].count(name) > 1:
            raise InputError(f"--compare takes NAME=PATH with a new name for each decoder: the name {name!r} is given "
                             "twice")
        if not sep or not path or not NAME_RE.fullmatch(name) or name in ("torch", opts.baseline):
            raise InputError(f"--compare takes NAME=PATH with a new name of letters, digits, '_', '-', '.', got {item!r}")
    backends = {"torch": get_backend("torch", checkpoint=opts.checkpoint, precision=opts.precision)}
    backends.update({name: get_backend("torch", checkpoint=path, precision=opts.precision) for name, _, path in others})
    if opts.baseline == "torch":  # the model itself (it said "pass checkpoint=... or call fit()" after reading the data)
        raise InputError("--baseline torch is the model --checkpoint gives; compare another decoder with --compare "
                         "NAME=RUN, or choose a baseline that is no decoder (analytic, or '' for none)")
    return backends


def _check_footprint_size(backends: dict[str, Any], opts: FootprintOptions, vds: Sequence[Any]) -> None:
    """Each decoder predicts footprints of its preset's size; the sessions' crops are their rig's patch (a
    mismatch was an internal size error in the metrics)."""
    sizes = {v.footprints.shape[1] for v in vds if v.footprints is not None and len(v.footprints)}
    for name, be in backends.items():
        for size in sizes - {be.patch}:
            flag = "--checkpoint" if name == "torch" else f"--compare {name}"
            where = f"the sessions under {opts.sessions}" if opts.sessions else f"the simulated rig ({opts.rig} preset)"
            raise InputError(f"{flag} predicts {be.patch}px footprints (preset {be.encoder.preset.name}); {where} "
                             f"hold {size}px footprint crops (the rig's patch): evaluate a decoder trained on "
                             f"{size}px patches of this rig")


def evaluate_footprints(opts: FootprintOptions, report: Report = Report()) -> Evaluation:
    """MSE, PSNR (data range 1) and SSIM (data range = GT peak) per object and backend, like the paper's
    Table 1; with ``plots``, one profile plot per object and backend (its brightest footprint)."""
    from sssphase_core.learning.backends import get_backend
    from sssphase_core.learning.evaluation import footprint_table
    from sssphase_core.relight.evaluation import lpips_note
    from sssphase_core.sim import UNSEEN_OBJECTS, rig_preset

    if opts.plots is not None:
        from sssphase_core.store.session import check_output_folder

        check_output_folder(opts.plots, "--plots")
    names = parse_names(opts.objects, () if opts.sessions else UNSEEN_OBJECTS)
    backends = _footprint_backends(opts)
    vds = load_views(names, chosen_views(opts.views, "0", opts.sessions), opts, footprints=True, report=report)
    _check_footprint_size(backends, opts, vds)
    names = names or view_objects(vds)
    if opts.baseline:
        analytic = opts.baseline == "analytic"
        extra = {"patch": backends["torch"].patch, "black": rig_preset(opts.rig).projector.black} if analytic else {}
        backends[opts.baseline] = get_backend(opts.baseline, **extra)
    report.say(lpips_note())
    results = {obj: _object_footprints(obj, [v for v in vds if v.object == obj], backends, opts.plots, report)
               for obj in names}
    precision = backends["torch"].precision
    note = ("PSNR: data range 1 (white reference = 1.0); SSIM: 11x11 Gaussian window, data range = each GT footprint's peak; "
            f"the decoders inferred in {precision}; {lpips_note()}.")
    used = used_views(opts.views, vds)
    return Evaluation({"objects": names, "views": used, "results": results, "note": note, "precision": precision},
                      [footprint_table(results, views=used, note=note)])


def _object_footprints(obj: str, obj_views: Sequence[Any], backends: dict[str, Any], plots: Path | None,
                       report: Report) -> dict[str, dict[str, float]]:
    """One object's metrics per backend (and its profile plots)."""
    import numpy as np

    from sssphase_core.learning.evaluation import footprint_metrics, summarise
    from sssphase_core.reporting.figures import plot_profiles

    gt = np.concatenate([np.asarray(v.footprints) for v in obj_views])
    bad = int(np.count_nonzero(~np.isfinite(gt).all(axis=(1, 2, 3))))
    if bad:  # the table read NaN (and its JSON was no JSON)
        raise DataError(f"{bad} of the {len(gt)} sampled footprint crops of {obj} hold NaN or infinite values: the "
                        "session's footprint crops are corrupt (a capture never stores them)")
    results, preds = {}, {}
    for bname, be in backends.items():
        with report.busy(f"{bname}: predicting {len(gt)} footprints of {obj}"):
            preds[bname] = np.concatenate([be.predict_footprints((v.psp, v.pixels)) for v in obj_views])
        results[bname] = summarise(footprint_metrics(preds[bname], gt))
    if plots is not None:
        plots.mkdir(parents=True, exist_ok=True)
        i = int(np.argmax(gt.sum(axis=(1, 2, 3))))
        for bname, pred in preds.items():
            plot_profiles(gt[i], pred[i], plots / f"{obj}_{bname}.png", title=f"{obj}: {bname}")
    return results


# --- figures -----------------------------------------------------------------------------------------


def pca_figure(checkpoint: Path | str, objects: str | Sequence[str], view: int, data: ViewOptions, stride: int, out: Path,
               report: Report = Report()) -> list[Any]:
    """``sss viz pca``: the PCA-RGB map of each object's ``view`` side by side (a joint PCA of the patch
    embeddings of the images shown, first 3 components as RGB, one pixel in ``stride`` along x and y),
    written to ``out``; default objects: every session of ``data.sessions``, else the simulator's soap and
    shovel. Returns the views shown."""
    from sssphase_core.learning.evaluation import PCA_TITLE, pca_maps
    from sssphase_core.learning.training import load_encoder
    from sssphase_core.reporting.figures import panels_figure

    enc = load_encoder(checkpoint)
    names = parse_names(objects, () if data.sessions else ("soap", "shovel"))
    vds = load_views(names, [view], replace(data, pixels_per_view=None), footprints=False, report=report)
    with report.busy(f"embedding one pixel in {stride} along x and y of {len(vds)} view(s)"):
        maps = pca_maps(enc, [(v.psp, v.pixels) for v in vds], stride)
    panels_figure(out, maps, [f"{v.object}, view {v.view}" for v in vds], f"{PCA_TITLE} (one pixel in {stride} along x and y)")
    return vds


@dataclass
class FootprintFigures:
    """``sss viz footprints``' two figures, the rows drawn and the camera pixels (N, 2) yx shown."""

    figure: Path
    profiles: Path
    rows: list[str]
    pixels: Any
    session: str


def profiles_path(out: Path) -> Path:
    """The centre-row profiles' figure beside :func:`footprint_figures`' ``out``: ``<out>_profiles.png``."""
    return out.with_name(out.stem + "_profiles.png")


def footprint_figures(session: Path | str, view: int, rows: str | Sequence[str], *, out: Path, pixels: int = 6,
                      checkpoint: Path | str | None = None, report: Report = Report()) -> FootprintFigures:
    """Footprints at ``pixels`` pixels spread over a session view's object, one row per source (``captured``:
    the session's dot-grid crops, or a backend), on a log scale relative to the first row's peak (``out``),
    and their centre-row profiles (``<out>_profiles.png``). A ``captured`` row the view lacks is left out."""
    import numpy as np

    from sssphase_core.relight import load_view
    from sssphase_core.relight.evaluation import footprints_at
    from sssphase_core.store.session import Session

    s = Session.open(session)
    rv = load_view(s, view)
    names = [b.strip() for b in (rows.split(",") if isinstance(rows, str) else rows) if b.strip()]
    if not names:
        raise InputError(f"--backend names no row (got {rows!r}): e.g. captured,analytic")
    if "captured" in names and "footprints/pixels" in s.arrays(view):
        candidates = np.asarray(s.load(view, "footprints/pixels"), np.int64)
    else:
        if "captured" in names:
            if names == ["captured"]:
                raise InputError(f"{session} view {view} has no captured footprints (capture with --footprints)")
            report.say(f"note: {session} view {view} has no captured footprints: that row is left out")
        names = [r for r in names if r != "captured"]
        candidates = np.argwhere(rv.proj.mask)
    chosen = candidates[np.linspace(0, len(candidates) - 1, pixels + 2)[1:-1].astype(int)]
    fps = footprints_at(rv, chosen, names, checkpoint=checkpoint)
    profiles = _draw_footprints(out, {name: f.mean(axis=-1) for name, f in fps.items()}, names, chosen,
                                f"{s.name}, view {view}")
    return FootprintFigures(out, profiles, names, chosen, s.name)


def _draw_footprints(out: Path, luminance: dict[str, Any], rows: list[str], chosen: Any, where: str) -> Path:
    import numpy as np

    from sssphase_core.reporting.figures import grid_figure, profiles_figure

    peak = np.maximum(next(iter(luminance.values())).max(axis=(1, 2)), 1e-12)  # each column's first-row peak
    grid = [[np.log10(np.maximum(luminance[name][i], 1e-30) / peak[i]) for i in range(len(chosen))] for name in rows]
    titles = [f"({y}, {x})" for y, x in chosen]
    grid_figure(out, grid, rows, titles, f"{where}: footprints at pixels (row, col), mean of RGB",
                units=f"log10 intensity / {rows[0]} peak", vmin=-4, vmax=0.3)
    k = next(iter(luminance.values())).shape[1]
    profiles = profiles_path(out)
    profiles_figure(profiles, {name: lum[:, k // 2, :] for name, lum in luminance.items()}, titles,
                    f"{where}: centre-row profiles", xlabel="offset (camera px)", ylabel="linear camera units")
    return profiles
