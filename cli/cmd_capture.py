"""Capture and sessions: ``sss capture``, ``validate``, ``import``, ``export``, ``calibrate projector`` and
``bench capture``. Heavy modules (zmq, numpy, torch) load inside commands."""

from __future__ import annotations

import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

console = Console(soft_wrap=True)  # result lines stay whole when piped (no terminal width)
#: ``sss capture --timeout``: at most a day (the daemon client waits in whole milliseconds, a C int).
MAX_TIMEOUT_S = 86400


def capture(
    object_name: Annotated[str, typer.Option("--object", help="session name; on the sim rig also the catalogue object")],
    views: Annotated[int, typer.Option(help="number of views (turntable steps)")] = 4,
    footprints: Annotated[bool, typer.Option(help="also capture dot grids and extract ground-truth footprints")] = False,
    reference: Annotated[list[str] | None, typer.Option(help="reference pattern: a name (checkerboard, stripes_x, ...) or an image file; repeatable")] = None,
    hdr: Annotated[bool, typer.Option(help="capture exposure brackets (1/4, 1, 4) and merge them")] = False,
    hdr_exposures: Annotated[str | None, typer.Option(help="the brackets' relative exposures, e.g. 0.25,1,4,16 (implies --hdr; longer ones lift dim dot grids out of the noise)")] = None,
    resume: Annotated[bool, typer.Option(help="continue an interrupted session")] = False,
    rig: Annotated[Path | None, typer.Option(help="rig file (TOML); default: the sim rig")] = None,
    out: Annotated[Path, typer.Option(help="session root folder")] = Path("sessions"),
    seed: Annotated[int, typer.Option(help="sim noise seed")] = 0,
    preset: Annotated[str, typer.Option(help="sim rig preset: cpu or paper")] = "cpu",
    transport: Annotated[str | None, typer.Option(help="sim light transport: burley (radially symmetric footprints), directional_dipole (skewed by the incidence direction) or radiative (random-walk profiles, no diffusion approximation)")] = None,
    anisotropy: Annotated[float | None, typer.Option(help="sim rig, --transport radiative: the media's phase-function mean cosine g in [0, 0.85] (0 isotropic, default; skin and milk scatter forward)")] = None,
    backdrop: Annotated[float | None, typer.Option(help="sim rig: a matte grey wall this many mm (60 to 1000) behind the turntable centre, facing the camera (default: the object floats in the dark)")] = None,
    randomise_rig: Annotated[bool, typer.Option(help="sim rig: draw projector gamma and black, lens blur, read noise, exposure, demosaicing and transport model (domain randomisation; reproducible from --seed and the object's name)")] = False,
    dot_spacing: Annotated[int | None, typer.Option(help="dot-grid spacing in projector pixels")] = None,
    keep_dots: Annotated[bool, typer.Option(help="keep the raw dot-grid frames")] = False,
    keep_unwrap: Annotated[bool, typer.Option(help="keep the unwrapping frames (default: only the decoded result)")] = False,
    timeout: Annotated[float, typer.Option(help="seconds without an answer before the daemon counts as gone, or a device call (a frame: raise it for exposures that long) as stalled")] = 10.0,
    dot_stride: Annotated[int, typer.Option(help="capture every S-th dot shift along x and y: footprints for 1/S^2 of the pixels from 1/S^2 of the dot frames (enough to train a decoder; the measured backend needs 1)")] = 1,
    device: Annotated[str, typer.Option(help="sim rig: where it renders (cpu, or cuda / cuda:N: the light transport on a GPU, the same images, 1080p in seconds; auto: the GPU where torch sees one, else cpu)")] = "cpu",
) -> None:
    """Capture a session through the daemon (starting a local sim daemon if none runs)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from sssphase_core.capture import CaptureRequest, RigSpec
    from sssphase_core.errors import InputError

    if not 0 < timeout <= MAX_TIMEOUT_S:  # NaN fails too
        raise InputError(f"--timeout must be a number of seconds in (0, {MAX_TIMEOUT_S}], got {timeout}")
    spec = RigSpec.from_toml(rig) if rig else RigSpec()
    req = CaptureRequest.from_options(
        object_name, spec, views=views, footprints=footprints, references=reference or (), hdr=hdr,
        hdr_exposures=hdr_exposures, keep_dots=keep_dots, keep_unwrap=keep_unwrap, resume=resume, out=out, seed=seed,
        preset=preset, dot_spacing=dot_spacing, transport=transport, randomise_rig=randomise_rig, dot_stride=dot_stride,
        anisotropy=anisotropy, backdrop=backdrop, device=device, on_drawn=lambda drawn: console.print("randomised sim rig: " + ", ".join(
            f"{k} {v}" for k, v in drawn.items() if k != "transport" or not transport)))

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    try:
        with _local_daemon(timeout) as client, ExitStack() as stack:
            tasks: dict[int, int] = {}
            bars: list[Progress] = []  # drawn at the first frame: a capture refused before it leaves no empty line

            def progress(view: int, done: int, total: int) -> None:
                if not bars:
                    bars.append(stack.enter_context(Progress(*columns, console=console)))
                if view not in tasks:
                    tasks[view] = bars[0].add_task(f"view {view + 1}/{views}", total=total)
                bars[0].update(tasks[view], completed=done)

            session = _captured(client, req, spec, progress, started=lambda: bool(bars))
    except KeyboardInterrupt:
        # cli.main ignores the exit code typer returns for Ctrl-C, so leave with it here
        Console(stderr=True, soft_wrap=True).print("[yellow]interrupted[/]: complete views are kept; rerun with --resume to continue")
        sys.exit(130)
    console.print(f"session {session.path}: {len(session.views())}/{views} views complete")


def _captured(client: Any, req: Any, spec: Any, progress: Any, started: Any) -> Any:
    """``run_capture``'s session; a daemon that died or went quiet once frames came (a remote one too) is said with
    how to go on."""
    from sssphase_core.capture import run_capture
    from sssphase_daemon.client import DaemonUnavailable

    try:
        return run_capture(client, req, spec, progress=progress,
                           ask_move=None if spec.turntable or req.views == 1 else _ask_move)
    except DaemonUnavailable as exc:
        if not started() or "--resume" in str(exc):
            raise
        raise DaemonUnavailable(f"{exc}: complete views are kept; continue with --resume once it runs again") from None


def _ask_move(view: int, angle: float) -> None:
    """A rig without a turntable: the user turns the object (one view: nothing to turn, nothing asked)."""
    from sssphase_core.errors import InputError

    if not sys.stdin.isatty():  # (typer's confirm printed "aborted" at the end of the input, no more)
        kept = f"; views 0 to {view - 1} are kept (--resume continues)" if view else ""
        raise InputError("the rig has no turntable, so each view waits for you to turn the object, and the input is "
                         "not a terminal: run it in a terminal, add a turntable to the rig file ([devices] turntable), "
                         f"or capture one view per session (--views 1){kept}")
    typer.confirm(f"turn the object to view {view} ({angle:.0f} deg) and press enter", default=True)


def _local_daemon(timeout: float):
    """The running local daemon's client, or one started here (each said on the console)."""
    from sssphase_daemon.client import local_client

    return local_client(timeout, on_start=lambda pid: console.print(
        f"[yellow]no daemon running:[/] started a local one (pid {pid})"),
        on_stop=lambda pid: console.print(f"stopped the local daemon (pid {pid})"),
        on_left=lambda pid: console.print(f"left the local daemon (pid {pid}) running: another client is using it "
                                          "(`sss daemon stop` ends it)"))


