"""`sss sim`: simulated capture of a catalogue object, written as viewable PNGs plus scene.json."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from sssphase_core.errors import InputError


def sim(
    object_name: str = typer.Option("apple", "--object", help="catalogue object (see the error for the list)"),
    views: int = typer.Option(2, "--views", min=1, help="turntable views, 360/views degrees apart"),
    out: Path = typer.Option(..., "--out", help="output folder (created)"),
    preset: str = typer.Option("cpu", "--preset", help="rig preset: cpu (256x192, K=32) or paper (1080p, K=90)"),
    seed: int = typer.Option(0, "--seed", help="sensor noise seed"),
    n_footprints: int = typer.Option(6, "--footprints", min=1, max=24, help="footprints in the montage"),
    decode: bool = typer.Option(True, "--decode/--no-decode", help="also capture the unwrapping set and decode it"),
) -> None:
    """Simulated capture per view: the 8 PSP images and white (noisy, developed, tone-mapped), mask,
    exact projector x/y correspondence and wrapped fringe phase, material labels, footprints (log).

    With --decode (default) the view's whole PSP capture plan (the 8 inputs plus the unwrapping
    ladder) is captured with sensor noise and decoded; the decoded correspondences, their reason
    codes and their error against the simulator's exact values are written too."""
    import numpy as np
    from rich.progress import Progress

    from sssphase_core import sim as simlib
    from sssphase_core.patterns import capture_plan, psp_config_for
    from sssphase_core.sim.materials import MATERIALS, dropped_fraction
    from sssphase_core.sim.rig import pixel_pitch_mm

    obj = simlib.get_object(object_name)
    rig = simlib.rig_preset(preset)
    out.mkdir(parents=True, exist_ok=True)
    wp, hp = rig.projector.width, rig.projector.height
    config = psp_config_for(wp, hp)
    period = config.period
    plan = [f for f in capture_plan(wp, hp, psp=config, unwrap=decode, gamma=rig.projector.gamma) if f.kind == "psp"]
    patterns = np.stack([f.pattern() for f in plan] + [np.ones((hp, wp), np.float32)])
    shown = {f.key: f"psp_{f.params['orientation']}_s{f.params['shift']}" for f in plan if f.params["period"] == period}
    names = [*shown.values(), "white"]
    summary, labels = [], set()
    with Progress() as bar:
        task = bar.add_task(f"sim {object_name}", total=views)
        for view in range(views):
            scene = simlib.SimScene(obj, rig=rig, view=view, n_views=views, seed=seed)
            rng = np.random.default_rng([seed, view])
            pixels_task = bar.add_task(f"  view {view}: lit pixels", total=None)
            frames = scene.capture(patterns, rng, progress=lambda done, total, t=pixels_task: bar.update(t, completed=done, total=total))
            bar.remove_task(pixels_task)
            vdir = out / f"view{view}"
            vdir.mkdir(exist_ok=True)
            white_level = float(np.percentile(frames[-1][scene.mask], 99)) if scene.mask.any() else 1.0
            keyed = {f.key: frame for f, frame in zip(plan, frames, strict=False)}
            for key, name in shown.items():
                _save(vdir / f"{name}.png", _tonemap(keyed[key], white_level))
            _save(vdir / "white.png", _tonemap(frames[-1], white_level))
            decoded = _decode_view(keyed, config, scene, vdir) if decode else {}
            _save(vdir / "mask.png", (scene.mask * 255).astype(np.uint8))
            for axis, name in enumerate(("x", "y")):
                coord = scene.proj_xy[..., axis]
                _save(vdir / f"proj_{name}.png", _colour_map(coord / ((wp, hp)[axis] - 1), "turbo"))
                _save(vdir / f"phase_{name}.png", _colour_map(np.mod(coord / period, 1.0), "twilight"))
            _save(vdir / "material.png", _label_map(scene.material))
            labels |= {simlib.MATERIAL_NAMES[i] for i in np.unique(scene.material[scene.mask])}
            pixels = _spread_pixels(scene.lit, n_footprints)
            _save(vdir / "footprints.png", _montage(scene.footprints(pixels)))
            summary.append({"view": view, "angle_deg": scene.angle, "mask_pixels": int(scene.mask.sum()),
                            "lit_pixels": int(scene.lit.sum()), "footprint_pixels_yx": pixels.tolist(),
                            "decode": decoded})
            if decoded:
                bar.console.print(
                    f"view {view}: decoded {decoded['valid_fraction']:.1%} of the object, correspondence error "
                    f"median {decoded['median_error_px']:.3f} px, p99 {decoded['p99_error_px']:.2f} px (projector px)")
            bar.advance(task)
    pitch = pixel_pitch_mm(rig)
    info = {
        "object": {"name": obj.name, "split": obj.split, "description": obj.description, "radius_mm": obj.radius,
                   "materials_seen": sorted(labels)},
        "dropped_energy_rgb": {name: dropped_fraction(MATERIALS[name].rate(rig.sss_scale), pitch, rig.patch).round(5).tolist()
                               for name in sorted(labels)},
        "rig": rig.to_dict(),
        "psp_period": period,
        "images": names,
        "seed": seed,
        "views": summary,
    }
    (out / "scene.json").write_text(json.dumps(info, indent=2))
    typer.echo(f"wrote {views} view(s) of {obj.name} to {out}")


