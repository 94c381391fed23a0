"""The locks that let one process at a time write a session (a capture or an import) or an output folder (a
relit pattern sequence)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sssphase_core.errors import InputError


@contextlib.contextmanager
def session_lock(out: Path, name: str) -> Iterator[None]:
    """One capture or import per session at a time: an exclusive lock on ``out/.<name>.lock`` (beside the
    session folder, so that it is taken before a resume drops partial views; removed by its holder when done).
    Two captures into one folder lost a view from the manifest while both reported success; two imports left
    a damaged session."""
    created = [d for d in (out, *out.parents) if not d.exists()]  # deepest first: removed again if left empty
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the session folder {out / name}: {exc.strerror or exc}") from None
    try:
        with _held(out / f".{name}.lock", f"session {out / name} is being written by {{holder}} (a capture or an "
                   "import): wait for it, or write another --object or --out"):
            yield
    finally:
        for d in created:  # a capture refused before it wrote anything leaves no empty folders behind
            try:
                d.rmdir()
            except OSError:  # not empty (the session, or another's files): kept
                break


@contextlib.contextmanager
def folder_lock(folder: Path, busy: str) -> Iterator[None]:
    """One writer of ``folder`` at a time: an exclusive lock on ``.<folder name>.lock`` beside it (removed by its
    holder when done); a second writer is refused with ``busy`` (``{holder}``: the holder's pid), not mixed in."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    with _held(folder.parent / f".{folder.name}.lock", busy):
        yield


@contextlib.contextmanager
def _held(path: Path, busy: str) -> Iterator[None]:
    """The lock file ``path`` held (its holder's pid written in it) while the block runs, then removed: nothing is
    left beside the folder once done."""
    handle = _locked(path, busy)
    try:
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()}")
        handle.flush()
        try:
            yield
        finally:
            path.unlink(missing_ok=True)
    finally:
        handle.close()  # releases the lock


def _locked(path: Path, busy: str, attempts: int = 10) -> Any:
    """The lock file ``path`` opened and exclusively locked; held elsewhere, refused with ``busy`` (its ``{holder}``
    filled in). A file its holder removed between our open and our lock is no lock at all (a third writer would
    create and lock a new one): then it is opened again."""
    import fcntl

    for _ in range(attempts):
        try:
            handle = open(path, "a+")  # noqa: SIM115 - held for the whole capture
        except OSError as exc:
            raise InputError(f"cannot create the lock file {path}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            handle.close()
            raise InputError(busy.replace("{holder}", holder)) from None  # (not format: a path may hold braces)
        try:
            if os.stat(path).st_ino == os.fstat(handle.fileno()).st_ino:
                return handle
        except FileNotFoundError:
            pass
        handle.close()  # the holder removed it as we opened it: try the path again
    raise InputError(f"could not lock {path}: it keeps being removed (another process writing there?)")
