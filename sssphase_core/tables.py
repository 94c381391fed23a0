"""Markdown tables that core returns for the CLI, the reports and the benchmarks to show."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Table:
    """A Markdown table: ``rows`` are sequences matching ``columns``; floats are shown with 3 significant digits."""

    title: str
    columns: Sequence[str]
    rows: list[Sequence[Any]] = field(default_factory=list)
    note: str = ""

    def markdown(self) -> str:
        def fmt(v: Any) -> str:
            if isinstance(v, float | np.floating):
                return "n/a" if not math.isfinite(v) else f"{v:.3g}"
            return str(v)

        lines = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |", "|" + "---|" * len(self.columns)]
        lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in self.rows]
        if self.note:
            lines += ["", self.note]
        return "\n".join(lines) + "\n"