def _decode_view(frames: dict, config, scene, vdir: Path) -> dict:
    """Decode a view's captured PSP frames, write the maps, and measure them against the exact values."""
    import numpy as np

    from sssphase_core.psp import Reason, decode

    rig = scene.rig
    wp, hp = rig.projector.width, rig.projector.height
    corr = decode(frames, config, (wp, hp))
    np.savez_compressed(vdir / "decoded.npz", xp=corr.xp, yp=corr.yp, mask=corr.mask, reason=corr.reason)
    lit = scene.mask & np.isfinite(scene.proj_xy[..., 0])  # exact correspondence exists (not shadowed)
    on_object = corr.mask & lit
    err = np.hypot(corr.xp - scene.proj_xy[..., 0], corr.yp - scene.proj_xy[..., 1])[on_object]
    _save(vdir / "decoded_x.png", _colour_map(np.where(corr.mask, corr.xp, np.nan) / (wp - 1), "turbo"))
    _save(vdir / "decoded_y.png", _colour_map(np.where(corr.mask, corr.yp, np.nan) / (hp - 1), "turbo"))
    _save(vdir / "reason.png", _label_map(np.where(corr.reason == 0, -1, corr.reason.astype(np.int16))))
    err_map = np.full(scene.mask.shape, np.nan, np.float32)
    err_map[on_object] = err
    _save(vdir / "decode_error.png", _colour_map(err_map / 0.5, "magma"))  # 0 .. 0.5 projector px
    return {
        "valid_fraction": float(on_object.sum() / max(lit.sum(), 1)),
        "valid_in_shadow": int((corr.mask & scene.mask & ~lit).sum()),  # lit only through scattering
        "median_error_px": float(np.median(err)) if err.size else float("nan"),
        "p99_error_px": float(np.percentile(err, 99)) if err.size else float("nan"),
        "reasons": {r.name: int((corr.reason[scene.mask] == r).sum()) for r in Reason},
        "error_map_scale_px": 0.5,
    }


def _save(path: Path, image) -> None:
    from PIL import Image

    Image.fromarray(image).save(path)


def _tonemap(linear, white_level: float):
    """Linear RGB -> sRGB uint8 with ``white_level`` at 90 % (NaN -> black)."""
    import numpy as np

    x = np.clip(np.nan_to_num(linear) / max(white_level, 1e-6) * 0.9, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).astype(np.uint8)


def _colour_map(values, cmap: str):
    """Values in [0, 1] (NaN -> black) through a matplotlib colour map -> RGB uint8."""
    import matplotlib
    import numpy as np

    rgb = matplotlib.colormaps[cmap](np.clip(np.nan_to_num(values), 0, 1))[..., :3]
    rgb[~np.isfinite(values)] = 0
    return (rgb * 255).astype(np.uint8)


def _label_map(labels):
    import matplotlib
    import numpy as np

    colours = matplotlib.colormaps["tab20"](np.arange(20))[:, :3]
    rgb = colours[np.mod(labels, 20)]
    rgb[labels < 0] = 0
    return (rgb * 255).astype(np.uint8)


def _spread_pixels(lit, n: int):
    """``n`` lit pixels spread over the object (evenly spaced in raster order of the lit set)."""
    import numpy as np

    ys, xs = np.nonzero(lit)
    if len(ys) == 0:
        raise InputError("no surface pixel is lit by the projector in this view")
    pick = np.linspace(0, len(ys) - 1, n + 2)[1:-1].astype(int)
    return np.stack([ys[pick], xs[pick]], axis=1)


def _montage(footprints, zoom: int = 4, decades: float = 4.0):
    """Footprints (N, K, K, 3) side by side on a log scale (``decades`` below the brightest), 2 rows."""
    import numpy as np

    n, k = footprints.shape[:2]
    peak = max(float(footprints.max()), 1e-12)
    logv = np.clip((np.log10(np.maximum(footprints, 1e-30) / peak) + decades) / decades, 0, 1)
    tiles = (logv * 255).astype(np.uint8).repeat(zoom, 1).repeat(zoom, 2)
    cols = (n + 1) // 2
    size = k * zoom + 2
    canvas = np.full((2 * size, cols * size, 3), 40, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, cols)
        canvas[r * size + 1 : r * size + 1 + k * zoom, c * size + 1 : c * size + 1 + k * zoom] = tile
    return canvas


def register(groups: dict[str, typer.Typer]) -> None:
    groups["root"].command("sim")(sim)
