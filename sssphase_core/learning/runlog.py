"""A run folder: its checkpoints (:func:`resolve_checkpoint`) and its training curves in the formats the
field reads, next to each other.

- ``last.pt`` / ``best.pt``: the latest checkpoint and the best monitored epoch's.

- ``metrics.jsonl``: one JSON row per epoch (the project's own record; resumable runs append).
- ``metrics.csv``: the same rows as a table (columns: the union of all keys), rewritten each epoch.
- ``tb/``: TensorBoard event files (``tensorboard --logdir RUN``) with every per-step loss term and the
  learning rate under ``step/``, and every epoch figure (kNN monitor, validation) under ``epoch/``;
  written when the ``tensorboard`` package is installed (the ``tb`` extra), skipped otherwise.
"""

from __future__ import annotations

import contextlib
import contextvars
import csv
import json
import math
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sssphase_core.errors import DataError
from sssphase_core.store.files import atomic_path

METRICS = "metrics.jsonl"
METRICS_CSV = "metrics.csv"
TB_DIR = "tb"
CHECKPOINT = "last.pt"
BEST = "best.pt"  # the epoch with the best monitored figure (kNN monitor / validation loss)
TB_MISSING = "TensorBoard event files need the tensorboard package: pip install 'sssphase[tb]'"


def tensorboard_available() -> bool:
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        return False
    return True


#: The most a run's metrics.jsonl may hold (about 500 bytes per epoch: half a million epochs).
MAX_METRICS_BYTES = 256 << 20


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The epoch rows of a ``metrics.jsonl`` (none when the file does not exist). A line that is not an epoch's
    row (damaged, edited: not a JSON object, or an ``epoch`` that is not a whole number) is left out with a warning naming it: a
    resumed run crashed on it after training its epoch, and again on every rerun."""
    if not path.exists() and not path.is_symlink():
        return []
    from sssphase_core.store.files import check_input_file

    check_input_file(path, "the run's metrics", MAX_METRICS_BYTES)  # a link to /dev/zero, a FIFO: refused by name
    rows, bad = [], []
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except (json.JSONDecodeError, RecursionError):
            row = None
        epoch = row.get("epoch", 0) if isinstance(row, dict) else None
        if isinstance(epoch, int) and not isinstance(epoch, bool):
            rows.append(row)
        else:
            bad.append(number)
    if bad:
        warnings.warn(f"{path}: line{'s' if len(bad) > 1 else ''} {', '.join(map(str, bad[:5]))}"
                      f"{' ...' if len(bad) > 5 else ''} not an epoch's row (damaged?): left out", UserWarning, stacklevel=2)
    return rows


class RunLog:
    """Writes one run's curves; ``resume_step`` drops TensorBoard events past a resumed checkpoint."""

    def __init__(self, out_dir: Path, *, resume_step: int = 0, enabled: bool = True) -> None:
        self.out_dir, self.enabled = Path(out_dir), enabled
        self.writer = None
        if enabled and tensorboard_available():
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.out_dir / TB_DIR), purge_step=resume_step or None)

    def step(self, global_step: int, values: dict[str, float]) -> None:
        """Per-step values (loss terms, ``lr``) at ``global_step`` (1-based: steps done)."""
        if self.writer is not None:
            for name, value in values.items():
                if math.isfinite(value):
                    self.writer.add_scalar(f"step/{name}", value, global_step)

    def epoch(self, row: dict[str, Any]) -> None:
        """One epoch's row (``epoch``, ``step``, means of the step values and the epoch figures); it replaces
        the rows of that epoch and later ones (a run resumed inside an epoch whose row was written)."""
        if not self.enabled:
            return
        rows = [r for r in read_rows(self.out_dir / METRICS) if r.get("epoch", 0) < row["epoch"]] + [row]
        with atomic_path(self.out_dir / METRICS) as tmp:
            tmp.write_text("".join(json.dumps(r) + "\n" for r in rows))
        columns = list(dict.fromkeys(k for r in rows for k in r))
        with atomic_path(self.out_dir / METRICS_CSV) as tmp, open(tmp, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns)
            writer.writeheader()
            writer.writerows(rows)
        if self.writer is not None:
            for name, value in row.items():
                if name not in ("epoch", "step") and isinstance(value, int | float) and math.isfinite(value):
                    self.writer.add_scalar(f"epoch/{name}", value, int(row["step"]))
            self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def resolve_checkpoint(path: Path | str) -> Path:
    """A run folder means its ``best.pt`` when training kept one, else its ``last.pt``; a file is itself."""
    path = Path(path)
    if path.is_dir():
        return path / BEST if (path / BEST).exists() else path / CHECKPOINT
    return path


