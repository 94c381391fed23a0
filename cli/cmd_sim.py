"""`sss sim`: simulated capture of a catalogue object, written as viewable PNGs plus scene.json."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from sssphase_core.errors import InputError


def sim(
    object_name: str = typer.Option("apple", "--object", help="catalogue object (`sss objects` lists them)"),
    views: int = typer.Option(2, "--views", min=1, help="turntable views, 360/views degrees apart"),
    out: Path = typer.Option(..., "--out", help="output folder (created)"),
    preset: str = typer.Option("cpu", "--preset", help="rig preset: cpu (256x192, K=32) or paper (1080p, K=90)"),
    transport: str = typer.Option("burley", "--transport", help="sim light transport: burley (radially symmetric footprints) or directional_dipole (skewed by the incidence direction)"),
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
    from sssphase_core.processing.patterns import capture_plan, psp_config_for
    from sssphase_core.reporting import figures as fig
    from sssphase_core.sim.materials import MATERIALS, dropped_fraction
    from sssphase_core.sim.rig import pixel_pitch_mm

    if views > simlib.MAX_VIEWS:  # as `sss capture`: the turntable's limit, before a view is rendered
        raise InputError(f"--views: the sim rig's turntable takes at most {simlib.MAX_VIEWS} views, got {views}")
    if not 0 <= seed <= 2**63 - 1:
        raise InputError(f"--seed must be 0 to {2**63 - 1} (2**63 - 1), got {seed}")
    obj = simlib.get_object(object_name)
    rig = simlib.rig_from_options({"preset": preset, "transport": transport})
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    if (out / "scene.json").is_file():  # an earlier `sss sim` here: its view folders go, none is left beside these
        import re
        import shutil

        for old in (p for p in out.iterdir() if p.is_dir() and not p.is_symlink() and re.fullmatch(r"view[0-9]+", p.name)):
            shutil.rmtree(old)
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
            what = f"{obj.name}, view {view}"
            for key, name in shown.items():
                fig.image_figure(vdir / f"{name}.png", _tonemap(keyed[key], white_level),
                                 f"{what}: {name.replace('_', ' ')} (tone-mapped, 99th pct of white = 90%)")
            fig.image_figure(vdir / "white.png", _tonemap(frames[-1], white_level), f"{what}: white (tone-mapped)")
            decoded = _decode_view(keyed, config, scene, vdir, what) if decode else {}
            fig.label_figure(vdir / "mask.png", scene.mask.astype(np.int16), {0: "background", 1: "object"},
                             f"{what}: object mask")
            for axis, name in enumerate(("x", "y")):
                coord = scene.proj_xy[..., axis]
                fig.value_figure(vdir / f"proj_{name}.png", coord, f"{what}: exact projector {name}", units="projector px",
                                 cmap="turbo", vmin=0, vmax=(wp, hp)[axis] - 1)
                fig.value_figure(vdir / f"phase_{name}.png", np.mod(coord / period, 1.0),
                                 f"{what}: fringe phase along {name} (period {period:g} px)", units="phase (cycles)",
                                 cmap="twilight", vmin=0, vmax=1)
            material = np.where(scene.mask, scene.material, -1)
            fig.label_figure(vdir / "material.png", material, dict(enumerate(simlib.MATERIAL_NAMES)), f"{what}: materials")
            labels |= {simlib.MATERIAL_NAMES[i] for i in np.unique(scene.material[scene.mask])}
            pixels = _spread_pixels(scene.lit, n_footprints)
            fps = scene.footprints(pixels)
            peak = max(float(fps.mean(axis=-1).max()), 1e-30)
            fig.panels_figure(vdir / "footprints.png", [np.log10(np.maximum(f.mean(axis=-1), 1e-30) / peak) for f in fps],
                              [f"({y}, {x})" for y, x in pixels], f"{what}: exact footprints at pixels (row, col), mean of RGB",
                              units="log10 intensity / brightest peak", vmin=-4, vmax=0)
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


def _decode_view(frames: dict, config, scene, vdir: Path, what: str) -> dict:
    """Decode a view's captured PSP frames, write the maps, and measure them against the exact values."""
    import numpy as np

    from sssphase_core.processing.psp import Reason, decode_camera
    from sssphase_core.reporting import figures as fig

    rig = scene.rig
    wp, hp = rig.projector.width, rig.projector.height
    corr = decode_camera(frames, config, (wp, hp), bayer="RGGB")  # the sim sensor's layout, as a capture decodes
    np.savez_compressed(vdir / "decoded.npz", xp=corr.xp, yp=corr.yp, mask=corr.mask, reason=corr.reason)
    lit = scene.mask & np.isfinite(scene.proj_xy[..., 0])  # exact correspondence exists (not shadowed)
    on_object = corr.mask & lit
    err = np.hypot(corr.xp - scene.proj_xy[..., 0], corr.yp - scene.proj_xy[..., 1])[on_object]
    for name, values, size in (("x", corr.xp, wp), ("y", corr.yp, hp)):
        fig.value_figure(vdir / f"decoded_{name}.png", np.where(corr.mask, values, np.nan),
                         f"{what}: decoded projector {name} (black: not decoded)", units="projector px", cmap="turbo",
                         vmin=0, vmax=size - 1)
    fig.label_figure(vdir / "reason.png", np.where(scene.mask, corr.reason.astype(np.int16), -1),
                     {r.value: r.name.lower().replace("_", " ") for r in Reason}, f"{what}: decoding outcome per pixel")
    err_map = np.full(scene.mask.shape, np.nan, np.float32)
    err_map[on_object] = err
    fig.value_figure(vdir / "decode_error.png", err_map, f"{what}: correspondence error against the exact map",
                     units="error (projector px)", cmap="magma", vmin=0, vmax=0.5)
    return {
        "valid_fraction": float(on_object.sum() / max(lit.sum(), 1)),
        "valid_in_shadow": int((corr.mask & scene.mask & ~lit).sum()),  # lit only through scattering
        "median_error_px": float(np.median(err)) if err.size else float("nan"),
        "p99_error_px": float(np.percentile(err, 99)) if err.size else float("nan"),
        "reasons": {r.name: int((corr.reason[scene.mask] == r).sum()) for r in Reason},
        "error_map_scale_px": 0.5,
    }


