"""`sss patterns`, `sss decode` and `sss bench psp`: projector patterns, PSP decoding, its benchmark."""

from __future__ import annotations

from pathlib import Path

import typer

from sssphase_cli.progress import LazyBar


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
    from sssphase_core.capture.pattern_files import write_patterns

    with LazyBar("writing patterns") as bar:
        written = write_patterns(out, projector, footprints=footprints, dot_spacing=dot_spacing, references=reference,
                                 period=period, shifts=shifts, unwrap=unwrap, gamma=gamma, hdr=hdr, progress=bar)
    typer.echo(f"{written.patterns} patterns ({written.planned} planned frames) written to {out}")


def decode_cmd(
    folder: Path = typer.Argument(..., help="folder of captured frames named by plan key (PNG/TIFF 8/16-bit, float TIFF, EXR or NPY)"),
    out: Path = typer.Option(..., "--out", help="output folder for maps (.npy) and viewable PNGs"),
    projector: str | None = typer.Option(None, "--projector", help="projector WxH (default: from plan.json)"),
    min_modulation: float = typer.Option(0.01, "--min-modulation", help="minimum fringe modulation B (normalised units)"),
    saturation: float | None = typer.Option(None, "--saturation", help="clipping level in the frames' units: integer files read as 0 to 1 (default 0.99), EXR/float files in their own units (default: none)"),
    bayer: str | None = typer.Option(None, "--bayer", help="the frames were demosaiced from a Bayer sensor of this layout (RGGB, GRBG, GBRG, BGGR) by a demosaicer that keeps each pixel's own sample (Malvar, OpenCV): silhouette pixels that only demosaicing lit are dropped (reason demosaic bleed)"),
) -> None:
    """Decode PSP frames into camera -> projector correspondences (xp, yp, mask, reason) + PNGs."""
    from sssphase_core.reporting.decoded import decode_folder

    with LazyBar("loading frames") as bar:
        result = decode_folder(folder, out, projector=projector, min_modulation=min_modulation, saturation=saturation,
                               bayer=bayer, progress=bar, report=typer.echo)
    typer.echo(f"decoded {result.coverage['VALID']} of {result.pixels} pixels -> {out}  ({result.coverage})")


def bench_psp(
    out: Path = typer.Option(..., "--out", help="JSON result file"),
    md: Path | None = typer.Option(None, "--md", help="also write a Markdown table here"),
    quick: bool = typer.Option(False, "--quick", help="small run (< 1 minute), for smoke tests"),
) -> None:
    """PSP decoding speed against OpenCV, accuracy against exact correspondences, error vs run time."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    from sssphase_core.store.results import check_result_paths

    check_result_paths(out, md)  # before the minutes of work (and torch's import), not after
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
