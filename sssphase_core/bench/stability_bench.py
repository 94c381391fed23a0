"""`sss bench stability`: relighting under extreme materials, exposures and geometry.

Each case is a simulated view (noisy PSP inputs and a noisy white frame, as a session captures them;
exact correspondences) relit under a checkerboard the way ``sss relight`` does it (the backend's
footprints, calibrated to the view's own fringes for a model: :func:`~sssphase_core.relight.pipeline.relight_view`)
with ``none``, ``analytic`` and ``exact`` (the simulator's footprints), plus ``torch`` and ``blend`` with a
checkpoint. Checked: no NaN/inf in the inputs, the footprints or the relit images; the error (PSNR
against the simulator's noise-free render) is reported per case and backend.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from sssphase_core.bench.output import Table, machine_info, write_bench_report
from sssphase_core.bench.relight_bench import SimView, sim_view, source_for
from sssphase_core.relight import emitted_light, lit_pixels
from sssphase_core.relight.evaluation import relight_metrics

SPHERE_RADIUS = 22.0  # mm: small objects keep the sweep quick


@dataclass(frozen=True)
class Case:
    """One stress case: a material (albedo, mean free path mm), a tilt, an exposure and a pattern gain."""

    name: str
    description: str
    albedo: tuple[float, float, float] = (0.8, 0.7, 0.6)
    mfp: tuple[float, float, float] = (2.0, 1.0, 0.5)
    tilt_deg: float | None = None  # a flat slab tilted this much away from the camera (None: a sphere)
    exposure: float = 1.0
    gain: float = 1.0  # pattern values are scaled by this (very low light)
    white_exposure: float | None = None  # the white frame's exposure (None: ``exposure``, one exposure for the view)
    extra: dict[str, Any] = field(default_factory=dict)


CASES = (
    Case("delta", "delta footprint (mean free path 1e-4 mm)", mfp=(1e-4, 1e-4, 1e-4)),
    Case("wide", "footprint wider than the patch (mean free path 60 mm)", mfp=(60.0, 60.0, 60.0)),
    Case("albedo0", "albedo 0 (black object)", albedo=(0.0, 0.0, 0.0)),
    Case("albedo1", "albedo 1 (no absorption)", albedo=(1.0, 1.0, 1.0)),
    Case("aniso10", "10:1 anisotropic footprints (slab at 84 deg: cos 0.1)", tilt_deg=84.3),
    Case("grazing", "grazing view beyond the clamp (slab at 88 deg)", tilt_deg=88.0),
    # (a white frame clipped as well leaves no energy to relight with: every backend at ~13 dB)
    Case("saturated", "PSP inputs saturated (exposure x8, the white frame at x1)", exposure=8.0, white_exposure=1.0),
    Case("lowlight", "very low light (exposure 1/200, pattern at 5 %)", exposure=0.005, gain=0.05),
)


def case_object(case: Case):
    """The simulated object of a case (a sphere, or a tilted slab)."""
    from sssphase_core.sim import geometry as g
    from sssphase_core.sim.materials import Material
    from sssphase_core.sim.objects import SimObject, uniform

    mat = Material(f"stress_{case.name}", case.albedo, case.mfp, 0.02, False)
    if case.tilt_deg is None:
        return SimObject(case.name, "test", case.description, SPHERE_RADIUS,
                         lambda p: g.sphere(p, (0.0, 0.0, 0.0), SPHERE_RADIUS), uniform(mat))
    rot = g.rotation_x(np.deg2rad(90.0 - case.tilt_deg))  # slab normal along y, tilted towards the camera (z)

    def sdf(p: np.ndarray) -> np.ndarray:
        return g.round_box(p @ rot, (0.0, 0.0, 0.0), (30.0, 2.0, 30.0), 0.5)

    return SimObject(case.name, "test", case.description, 45.0, sdf, uniform(mat))


class _FiniteCheck:
    """A footprint source that notes whether every footprint it gave was finite."""

    def __init__(self, source: Callable) -> None:
        self.source, self.finite = source, True

    def __call__(self, pixels: np.ndarray) -> Any:
        out = self.source(pixels)
        self.finite &= bool(torch.isfinite(out).all()) if torch.is_tensor(out) else bool(np.isfinite(out).all())
        return out


def run_case(case: Case, backends: Sequence[str], checkpoint: Path | str | None = None) -> list[dict[str, Any]]:
    """Relit error and finiteness checks of one case for each backend."""
    from sssphase_core.processing.patterns import checkerboard
    from sssphase_core.relight.backends import MODEL_FREE, make_sources
    from sssphase_core.relight.choices import widen_for
    from sssphase_core.relight.pipeline import relight_view
    from sssphase_core.sim import rig_preset

    projector = rig_preset("cpu").projector
    hp, wp = projector.height, projector.width
    pattern = checkerboard(wp, hp, 16) * np.float32(case.gain)
    sv: SimView = sim_view(case_object(case), exposure=case.exposure, patterns={"checkerboard": pattern},
                           white_exposure=case.white_exposure or case.exposure)
    pixels, _ = lit_pixels(sv.proj, emitted_light(pattern[None], sv.proj.gamma))
    rows = []
    for backend in backends:
        t0 = time.perf_counter()
        pairs = [source_for(backend, sv, None)] if backend == "exact" else make_sources(backend, sv, checkpoint=checkpoint)
        checked = [(_FiniteCheck(src), k) for src, k in pairs]
        (source, patch), *also = checked
        calibrate = backend not in MODEL_FREE  # and widened as `sss relight` widens the backend by default
        images, _ = relight_view(source, patch, sv, [pattern], calibrate=calibrate, also=also,
                                 widen=widen_for(backend, None) if calibrate else None)
        out = images[0]
        seconds = time.perf_counter() - t0
        ref = sv.captured["checkerboard"]
        finite = {"psp": bool(np.isfinite(sv.psp).all()), "footprints": all(c.finite for c, _ in checked),
                  "relit": bool(np.isfinite(out).all()), "reference": bool(np.isfinite(ref).all())}
        mask = sv.proj.mask
        nan = {"mse": float("nan"), "psnr": float("nan"), "ssim": float("nan")}
        met = relight_metrics(out, ref, mask) if mask.any() else nan
        peak = float(ref[mask].max()) if mask.any() else 0.0
        rel = relight_metrics(out, ref, mask, data_range=peak) if peak > 0 else nan
        model = getattr(pairs[0][0], "backend", None)  # a decoder: how many pixels it gave the analytic model
        handed = model.beyond_domain / model.predicted if getattr(model, "predicted", 0) else None
        rows.append({"case": case.name, "description": case.description, "backend": backend, "valid_pixels": int(mask.sum()),
                     "lit_pixels": len(pixels), "ref_peak": peak,
                     "psnr": met["psnr"], "psnr_at_peak": rel["psnr"], "ssim": met["ssim"], "mse": met["mse"], "seconds": seconds,
                     "finite": all(finite.values()), "beyond_training_widths": handed,
                     **{f"finite_{k}": v for k, v in finite.items()}})
    # the baseline measured in the same run: the better of no scattering and the analytic model, which need no training
    baseline = [r["psnr"] for r in rows if r["backend"] in ("none", "analytic")]
    for r in rows:
        r["vs_baseline_db"] = r["psnr"] - max(baseline) if baseline and r["backend"] not in ("none", "analytic") else None
    return rows


def run(out: Path, *, cases: Sequence[str] | None = None,
        backends: Sequence[str] = ("none", "analytic", "exact", "torch", "blend"),
        checkpoint: Path | str | None = None, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """All (or the named) cases; writes ``out`` (JSON) and ``out.md``. Returns the result."""
    from sssphase_core.errors import InputError
    from sssphase_core.relight.choices import uses_decoder

    chosen = [c for c in CASES if cases is None or c.name in cases]
    unknown = set(cases or ()) - {c.name for c in CASES}
    if unknown:
        raise InputError(f"unknown stability cases {sorted(unknown)}; choose from {', '.join(c.name for c in CASES)}")
    use = [b for b in backends if not uses_decoder(b) or checkpoint is not None]
    rows: list[dict[str, Any]] = []
    for case in chosen:
        if progress:
            progress(f"{case.name}: {case.description}")
        rows += run_case(case, use, checkpoint)
    bad = [f"{r['case']}/{r['backend']}" for r in rows if not r["finite"]]
    note = ("PSNR: peak 1.0 (linear camera units), PSNR@peak: peak = the reference's maximum; against the "
            "noise-free render, on the valid mask; relit as `sss relight` does (a model calibrated to the view's own "
            "fringes; the white frame captured with its noise). "
            + (f"NON-FINITE values in: {', '.join(bad)}." if bad else "No NaN/inf anywhere."))
    note += (" vs best: PSNR minus the better of none and analytic in the same case (the models that need no "
             "training), where both ran; to analytic: the decoder's pixels beyond its training widths, given the "
             "analytic model's footprints (learning.domain).")
    table = Table("Stability sweep", ["case", "backend", "valid px", "ref peak", "PSNR (dB)", "PSNR@peak (dB)", "vs best (dB)", "SSIM",
                                      "to analytic", "finite", "time (s)"],
                  [[r["case"], r["backend"], r["valid_pixels"], r["ref_peak"], r["psnr"], r["psnr_at_peak"],
                    "" if r["vs_baseline_db"] is None else f"{r['vs_baseline_db']:+.1f}", r["ssim"],
                    "" if r["beyond_training_widths"] is None else f"{r['beyond_training_widths']:.1%}",
                    "yes" if r["finite"] else "NO", r["seconds"]] for r in rows], note=note)
    result = {"machine": machine_info(), "cases": [c.__dict__ for c in chosen], "rows": rows, "non_finite": bad,
              "skipped": [b for b in backends if b not in use]}
    write_bench_report(result, [table], Path(out), md=Path(out).with_suffix(".md"), title="Relighting stability")
    return result
