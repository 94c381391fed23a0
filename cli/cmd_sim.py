"""`sss sim`: simulated capture of a catalogue object, written as viewable PNGs plus scene.json."""

from __future__ import annotations

from pathlib import Path

import typer

from sssphase_cli.progress import LazyBar


class _SimBar(LazyBar):
    """`sss sim`'s bar of views and, below it, the lit pixels of the view being rendered."""

    def __init__(self, object_name: str) -> None:
        super().__init__(f"sim {object_name}")
        self.pixels: dict[int, int] = {}

    def __call__(self, view: int | None, done: int, total: int | None) -> None:  # type: ignore[override]
        self.start(total)
        if view is None:  # a view is done: its pixel task goes
            for task in self.pixels.values():
                self.bar.remove_task(task)
            self.pixels.clear()
            self.bar.update(self.task, completed=done)
            return
        if view not in self.pixels:
            self.pixels[view] = self.bar.add_task(f"  view {view}: lit pixels", total=None)
        self.bar.update(self.pixels[view], completed=done, total=total)


def sim(
    object_name: str = typer.Option("apple", "--object", help="catalogue object (`sss objects` lists them)"),
    views: int = typer.Option(2, "--views", min=1, help="turntable views, 360/views degrees apart"),
    out: Path = typer.Option(..., "--out", help="output folder (created)"),
    preset: str = typer.Option("cpu", "--preset", help="rig preset: cpu (256x192, K=32) or paper (1080p, K=90)"),
    transport: str = typer.Option("burley", "--transport", help="sim light transport: burley (radially symmetric footprints), directional_dipole (skewed by the incidence direction) or radiative (random-walk profiles, no diffusion approximation)"),
    anisotropy: float | None = typer.Option(None, "--anisotropy", help="--transport radiative: the media's phase-function mean cosine g in [0, 0.85] (default 0, isotropic)"),
    backdrop: float | None = typer.Option(None, "--backdrop", help="a matte grey wall this many mm (60 to 1000) behind the turntable centre, facing the camera (default: the object floats in the dark)"),
    seed: int = typer.Option(0, "--seed", help="sensor noise seed"),
    n_footprints: int = typer.Option(6, "--footprints", min=1, max=24, help="footprints in the montage"),
    decode: bool = typer.Option(True, "--decode/--no-decode", help="also capture the unwrapping set and decode it"),
) -> None:
    """Simulated capture per view: the 8 PSP images and white (noisy, developed, tone-mapped), mask,
    exact projector x/y correspondence and wrapped fringe phase, material labels, footprints (log).

    With --decode (default) the view's whole PSP capture plan (the 8 inputs plus the unwrapping
    ladder) is captured with sensor noise and decoded; the decoded correspondences, their reason
    codes and their error against the simulator's exact values are written too."""
    from sssphase_core.reporting.sim_views import run_sim

    with _SimBar(object_name) as bar:
        result = run_sim(object_name, views, out, preset=preset, transport=transport, anisotropy=anisotropy, seed=seed,
                         backdrop=backdrop, n_footprints=n_footprints, decode=decode, progress=bar, report=bar.print)
    typer.echo(f"wrote {views} view(s) of {result.name} to {out}")


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

    columns = {}  # one column per preset, one row per setting: readable at 80 columns (the camera's size was cut)
    for name in PRESETS:
        rig = rig_preset(name)
        psp = psp_config_for(rig.projector.width, rig.projector.height)
        columns[name] = (f"{rig.camera.width}x{rig.camera.height}", f"{rig.projector.width}x{rig.projector.height}",
                         str(rig.patch), f"{psp.period:g} x {psp.n_shifts} shifts",
                         ", ".join(f"{p:g}" for p in psp.unwrap_periods), str(dot_spacing_for(rig.patch)),
                         f"{pixel_pitch_mm(rig):.3f}", f"{rig.sss_scale:g}")
    table = Table(title="Rig presets (sss capture/sim --preset NAME; a real rig: --rig RIG.toml, see HARDWARE.md)")
    table.add_column("setting")
    for name in columns:
        table.add_column(name, no_wrap=True)
    for i, setting in enumerate(("camera", "projector", "patch K", "fringe period (px)", "unwrapping periods (px)",
                                 "dot spacing (px)", "camera pixel (mm)", "scattering scale")):
        table.add_row(setting, *(values[i] for values in columns.values()))
    Console(soft_wrap=True).print(table)


def bench_sim(
    out: Path = typer.Option(Path("benchmarks/sim.json"), help="JSON output (a Markdown table is written next to it)."),
    device: str = typer.Option("auto", help="where the accelerated path renders: auto, cuda, cuda:N (cpu: the plumbing)"),
    preset: str = typer.Option("paper", help="sim rig preset (`sss rigs`): paper = 1920x1080, K = 90"),
    object_name: str = typer.Option("soap", "--object", help="sim object (`sss objects`)"),
    md: Path | None = typer.Option(None, help="Markdown output (default: next to --out)"),
    transport: str = typer.Option("burley", help="light transport: burley or radiative (the ones ported to the device)"),
) -> None:
    """The simulator on a GPU: one view's whole capture plan rendered there, against its numpy path in the same
    run; the sensor per frame; the two paths' footprints and images compared."""
    from rich.console import Console

    from sssphase_cli.output import write_result
    from sssphase_core.compute import check_device
    from sssphase_core.errors import InputError
    from sssphase_core.sim import get_object, rig_preset

    check_device(device)
    rig_preset(preset)
    get_object(object_name)  # unknown names are one line before any work
    if transport not in ("burley", "radiative"):
        raise InputError(f"--transport {transport!r}: the device path renders burley or radiative (the directional "
                         "dipole stays on the CPU)")
    from sssphase_core.bench.sim_accel_bench import markdown, run

    console = Console(soft_wrap=True)
    with console.status("sss bench sim") as status:
        result = run(device=device, preset=preset, object_name=object_name, transport=transport,
                     progress=lambda stage: status.update(f"sss bench sim: {stage}"))
    write_result(console, out, md, result, markdown(result))


def register(groups: dict[str, typer.Typer]) -> None:
    groups["bench"].command("sim")(bench_sim)
    groups["root"].command("sim")(sim)
    groups["root"].command("objects")(objects)
    groups["root"].command("rigs")(rigs)
