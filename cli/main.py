"""Entry point of the `sss` command.

Command groups are created here; each area of the product registers its commands from its own
module (``register(groups)``), so this file only lists the modules. Command modules import only
typer/rich/stdlib at top level and load heavy libraries (torch, zmq, opencv) inside the command.
"""

from __future__ import annotations

import errno
import importlib
import importlib.util
import logging
import os
import signal
import sys
import warnings

import typer
from rich.console import Console
from rich.markup import escape

from sssphase_core.errors import SssError

err_console = Console(stderr=True, soft_wrap=True)

app = typer.Typer(
    name="sss",
    no_args_is_help=True,
    add_completion=False,
    help="Capture translucent objects with phase-shift patterns, learn their subsurface scattering, relight them.",
)

GROUP_HELP = {
    "bench": "Benchmarks: error against run time, written to JSON and Markdown.",
    "train": "Training: SimSiam pretraining and decoder fitting.",
    "eval": "Evaluation: kNN accuracy, footprint and relighting metrics.",
    "viz": "Visualisations: PCA-RGB feature maps, footprint profiles.",
    "daemon": "The acquisition daemon: start, stop, status, keys, connection (for clients on other machines).",
    "calibrate": "Rig calibration: the projector's response, camera and projector as a stereo pair, the turntable's axis.",
    "repro": "Reproduce the paper's experiments at its scale within a time budget.",
}