#: The checkpoints a command has read so far (resolved path -> (inode, size, mtime)), within :func:`one_version`.
_READ: contextvars.ContextVar[dict[str, tuple[int, int, int]] | None] = contextvars.ContextVar("sss_read", default=None)


@contextlib.contextmanager
def one_version() -> Iterator[None]:
    """Within it, every read of a checkpoint file is of the version read first (:func:`check_same_version`): an
    evaluation whose checkpoint a running training replaced at an epoch end scored its first view with one model and
    the next with another, under one name."""
    token = _READ.set({})
    try:
        yield
    finally:
        _READ.reset(token)


def check_same_version(path: Path) -> None:
    """Refuse, within :func:`one_version`, a checkpoint file that changed since the command first read it."""
    read = _READ.get()
    if read is None:
        return
    st = path.stat()
    first = read.setdefault(str(path.resolve()), (st.st_ino, st.st_size, st.st_mtime_ns))
    if first != (st.st_ino, st.st_size, st.st_mtime_ns):
        raise DataError(f"{path} was replaced while this command ran (a training writing it at each epoch end?), so "
                        "its views would be scored with different models: run it again once the training is done, or "
                        "give a copy of the checkpoint")


def check_checkpoint_file(path: Path | str) -> Path:
    """The checkpoint ``path`` means (:func:`resolve_checkpoint`), refused with a :class:`DataError` when it
    is missing, empty or not a file ``torch.save`` wrote (checked without importing torch)."""
    from sssphase_core.store.files import check_input_file

    folder, path = Path(path).is_dir(), resolve_checkpoint(path)
    if not path.exists():
        raise DataError(f"no checkpoint in the run folder {path.parent} (neither {BEST} nor {CHECKPOINT}): has "
                        "training written one there?" if folder else f"no checkpoint at {path}")
    check_input_file(path, "checkpoint")  # a FIFO or a device would block torch.load
    if path.is_file() and path.stat().st_size == 0:
        raise DataError(f"cannot read checkpoint {path}: the file is empty")
    if path.is_file():
        with open(path, "rb") as f:
            if f.read(4) != b"PK\x03\x04":  # what torch.save writes (torch's own error for others: "101")
                raise DataError(f"{path} is not a checkpoint file (not written by torch.save)")
        _check_stored_members(path)
    return path


def _check_stored_members(path: Path) -> None:
    """torch.save stores its members uncompressed; a compressed member (a 5 MB deflate bomb unpacked to
    gigabytes in torch.load) or one declared longer than the file is refused before torch reads it."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            members = z.infolist()
    except (zipfile.BadZipFile, OSError, ValueError):
        return  # (a cut file: load_checkpoint says so in torch's terms)
    size = path.stat().st_size
    for m in members:
        if m.compress_type != zipfile.ZIP_STORED or m.file_size > size:
            raise DataError(f"{path} is not a checkpoint torch.save wrote: its member {m.filename[:80]!r} is "
                            f"{'compressed' if m.compress_type != zipfile.ZIP_STORED else 'declared longer than the file'} "
                            f"({m.file_size:,} bytes unpacked)")
