"""Files written atomically: a reader (or a crash) sees the old file or the new one, never half."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: Path | str, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; it replaces ``path`` in one rename when the block
    ends without error, and is removed (the old file staying) when it raises. The temporary file's data
    is flushed to the disk (fsync) before the rename and the folder's entry after it, so a power cut
    leaves the old file or the whole new one, not an empty file under the final name.

    ``suffix`` ends the temporary name (``.npz`` for ``np.savez``, which would append it). The name
    carries the process id and a random part, so two writers never share a temporary file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # at most ~70 characters whatever the final name's length (a name that fits must not fail for its temporary)
    tmp = path.with_name(f".{path.name[:40]}.{os.getpid()}-{secrets.token_hex(3)}.tmp{suffix}")
    try:
        yield tmp
        sync(tmp)
        os.replace(tmp, path)
        sync(path.parent)
    except OSError as exc:  # an error about the temporary file names the file the user asked for
        if exc.filename is not None and str(exc.filename) == str(tmp) and exc.errno is not None:
            raise type(exc)(exc.errno, exc.strerror, str(path)) from None
        raise
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


@contextlib.contextmanager
def atomic_folder(path: Path | str) -> Iterator[Path]:
    """:func:`atomic_path` for a folder: a temporary folder beside ``path`` to fill; it replaces ``path`` (a
    folder from before is removed) when the block ends without error, its files on the disk first, and is
    removed when the block raises, ``path`` as it was. A crash between the two renames leaves the old folder
    under a ``.old`` name beside it, not a half-written one under ``path``."""
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tag = f"{os.getpid()}-{secrets.token_hex(3)}"
    tmp, old = (path.with_name(f".{path.name[:40]}.{tag}.{end}") for end in ("tmp", "old"))
    tmp.mkdir()
    try:
        yield tmp
        sync_tree(tmp)
        if path.is_dir() and not path.is_symlink():
            os.replace(path, old)
        os.replace(tmp, path)
        sync(path.parent)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)


def sync(path: Path | str) -> None:
    """Flush a file's data, or a folder's entries, to the disk (``fsync``). File systems that cannot
    (some network and FUSE mounts answer EINVAL) are left as they are."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def sync_tree(folder: Path | str) -> None:
    """:func:`sync` every file and folder under ``folder`` (a session view written as a folder of
    chunks, before it is renamed into place), then ``folder`` itself."""
    for root, dirs, files in os.walk(folder):
        for name in files:
            sync(Path(root) / name)
        for name in dirs:
            sync(Path(root) / name)
    sync(folder)


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


#: the PNG ``Software`` text of every figure sssphase writes (:func:`save_figure`, :func:`ours_to_replace`)
FIGURE_SOFTWARE = "sssphase"


def save_figure(fig: object, path: Path | str, **kwargs: object) -> Path:
    """``fig.savefig(path, ...)`` through :func:`atomic_path` (the format from ``path``'s suffix); a PNG says
    :data:`FIGURE_SOFTWARE` in its ``Software`` text, so a later run knows the file as its own."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        kwargs = {"metadata": {"Software": FIGURE_SOFTWARE}, **kwargs}
    with atomic_path(path, path.suffix) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".") or None, **kwargs)  # type: ignore[attr-defined]
    return path


def ours_to_replace(path: Path | str, what: str) -> None:
    """Refuse, in one line before any work, to replace a file at ``path`` that is not a figure sssphase wrote
    (:func:`save_figure`): a user's image named as an output would be lost."""
    from sssphase_core.errors import InputError

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    ours = False
    if path.is_file() and not path.is_symlink():
        try:
            from PIL import Image

            with Image.open(path) as im:
                ours = getattr(im, "text", {}).get("Software") == FIGURE_SOFTWARE
        except (OSError, ValueError, SyntaxError):  # not an image PIL reads
            ours = False
    if not ours:
        raise InputError(f"{what} {path} exists and is not a figure sssphase wrote: give another name or remove it")


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


#: How deep a configuration, manifest or plan may nest (tables in tables, lists in lists): the project's own
#: files nest 5 deep; deeper input is hostile or broken, and code that walks it must not recurse without end.
MAX_NESTING = 32

#: Most dots in a row of TOML text between separators (``a.b.c... = 1``, ``[a.b.c...]``): tomllib builds one
#: table per dotted-key part in quadratic time (100,000 parts took 8.8 s), so a 1 MiB rig file could hold a
#: parser for minutes. Counted in linear time (spaces dropped, split at newlines, commas, ``=`` and brackets).
MAX_DOTS = 2 * MAX_NESTING
_TOML_SEPARATORS = re.compile(r"[\n,=\[\]{}]")


def _longest_dotted_run(text: str) -> int:
    return max((piece.count(".") for piece in _TOML_SEPARATORS.split(text.replace(" ", "").replace("\t", ""))), default=0)


def check_nesting(value: object, what: str, max_depth: int = MAX_NESTING) -> None:
    """Refuse ``value`` (parsed JSON or TOML) nested more than ``max_depth`` deep, walking it without recursion."""
    from sssphase_core.errors import InputError

    stack: list[tuple[object, int]] = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth >= max_depth:
                raise InputError(f"{what} nests deeper than {max_depth} levels: not a file this program wrote")
            stack.extend((v, depth + 1) for v in (item.values() if isinstance(item, dict) else item))


def read_json_input(path: Path | str, what: str, max_bytes: int = 1 << 24) -> object:
    """A JSON input file (a manifest, a plan, a record) parsed, bounded in size (:func:`check_input_file`) and
    nesting (:func:`check_nesting`); any fault is an :class:`InputError` naming the file in one line."""
    import json

    from sssphase_core.errors import InputError

    text = read_input_text(path, what, max_bytes)
    try:
        value = json.loads(text)
    except RecursionError:
        raise InputError(f"{what} {path} nests deeper than {MAX_NESTING} levels: not a file this program wrote") from None
    except ValueError as exc:
        raise InputError(f"{what} {path} is not valid JSON ({str(exc).splitlines()[0][:80]})") from None
    check_nesting(value, f"{what} {path}")
    return value


def read_toml_input(path: Path | str, what: str, max_bytes: int = 1 << 20) -> dict:
    """A TOML input file (a rig file, a run configuration) parsed like :func:`read_json_input`; a dotted key of
    more than :data:`MAX_DOTS` parts is refused before parsing (the parser is quadratic in them)."""
    import tomllib

    from sssphase_core.errors import InputError

    text = read_input_text(path, what, max_bytes)
    if _longest_dotted_run(text) > MAX_DOTS:
        raise InputError(f"{what} {path} has a dotted key of more than {MAX_DOTS} parts: not a configuration")
    try:
        value = tomllib.loads(text)
    except RecursionError:
        raise InputError(f"{what} {path} nests deeper than {MAX_NESTING} levels: not a configuration") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{what} {path} is not valid TOML: {exc}") from None
    check_nesting(value, f"{what} {path}")
    return value