def validate(session: Annotated[Path, typer.Argument(help="session folder")]) -> None:
    """Check a session: every view complete, every array present and matching its checksum, and the images finite linear light."""
    from sssphase_core.errors import DataError
    from sssphase_core.store.session import Session

    s = Session.open(session)
    problems = s.validate()
    if problems:
        for p in problems:
            console.print(f"[red]{escape(p)}[/]")
        raise DataError(f"{session}: {len(problems)} problem(s)")
    n = sum(len(s.arrays(v)) for v in s.views())
    console.print(f"[green]ok[/] {session}: {len(s.views())} views, {n} arrays, checksums match, images are finite light")


def import_images(
    folder: Annotated[Path, typer.Argument(help="folder of images (view_000/, view_001/ ... or one view)")],
    object_name: Annotated[str, typer.Option("--object", help="session name")],
    projector: Annotated[str, typer.Option(help="projector size WxH, e.g. 1920x1080")],
    out: Annotated[Path, typer.Option(help="session root folder")] = Path("sessions"),
    gamma: Annotated[float, typer.Option(help="the projector's gamma (pattern value -> light)")] = 2.2,
    patch: Annotated[int, typer.Option(help="footprint crop size K for dot-grid frames")] = 32,
    encoding: Annotated[str, typer.Option(help="how 8/16-bit files map codes to light: auto (their sRGB / ICC / gAMA "
                                               "tag; untagged: sRGB where the fringes average half the white's light "
                                               "only as sRGB codes, else linear), linear (a camera's raw codes) or srgb; float "
                                               "files are linear")] = "auto",
    bayer: Annotated[str, typer.Option(help="the camera demosaiced its Bayer frames of this layout (RGGB, GRBG, GBRG, "
                                            "BGGR): silhouette pixels only demosaicing lit are dropped; auto: the layout "
                                            "the frames' noise shows, if any; none: never")] = "auto",
    demosaic: Annotated[str, typer.Option(help="with --bayer, how it demosaiced: malvar or opencv (relit fringes are "
                                               "then compared through it), or other")] = "other",
    angles: Annotated[str | None, typer.Option(help="each view's turntable angle in degrees, in view order (e.g. "
                                                    "0,90,180,270): `sss geometry` merges the views with them")] = None,
    bit_depth: Annotated[int | None, typer.Option(help="the camera's bits per sample (10, 12, 14) when 16-bit files "
                                                       "hold its codes in their low bits: its top code is then white "
                                                       "(default: the files' own range)")] = None,
) -> None:
    """Import frames from another rig (named by plan key, '/' as '__' or folders; see SESSION_FORMAT.md)."""
    from sssphase_core.capture import import_folder
    from sssphase_core.capture.importer import parse_angles
    from sssphase_core.processing.patterns import parse_projector_size
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)  # before any frame is read: a file, a broken link or a session's own folder
    session = import_folder(folder, out, object_name, parse_projector_size(projector), patch=patch, gamma=gamma,
                            encoding=encoding, bayer=bayer, demosaic=demosaic,
                            angles=parse_angles(angles) if angles is not None else None, bit_depth=bit_depth)
    rig = session.manifest["rig"]
    for v, info in sorted(session.manifest["views"].items(), key=lambda kv: int(kv[0])):
        found = str(info.get("bayer_detected", "none"))
        if found.split(":")[0] != "none":
            console.print(f"view {v}: demosaiced from a {found}; pixels only demosaicing lit at the "
                          "silhouette are dropped (--bayer none keeps them)")
        elif "matches no layout clearly" in found:  # a colour filter array suspected, not applied
            console.print(f"view {v}: {found.removeprefix('none: ')}: if the camera demosaiced its frames, pass "
                          "--bayer LAYOUT")
        if "raw_bayer" in info:
            console.print(f"view {v}: grey frames read as raw Bayer samples ({info['raw_bayer']})")
        method, _, why = str(info.get("demosaic_detected", "")).partition(": ")
        if method in ("malvar", "opencv"):
            console.print(f"view {v}: {why}: relit fringes are compared through {method} demosaicing "
                          "(--demosaic names another)")
    if rig["frame_encoding"] != "linear":
        console.print(f"frames decoded from {rig['frame_encoding']} to linear light ({rig['frame_encoding_from']}; "
                      "--encoding linear reads the codes as light)")
    scale = rig.get("frame_scale", 1.0)
    if "frame_bit_depth" in rig and scale != 1.0:
        console.print(f"{rig['frame_bit_depth']}-bit codes: scaled by {scale:.4g}, which puts the camera's top code at 1 "
                      "(the rig's frame_scale in the manifest)")
    elif scale != 1.0:
        console.print(f"frames in linear units far from the camera's (float, or integers wider than 16 bits): scaled by {scale:.4g}, which puts the white capture's "
                      "99.9th percentile at 1 (the rig's frame_scale in the manifest)")
    console.print(f"imported {len(session.views())} view(s) into {session.path}")


