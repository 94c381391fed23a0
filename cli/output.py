"""Writing a command's result files (a JSON record and its Markdown table) and saying where they went."""

from __future__ import annotations

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
