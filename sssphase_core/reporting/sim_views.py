"""`sss sim`: a simulated capture of a catalogue object per view, written as viewable PNGs plus ``scene.json``
(the PSP images and white, mask, exact correspondence and fringe phase, materials, exact footprints; with
``decode``, the decoded correspondence and its error against the exact one)."""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core import sim as simlib
from sssphase_core.errors import InputError
from sssphase_core.processing.patterns import PSPConfig, capture_plan, psp_config_for
from sssphase_core.reporting import figures as fig
from sssphase_core.store.files import atomic_path, write_text
from sssphase_core.store.session import check_output_folder

#: ``progress(view, done, total)``: ``view`` None: views done of all; else lit pixels rendered in that view.
SimProgress = Callable[[int | None, int, int | None], None]
MAX_SEED = 2**63 - 1


@dataclass
class SimRun:
    """What :func:`run_sim` wrote: ``info`` is ``scene.json``'s content (its ``views``: one summary per view)."""

    out: Path
    name: str
    info: dict[str, Any]


def run_sim(object_name: str, views: int, out: Path, *, preset: str = "cpu", transport: str = "burley", seed: int = 0,
            n_footprints: int = 6, decode: bool = True, progress: SimProgress | None = None,
            report: Callable[[str], None] | None = None, anisotropy: float | None = None,
            backdrop: float | None = None) -> SimRun:
    """Simulate ``views`` turntable views of ``object_name`` on the ``preset`` rig with light transport ``transport``
    (``anisotropy``: the radiative transport's phase-function g; ``backdrop``: a grey wall that many mm behind the
    turntable centre) into ``out`` (an earlier run's
    figures there are removed: :func:`remove_earlier_sim`). With ``decode`` the whole PSP plan is captured with sensor noise and
    decoded, and ``report(line)`` tells each view's decoded share and error."""
    from sssphase_core.sim.materials import MATERIALS, dropped_fraction
    from sssphase_core.sim.rig import pixel_pitch_mm

    if views > simlib.MAX_VIEWS:  # as `sss capture`: the turntable's limit, before a view is rendered
        raise InputError(f"--views: the sim rig's turntable takes at most {simlib.MAX_VIEWS} views, got {views}")
    if not 0 <= seed <= MAX_SEED:
        raise InputError(f"--seed must be 0 to {MAX_SEED} (2**63 - 1), got {seed}")
    obj = simlib.get_object(object_name)
    rig = simlib.rig_from_options({"preset": preset, "transport": transport,
                                   **simlib.anisotropy_option(transport, anisotropy),
                                   **({"backdrop": backdrop} if backdrop is not None else {})})
    check_output_folder(out)
    remove_earlier_sim(out)
    out.mkdir(parents=True, exist_ok=True)
    wp, hp = rig.projector.width, rig.projector.height
    config = psp_config_for(wp, hp)
    plan = [f for f in capture_plan(wp, hp, psp=config, unwrap=decode, gamma=rig.projector.gamma) if f.kind == "psp"]
    patterns = np.stack([f.pattern() for f in plan] + [np.ones((hp, wp), np.float32)])
    shown = {f.key: f"psp_{f.params['orientation']}_s{f.params['shift']}" for f in plan if f.params["period"] == config.period}
    summary, labels = [], set()
    tell = progress or (lambda view, done, total: None)
    tell(None, 0, views)
    for view in range(views):
        scene = simlib.SimScene(obj, rig=rig, view=view, n_views=views, seed=seed)
        frames = scene.capture(patterns, np.random.default_rng([seed, view]),
                               progress=lambda done, total, v=view: tell(v, done, total))
        keyed = {f.key: frame for f, frame in zip(plan, frames, strict=False)}
        entry = _write_view(scene, out / f"view{view}", keyed, frames[-1], shown, config, n_footprints, decode)
        labels |= {simlib.MATERIAL_NAMES[i] for i in np.unique(scene.material[scene.mask])}
        summary.append(entry)
        decoded = entry["decode"]
        if decoded and report is not None:
            report(f"view {view}: decoded {decoded['valid_fraction']:.1%} of the object, correspondence error "
                   f"median {decoded['median_error_px']:.3f} px, p99 {decoded['p99_error_px']:.2f} px (projector px)")
        tell(None, view + 1, views)
    pitch = pixel_pitch_mm(rig)
    info = {
        "object": {"name": obj.name, "split": obj.split, "description": obj.description, "radius_mm": obj.radius,
                   "materials_seen": sorted(labels)},
        "dropped_energy_rgb": {name: dropped_fraction(MATERIALS[name].rate(rig.sss_scale), pitch, rig.patch).round(5).tolist()
                               for name in sorted(labels)},
        "rig": rig.to_dict(),
        "psp_period": config.period,
        "images": [*shown.values(), "white"],
        "seed": seed,
        "views": summary,
    }
    write_text(out / "scene.json", json.dumps(info, indent=2))
    return SimRun(out, obj.name, info)