def _print_version(value: bool) -> None:
    if value:
        from sssphase_core import __version__

        typer.echo(f"sss (sssphase) {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """Capture translucent objects with phase-shift patterns, learn their subsurface scattering, relight them."""
    # Runs before any command (not for `sss --help`, which stays fast): the plugin manager hands core
    # the model backends of plugins; it imports numpy and reads every installed package's entry points.
    import sssphase_plugins.manager  # noqa: F401


groups: dict[str, typer.Typer] = {"root": app}
for _name, _help in GROUP_HELP.items():
    groups[_name] = typer.Typer(no_args_is_help=True, help=_help)

# One module per product area; each defines register(groups: dict[str, typer.Typer]).
COMMAND_MODULES = [
    "sssphase_cli.cmd_psp",  # patterns, decode, bench psp
    "sssphase_cli.cmd_sim",  # sim, objects, rigs
    "sssphase_cli.cmd_daemon",  # devices, plugins, daemon start|stop|status|keys, bench daemon
    "sssphase_cli.cmd_capture",  # capture, validate, import, export, calibrate projector, bench capture
    "sssphase_cli.cmd_udev",  # udev install
    "sssphase_cli.cmd_learn",  # train, eval knn/footprints, viz pca
    "sssphase_cli.cmd_relight",  # relight, geometry, eval relight, report, demo, bench relight/store/stability/gap
    "sssphase_cli.cmd_view",  # view (the browser: live view, live decode, sessions, relight)
    "sssphase_cli.cmd_repro",  # repro paper
]


def _register_all() -> None:
    for mod_name in COMMAND_MODULES:
        importlib.import_module(mod_name).register(groups)
    for name, group in groups.items():
        if name != "root" and (group.registered_commands or group.registered_groups):
            app.add_typer(group, name=name)


_register_all()


def _unwrap_docstrings() -> None:
    """Each command's help from its docstring with the source's line breaks joined within paragraphs: `sss --help`
    showed them mid-sentence ("... tone-mapped), mask,⏎ exact projector ...")."""
    import inspect

    for group in groups.values():
        for command in group.registered_commands:
            doc = command.help or (inspect.getdoc(command.callback) if command.callback else None)
            if doc:
                command.help = "\n\n".join(" ".join(part.split()) for part in doc.split("\n\n"))


_unwrap_docstrings()


def _flags_show_no_type() -> None:
    """A flag takes no value, so ``--help`` shows no ``<bool>`` type for it (typer 0.29 prints one)."""
    from typer.core import TyperOption

    shown = getattr(TyperOption, "display_type_rich", None)
    if shown is None:
        return

    def display_type_rich(self, ctx):  # noqa: ANN001, ANN202 - typer's own signature
        return None if self.is_flag and not self.count else shown(self, ctx)

    TyperOption.display_type_rich = display_type_rich  # type: ignore[method-assign]


_flags_show_no_type()


def _interrupt_on_sigterm(signum: int, frame: object) -> None:
    raise KeyboardInterrupt  # `kill PID` says "interrupted" and keeps work done, as Ctrl-C does


#: The warnings this command has shown, as (text, category).
_WARNED: set[tuple[str, type[Warning]]] = set()


def _one_line_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                      file: object = None, line: str | None = None) -> None:
    """A warning as one line, without the source line that Python prints under it (SSS_DEBUG=1 keeps that),
    and once per command: Python's own once-per-place rule forgets what it showed whenever any code changes the
    warning filters (each backend of ``sss relight`` re-read a half-transparent pattern and said so again)."""
    text = " ".join(str(message).split())
    if (text, category) in _WARNED:
        return
    _WARNED.add((text, category))
    err_console.print(f"[yellow]warning:[/] {escape(text)}" + ("" if category is UserWarning else f" ({category.__name__})"))


def _is_usage_exception(exc: BaseException, name: str) -> bool:
    """Whether ``exc`` is click's ``name`` exception, by class name.

    Typer >= 0.29 vendors click (``typer._click``) instead of depending on it, so the classes are not
    importable from a stable public module; their names and attributes (``exit_code``, ``show``) are.
    """
    return any(cls.__name__ == name for cls in type(exc).__mro__)


def _usage_line(exc: Exception) -> str:
    """Click's usage error as one line: its message and where help is (click prints four lines)."""
    message = " ".join(exc.format_message().split())  # type: ignore[attr-defined]
    ctx = getattr(exc, "ctx", None)
    if ctx is None:
        return message
    return f"{message} (see '{ctx.command_path} --help')"


#: errno values that describe the user's paths and disks, reported as one line (not an internal error).
FILE_SYSTEM_ERRORS = {errno.ENOTDIR, errno.EISDIR, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EROFS, errno.EEXIST,
                      errno.ENOENT, errno.ENAMETOOLONG, errno.EDQUOT, errno.ELOOP, errno.EFBIG}


#: what an interrupted command leaves, and how to go on (by its first word)
INTERRUPTED = {
    "import": "the views imported completely so far (if any) are kept; the same command again continues from them",
    "capture": "the views captured so far are kept; rerun with --resume to continue",
    "train": "training continues from its last checkpoint when the command is rerun",
    "relight": "the footprints computed so far are kept in --out's cache; the same command again computes only the rest",
    "demo": "work done so far is kept; rerun the command to resume",
    "patterns": "the patterns written so far are kept in --out; rerun into a new or emptied folder",
    "": "outputs written so far are kept; rerun the command to redo the rest",
}


def _path_flags() -> set[str]:
    """The flags of every command's options whose value is a path (a ``Path`` or ``Path | None`` parameter),
    in every group and sub-group."""
    import inspect
    import pathlib
    import typing

    from typer.models import ArgumentInfo, ParameterInfo

    def is_path(hint: object) -> bool:
        return hint is pathlib.Path or pathlib.Path in typing.get_args(hint)

    flags: set[str] = set()
    typers, commands = [app], []
    while typers:  # every group and sub-group (`sss daemon keys`, `sss udev install`)
        group = typers.pop()
        commands += group.registered_commands
        typers += [g.typer_instance for g in group.registered_groups if g.typer_instance is not None]
    for info in commands:
        try:
            hints = typing.get_type_hints(info.callback, include_extras=True)
        except Exception:  # noqa: BLE001 - a command whose hints do not resolve: its options are not checked
            continue
        for name, param in inspect.signature(info.callback).parameters.items():
            hint, meta = hints.get(name), [param.default]
            if typing.get_origin(hint) is typing.Annotated:
                hint, *extra = typing.get_args(hint)
                meta += extra
            infos = [m for m in meta if isinstance(m, ParameterInfo)]
            if not is_path(hint) or any(isinstance(i, ArgumentInfo) for i in infos):
                continue
            decls = [d for i in infos for d in (*(getattr(i, "param_decls", None) or ()), i.default)  # typer.Option("--dir")
                     if isinstance(d, str) and d.startswith("--")]
            flags.update(decls or [f"--{name.replace('_', '-')}"])
    return flags


def _empty_path_option(argv: list[str]) -> str | None:
    """The first path option given an empty value (``--out ""`` or ``--out=``): a ``Path("")`` is the current
    folder, where the command would write or read in silence."""
    if not any(a == "" or a.endswith("=") for a in argv):
        return None
    flags = _path_flags()
    for i, arg in enumerate(argv):
        if (arg in flags and i + 1 < len(argv) and argv[i + 1] == "") or (arg.endswith("=") and arg[:-1] in flags):
            return arg.removesuffix("=")
    return None


def main() -> None:
    """Run the CLI; user-facing errors are printed as one clear message, never a traceback."""
    try:
        _run()
    except SystemExit as done:
        _leave_hung_plugins_behind(done.code)
        raise


def _leave_hung_plugins_behind(code: object) -> None:
    """Exit at once when a plugin's discovery thread still hangs: the interpreter's teardown under a native call
    still running in it crashed (`sss devices` printed its table, then died of SIGSEGV or abort in depthai)."""
    import threading

    if any(t.is_alive() and t.name == "sss-discover" for t in threading.enumerate()):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code if isinstance(code, int) else (0 if code is None else 1))


