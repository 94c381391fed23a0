"""Result files of runs that tabulate (benchmarks, ``sss eval relight``): a JSON record and, beside it, its
Markdown tables (:func:`write_report`), on paths checked before the work (:func:`check_result_paths`)."""

from __future__ import annotations

import json
import math
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


def check_result_paths(out: Path | str, md: Path | str | None = None) -> None:
    """Refuse result files that would land inside a session (``--out S/apple/manifest.json`` replaced a
    session's manifest), on an existing folder, or a JSON and its Markdown on one path."""
    from sssphase_core.errors import InputError
    from sssphase_core.store.session import refuse_inside_session

    for path in (Path(out), *([Path(md)] if md is not None else [])):
        refuse_inside_session(path.parent, what=f"--out {path}: its folder")
        if path.is_dir():
            raise InputError(f"--out {path} is a folder: give a file name (e.g. {path / 'result.json'})")
        above = next((a for a in path.parents if a.exists()), None)  # "afile: File exists" came after all the work
        if above is not None and not above.is_dir():
            raise InputError(f"--out {path}: {above} is a file, so no folder can be made there")
    if md is not None and Path(md).resolve() == Path(out).resolve():
        raise InputError(f"--out {out}: the JSON record and its Markdown table would be the same file; give a .json name")


def write_report(result: dict[str, Any], tables: Sequence[Table], out: Path, md: Path | None = None, title: str = "") -> None:
    """Write ``result`` as JSON to ``out`` and, if ``md`` is given, the tables as Markdown."""
    out = Path(out)
    check_result_paths(out, md)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps(jsonable(result), indent=1) + "\n")
    if md is not None:
        md = Path(md)
        md.parent.mkdir(parents=True, exist_ok=True)
        head = f"## {title}\n\n" if title else ""
        write_text(md, head + "\n".join(t.markdown() for t in tables))