#: the files :func:`_write_view` writes in a view folder (and nothing else there is ours)
VIEW_FILES = re.compile(r"(psp_[xy]_s[0-9]+|white|mask|proj_[xy]|phase_[xy]|material|footprints|decoded_[xy]|reason"
                        r"|decode_error)\.png|decoded\.npz")


def remove_earlier_sim(out: Path) -> None:
    """An earlier `sss sim` in ``out``: its view folders' files go, so none is left beside a new run's; a file it
    did not write stays, with its folder. A ``scene.json`` that `sss sim` did not write is refused (it would be
    overwritten), in one line before any work."""
    from sssphase_core.store.files import read_json_input

    scene = out / "scene.json"
    if not scene.exists() and not scene.is_symlink():
        return
    try:  # bounded in size, a FIFO refused: read_json_input
        info = read_json_input(scene, "the scene record")
        ours = isinstance(info, dict) and {"object", "rig", "images", "views"} <= info.keys()
    except (OSError, InputError):
        ours = False
    if not ours:
        raise InputError(f"--out {out} holds a scene.json that sss sim did not write: give another folder")
    for folder in (p for p in out.iterdir() if p.is_dir() and not p.is_symlink() and re.fullmatch(r"view[0-9]+", p.name)):
        for f in folder.iterdir():
            if f.is_file() and not f.is_symlink() and VIEW_FILES.fullmatch(f.name):
                f.unlink()
        with contextlib.suppress(OSError):  # a file of the user's keeps its folder
            folder.rmdir()


def _write_view(scene: Any, vdir: Path, keyed: dict[str, np.ndarray], white: np.ndarray, shown: dict[str, str],
                config: PSPConfig, n_footprints: int, decode: bool) -> dict[str, Any]:
    """One view's figures into ``vdir``; its entry in ``scene.json``."""
    rig, view, period = scene.rig, scene.view, config.period
    wp, hp = rig.projector.width, rig.projector.height
    vdir.mkdir(exist_ok=True)
    white_level = float(np.percentile(white[scene.object_mask], 99)) if scene.object_mask.any() else 1.0
    what = f"{scene.obj.name}, view {view}"
    for key, name in shown.items():
        fig.image_figure(vdir / f"{name}.png", tonemap(keyed[key], white_level),
                         f"{what}: {name.replace('_', ' ')} (tone-mapped, 99th pct of white = 90%)")
    fig.image_figure(vdir / "white.png", tonemap(white, white_level), f"{what}: white (tone-mapped)")
    decoded = decode_view(keyed, config, scene, vdir, what) if decode else {}
    fig.label_figure(vdir / "mask.png", scene.mask.astype(np.int16) + (scene.mask & ~scene.object_mask),
                     {0: "background", 1: "object", 2: "backdrop"}, f"{what}: object mask")
    for axis, name in enumerate(("x", "y")):
        coord = scene.proj_xy[..., axis]
        fig.value_figure(vdir / f"proj_{name}.png", coord, f"{what}: exact projector {name}", units="projector px",
                         cmap="turbo", vmin=0, vmax=(wp, hp)[axis] - 1)
        fig.value_figure(vdir / f"phase_{name}.png", np.mod(coord / period, 1.0),
                         f"{what}: fringe phase along {name} (period {period:g} px)", units="phase (cycles)",
                         cmap="twilight", vmin=0, vmax=1)
    material = np.where(scene.mask, scene.material, -1)
    fig.label_figure(vdir / "material.png", material, dict(enumerate(simlib.MATERIAL_NAMES)), f"{what}: materials")
    pixels = spread_pixels(scene.lit & scene.object_mask, n_footprints)
    fps = scene.footprints(pixels)
    peak = max(float(fps.mean(axis=-1).max()), 1e-30)
    fig.panels_figure(vdir / "footprints.png", [np.log10(np.maximum(f.mean(axis=-1), 1e-30) / peak) for f in fps],
                      [f"({y}, {x})" for y, x in pixels], f"{what}: exact footprints at pixels (row, col), mean of RGB",
                      units="log10 intensity / brightest peak", vmin=-4, vmax=0)
    return {"view": view, "angle_deg": scene.angle, "mask_pixels": int(scene.object_mask.sum()),
            "lit_pixels": int(scene.lit.sum()), "footprint_pixels_yx": pixels.tolist(), "decode": decoded}


