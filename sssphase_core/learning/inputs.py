"""What the learning commands share before any training: how a runner reports, the data options, the
views they read (captured sessions or the simulator) and the checks made before any work.

The session-level runners (``sssphase_core.reporting.learning_runs``) take a :class:`Report`: lines go to
``say``, a long step runs inside ``status(text)`` and training steps go to the callback ``steps()`` yields
(``training.StepProgress``). ``style(text, kind)`` marks a word (kinds ``strong``, ``note``, ``warning``,
``done``); the CLI colours it, a notebook keeps the plain text (the default ``Report()`` prints).
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from sssphase_core.errors import InputError

if TYPE_CHECKING:
    from sssphase_core.learning.data import PatchDataset, ViewData

#: Where simulated views are cached (``--cache``).
DEFAULT_CACHE = Path(".sss_cache")
#: A learning rate above it diverges, or, with the decoder's bounded heads, silently learns nothing
#: (SimSiam's SGD rate is 0.05 x batch/256, 0.8 at batch 4096; Adam's 1e-3).
MAX_LR = 10.0


def _plain(text: str, kind: str) -> str:
    return text


@dataclass(frozen=True)
class Report:
    """How a runner tells its caller what it does (see the module's docstring)."""

    say: Callable[[str], None] = print
    status: Callable[[str], AbstractContextManager[Any]] | None = None  # None: the text is said, then the step runs
    steps: Callable[[], AbstractContextManager[Any]] | None = None  # yields a StepProgress (None: no progress)
    style: Callable[[str, str], str] = _plain

    def busy(self, text: str) -> AbstractContextManager[Any]:
        """The context a long step runs in."""
        if self.status is not None:
            return self.status(text)
        self.say(text)
        return contextlib.nullcontext()

    @contextlib.contextmanager
    def training(self) -> Iterator[Any]:
        """The training loops' ``progress`` callback while they run (None: none)."""
        if self.steps is None:
            yield None
        else:
            with self.steps() as progress:
                yield progress


@dataclass(frozen=True)
class RunConfigFile:
    """A run's options file (the CLI's ``config.toml``): ``check(out, resuming)`` refuses, before any data is
    read, a resumed run whose options changed; ``save(out, resuming) -> path`` writes it before training."""

    check: Callable[[Path, bool], None]
    save: Callable[[Path, bool], Path]


@dataclass(kw_only=True)
class ViewOptions:
    """The data a learning command reads: ``objects`` and ``views`` (comma-separated text as typed, or lists;
    empty/None: the command's defaults) of captured ``sessions`` (a folder of sessions, or one session
    folder), or else of the simulator (``n_views`` turntable views, ``rig`` preset, views cached in ``cache``)."""

    objects: str | Sequence[str] = ""
    views: str | Sequence[int] | None = None
    n_views: int = 4
    rig: str = "cpu"
    pixels_per_view: int | None = 2000  # surface pixels sampled per view (None: all)
    seed: int = 0
    cache: Path = DEFAULT_CACHE
    sessions: Path | None = None


def parse_names(text: str | Sequence[str], default: Sequence[str]) -> list[str]:
    """Comma-separated names (or a list), each once (``apple,apple`` read the session twice and skewed kNN's
    accuracies); ``default`` when none is given."""
    if not text:
        return list(default)
    return list(dict.fromkeys(t.strip() for t in (text.split(",") if isinstance(text, str) else text) if t.strip()))


def parse_ints(text: str, option: str = "--views") -> list[int]:
    """Comma-separated integers; an :class:`InputError` naming ``option`` otherwise."""
    try:
        return [int(t) for t in text.split(",") if t.strip()]
    except ValueError as exc:
        raise InputError(f"{option} expects comma-separated integers, got {text!r}") from exc


def chosen_views(views: str | Sequence[int] | None, sim_default: str, sessions: Path | None,
                 option: str = "--views") -> list[int] | None:
    """The views given (each once: a view named twice trained twice as often), else every complete view of the
    sessions (None), else the simulator's default views. ``option``: the flag that gave them, for its errors."""
    if views is not None:
        return list(dict.fromkeys(parse_ints(views, option) if isinstance(views, str) else [int(v) for v in views]))
    return None if sessions is not None else parse_ints(sim_default, option)


def used_views(views: str | Sequence[int] | None, vds: Sequence[ViewData]) -> str:
    """The views as given, or the views that were read (the sessions' own), for tables and JSON."""
    if views is None:
        return ",".join(map(str, sorted({v.view for v in vds})))
    return views if isinstance(views, str) else ",".join(map(str, views))


def describe_views(vds: Sequence[ViewData]) -> str:
    """``apple view 0,1; pear view 0``."""
    views: dict[str, list[int]] = {}
    for v in vds:
        views.setdefault(v.object, []).append(v.view)
    return "; ".join(f"{o} view {','.join(map(str, vs))}" for o, vs in views.items())


def view_objects(vds: Sequence[ViewData]) -> list[str]:
    """The objects of ``vds``, in order, each once."""
    return list(dict.fromkeys(v.object for v in vds))


def load_views(names: Sequence[str], views: list[int] | dict[str, list[int]] | None, opts: ViewOptions, *,
               footprints: bool, noisy: bool = False, role: str = "data", report: Report = Report()) -> list[ViewData]:
    """The training or evaluation data: views of captured sessions (``opts.sessions``; ``views`` None: every
    complete view, or a list per object) or else rendered by the simulator; says where they came from."""
    if opts.sessions is not None:
        if opts.rig != ViewOptions.rig:  # it was ignored without a word
            warnings.warn(f"--rig {opts.rig} chooses the simulated rig; the data come from --sessions {opts.sessions}, "
                          "captured with their own rig: --rig is not used", UserWarning, stacklevel=2)
        if opts.cache is not None and Path(opts.cache) != Path(ViewOptions.cache):
            warnings.warn(f"--cache {opts.cache} holds simulated views; the data come from --sessions {opts.sessions}: "
                          "--cache is not used", UserWarning, stacklevel=2)
        return _session_views(names, views, opts, footprints=footprints, role=role, report=report)
    wanted = sorted({v for vs in (views.values() if isinstance(views, dict) else [views or []]) for v in vs})
    if wanted and wanted[-1] >= opts.n_views:  # view 0 was simulated before "view must be in [0, 1)"
        raise InputError(f"views {','.join(map(str, wanted))} need --n-views above {wanted[-1]} (the turntable's views "
                         f"per object; it is {opts.n_views}): pass --views within 0..{opts.n_views - 1} or raise --n-views")
    from sssphase_core.learning.data import simulate_views
    from sssphase_core.store.session import check_output_folder

    if opts.cache is not None:
        check_output_folder(opts.cache, "--cache")  # a folder of its own, never a file or a session's folder
    with report.busy(f"simulating {len(names)} object(s) x {len(views or [])} view(s) (cached in {opts.cache})"):
        vds = simulate_views(names, views, n_views=opts.n_views, rig=opts.rig, pixels_per_view=opts.pixels_per_view,
                             footprints=footprints, noisy_footprints=noisy, seed=opts.seed, cache_dir=opts.cache)
    report.say(f"{role}: the simulated rig ({opts.rig} preset{', exact footprints' if footprints and not noisy else ''}): "
               f"{describe_views(vds)}; pass --sessions DIR to use your own captures")
    return vds


def _session_views(names: Sequence[str], views: Any, opts: ViewOptions, *, footprints: bool, role: str,
                   report: Report) -> list[ViewData]:
    from sssphase_core.learning.data import session_views

    sessions = Path(opts.sessions)  # type: ignore[arg-type]
    with report.busy(f"reading sessions under {opts.sessions}"):
        vds = session_views(sessions, names or None, views or None, pixels_per_view=opts.pixels_per_view, footprints=footprints,
                            seed=opts.seed)
    if not vds:
        from sssphase_core.store.session import inside_session_hint

        why = "" if sessions.is_dir() else " (a file, not a folder)" if sessions.exists() else " (no such folder)"
        raise InputError(f"no complete session views under {opts.sessions}{why}{inside_session_hint([sessions])}")
    report.say(f"{role}: captured sessions under {opts.sessions}: {describe_views(vds)}")
    return vds


def decoder_view_choice(names: Sequence[str], views: str | Sequence[int] | None, val_views: str | Sequence[int] | None,
                        sessions: Path | None) -> tuple[Any, Any]:
    """The training and held-out views of a decoder run: as given; else with ``sessions`` each session's last
    view held out when it has two or more (``held_out_split``), else the simulator's views 0-2 and 3.
    A view list per object is a dict; ``[]``: no validation."""
    train_views, held = chosen_views(views, "0,1,2", sessions), chosen_views(val_views, "3", sessions, "--val-views")
    if sessions is not None and held is None:
        from sssphase_core.learning.data import held_out_split

        split_train, split_val = held_out_split(sessions, names or None)
        if train_views is None:
            return (split_train, split_val) if any(split_val.values()) else (None, [])
        left = {o: [v for v in vs if v not in train_views] for o, vs in split_val.items()}  # the views given train
        held = left if any(left.values()) else []
    return train_views, held


def training_data_from_sessions(names: Sequence[str], opts: ViewOptions, choice: tuple[Any, Any], *, noisy: bool = False,
                                report: Report = Report()) -> tuple[list[ViewData], list[ViewData]]:
    """A decoder run's training and validation views with footprint targets (``choice``: the
    :func:`decoder_view_choice`), captured or simulated; a validation view that also trains is refused."""
    train_views, held = choice
    train = load_views(names, train_views, opts, footprints=True, noisy=noisy, report=report)
    val = load_views(names, held, opts, footprints=True, noisy=noisy, role="validation (held out)",
                     report=report) if held else []
    both = sorted({(v.object, v.view) for v in train} & {(v.object, v.view) for v in val})
    if both:  # it was labelled "held out" and chose best.pt
        raise InputError(f"--val-views: {', '.join(f'{o} view {v}' for o, v in both)} "
                         f"{'is also a training view' if len(both) == 1 else 'are also training views'}; validation views "
                         "must be held out")
    return train, val


def check_lr(lr: float) -> None:
    """A learning rate is a finite number > 0 (NaN or a negative one would fail or diverge after the first step)
    and at most :data:`MAX_LR`."""
    if not (math.isfinite(lr) and lr > 0):
        raise InputError(f"--lr must be a finite number > 0, got {lr}")
    if lr > MAX_LR:
        raise InputError(f"--lr must be at most {MAX_LR:g}, got {lr:g} (defaults: 0.05 for pretraining, 1e-3 for the decoder)")


#: SimSiam's projector and predictor normalise over the batch (BatchNorm1d): a batch of one has nothing to
#: normalise over (torch refuses it in training mode). The loop only takes whole batches, so none is smaller.
MIN_PRETRAIN_BATCH = 2

#: SimSiam's augmentation sets (``augment.two_views``): the paper's PSP weak/strong pair, or ImageNet's
AUGMENT_KINDS = ("psp", "imagenet")

#: the decoder's output heads (``models.decoder.Decoder``)
DECODER_HEADS = ("reciprocal", "direct")


def check_pretrain_options(batch_size: int, warmup_epochs: float, augment: str = "psp",
                           decorrelate: float = 0.0) -> None:
    """Refuse, before any work (and before torch is imported), a batch too small for SimSiam's BatchNorm, a
    warmup that is not a finite number >= 0 (NaN or infinity cannot count steps; a negative one would mean
    none), an unknown augmentation set and a decorrelation weight that is not a finite number >= 0 (a
    negative one rewards collapse)."""
    if not (math.isfinite(decorrelate) and decorrelate >= 0):
        raise InputError(f"--decorrelate must be a finite number >= 0, got {decorrelate}")
    if augment not in AUGMENT_KINDS:
        raise InputError(f"--augment must be one of {', '.join(AUGMENT_KINDS)}, got {augment!r}")
    if batch_size < MIN_PRETRAIN_BATCH:
        raise InputError(f"--batch-size must be at least {MIN_PRETRAIN_BATCH} for pretraining, got {batch_size}: "
                         "SimSiam's projector and predictor normalise over the batch (BatchNorm)")
    if not (math.isfinite(warmup_epochs) and warmup_epochs >= 0):
        raise InputError(f"--warmup-epochs must be a finite number >= 0, got {warmup_epochs}")


def check_aux_class_count(n: int) -> None:
    """``n`` (``--aux-classes``) is 0 (no auxiliary head) or a number of the simulator's material classes >= 2."""
    from sssphase_core.sim.materials import MATERIAL_NAMES  # what material labels index

    if n != 0 and not 2 <= n <= len(MATERIAL_NAMES):
        raise InputError(f"--aux-classes must be 0 (no auxiliary material head) or a number of material classes from 2 "
                         f"to {len(MATERIAL_NAMES)} (the simulator's materials, which label the data), got {n}")


def check_batch(batch_size: int, ds: PatchDataset, what: str) -> None:
    """Before the run's folder is written: at least one whole batch (the loop drops a last, partial one)."""
    if len(ds) < batch_size:
        raise InputError(f"--batch-size {batch_size} is more than the {len(ds)} {what}: lower it, or sample more "
                         "--pixels-per-view / views")


def check_run_out(out: Path, kind: str, resume: bool, config_file: RunConfigFile | None = None,
                  epochs: int | None = None) -> bool:
    """Before any data is read: refuse an ``out`` that is a session or holds sessions or another kind of run,
    a run resumed with fewer ``epochs`` than it has trained (it trained nothing and its config.toml then said
    the wrong number), or (``config_file.check``) one resumed with options that shaped it changed. True when
    the run will resume from ``out``."""
    from sssphase_core.learning.training import check_run_folder
    from sssphase_core.store.session import MANIFEST, check_output_folder

    check_output_folder(out)  # not inside a session (a view folder)
    if out.is_dir() and any((child / MANIFEST).is_file() for child in out.iterdir() if child.is_dir()):
        raise InputError(f"--out {out} holds sessions: give the run a folder of its own (e.g. runs/{kind})")
    ckpt = check_run_folder(out, kind)
    resuming = ckpt is not None and resume
    done = int((ckpt or {}).get("loop", {}).get("epoch", 0)) if resuming else 0
    if epochs is not None and done > epochs:
        raise InputError(f"{out} holds a run that has trained {done} epochs: --epochs {epochs} would train none; "
                         f"pass --epochs above {done} to continue it, or --no-resume or another --out for a new run")
    if config_file is not None:
        config_file.check(out, resuming)
    return resuming
