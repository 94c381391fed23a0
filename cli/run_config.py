"""A run's full configuration as ``RUN/config.toml``, and ``--config FILE`` to repeat or vary it.

The file names the command and holds every option's resolved value::

    command = "train pretrain"
    [options]
    epochs = 4
    pixels_per_view = 500
    sessions = "sessions"

``--config`` is read before the other options, so its values become their defaults and flags given on
the command line override them (``sss train pretrain --config runs/a/config.toml --out runs/b --lr 0.1``).
"""

from __future__ import annotations

import tomllib
import warnings
from pathlib import Path
from typing import Annotated, Any

import typer

from sssphase_core.learning.inputs import RunConfigFile

CONFIG = "config.toml"
NOT_SAVED = {"config", "resume"}  # how to run, not what the run is
SIMULATION_ONLY = ("rig", "n_views", "cache")  # options of simulated data, left out of a run on --sessions


def _command_name(ctx: typer.Context) -> str:
    """``"train pretrain"`` for ``sss train pretrain``, whatever the program is called (``python -m ...``)."""
    names = []
    while ctx.parent is not None:
        names.append(ctx.info_name or "")
        ctx = ctx.parent
    return " ".join(reversed(names))


def _load(ctx: typer.Context, param: Any, value: Path | None) -> Path | None:
    """Eager callback of ``--config``: the file's options become the defaults of the other options."""
    from sssphase_core.errors import InputError

    if value is None or ctx.resilient_parsing:
        return value
    path = Path(value)
    if path.is_dir():
        path = path / CONFIG
    try:
        from sssphase_core.store.files import read_toml_input

        data = read_toml_input(path, "--config")
    except FileNotFoundError:
        raise InputError(f"--config {value}: the folder has no {CONFIG}" if Path(value).is_dir()
                         else f"--config {value}: no such file") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InputError(f"--config {path} is not a readable TOML file: {exc}") from None
    command, options = data.get("command"), data.get("options")
    if not isinstance(command, str) or not isinstance(options, dict):
        raise InputError(f"--config {path} needs a `command` name and an `[options]` table")
    if command != _command_name(ctx):
        raise InputError(f"--config {path} is a configuration of `sss {command}`, not of `sss {_command_name(ctx)}`")
    known = {p.name for p in ctx.command.params} - NOT_SAVED
    unknown = sorted(set(options) - known)
    if unknown:
        raise InputError(f"--config {path}: unknown option(s) {', '.join(unknown)} for `sss {command}`")
    kinds = _option_kinds(ctx)
    for name, option in options.items():  # checked here, in the file's terms (click said "Invalid value for '--epochs'")
        expected = kinds.get(name)
        if expected and not _is_kind(option, expected):
            shown = str(option).lower() if isinstance(option, bool) else repr(option)
            raise InputError(f"--config {path}: {name} must be {expected}, got {shown}")
    folder = path.parent
    recorded = options.get("out")
    if (isinstance(recorded, str) and any((folder / name).is_file() for name in ("last.pt", "best.pt"))
            and Path(recorded).resolve() != folder.resolve()):
        # a run folder copied or moved: its recorded --out is the original, which continuing it would overwrite
        warnings.warn(f"--config {value}: this run was recorded at {recorded}; it continues here, in {folder} "
                      "(pass --out to choose another folder)", UserWarning, stacklevel=2)
        options = {**options, "out": str(folder)}
    ctx.default_map = {**(ctx.default_map or {}), **options}
    return path


def _option_kinds(ctx: typer.Context) -> dict[str, str]:
    """What each option of the running command takes in a config file, from its function's type hints:
    ``"a number"``, ``"a whole number"``, ``"true or false"``, ``"a string"``, ``"a path (not empty)"`` (an empty
    one is the current folder) or a list of strings or paths; options of another type are left out."""
    import types
    import typing

    try:
        hints = typing.get_type_hints(ctx.command.callback, include_extras=False)  # type: ignore[arg-type]
    except Exception:  # noqa: BLE001  (a command without readable hints: nothing to check)
        return {}
    out = {}
    for name, hint in hints.items():
        union = isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union
        args = [a for a in (typing.get_args(hint) if union else (hint,)) if a is not type(None)]
        if len(args) != 1:
            continue
        arg = args[0]
        if arg is bool:
            out[name] = "true or false"
        elif arg is int:
            out[name] = "a whole number"
        elif arg is float:
            out[name] = "a number"
        elif arg is str:
            out[name] = "a string"
        elif arg is Path:
            out[name] = "a path (not empty)"
        elif typing.get_origin(arg) is list and typing.get_args(arg) == (str,):
            out[name] = "a list of strings"
        elif typing.get_origin(arg) is list and typing.get_args(arg) == (Path,):
            out[name] = "a list of paths (none empty)"
    return out


