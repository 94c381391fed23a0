"""mkdocs hook: the CLI reference page, generated from the Typer app at build time.

Walks ``typer.main.get_command(sssphase_cli.main.app)`` recursively and writes ``reference/cli.md``
(a generated file: nothing under docs/ to go stale) with every command and subcommand, its help and its
arguments and options. Only the command objects' attributes are read (typer >= 0.29 vendors click as
``typer._click``; click itself is never imported here), so a command added to the app appears in the
next build. tests/test_docs.py checks that every command of the app is on the built page.
"""

from __future__ import annotations

import inspect
import typing

PAGE = "reference/cli.md"


def walk(command, path=("sss",)):
    """(path, command) for ``command`` and every visible subcommand below it, depth first, by name."""
    yield path, command
    for name in sorted(getattr(command, "commands", {}) or {}):
        sub = command.commands[name]
        if getattr(sub, "hidden", False):
            continue
        yield from walk(sub, (*path, name))


def command_id(path) -> str:
    return "-".join(path)


def _type_name(param) -> str:
    click_type = getattr(param, "type", None)
    if click_type is not None and getattr(click_type, "name", None):
        return str(click_type.name).upper()
    annotation = getattr(getattr(param, "type_descriptor", None), "annotation", None)
    if annotation is None:
        return ""
    origin = typing.get_origin(annotation)
    if origin is not None:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if origin in (list, tuple, set) and args:
            return f"{_type_name_of(args[0])} …"
        if args:
            return _type_name_of(args[0])
    return _type_name_of(annotation)


def _type_name_of(annotation) -> str:
    if inspect.isclass(annotation):
        if issubclass(annotation, bool):
            return ""
        return {"str": "TEXT", "int": "INTEGER", "float": "FLOAT", "Path": "PATH"}.get(
            annotation.__name__, annotation.__name__.upper()
        )
    return str(annotation)


def _cell(text) -> str:
    """One Markdown table cell: one line, pipes escaped."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _default(param) -> str:
    default = getattr(param, "default", None)
    if getattr(param, "required", False) or default is None or callable(default):
        return ""
    if getattr(param, "show_default", True) is False:
        return ""
    if isinstance(default, bool):
        if not getattr(param, "secondary_opts", None):
            return "" if default is False else "on"
        return "`" + (param.opts[0] if default else param.secondary_opts[0]) + "`"
    if isinstance(default, (list, tuple)):
        if not default:
            return ""
        return "`" + ", ".join(str(d) for d in default) + "`"
    text = str(default)
    return f"`{text}`" if text != "" else '`""`'


def render_params(command) -> list[str]:
    params = [p for p in getattr(command, "params", []) if not getattr(p, "hidden", False)]
    arguments = [p for p in params if getattr(p, "param_type_name", "") == "argument"]
    options = [p for p in params if getattr(p, "param_type_name", "") == "option"]
    lines: list[str] = []
    if arguments:
        lines += ["", "| argument | type | required | description |", "|---|---|---|---|"]
        for p in arguments:
            name = (getattr(p, "metavar", None) or p.name or "").upper()
            required = "yes" if getattr(p, "required", False) else "no"
            lines.append(
                f"| `{name}` | {_type_name(p)} | {required} | {_cell(getattr(p, 'help', '') or '')} |"
            )
    if options:
        lines += ["", "| option | type | default | description |", "|---|---|---|---|"]
        for p in options:
            flags = " / ".join(f"`{o}`" for o in [*p.opts, *(getattr(p, "secondary_opts", None) or [])])
            kind = "flag" if getattr(p, "is_flag", False) else _type_name(p)
            help_text = _cell(getattr(p, "help", "") or "")
            if getattr(p, "required", False):
                help_text = "**required.** " + help_text
            lines.append(f"| {flags} | {kind} | {_default(p)} | {help_text} |")
    return lines


def usage(path, command) -> str:
    pieces = [" ".join(path)]
    if getattr(command, "commands", None):
        pieces.append("COMMAND [ARGS]...")
    elif any(getattr(p, "param_type_name", "") == "option" for p in getattr(command, "params", [])):
        pieces.append("[OPTIONS]")
    for p in getattr(command, "params", []):
        if getattr(p, "param_type_name", "") == "argument" and not getattr(p, "hidden", False):
            name = (getattr(p, "metavar", None) or p.name or "").upper()
            pieces.append(name if getattr(p, "required", False) else f"[{name}]")
    return " ".join(pieces)


def render(root) -> str:
    """The reference page's Markdown for the click command ``root`` (the app's top-level group)."""
    lines = [
        "# CLI reference",
        "",
        "Every `sss` command and subcommand with its arguments and options. This page is generated from the",
        "Typer app each time the site is built (`docs/hooks/cli_reference.py`), so it lists what the installed",
        "`sss` accepts; `sss COMMAND --help` prints the same.",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    entries = list(walk(root))
    for path, command in entries[1:]:
        summary = (getattr(command, "short_help", None) or getattr(command, "help", "") or "").strip()
        summary = summary.split("\n\n")[0]
        lines.append(f"| [`{' '.join(path)}`](#{command_id(path)}) | {_cell(summary)} |")
    for path, command in entries:
        depth = min(len(path) + 1, 4)
        lines += ["", "#" * depth + f" `{' '.join(path)}` {{ #{command_id(path)} }}", ""]
        if getattr(command, "deprecated", False):
            lines += ['!!! warning "Deprecated"', ""]
        lines += ["```text", usage(path, command), "```", ""]
        help_text = inspect.cleandoc(getattr(command, "help", "") or "").replace("\b\n", "")
        if help_text:
            lines.append(help_text)
        subcommands = [(p, c) for p, c in entries if len(p) == len(path) + 1 and p[: len(path)] == path]
        if subcommands:
            lines += ["", "| subcommand | what it does |", "|---|---|"]
            for sub_path, sub in subcommands:
                summary = (getattr(sub, "short_help", None) or getattr(sub, "help", "") or "").split("\n\n")[
                    0
                ]
                lines.append(f"| [`{sub_path[-1]}`](#{command_id(sub_path)}) | {_cell(summary)} |")
        lines += render_params(command)
        epilog = getattr(command, "epilog", None)
        if epilog:
            lines += ["", inspect.cleandoc(epilog)]
    return "\n".join(lines) + "\n"


def app_command():
    import typer.main

    from sssphase_cli.main import app

    return typer.main.get_command(app)


def on_files(files, config):
    from mkdocs.structure.files import File

    files.append(File.generated(config, PAGE, content=render(app_command())))
    return files
