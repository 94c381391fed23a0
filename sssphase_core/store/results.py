"""Result files of runs that tabulate (benchmarks, ``sss eval relight``): a JSON record and, beside it, its
Markdown tables (:func:`write_report`), on paths checked before the work (:func:`check_result_paths`)."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.store.files import write_text
from sssphase_core.tables import Table


def jsonable(obj: Any) -> Any:
    """``obj`` as JSON takes it: numpy arrays and scalars as lists and numbers, NaN and inf as null, paths as text."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


#: What marks a result file as sssphase's own (``written_by`` of the JSON record, the Markdown's last line):
#: only such a file is replaced by a new result (``--out notes.json`` replaced the user's notes.json and notes.md).
WRITTEN_BY = "sssphase"
MARKDOWN_MARK = "<!-- written by sssphase -->"


def is_our_result(path: Path) -> bool:
    """Whether ``path`` is a result file sssphase wrote: a JSON object whose ``written_by`` is sssphase, or a
    Markdown file whose last line is :data:`MARKDOWN_MARK` (read at most 64 MiB, a regular file only)."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.files import check_input_file

    try:
        check_input_file(path, "--out", max_bytes=64 << 20)
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError, InputError):
        return False
    if text.rstrip().endswith(MARKDOWN_MARK):
        return True
    try:
        record = json.loads(text)
    except ValueError:
        return False
    return isinstance(record, dict) and record.get("written_by") == WRITTEN_BY


def check_result_paths(out: Path | str, md: Path | str | None = None) -> None:
    """Refuse result files that would land inside a session (``--out S/apple/manifest.json`` replaced a
    session's manifest), on an existing folder or a file sssphase did not write, or a JSON and its
    Markdown on one path."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import refuse_inside_session

    for path in (Path(out), *([Path(md)] if md is not None else [])):
        refuse_inside_session(path.parent, what=f"--out {path}: its folder")
        if path.is_dir():
            raise InputError(f"--out {path} is a folder: give a file name (e.g. {path / 'result.json'})")
        above = next((a for a in path.parents if a.exists()), None)  # "afile: File exists" came after all the work
        if above is not None and not above.is_dir():
            raise InputError(f"--out {path}: {above} is a file, so no folder can be made there")
        if above is not None and not os.access(above, os.W_OK | os.X_OK):  # "Permission denied" came after the work
            raise InputError(f"--out {path}: this user may not write in {above}")
        if (path.exists() or path.is_symlink()) and not is_our_result(path):
            which = "" if path == Path(out) else f" (the Markdown table of --out {out})"
            raise InputError(f"--out: {path}{which} exists and is not a result sssphase wrote: give another name or "
                             "remove it (nothing was written)")
    if md is not None and Path(md).resolve() == Path(out).resolve():
        raise InputError(f"--out {out}: the JSON record and its Markdown table would be the same file; give a .json name")


def write_result_files(result: dict[str, Any], out: Path | str, md: Path | str | None, markdown: str) -> None:
    """``result`` as a JSON record at ``out`` and ``markdown`` at ``md`` (if given), each marked as sssphase's
    own (:func:`is_our_result`), on paths :func:`check_result_paths` accepts."""
    out = Path(out)
    check_result_paths(out, md)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps({**jsonable(result), "written_by": WRITTEN_BY}, indent=1, default=str) + "\n")
    if md is not None:
        md = Path(md)
        md.parent.mkdir(parents=True, exist_ok=True)
        write_text(md, markdown.rstrip("\n") + f"\n\n{MARKDOWN_MARK}\n")


def write_report(result: dict[str, Any], tables: Sequence[Table], out: Path, md: Path | None = None, title: str = "") -> None:
    """Write ``result`` as JSON to ``out`` and, if ``md`` is given, the tables as Markdown."""
    head = f"## {title}\n\n" if title else ""
    write_result_files(result, out, md, head + "\n".join(t.markdown() for t in tables))