def _run() -> None:
    signal.signal(signal.SIGTERM, _interrupt_on_sigterm)
    if (flag := _empty_path_option(sys.argv[1:])) is not None:
        err_console.print(f"[bold red]error:[/] {flag} is empty: give a path (an empty one would be the current folder)")
        sys.exit(2)
    if not os.environ.get("SSS_DEBUG"):
        warnings.showwarning = _one_line_warning
        # zarr decodes chunks on a background asyncio loop: when one chunk is damaged, its sibling tasks
        # are dropped at exit and asyncio logs each with a traceback. The error itself is reported once.
        logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    try:
        rc = app(standalone_mode=False)
        if rc == 130:  # typer turns KeyboardInterrupt (Ctrl-C, or SIGTERM above) into exit code 130
            raise KeyboardInterrupt
        sys.exit(rc if isinstance(rc, int) else 0)
    except SssError as exc:  # one line: a path holding a newline is shown with it escaped
        text = str(exc).replace("\r", "\\r").replace("\n", "\\n")
        err_console.print(f"[bold red]error:[/] {escape(text)}")
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print(f"[yellow]interrupted[/] ({INTERRUPTED.get(sys.argv[1] if len(sys.argv) > 1 else '', INTERRUPTED[''])})")
        sys.exit(130)
    except MemoryError as exc:  # an input far larger than the machine can hold: say so, no traceback
        detail = str(exc).splitlines()[0] if str(exc) else "the machine's memory is exhausted"
        err_console.print(f"[bold red]error:[/] out of memory ({escape(detail)}): use smaller inputs, "
                          "fewer pixels per view or a smaller --chunk / --batch-size")
        sys.exit(2)
    except Exception as exc:  # click's own usage errors and anything unexpected
        if _is_usage_exception(exc, "Exit"):
            sys.exit(exc.exit_code)  # type: ignore[attr-defined]
        if _is_usage_exception(exc, "ClickException"):
            err_console.print(f"[bold red]error:[/] {escape(_usage_line(exc))}")
            sys.exit(exc.exit_code)  # type: ignore[attr-defined]
        if _is_usage_exception(exc, "Abort") and isinstance(exc.__cause__, EOFError):
            # click turns an EOFError into Abort ("aborted"): here a file that ended early (an empty .npy)
            detail = str(exc.__cause__).splitlines()[0] if str(exc.__cause__) else "no data left"
            err_console.print(f"[bold red]error:[/] an input file ended early (EOFError: {escape(detail)}): "
                              "an empty or truncated file?")
            sys.exit(2)
        if _is_usage_exception(exc, "Abort"):
            err_console.print("[yellow]aborted[/]")
            sys.exit(1)
        if os.environ.get("SSS_DEBUG"):
            raise
        if isinstance(exc, OSError) and exc.errno in FILE_SYSTEM_ERRORS:  # the user's paths: a file given as a
            where = f"{exc.filename}: " if exc.filename else ""  # folder, no permission, a full disk
            err_console.print(f"[bold red]error:[/] {escape(where + (exc.strerror or str(exc)))}")
            sys.exit(2)
        err_console.print(f"[bold red]internal error:[/] {escape(f'{type(exc).__name__}: {exc}')}\n"
                          "(set SSS_DEBUG=1 for a traceback)")
        sys.exit(1)


if __name__ == "__main__":
    main()