def export(
    session: Annotated[Path, typer.Argument(help="session folder")],
    out: Annotated[Path, typer.Option(help="output folder (OUT/<object>/view_NNN/...)")] = Path("export"),
    views: Annotated[str, typer.Option(help="comma-separated views (default: all complete views)")] = "",
) -> None:
    """Export a session's images, decoded maps and footprints as float32 OpenEXR."""
    from sssphase_core.errors import InputError
    from sssphase_core.reporting.export import export_session
    from sssphase_core.store import exr
    from sssphase_core.store.session import Session, check_output_folder, claim_output, refuse_inside_session

    if not exr.available():
        raise InputError(exr.MISSING)
    check_output_folder(out)
    s = Session.open(session)
    try:
        chosen = list(dict.fromkeys(int(v) for v in views.split(",") if v.strip())) or None
    except ValueError:
        raise InputError(f"--views must be comma-separated integers, got {views!r}") from None
    if views.strip() and chosen is None:
        raise InputError(f"--views {views!r} names no view: give comma-separated view numbers, or leave it out for all")
    missing = sorted(set(chosen or []) - set(s.views()))
    if missing:
        raise InputError(f"{session} has no complete view {', '.join(map(str, missing))} (complete: {s.views()})")
    if not s.views():
        raise InputError(f"{session} has no complete view to export (an interrupted capture? `sss validate {session}`)")
    refuse_inside_session(out / s.name, what=f"--out {out}: its folder")
    claim_output(out, [s])  # OUT/<object>: another session's export of the same object is not mixed into
    written = export_session(s, out, chosen)
    console.print(f"wrote {len(written)} files under {out / s.name}")


