"""Run inside a small tmpfs (see ``test_full_disk.py``): every writer of the project, on a disk with
~48 KB left, must raise and leave the old file whole and no temporary behind. Prints one JSON line:
``{writer: {"raised": str, "old_kept": bool, "left": [names]}}``."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(sys.argv[1])
FREE = 48_000
BIG = np.random.default_rng(0).random((200, 200, 3), dtype=np.float32)  # 480 kB, incompressible


def fill(root: Path) -> None:
    """Fill the file system but ``FREE`` bytes (a ballast file)."""
    st = os.statvfs(root)
    with open(root / "ballast", "wb") as f:
        f.write(b"\0" * max(st.f_bavail * st.f_frsize - FREE, 0))


def session_view(folder: Path) -> None:
    from sssphase_core.store.session import Session

    s = Session.create(folder, "obj")
    w = s.begin_view(0)
    w.write("psp", BIG)
    w.commit()


def checkpoint(path: Path) -> None:
    import torch

    from sssphase_core.learning.training.checkpoints import save_checkpoint

    save_checkpoint(path, {"w": torch.from_numpy(BIG)})


def figure(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sssphase_core.store.files import save_figure

    fig = plt.figure(figsize=(12, 12))
    fig.add_subplot().imshow(BIG)
    save_figure(fig, path)


def main() -> None:
    from sssphase_core.relight.images import write_images
    from sssphase_core.store.files import write_bytes, write_text
    from sssphase_core.store.results import write_report
    from sssphase_core.store.session import write_json_atomic

    writers = {
        "text.txt": lambda p: write_text(p, "x" * 200_000),
        "bytes.bin": lambda p: write_bytes(p, BIG.tobytes()),
        "manifest.json": lambda p: write_json_atomic(p, {"rows": BIG[:40].tolist()}),
        "report.json": lambda p: write_report({"rows": BIG[:40].tolist()}, [], p, md=p.with_suffix(".md")),
        "figure.png": figure,
        "relit.png": lambda p: write_images(p.with_suffix(""), BIG, formats=("png",)),
        "relit.exr": lambda p: write_images(p.with_suffix(""), BIG, formats=("exr",)),
        "best.pt": checkpoint,
        "sessions": session_view,
    }
    out = {}
    for name, write in writers.items():
        folder = ROOT / name.replace(".", "_")
        folder.mkdir()
        old = folder / name
        if name != "sessions":
            old.write_bytes(b"old and whole")
        fill(ROOT)
        raised = ""
        try:
            write(old)
        except Exception as exc:  # noqa: BLE001 (what each writer raises is reported, and checked by the test)
            raised = f"{type(exc).__name__}: {exc}"[:200]
        kept = old.read_bytes() == b"old and whole" if name != "sessions" else not any((old / "obj").glob("view_*"))
        left = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name.startswith("."))
        out[name] = {"raised": raised, "old_kept": kept, "left": left}
        (ROOT / "ballast").unlink()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