def decode_view(frames: dict, config, scene, vdir: Path, what: str) -> dict:
    """Decode a view's captured PSP frames, write the maps, and measure them against the exact values."""
    from sssphase_core.processing.psp import Reason, decode_camera

    rig = scene.rig
    wp, hp = rig.projector.width, rig.projector.height
    corr = decode_camera(frames, config, (wp, hp), bayer="RGGB")  # the sim sensor's layout, as a capture decodes
    with atomic_path(vdir / "decoded.npz", ".npz") as tmp:
        np.savez_compressed(tmp, xp=corr.xp, yp=corr.yp, mask=corr.mask, reason=corr.reason)
    lit = scene.object_mask & np.isfinite(scene.proj_xy[..., 0])  # exact correspondence exists (not shadowed)
    on_object = corr.mask & lit
    err = np.hypot(corr.xp - scene.proj_xy[..., 0], corr.yp - scene.proj_xy[..., 1])[on_object]
    for name, values, size in (("x", corr.xp, wp), ("y", corr.yp, hp)):
        fig.value_figure(vdir / f"decoded_{name}.png", np.where(corr.mask, values, np.nan),
                         f"{what}: decoded projector {name} (black: not decoded)", units="projector px", cmap="turbo",
                         vmin=0, vmax=size - 1)
    fig.label_figure(vdir / "reason.png", np.where(scene.mask, corr.reason.astype(np.int16), -1),
                     {r.value: r.name.lower().replace("_", " ") for r in Reason}, f"{what}: decoding outcome per pixel",
                     other="off the object")
    err_map = np.full(scene.mask.shape, np.nan, np.float32)
    err_map[on_object] = err
    fig.value_figure(vdir / "decode_error.png", err_map, f"{what}: correspondence error against the exact map",
                     units="error (projector px)", cmap="magma", vmin=0, vmax=0.5)
    return {
        "valid_fraction": float(on_object.sum() / max(lit.sum(), 1)),
        "valid_in_shadow": int((corr.mask & scene.object_mask & ~lit).sum()),  # lit only through scattering
        "median_error_px": float(np.median(err)) if err.size else float("nan"),
        "p99_error_px": float(np.percentile(err, 99)) if err.size else float("nan"),
        "reasons": {r.name: int((corr.reason[scene.mask] == r).sum()) for r in Reason},
        "error_map_scale_px": 0.5,
    }


def tonemap(linear, white_level: float):
    """Linear RGB -> sRGB in [0, 1] with ``white_level`` at 90 % (NaN -> black)."""
    x = np.clip(np.nan_to_num(linear) / max(white_level, 1e-6) * 0.9, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return srgb.astype(np.float32)


def spread_pixels(lit, n: int):
    """``n`` lit pixels spread over the object (evenly spaced in raster order of the lit set)."""
    ys, xs = np.nonzero(lit)
    if len(ys) == 0:
        raise InputError("no surface pixel is lit by the projector in this view")
    pick = np.linspace(0, len(ys) - 1, n + 2)[1:-1].astype(int)
    return np.stack([ys[pick], xs[pick]], axis=1)