def _tonemap(linear, white_level: float):
    """Linear RGB -> sRGB in [0, 1] with ``white_level`` at 90 % (NaN -> black)."""
    import numpy as np

    x = np.clip(np.nan_to_num(linear) / max(white_level, 1e-6) * 0.9, 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return srgb.astype(np.float32)


def _spread_pixels(lit, n: int):
    """``n`` lit pixels spread over the object (evenly spaced in raster order of the lit set)."""
    import numpy as np

    ys, xs = np.nonzero(lit)
    if len(ys) == 0:
        raise InputError("no surface pixel is lit by the projector in this view")
    pick = np.linspace(0, len(ys) - 1, n + 2)[1:-1].astype(int)
    return np.stack([ys[pick], xs[pick]], axis=1)


def objects() -> None:
    """The simulated rig's object catalogue: split, materials and whether their coefficients are measured."""
    from rich.console import Console
    from rich.table import Table

    from sssphase_core.sim import CATALOGUE
    from sssphase_core.sim.materials import MATERIALS
    from sssphase_core.sim.objects import object_materials

    table = Table(title="Simulated objects (sss capture --object NAME)")
    for col in ("object", "split", "description", "materials (* measured: Jensen et al. 2001)"):
        table.add_column(col)
    for obj in CATALOGUE.values():
        mats = ", ".join(m + ("*" if MATERIALS[m].measured else "") for m in object_materials(obj))
        table.add_row(obj.name, obj.split, obj.description, mats)
    Console(soft_wrap=True).print(table)


def rigs() -> None:
    """Simulated rig presets (--preset): camera/projector resolution, footprint patch, fringe periods."""
    from rich.console import Console
    from rich.table import Table

    from sssphase_core.capture import dot_spacing_for
    from sssphase_core.processing.patterns import psp_config_for
    from sssphase_core.sim.rig import PRESETS, pixel_pitch_mm, rig_preset

    table = Table(title="Rig presets (sss capture/sim --preset NAME; a real rig: --rig RIG.toml, see HARDWARE.md)")
    for col in ("preset", "camera", "projector", "patch K", "fringe period (px)", "unwrapping periods (px)",
                "dot spacing (px)", "camera pixel (mm)", "scattering scale"):
        table.add_column(col)
    for name in PRESETS:
        rig = rig_preset(name)
        psp = psp_config_for(rig.projector.width, rig.projector.height)
        table.add_row(name, f"{rig.camera.width}x{rig.camera.height}", f"{rig.projector.width}x{rig.projector.height}",
                      str(rig.patch), f"{psp.period:g} x {psp.n_shifts} shifts",
                      ", ".join(f"{p:g}" for p in psp.unwrap_periods), str(dot_spacing_for(rig.patch)),
                      f"{pixel_pitch_mm(rig):.3f}", f"{rig.sss_scale:g}")
    Console(soft_wrap=True).print(table)


def register(groups: dict[str, typer.Typer]) -> None:
    groups["root"].command("sim")(sim)
    groups["root"].command("objects")(objects)
    groups["root"].command("rigs")(rigs)
