"""Progress bars drawn from core's plain callbacks (core never imports rich)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from rich.console import Console

#: Seconds between two progress lines of a task where no bar can be drawn (output to a file or a pipe).
PLAIN_EVERY_S = 30.0


def plain_progress(console: Console, every_s: float = PLAIN_EVERY_S) -> Callable[[str, int, int, str], None]:
    """A ``progress(task, done, total, info)`` callback that prints a line per task at most every ``every_s``
    seconds, at each tenth of the way and at its end: a bar written to a log file appeared only once the work was
    done (`sss demo > log`: "[pretrain] running" for nine minutes, then the finished bars)."""
    import time

    said: dict[str, tuple[float, int]] = {}  # task -> (when, which tenth) last said

    def update(task: str, done: int, total: int, info: str) -> None:
        now, tenth = time.monotonic(), (10 * done) // max(1, total)
        when, last = said.get(task, (now, 0))
        if task in said and done < total and tenth == last and now - when < every_s:
            return
        if task in said and done >= total and last == 10:
            return
        said[task] = (now, tenth)
        console.print(f"{task}: {done}/{total}" + (f" {info}" if info else ""), highlight=False)

    return update


@contextlib.contextmanager
def step_bar(console: Console) -> Iterator[Callable[[str, int, int, str], None]]:
    """A ``progress(task, done, total, info)`` callback (``training.StepProgress``) drawing one bar per task, or
    printing a line now and then (:func:`plain_progress`) where the console is no terminal."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    if not console.is_terminal:
        yield plain_progress(console)
        return

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[info]}"), TimeRemainingColumn(), console=console) as bar:
        tasks: dict[str, int] = {}

        def update(task: str, done: int, total: int, info: str) -> None:
            if task not in tasks:
                tasks[task] = bar.add_task(task, total=total, info="")
            bar.update(tasks[task], completed=done, total=total, info=info)

        yield update


class LazyBar:
    """A rich progress bar for a library call that reports ``progress(done, total)``: started on the first
    report (so a run refused before any work prints only its error), stopped at the last report or when the
    block ends. ``print`` writes a line above the bar while it is shown."""

    def __init__(self, description: str) -> None:
        self.description = description
        self.bar = None
        self.task = None

    def start(self, total: int | None) -> None:
        """Show the bar (once) with its main task of ``total`` steps."""
        if self.bar is None:
            from rich.progress import Progress

            self.bar = Progress()
            self.bar.start()
            self.task = self.bar.add_task(self.description, total=total)

    def __call__(self, done: int, total: int) -> None:
        self.start(total)
        self.bar.update(self.task, completed=done)
        if done >= total:
            self.close()

    def print(self, line: str) -> None:
        if self.bar is not None:
            self.bar.console.print(line)
        else:
            print(line)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None

    def __enter__(self) -> LazyBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
