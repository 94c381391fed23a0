"""Writing a command's result files (a JSON record and its Markdown table) and saying where they went."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from rich.console import Console

from sssphase_core.store.files import write_text


def write_result(console: Console, out: Path, md: Path | None, result: dict[str, Any], markdown: str) -> Path:
    """``result`` as JSON to ``out`` and ``markdown`` to ``md`` (default: ``out`` with ``.md``); prints the
    table and the paths. Returns the Markdown path."""
    from sssphase_core.bench.output import check_result_paths

    md = md or out.with_suffix(".md")
    check_result_paths(out, md)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps(result, indent=1, default=str))
    md.parent.mkdir(parents=True, exist_ok=True)
    write_text(md, markdown)
    console.print(markdown)
    console.print(f"wrote {out} and {md}")
    return md
