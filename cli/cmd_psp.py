"""`sss patterns`, `sss decode` and `sss bench psp`: projector patterns, PSP decoding, its benchmark."""

from __future__ import annotations

import json
import math
from pathlib import Path

import typer

from sssphase_core.errors import DataError, InputError


def _save_png(path: Path, image) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def patterns(
    out: Path = typer.Option(..., "--out", help="output folder (created)"),
    projector: str = typer.Option("1920x1080", "--projector", help="projector resolution WxH"),
    footprints: bool = typer.Option(False, "--footprints", help="include the dot grids (spacing² frames)"),
    dot_spacing: int = typer.Option(55, "--dot-spacing", min=1, help="dot-grid spacing in projector px"),
    reference: list[str] = typer.Option([], "--reference", help="reference pattern(s) besides white and black (always written: an import needs both): checkerboard, stripes_x, stripes_y"),
    period: float | None = typer.Option(None, "--period", help="high-frequency period in px (default: preset for the resolution)"),
    shifts: int = typer.Option(4, "--shifts", min=3, help="phase shifts per fringe set"),
    unwrap: bool = typer.Option(True, "--unwrap/--no-unwrap", help="include the lower-frequency unwrapping sets"),
    gamma: float = typer.Option(2.2, "--gamma", help="projector gamma to pre-distort for"),
    hdr: str = typer.Option("", "--hdr", help="comma-separated exposure bracket, e.g. 1,4,16 (listed in plan.json)"),
) -> None:
    """Write the capture plan's projector patterns as 8-bit PNGs named by plan key, plus plan.json."""
    import numpy as np
    from rich.progress import Progress

    from sssphase_core.capture.importer import GAMMA_RANGE, MAX_SHIFTS
    from sssphase_core.processing.patterns import (
        PSPConfig,
        capture_plan,
        parse_projector_size,
        period_ladder,
        psp_config_for,
    )

    w, h = parse_projector_size(projector)
    if period is not None and not (math.isfinite(period) and period >= 2):
        raise InputError(f"--period must be a finite fringe period of at least 2 projector px, got {period}")
    if shifts > MAX_SHIFTS:  # what `sss import` and the decoder take
        raise InputError(f"--shifts must be 3 to {MAX_SHIFTS}, got {shifts}")
    if not GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]:  # NaN fails too
        raise InputError(f"--gamma must be a number in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}] (as a rig file's), got {gamma}")
    if period is not None and period > max(w, h):  # its frame names would also read p1e+06, which import refuses
        raise InputError(f"--period {period:g} is longer than the {w}x{h} projector: the fringes need at least one "
                         "period across it")
    if period is None:
        config = psp_config_for(w, h, n_shifts=shifts)
        if config.period > max(w, h):  # the default period is not shorter than a tiny projector either
            raise InputError(f"a {w}x{h} projector is smaller than one fringe period ({config.period:g} px): "
                             "PSP needs a few periods across it")
    else:
        config = PSPConfig(period=period, n_shifts=shifts, unwrap_periods=period_ladder(period, max(w, h)))
    try:
        exposures = tuple(float(e) for e in hdr.split(",") if e.strip())
    except ValueError:
        raise InputError(f"--hdr must be comma-separated numbers, got {hdr!r}") from None
    references = list(dict.fromkeys(["white", "black", *reference]))  # every import needs both (mask, light)
    plan = capture_plan(w, h, psp=config, unwrap=unwrap, footprints=footprints, dot_spacing=dot_spacing,
                        references=references, hdr_exposures=exposures, gamma=gamma)
    from sssphase_core.store.imageio import IMAGE_SUFFIXES
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    unique = list({f.key: f for f in plan}.values())
    held = None
    if out.is_dir():  # (bounded: the folder's own entries and the paths this plan writes, never a whole tree)
        mine = (out / f"{f.key}{suffix}" for f in unique for suffix in IMAGE_SUFFIXES)
        held = next((p for p in (*sorted(out.iterdir()), *mine) if p.is_file() and
                     (p.name == "plan.json" or p.suffix.lower() in IMAGE_SUFFIXES)), None)
    if held is not None:  # captured frames share the patterns' names; an earlier set would be left beside this one
        raise InputError(f"--out {out} already holds {held.relative_to(out)}: write the patterns into a new folder "
                         "(nothing was written)")
    out.mkdir(parents=True, exist_ok=True)
    with Progress() as bar:
        task = bar.add_task("writing patterns", total=len(unique))
        for frame in unique:
            img = np.round(np.clip(frame.pattern(), 0, 1) * 255).astype(np.uint8)
            _save_png(out / f"{frame.key}.png", img)
            bar.advance(task)
    (out / "plan.json").write_text(plan.to_json() + "\n")
    typer.echo(f"{len(unique)} patterns ({len(plan)} planned frames) written to {out}")