def _is_kind(value: Any, kind: str) -> bool:
    """Whether a TOML ``value`` is what :func:`_option_kinds` says (a bool is no number: true ran as a batch of 1)."""
    if kind == "true or false":
        return isinstance(value, bool)
    if isinstance(value, bool):
        return False
    if kind == "a whole number":
        return isinstance(value, int)
    if kind == "a number":
        return isinstance(value, int | float)
    if kind == "a string":
        return isinstance(value, str)
    if kind == "a path (not empty)":
        return isinstance(value, str) and value != ""
    return isinstance(value, list) and all(isinstance(v, str) and (v or "path" not in kind) for v in value)


ConfigOpt = Annotated[Path | None, typer.Option(
    "--config", callback=_load, is_eager=True,
    help="A run's config.toml (or its run folder) whose options become the defaults; flags override them.")]


def _toml_value(value: Any) -> Any:
    if isinstance(value, Path):  # absolute: `--config RUN` from another folder reads the same data, writes the same run
        return str(value.resolve())
    if isinstance(value, list | tuple):
        return [_toml_value(v) for v in value]
    return value


def _same(now: Any, saved: Any, is_path: bool) -> bool:
    """Whether an option's value equals the saved one (paths compared resolved: a file written before paths
    were stored absolute holds them as given, relative to where the run was started)."""
    if not is_path or now is None or saved is None:
        return now == saved
    as_list = lambda v: [v] if isinstance(v, str) else list(v)  # noqa: E731
    return [str(Path(x).resolve()) for x in as_list(now)] == [str(Path(x).resolve()) for x in as_list(saved)]


#: Options a resumed run may change: how long and where it runs, not what it learns from.
RESUMABLE = {"epochs", "time_limit", "device", "deterministic", "ckpt_every", "cache", "out"}


def _refuse_a_foreign_config(path: Path, command: str) -> None:
    """Refuse to replace a ``config.toml`` that is not this command's run options (``--out ~/project`` replaced
    the user's own config.toml)."""
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training.loop import CHECKPOINT
    from sssphase_core.store.files import read_toml_input

    if not (path.exists() or path.is_symlink()) or (path.parent / CHECKPOINT).is_file():  # a run's own (damaged) file
        return
    try:
        saved = read_toml_input(path, "the run's saved options") if path.is_file() and not path.is_symlink() else {}
    except (OSError, InputError):
        saved = {}
    if saved.get("command") != command or not isinstance(saved.get("options"), dict):
        raise InputError(f"{path} is not the options file of a `sss {command}` run: refusing to replace it; "
                         "give a new or empty --out")


def check_run_config(ctx: typer.Context, *args: Any, **kwargs: Any) -> None:
    """:func:`save_run_config`'s check alone (before any data is read)."""
    save_run_config(ctx, *args, write=False, **kwargs)


def save_run_config(ctx: typer.Context, out: Path, *, resuming: bool = False, write: bool = True) -> Path:
    """Write ``out/config.toml`` with every resolved option of the running command (None left out).

    ``resuming`` (a run continues from ``out``'s checkpoint): an option that shaped the run (data, model,
    optimiser) differing from the saved one is refused, so the file keeps saying what the run is."""
    import tomli_w

    options = {k: _toml_value(v) for k, v in ctx.params.items() if k not in NOT_SAVED and v is not None}
    if options.get("sessions") is not None:  # captured data: the simulator's options shaped nothing
        for k in SIMULATION_ONLY:
            options.pop(k, None)
    saved_path = out / CONFIG
    if resuming:
        from sssphase_core.errors import InputError

        try:
            from sssphase_core.store.files import read_toml_input

            saved = read_toml_input(saved_path, "the run's saved options").get("options")
        except (OSError, InputError):
            saved = None
        if not isinstance(saved, dict):  # a run of the API or the demo, or a damaged file: it resumed with any options
            raise InputError(f"{out} holds a checkpoint but no readable {CONFIG}: the options it was trained with are "
                             "unknown, so it is not resumed with these; pass --no-resume to start afresh there, or "
                             "another --out")
        paths = {k for k, v in ctx.params.items() if isinstance(v, Path) or (isinstance(v, list | tuple) and v
                                                                              and all(isinstance(x, Path) for x in v))}
        changed = sorted(k for k in saved if k not in RESUMABLE and not _same(options.get(k), saved[k], k in paths))
        if changed:
            k = changed[0]
            raise InputError(f"{out} holds a run made with --{k.replace('_', '-')} {saved.get(k)!r}, not {options.get(k)!r}"
                             f"{f' (and {len(changed) - 1} more)' if len(changed) > 1 else ''}: resume it with its own "
                             f"options (--config {out}), or pass --no-resume or another --out")
    _refuse_a_foreign_config(saved_path, _command_name(ctx))
    if not write:
        return saved_path
    from sssphase_core.store.files import atomic_path

    with atomic_path(out / CONFIG) as tmp:
        tmp.write_text(tomli_w.dumps({"command": _command_name(ctx), "options": options}))
    return out / CONFIG


def run_config_file(ctx: typer.Context) -> RunConfigFile:
    """The running command's ``config.toml`` as the runners take it (checked before the data, saved before training)."""
    return RunConfigFile(check=lambda out, resuming: check_run_config(ctx, out, resuming=resuming),
                         save=lambda out, resuming: save_run_config(ctx, out, resuming=resuming))