def calibrate_projector(
    rig: Annotated[Path | None, typer.Option(help="rig file (TOML) to calibrate; its \"projector\" table is rewritten "
                                             "(default: the sim rig, written to --out)")] = None,
    out: Annotated[Path | None, typer.Option(help="rig file to write (default: --rig itself, else rig.toml)")] = None,
    levels: Annotated[int, typer.Option(min=4, max=256, help="grey levels in the ramp, 0 to 1")] = 17,
    object_name: Annotated[str, typer.Option("--object", help="sim rig: the catalogue object lit by the ramp")] = "soap",
    check: Annotated[bool, typer.Option("--check", help="sim rig: capture a view with 2.2 and with the fitted curve "
                                        "and compare the correspondence error with the simulator's exact map")] = False,
) -> None:
    """Fit the projector's response (gamma and black per colour) from a grey ramp captured through the daemon."""
    from sssphase_core.capture.calibration import CalibrationRequest, calibrate_projector
    from sssphase_daemon.client import local_client

    req = CalibrationRequest(rig, out, levels, object_name, check)
    with local_client(on_start=lambda pid: console.print(f"started a local daemon (pid {pid})")) as client:
        calibrate_projector(client, req, status=console.status, on_fit=_print_response, on_check=lambda label, err:
                            console.print(f"correspondence error with {label}: median {err:.3f} projector px"))
    console.print(f"wrote the {escape('[projector]')} table of {req.target}: capture with `sss capture --rig {req.target}`")


