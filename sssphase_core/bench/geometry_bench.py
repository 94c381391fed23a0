"""``sss bench geometry``: how far each backend's correspondences for geometry are from the exact projector
points, against the decoded ones, on simulated sessions (the simulator's exact points score them; nothing
else reads them).

Each view runs through :func:`sssphase_core.relight.runner.geometry_session`, as `sss geometry` does, once
per backend; the table gives the median distance to the exact points and the median signed error along the
baseline (x), decoded and corrected, and the seconds the correction took (error against run time); a second
table the same in 3D: both triangulated with the rig's exact calibration, against the exact surface, in mm.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from sssphase_core.bench.output import Table, machine_info, write_bench_report
from sssphase_core.errors import InputError


def run(sessions: list[Any], out: Path, backends: tuple[str, ...] = ("exact", "analytic"),
        checkpoint: Path | str | None = None, progress: Any = None) -> dict[str, Any]:
    """Score every complete view of ``sessions`` (simulated) for each backend; writes JSON and Markdown."""
    from sssphase_core.relight.choices import uses_decoder
    from sssphase_core.relight.runner import geometry_session

    if not sessions:
        raise InputError("no sessions given")
    rows = []
    for s in sessions:
        transport = s.manifest.get("rig", {}).get("options", {}).get("transport", "burley")
        for backend in backends:
            if progress:
                progress(f"{s.name}: {backend}")
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                done = geometry_session(s, backend=backend, checkpoint=checkpoint if uses_decoder(backend) else None,
                                        out=Path(tmp))
                seconds = (time.perf_counter() - t0) / max(1, len(done))
            for g in done:
                if g.exact is None:
                    raise InputError(f"{s.path} view {g.view} has no exact points (gt/proj_xy): only a simulated session can "
                                     "be scored")
                depth = g.exact_3d or (float("nan"),) * 4
                rows.append({"object": g.object, "view": g.view, "transport": transport, "backend": backend,
                             "decoded_px": g.exact[0], "decoded_bias_x": g.exact[1], "corrected_px": g.exact[2],
                             "corrected_bias_x": g.exact[3], "decoded_mm": depth[0], "decoded_depth_bias_mm": depth[1],
                             "corrected_mm": depth[2], "corrected_depth_bias_mm": depth[3],
                             "reprojection_px": g.reprojection, "seconds": seconds})
    table = Table("Correspondences for geometry against the exact projector points (projector px; baseline along x)",
                  ["object", "transport", "backend", "decoded median", "corrected median", "decoded bias x",
                   "corrected bias x", "|bias| removed", "correction s"])
    for r in rows:
        removed = 1 - abs(r["corrected_bias_x"]) / abs(r["decoded_bias_x"]) if r["decoded_bias_x"] else float("nan")
        table.rows.append([r["object"], r["transport"], r["backend"], r["decoded_px"], r["corrected_px"], r["decoded_bias_x"],
                           r["corrected_bias_x"], removed, r["seconds"]])
    table.note = ("median: of the distance to the exact point that lit each pixel; bias x: the median signed error along "
                  "the projector-camera baseline; '|bias| removed': 1 - |corrected| / |decoded| (negative: the correction "
                  "added to it). exact and analytic footprints are centred where light enters (the shift is predicted "
                  "by relighting the fringes); a learned model's where its training crops were cut (the shift is the "
                  "entry point inside them: relight.geometry.entry_shift).")
    points = Table("The same correspondences triangulated, against the exact surface (mm, the rig's own calibration)",
                   ["object", "transport", "backend", "decoded median", "corrected median", "decoded depth bias",
                    "corrected depth bias", "|bias| removed", "reprojection px"])
    for r in rows:
        removed = (1 - abs(r["corrected_depth_bias_mm"]) / abs(r["decoded_depth_bias_mm"])
                   if r["decoded_depth_bias_mm"] else float("nan"))
        points.rows.append([r["object"], r["transport"], r["backend"], r["decoded_mm"], r["corrected_mm"],
                            r["decoded_depth_bias_mm"], r["corrected_depth_bias_mm"], removed, r["reprojection_px"]])
    points.note = ("median: of the distance from each pixel's triangulated point to the one its exact projector point "
                   "gives; depth bias: the median signed error along the camera's axis (positive: too far); reprojection: "
                   "the corrected points' median miss in the projector (the calibration is exact, so this is the "
                   "correspondences' own inconsistency).")
    payload = {"machine": machine_info(), "backends": list(backends), "rows": rows}
    write_bench_report(payload, [table, points], out, out.with_suffix(".md"), title="sss bench geometry")
    return payload
