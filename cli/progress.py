"""Progress bars drawn from core's plain callbacks (core never imports rich)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from rich.console import Console


@contextlib.contextmanager
def step_bar(console: Console) -> Iterator[Callable[[str, int, int, str], None]]:
    """A ``progress(task, done, total, info)`` callback (``training.StepProgress``) drawing one bar per task."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[info]}"), TimeRemainingColumn(), console=console) as bar:
        tasks: dict[str, int] = {}

        def update(task: str, done: int, total: int, info: str) -> None:
            if task not in tasks:
                tasks[task] = bar.add_task(task, total=total, info="")
            bar.update(tasks[task], completed=done, total=total, info=info)

        yield update
