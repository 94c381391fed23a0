"""``sss bench axis``: the turntable's axis refined from the views' own overlaps (``sss geometry --refine-axis``)
against the merge about the axis as given, on simulated turntable sessions (the simulator's exact surface scores
both; nothing else reads it).

Each session's views run through :func:`sssphase_core.relight.runner.geometry_session` once, as `sss geometry`
does; their points are then merged (:func:`~sssphase_core.relight.merged_points.merge_views`) about the rig's own
axis and about one turned ``tilt`` degrees about the camera's axis and moved ``move`` along x (a board's axis gone
astray), each without and with the refinement: the merged points' median distance to the exact surface, how well
neighbouring views agree (what a lab reads, without a truth), the refined axis's distance from the true one, whether
it was taken, and the seconds the refinement took (error against run time). The ratio is refined over given.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.bench.output import Table, machine_info, write_bench_report
from sssphase_core.errors import InputError


def run(sessions: list[Any], out: Path, tilt: float = 3.0, move: float = 8.0, backends: tuple[str, ...] = ("exact",),
        views: str = "", progress: Any = None) -> dict[str, Any]:
    """Score the axis refinement on every simulated turntable session of ``sessions``; writes JSON and Markdown."""
    import cv2

    from sssphase_core.sim import session_rig_calibration

    if not sessions:
        raise InputError("no sessions given")
    if not (np.isfinite(tilt) and np.isfinite(move) and 0 <= tilt <= 30 and abs(move) <= 1000):
        raise InputError(f"--tilt must be 0 to 30 degrees and --move at most 1000 (the calibration's unit), got {tilt!r}, {move!r}")
    rows = []
    for s in sessions:
        rig = session_rig_calibration(s.manifest.get("rig", {}))
        if rig is None or rig.turntable_axis is None or len(s.views()) < 2:
            raise InputError(f"{s.path}: not a simulated turntable session of two or more views (sss capture --object "
                             "NAME --views 4)")
        turn = cv2.Rodrigues(np.array([0.0, 0.0, np.deg2rad(tilt)]))[0]
        starts = {"the rig's own": rig,
                  f"turned {tilt:g} deg, moved {move:g}": replace(rig, turntable_axis=turn @ rig.turntable_axis,
                                                                  turntable_point=rig.turntable_point + [move, 0.0, 0.0])}
        for backend in backends:
            rows += _session_rows(s, rig, starts, backend, views, progress)
    table = Table("The merge about the axis as given and refined from the views' overlaps (the exact surface scores it)",
                  ["object", "backend", "axis given", "to the surface: given", "refined", "refined / given",
                   "views agree: given", "refined", "refined axis off (deg)", "off (unit)", "taken", "refinement s"])
    for r in rows:
        table.rows.append([r["object"], r["backend"], r["axis_given"], r["given_mm"], r["refined_mm"],
                           r["refined_mm"] / r["given_mm"], r["given_agree"], r["refined_agree"], r["refined_tilt_deg"],
                           r["refined_shift"], "yes" if r["taken"] else "kept" if r["refused"] is None else "refused",
                           r["seconds"]])
    table.note = ("backend: the footprints whose scattering shift `sss geometry` takes out of the decoded points "
                  "(exact: the simulator's, evaluation only; analytic: radially symmetric, which leaves the bias along "
                  "the baseline at grazing incidence); to the surface: the merged points' median distance to the exact "
                  "surface of the turntable at 0 degrees (median over the views); views agree: the median distance from "
                  "each view's points to the nearest of the view before where they overlap; refined axis off: the "
                  "refined axis's angle to the true one and its distance from it, taken or not; taken: the restarts "
                  "came back to it (else the axis as given stands and the merge is the given one).")
    payload = {"machine": machine_info(), "backends": list(backends), "tilt_deg": tilt, "move": move, "rows": rows}
    write_bench_report(payload, [table], out, out.with_suffix(".md"), title="sss bench axis")
    return payload


def _session_rows(s: Any, rig: Any, starts: dict[str, Any], backend: str, views: str, progress: Any) -> list[dict]:
    """One session's rows for one backend: its views' points made once, merged about each start without and with
    the refinement."""
    from sssphase_core.processing.triangulation import axes_apart
    from sssphase_core.relight.merged_points import merge_views
    from sssphase_core.relight.runner import geometry_session

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        if progress:
            progress(f"{s.name}: the views' points ({backend})")
        done = geometry_session(s, backend=backend, out=Path(tmp) / "g", views=views)
        clouds = {g.view: (np.load(g.path)["points"], np.asarray(s.load(g.view, "white"), np.float32)) for g in done}
        for name, start in starts.items():
            if progress:
                progress(f"{s.name}: merging about {name}")
            given = merge_views(s, clouds, start, Path(tmp) / "given", rig)
            t0 = time.perf_counter()
            refined = merge_views(s, clouds, start, Path(tmp) / "refined", rig, refine=True)
            seconds = time.perf_counter() - t0
            r = refined.refinement
            tilt_off, shift_off = axes_apart(r.axis, r.point, rig.turntable_axis, rig.turntable_point)
            rows.append({"object": s.name, "backend": backend, "views": list(clouds), "axis_given": name,
                         "given_mm": float(np.nanmedian(list(given.exact.values()))),
                         "refined_mm": float(np.nanmedian(list(refined.exact.values()))),
                         "given_agree": given.agreement, "refined_agree": refined.agreement,
                         "taken": refined.refined_calibration is not None, "refused": r.refused,
                         "refined_tilt_deg": tilt_off, "refined_shift": shift_off, "slide_tilt_deg": r.slide_tilt,
                         "seconds": seconds})
    return rows
