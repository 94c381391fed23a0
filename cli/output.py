"""Writing a command's result files (a JSON record and its Markdown table) and saying where they went."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rich.console import Console


def write_result(console: Console, out: Path, md: Path | None, result: dict[str, Any], markdown: str) -> Path:
    """``result`` as JSON to ``out`` and ``markdown`` to ``md`` (default: ``out`` with ``.md``); prints the
    table and the paths. Returns the Markdown path."""
    from sssphase_core.store.results import write_result_files

    md = md or out.with_suffix(".md")
    write_result_files(result, out, md, markdown)
    console.print(markdown)
    console.print(f"wrote {out} and {md}")
    return md


@contextlib.contextmanager
def stdout_to_stderr() -> Iterator[None]:
    """What plugins and their native libraries print on stdout goes to stderr for the block (depthai's "USB protocol
    not available" warning broke `sss devices --json` for any JSON reader)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no stdout to keep clean
        yield
        return
    os.dup2(2, 1)
    try:
        yield
    finally:
        with contextlib.suppress(AttributeError, OSError, ValueError):
            sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
