"""``sss view``: the rig live, its sessions and relighting in the browser (``sssphase_view``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

console = Console(soft_wrap=True)


def view(
    sessions: Annotated[Path | None, typer.Option(help="folder of sessions to browse and relight")] = None,
    checkpoint: Annotated[Path | None, typer.Option(help="decoder run folder or .pt for the torch and blend backends")] = None,
    rig: Annotated[Path | None, typer.Option(help="rig file of the devices to see live (default: the sim rig)")] = None,
    out: Annotated[Path, typer.Option(help="where relit images, their footprint caches and uploads go")] = Path("view_out"),
    host: Annotated[str, typer.Option(help="address to listen on (loopback unless --allow-remote)")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=0, max=65535, help="port (0: a free one)")] = 8765,
    allow_remote: Annotated[bool, typer.Option("--allow-remote", help="listen off loopback (over HTTPS: --tls-cert and "
                                               "--tls-key; the token is still required)")] = False,
    tls_cert: Annotated[Path | None, typer.Option(help="serve over HTTPS with this PEM certificate (chain) for the "
                                                  "machine's name; needed off loopback")] = None,
    tls_key: Annotated[Path | None, typer.Option(help="the PEM private key of --tls-cert")] = None,
    open_browser: Annotated[bool, typer.Option("--open", help="open the page in the default browser")] = False,
    calibration: Annotated[Path | None, typer.Option(help="the rig's camera-projector calibration (OpenCV YAML, XML or "
                                                     "JSON, as `sss calibrate stereo` writes it) for the depth and "
                                                     "surface maps of sessions and live decode; a simulated rig has its "
                                                     "own")] = None,
) -> None:
    """Serve the live view, live decode, sessions and relighting on a local web page; prints its URL with
    the token every request needs. A local daemon is started for the live view when none runs."""
    from sssphase_core.capture.plan import RigSpec
    from sssphase_core.errors import InputError
    from sssphase_core.learning.runlog import check_checkpoint_file
    from sssphase_core.store.session import check_output_folder
    from sssphase_view.live import LiveRig
    from sssphase_view.server import serve

    check_output_folder(out)
    if (tls_cert is None) != (tls_key is None):
        raise InputError("--tls-cert and --tls-key go together: give the certificate and its private key")
    if checkpoint is not None:
        check_checkpoint_file(checkpoint)
    spec = RigSpec.from_toml(rig) if rig is not None else RigSpec()

    def ready(url: str) -> None:
        console.print(f"sss view: {url}\n(the token in the URL is required; Ctrl-C stops it)", highlight=False)
        if open_browser:
            import webbrowser

            webbrowser.open(url)

    try:
        serve(host=host, port=port, sessions=sessions, checkpoint=checkpoint, out=out, rig=LiveRig(spec),
              allow_remote=allow_remote, calibration=calibration, on_ready=ready,
              tls=(tls_cert, tls_key) if tls_cert is not None and tls_key is not None else None)
    except KeyboardInterrupt:  # (uvicorn re-raises the signal it stopped on, or returns: said alike either way)
        pass
    Console(stderr=True, soft_wrap=True).print(f"the view stopped; the images it relit are kept in {out}",
                                               highlight=False)


def bench_view(
    out: Annotated[Path, typer.Option(help="JSON result file (a Markdown table is written next to it)")] = Path("benchmarks/view.json"),
    frames: Annotated[int, typer.Option(min=5, max=10_000, help="live frames per run")] = 40,
    patterns: Annotated[int, typer.Option(min=1, max=100, help="new patterns relit after the first")] = 5,
    paper: Annotated[bool, typer.Option("--paper", help="also the live view at the paper preset (1080p, slow)")] = False,
    md: Annotated[Path | None, typer.Option(help="Markdown table file (default: next to --out)")] = None,
) -> None:
    """How fast `sss view` answers: live frames/s and latency, live decode refresh, relight per new pattern."""
    from sssphase_cli.output import write_result
    from sssphase_view.bench import run_bench

    with console.status("sss bench view") as status:
        result, markdown = run_bench(frames=frames, patterns=patterns, paper=paper,
                                     progress=lambda text: status.update(f"sss bench view: {text}"))
    write_result(console, out, md, result, markdown)


def register(groups: dict[str, typer.Typer]) -> None:
    groups["root"].command("view")(view)
    groups["bench"].command("view")(bench_view)
