"""``sss bench store``: bytes per stored footprint against float32, and what the compact store costs in
relit PSNR, on sessions captured with ``--footprints --keep-dots``.

For each view the light transport is extracted again from the kept raw dot frames twice, the baseline
as float32 with every value kept, the store as the capture writes it (float16, values below the noise
floor zeroed, Blosc zstd with shuffle); both are written with the session codec and relit with the
``measured`` backend under the view's reference patterns, against the same references.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.bench.output import Table, machine_info, write_bench_report
from sssphase_core.errors import InputError


def _stored_bytes(array: np.ndarray) -> int:
    from sssphase_core.store.session import _zarr_write

    with tempfile.TemporaryDirectory() as tmp:
        _zarr_write(Path(tmp) / "a", array)
        return sum(f.stat().st_size for f in Path(tmp).rglob("*") if f.is_file())


def _transport(session: Any, view: int, rv: Any, dtype: type, drop_noise: bool):
    from sssphase_core.processing.footprints import DotTransportExtractor, dark_reference

    plan = session.manifest["plan"]
    frames = list({f["key"]: f for f in plan["frames"] if f["kind"] == "dots"}.values())  # one kept frame per dot grid
    spacing, patch = frames[0]["params"]["spacing"], int(session.manifest["rig"].get("patch") or 32)
    tx = DotTransportExtractor(rv.proj.xp, rv.proj.yp, rv.proj.mask, spacing, patch, rv.proj.projector_size, dtype=dtype)
    dark = dark_reference(np.asarray(session.load(view, "black")), rv.white)
    dots = session.read(view, "dots")
    for i, f in enumerate(frames):
        tx.add(f["params"]["shift_x"], f["params"]["shift_y"], np.asarray(dots[i], np.float32) - dark)
    pixels, dots_xy, crops = tx.result(drop_noise=drop_noise)
    return pixels, dots_xy, crops, tx.noise  # the store keeps the union of the masks; relighting picks one


def run(sessions: list[Any], out: Path, progress=None) -> dict[str, Any]:
    """Measure every complete view with kept dot frames and reference captures; writes JSON and Markdown."""
    from sssphase_core.processing.footprints import DENOISE_SMOOTHING
    from sssphase_core.relight import load_view, relight
    from sssphase_core.relight.evaluation import relight_metrics
    from sssphase_core.relight.transport import denoised_transport

    rows = []
    for s in sessions:
        for view in s.views():
            if "dots" not in s.arrays(view):
                raise InputError(f"{s.path} view {view} has no raw dot frames: capture with --footprints --keep-dots")
            rv = load_view(s, view)
            names = sorted(rv.references)
            if not names:
                raise InputError(f"{s.path} view {view} has no reference captures (capture with --reference checkerboard)")
            result: dict[str, Any] = {"object": s.name, "view": view}
            for label, dtype, drop in (("float32", np.float32, False), ("store", np.float16, True)):
                if progress:
                    progress(f"{s.name} view {view}: {label}")
                t0 = time.perf_counter()
                pixels, dots, crops, noise = _transport(s, view, rv, dtype, drop)
                seconds = time.perf_counter() - t0
                source = denoised_transport(rv, pixels, dots, crops, noise, DENOISE_SMOOTHING)
                relit = relight(source, rv.proj, [rv.references[n] for n in names], crops.shape[1], white=rv.white)
                psnr = float(np.mean([relight_metrics(img, rv.captured[n], rv.proj.mask)["psnr"] for n, img in zip(names, relit, strict=True)]))
                result[label] = {"bytes": _stored_bytes(crops), "footprints": len(crops), "psnr": psnr, "extract_s": seconds}
            base = result["float32"]
            result["raw_float32_bytes"] = int(base["footprints"] * np.prod(crops.shape[1:]) * 4)
            rows.append(result)
    table = Table("Footprint store: bytes per footprint against float32, and relit PSNR (measured backend, vs the render)",
                  ["object", "view", "footprints", "float32 B/fp", "store B/fp", "store / float32", "PSNR float32", "PSNR store",
                   "change (dB)"])
    for r in rows:
        n = r["store"]["footprints"]
        table.rows.append([r["object"], r["view"], n, r["float32"]["bytes"] / n, r["store"]["bytes"] / n,
                           r["store"]["bytes"] / r["raw_float32_bytes"], r["float32"]["psnr"], r["store"]["psnr"],
                           r["store"]["psnr"] - r["float32"]["psnr"]])
    table.note = ("float32 B/fp: the baseline written with the session codec (LZ4); 'store / float32': the store's bytes "
                  "over the raw float32 size (N x K x K x 3 x 4 bytes); both relit in the same run.")
    payload = {"machine": machine_info(), "rows": rows}
    write_bench_report(payload, [table], out, out.with_suffix(".md"), title="sss bench store")
    return payload