def _read_plan(path: Path) -> dict:
    """A folder's ``plan.json`` (as `sss patterns` writes it), checked: one line naming the file otherwise."""
    from sssphase_core.store.session import plan_problem

    try:
        plan = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path}: not a readable capture plan ({type(exc).__name__}: {str(exc).splitlines()[0][:80]})") from None
    problem = plan_problem(plan) or (None if isinstance(plan, dict) and "projector" in plan else "it names no projector size")
    if problem:
        raise InputError(f"{path}: {problem}")
    return plan


def _psp_from_plan(plan: dict, path: Path):
    from sssphase_core.processing.patterns import PSPConfig

    psp = plan.get("psp")
    if not isinstance(psp, dict) or not psp:
        raise InputError(f"{path} has no PSP configuration (psp: period, n_shifts, unwrap_periods)")
    try:
        return PSPConfig(period=psp["period"], n_shifts=psp["n_shifts"], unwrap_periods=tuple(psp["unwrap_periods"]),
                         orientations=tuple(psp.get("orientations", ("x", "y"))))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: its psp configuration is incomplete or of the wrong type ({type(exc).__name__}: {exc})") from None


def decode_cmd(
    folder: Path = typer.Argument(..., help="folder of captured frames named by plan key (PNG/TIFF 8/16-bit, float TIFF, EXR or NPY)"),
    out: Path = typer.Option(..., "--out", help="output folder for maps (.npy) and viewable PNGs"),
    projector: str | None = typer.Option(None, "--projector", help="projector WxH (default: from plan.json)"),
    min_modulation: float = typer.Option(0.01, "--min-modulation", help="minimum fringe modulation B (normalised units)"),
    saturation: float | None = typer.Option(None, "--saturation", help="clipping level in the frames' units: integer files read as 0 to 1 (default 0.99), EXR/float files in their own units (default: none)"),
    bayer: str | None = typer.Option(None, "--bayer", help="the frames were demosaiced from a Bayer sensor of this layout (RGGB, GRBG, GBRG, BGGR) by a demosaicer that keeps each pixel's own sample (Malvar, OpenCV): silhouette pixels that only demosaicing lit are dropped (reason demosaic bleed)"),
) -> None:
    """Decode PSP frames into camera -> projector correspondences (xp, yp, mask, reason) + PNGs."""
    import numpy as np
    from rich.progress import Progress

    from sssphase_core.capture.importer import MIN_FRAME_SIDE, frame_files, frame_scale, psp_config_from_names
    from sssphase_core.processing.isp import check_layout
    from sssphase_core.processing.patterns import parse_projector_size, psp_config_for, psp_key
    from sssphase_core.processing.psp import Reason, decode_camera, wrapped_phase
    from sssphase_core.store.imageio import read_frame, stores_integers

    if not folder.is_dir():
        raise InputError(f"{folder} is not a folder")
    if bayer is not None:
        bayer = check_layout(bayer.upper())
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)
    plan_path = folder / "plan.json"
    plan = _read_plan(plan_path) if plan_path.is_file() else None
    if projector is not None:
        size = parse_projector_size(projector)
    elif plan is not None:
        size = tuple(plan["projector"])
    else:
        raise InputError(f"no plan.json in {folder}: give --projector WxH")
    files = frame_files(folder, strict=False)  # other images (e.g. this command's own figures) are not frames
    if plan is not None:
        config = _psp_from_plan(plan, plan_path)
    elif any(key.startswith("psp/") for key in files):  # the file names say the periods and shifts, as for `sss import`
        config = psp_config_from_names(folder, files)
    else:
        config = psp_config_for(*size)  # (names the first missing frame below)
    keys = [psp_key(o, p, n) for o in ("x", "y") for p in config.periods for n in range(config.n_shifts)]
    missing = [key for key in keys if key not in files]
    if missing and any(p.is_dir() and p.name.startswith("view_") for p in folder.iterdir()):
        raise InputError(f"{folder} holds view folders: decode one view at a time (sss decode {folder / 'view_000'} ...)")
    if missing:
        raise DataError(f"frame {missing[0]!r} not found in {folder} (expected {missing[0].replace('/', '__')}.png/.tif/"
                        f".exr/.npy or {missing[0]}.*; {len(missing)} of {len(keys)} PSP frames missing)")
    if saturation is None and any(stores_integers(files[key]) for key in keys):
        saturation = 0.99  # integer files clip at their top code; EXR and float files do not clip
    frames = {}
    with Progress() as bar:
        task = bar.add_task("loading frames", total=len(keys))
        for key in keys:
            frames[key] = read_frame(files[key], encoding="auto")  # tagged sRGB files as light, as `sss import` reads them
            first = frames[keys[0]]
            if frames[key].shape != first.shape:
                raise DataError(f"{files[key]} is {frames[key].shape[1]}x{frames[key].shape[0]}, but {files[keys[0]]} is "
                                f"{first.shape[1]}x{first.shape[0]}: every frame must come from the same camera")
            if min(first.shape[:2]) < MIN_FRAME_SIDE:  # as `sss import` refuses them
                raise InputError(f"{files[key]} is {first.shape[1]}x{first.shape[0]}: smaller than a camera frame "
                                 f"(at least {MIN_FRAME_SIDE} px a side)")
            bar.advance(task)
    level = max(float(np.percentile(f, 99.9)) for f in frames.values())
    if not any(stores_integers(files[key]) for key in keys) and not (level > 0 and np.isfinite(level)):
        raise InputError(f"the PSP frames in {folder} hold no light (99.9th percentile {level:.3g}): they must be "
                         "linear images of the fringe patterns")
    scale = frame_scale([files[key] for key in keys], [level])  # float frames in a renderer's units, as `sss import`
    if scale != 1.0:
        frames = {k: (f.astype(np.float64) * scale).astype(np.float32) for k, f in frames.items()}
        saturation = None if saturation is None else saturation * scale
        typer.echo(f"float frames at level {level:.3g} (99.9th percentile) scaled to 1 (the decoder's thresholds are "
                   "in camera units)")
    corr = decode_camera(frames, config, size, bayer=bayer, min_modulation=min_modulation, saturation=saturation)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("xp", "yp", "mask", "reason", "modulation", "offset", "modulation_ratio"):
        np.save(out / f"{name}.npy", getattr(corr, name))
    from sssphase_core.reporting import figures as fig

    for o in ("x", "y"):
        stack = [frames[psp_key(o, config.period, n)] for n in range(config.n_shifts)]
        phi, _, _ = wrapped_phase([f.astype(np.float32).mean(-1) if f.ndim == 3 else f for f in stack])
        fig.value_figure(out / f"phase_{o}.png", np.where(corr.mask, (phi + np.pi) / (2 * np.pi), np.nan),
                         f"wrapped phase along {o} (period {config.period:g} px)", units="phase (cycles)",
                         cmap="twilight", vmin=0, vmax=1)
    for name, values, extent in (("xp", corr.xp, size[0]), ("yp", corr.yp, size[1])):
        fig.value_figure(out / f"{name}.png", np.where(corr.mask, values, np.nan),
                         f"decoded projector {name[0]} (black: not decoded)", units="projector px", cmap="turbo",
                         vmin=0, vmax=extent - 1)
    fig.label_figure(out / "mask.png", corr.mask.astype(np.int16), {0: "not decoded", 1: "decoded"}, "decoded pixels")
    fig.label_figure(out / "reason.png", corr.reason.astype(np.int16),
                     {r.value: r.name.lower().replace("_", " ") for r in Reason}, "decoding outcome per pixel")
    fig.value_figure(out / "modulation.png", corr.modulation, "fringe modulation B", units="linear camera units",
                     cmap="magma", vmin=0, vmax=float(np.percentile(corr.modulation, 99.5)) or 1.0)
    coverage = corr.coverage()
    summary = {"projector": list(size), "psp": {"period": config.period, "n_shifts": config.n_shifts,
               "unwrap_periods": list(config.unwrap_periods)}, "coverage": coverage}
    (out / "decode.json").write_text(json.dumps(summary, indent=1) + "\n")
    typer.echo(f"decoded {coverage['VALID']} of {corr.mask.size} pixels -> {out}  ({coverage})")