def calibrate_stereo(
    session: Annotated[Path, typer.Argument(help="A session of a printed checkerboard, one pose per view (`sss capture "
                                            "--object board --views 10`: without a turntable it asks for each move).",
                                            metavar="SESSION")],
    board: Annotated[str, typer.Option(help="The board's inner corners, COLSxROWS (a board of 10 x 7 squares: 9x6).")],
    square: Annotated[float, typer.Option(help="The side of one square, in the unit the 3D points are to have (mm).")],
    out: Annotated[Path, typer.Option(help="Calibration file to write (.yml, .yaml, .xml or .json), for `sss geometry "
                                      "--calibration`.")] = Path("calibration.yml"),
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
    unit: Annotated[str, typer.Option(help="The unit of --square, written into the file for the points it gives.")] = "mm",
    lens: Annotated[str, typer.Option(help="Distortion terms to estimate for each device: k1 (one radial term, square "
                                      "pixels), radial (k1, k2, k3) or full (k1, k2, p1, p2, k3 and fx, fy apart); more "
                                      "terms need more and wider poses.")] = "k1",
) -> None:
    """Calibrate the camera and the projector as a stereo pair from a session of a checkerboard: corners in the white
    capture, their projector points through local homographies of the decoded correspondences (Moreno and Taubin)."""
    from sssphase_core.capture.stereo_calibration import (
        MORE_POSES,
        against_simulated_rig,
        calibrate_stereo,
        check_calibration_out,
        parse_board,
        write_calibration,
    )
    from sssphase_core.relight.runner import choose_views
    from sssphase_core.store.session import Session

    corners = parse_board(board)
    check_calibration_out(out)
    s = Session.open(session)
    chosen = choose_views(s, views)
    with console.status(f"finding the board in {len(chosen)} views") as status:
        result = calibrate_stereo(s, corners, square, chosen, progress=lambda done, total: status.update(
            f"finding the board: view {done} of {total}"), unit=unit, lens=lens)
    for v, why in result.skipped.items():
        console.print(f"view {v} left out: {why}")
    c = result.calibration
    console.print(f"calibrated from {len(result.views)} views: RMS reprojection error camera {result.camera_rms:.3f} px, "
                  f"projector {result.projector_rms:.3f} px, the pair {result.stereo_rms:.3f} px; focal length camera "
                  f"{c.camera_matrix[0, 0]:.1f} px (+-{100 * result.uncertainty['camera'][0]:.1f}%), projector "
                  f"{c.projector_matrix[0, 0]:.1f} px (+-{100 * result.uncertainty['projector'][0]:.1f}%); baseline "
                  f"{c.baseline:.1f} {c.unit}")
    if line := against_simulated_rig(s, c):
        console.print(line)
    if shaky := result.shaky():
        console.print(f"[yellow]warning[/]: the poses leave the calibration uncertain ({'; '.join(shaky)}): {MORE_POSES}")
    console.print(f"wrote {write_calibration(out, result.calibration, result.errors)}: triangulate with "
                  f"`sss geometry SESSION --calibration {out}`")


