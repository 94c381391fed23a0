"""Files written atomically: a reader (or a crash) sees the old file or the new one, never half."""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: Path | str, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; it replaces ``path`` in one rename when the block
    ends without error, and is removed (the old file staying) when it raises.

    ``suffix`` ends the temporary name (``.npz`` for ``np.savez``, which would append it). The name
    carries the process id and a random part, so two writers never share a temporary file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # at most ~70 characters whatever the final name's length (a name that fits must not fail for its temporary)
    tmp = path.with_name(f".{path.name[:40]}.{os.getpid()}-{secrets.token_hex(3)}.tmp{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def write_text(path: Path | str, text: str) -> Path:
    """``path.write_text(text)`` through :func:`atomic_path`: a full disk leaves the old file (or none)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def write_bytes(path: Path | str, data: bytes) -> Path:
    """``path.write_bytes(data)`` through :func:`atomic_path`."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def save_figure(fig: object, path: Path | str, **kwargs: object) -> Path:
    """``fig.savefig(path, ...)`` through :func:`atomic_path` (the format from ``path``'s suffix)."""
    path = Path(path)
    with atomic_path(path, path.suffix) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or None, **kwargs)  # type: ignore[attr-defined]
    return path


def check_input_file(path: Path | str, what: str, max_bytes: int | None = None) -> Path:
    """``path`` as an input file: a regular file (a FIFO, a device or a socket would block or never end a
    read: refused by name), at most ``max_bytes`` long. Missing files are left to the caller's own message."""
    import stat

    from sssphase_core.errors import InputError

    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return path
    except OSError as exc:
        raise InputError(f"{what} {path}: {exc.strerror}") from None
    if stat.S_ISDIR(st.st_mode):
        return path  # (a folder: the caller says what it wanted instead)
    if not stat.S_ISREG(st.st_mode):
        kind = "a FIFO" if stat.S_ISFIFO(st.st_mode) else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) \
            else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file"
        raise InputError(f"{what} {path} is {kind}, not a file: give a regular file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputError(f"{what} {path} is {st.st_size:,} bytes, more than the {max_bytes:,} such a file can be")
    return path


def read_input_text(path: Path | str, what: str, max_bytes: int = 1 << 24) -> str:
    """The text of an input file (a rig file, a run configuration, a manifest) checked by
    :func:`check_input_file` first; text that is not UTF-8 is an :class:`InputError` naming the file."""
    from sssphase_core.errors import InputError

    path = check_input_file(path, what, max_bytes)
    try:
        return Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{what} {path} is not UTF-8 text (byte {exc.start})") from None