def bench_psp(
    out: Path = typer.Option(..., "--out", help="JSON result file"),
    md: Path | None = typer.Option(None, "--md", help="also write a Markdown table here"),
    quick: bool = typer.Option(False, "--quick", help="small run (< 1 minute), for smoke tests"),
) -> None:
    """PSP decoding speed against OpenCV, accuracy against exact correspondences, error vs run time."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from sssphase_core.bench import psp_bench
    from sssphase_core.bench.output import write_bench_report

    with Progress(SpinnerColumn(), TextColumn("{task.description}"), TimeElapsedColumn()) as bar:
        task = bar.add_task("bench psp", total=None)
        result, tables = psp_bench.run(quick=quick, progress=lambda msg: bar.update(task, description=msg))
    write_bench_report(result, tables, out, md, title="sss bench psp" + (" (quick)" if quick else ""))
    s = result["speed"]
    typer.echo(
        f"decode + unwrap {s['ours_ms_per_phase_map']:.1f} ms/phase map vs OpenCV PSP {s['opencv_psp_3step_ms']:.1f} ms "
        f"({s['ratio_opencv_over_ours_per_map']:.1f}x) -> {out}"
    )


def register(groups: dict[str, typer.Typer]) -> None:
    groups["root"].command("patterns")(patterns)
    groups["root"].command("decode")(decode_cmd)
    groups["bench"].command("psp")(bench_psp)