def calibrate_turntable(
    session: Annotated[Path, typer.Argument(help="A session of a checkerboard standing on the turntable, turned through "
                                            "several angles (`sss capture --object board --views 24`: views where the "
                                            "whole board is seen are used).", metavar="SESSION")],
    board: Annotated[str, typer.Option(help="The board's inner corners, COLSxROWS (a board of 10 x 7 squares: 9x6).")],
    calibration: Annotated[Path, typer.Option(help="The rig's camera-projector calibration (`sss calibrate stereo` "
                                              "wrote it): the board's corners are triangulated with it, and the "
                                              "axis is added to it.")],
    square: Annotated[float | None, typer.Option(help="The side of one square, to check the calibration's scale by.")] = None,
    out: Annotated[Path | None, typer.Option(help="Write the calibration with the axis here instead of into "
                                             "--calibration (.yml, .yaml, .xml or .json).")] = None,
    views: Annotated[str, typer.Option(help="Comma-separated views (default: all).")] = "",
) -> None:
    """Find the turntable's axis from a checkerboard standing on it: each view's corners triangulated, the board's
    turns fitted to one axis; `sss geometry` then merges a session's views into one point cloud."""
    from sssphase_core.capture.stereo_calibration import (
        CALIBRATION_SUFFIXES,
        calibration_entries,
        check_calibration_out,
        parse_board,
        write_calibration,
    )
    from sssphase_core.capture.turntable_calibration import calibrate_turntable, turntable_report
    from sssphase_core.errors import InputError
    from sssphase_core.processing.triangulation import read_calibration
    from sssphase_core.relight.runner import choose_views
    from sssphase_core.store.session import Session

    corners = parse_board(board)
    stereo = read_calibration(calibration)  # (a folder or a missing file: said of --calibration)
    target = out or calibration
    if out is not None:
        check_calibration_out(out)
    elif calibration.suffix.lower() not in CALIBRATION_SUFFIXES:
        raise InputError(f"--calibration {calibration}: name a .yml, .yaml, .xml or .json file (OpenCV writes the "
                         "format its suffix names)")
    errors, others = calibration_entries(calibration)
    if out is None and others:  # rewritten in place, they would be lost
        raise InputError(f"--calibration {calibration} holds entries sss does not write ({', '.join(others[:6])}): give "
                         "--out FILE for the calibration with the turntable's axis, and the file stays as it is")
    s = Session.open(session)
    chosen = choose_views(s, views)
    with console.status(f"finding the board in {len(chosen)} views") as status:
        result = calibrate_turntable(s, corners, stereo, square=square, views=chosen, progress=lambda done, total:
                                     status.update(f"finding the board: view {done} of {total}"))
    for text, warning in turntable_report(result, s, square):
        console.print(text.replace(warning, f"[yellow]{warning}[/]", 1) if warning else text)
    console.print(f"wrote {write_calibration(target, result.calibration, errors)}: `sss geometry SESSION --calibration "
                  f"{target}` merges a session's views")


def _print_response(fitted) -> None:
    table = Table(title=f"projector response ({fitted.pixels} camera pixels; fit rms {fitted.rms:.4f} in relative light)")
    for col in ("colour", "gamma", "black (relative to white)"):
        table.add_column(col)
    for name, g, b in zip("RGB", fitted.gamma_rgb, fitted.black_rgb, strict=True):
        table.add_row(name, f"{g:.3f}", f"{b:.4f}")
    table.add_row("used", f"{fitted.gamma:.3f}", f"{fitted.black:.4f}")
    console.print(table)


def bench_capture(
    out: Annotated[Path, typer.Option(help="JSON result file (a Markdown table is printed and written next to it)")],
    preset: Annotated[str, typer.Option(help="sim rig preset (`sss rigs`): paper = 1920x1080, K = 90")] = "paper",
    object_name: Annotated[str, typer.Option("--object", help="sim object (`sss objects`)")] = "soap",
    footprints: Annotated[bool, typer.Option("--footprints/--no-footprints", help="capture the dot grids too")] = True,
    keep: Annotated[Path | None, typer.Option(help="keep the session under this folder (default: removed)")] = None,
    md: Annotated[Path | None, typer.Option(help="Markdown table file (default: next to --out)")] = None,
) -> None:
    """One sim view captured through a daemon: time, peak RSS of daemon and client, session size."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from sssphase_cli.output import write_result
    from sssphase_core.sim import rig_preset
    from sssphase_daemon.bench import capture_bench

    rig_preset(preset)  # an unknown preset is one line, before a daemon starts
    with Progress(TextColumn("capturing"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=console, transient=True) as bar:
        task = bar.add_task("view", total=None)
        result, markdown = capture_bench(preset, object_name, footprints=footprints, out=keep,
                                         progress=lambda view, done, total: bar.update(task, completed=done, total=total))
    write_result(console, out, md, result, markdown)


def register(groups: dict[str, typer.Typer]) -> None:
    root = groups["root"]
    root.command("capture")(capture)
    root.command("validate")(validate)
    root.command("import")(import_images)
    root.command("export")(export)
    groups["calibrate"].command("projector")(calibrate_projector)
    groups["calibrate"].command("stereo")(calibrate_stereo)
    groups["calibrate"].command("turntable")(calibrate_turntable)
    groups["bench"].command("capture")(bench_capture)
