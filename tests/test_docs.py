"""The documentation site builds with ``mkdocs build --strict`` (no broken link, no missing page, no
warning), the README stays a front page, and the generated CLI reference lists every command of the app."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import typer.main

from sssphase_cli.main import app

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250
SETUP_COMMANDS = (  # CI runs the second one: the README must keep saying it
    'pip install -c constraints.txt -e . && sss demo --out demo',
    'pip install -c constraints.txt -e ".[dev]" -e examples/sssphase-example-plugin && python -m pytest -q',
)


def command_paths(command=None, path=("sss",)):
    """Every visible command and subcommand path of the Typer app, walked here (not by the docs hook)."""
    command = command if command is not None else typer.main.get_command(app)
    yield path
    for name, sub in (getattr(command, "commands", None) or {}).items():
        if not getattr(sub, "hidden", False):
            yield from command_paths(sub, (*path, name))


def missing_commands(html: str) -> list[str]:
    """Command paths that have no section (heading id and name) on the built CLI reference page."""
    return [
        " ".join(path)
        for path in command_paths()
        if f'id="{"-".join(path)}"' not in html or f"<code>{' '.join(path)}</code>" not in html
    ]


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(ROOT / "mkdocs.yml"),
         "--site-dir", str(out)],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=300,
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"mkdocs build --strict failed (docs extra installed?):\n{log[-6000:]}"
    assert "WARNING" not in log, log[-6000:]
    return out


def test_readme_is_a_front_page():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= README_MAX_LINES, "measurements go to docs/benchmarks/, not the README"
    for command in SETUP_COMMANDS:
        assert command in text


def test_site_builds_strict_with_every_page(site: Path):
    for page in ("index.html", "getting-started/index.html", "rig/index.html", "plugins/index.html",
                 "session-format/index.html", "protocol/index.html", "architecture/index.html",
                 "reference/api/processing/index.html", "benchmarks/psp/index.html", "results/psp/index.html"):
        assert (site / page).is_file(), page
    # the pages that include files kept where they live carry their content
    assert "Bench checklist" in (site / "rig/index.html").read_text(encoding="utf-8")
    assert "sssphase_devices" in (site / "plugins/index.html").read_text(encoding="utf-8")
    assert "manifest.json" in (site / "session-format/index.html").read_text(encoding="utf-8")
    # mkdocstrings rendered the core's API from its docstrings
    assert "decode" in (site / "reference/api/processing/index.html").read_text(encoding="utf-8")


def test_cli_reference_lists_every_command(site: Path):
    html = (site / "reference/cli/index.html").read_text(encoding="utf-8")
    paths = list(command_paths())
    assert len(paths) > 30 and ("sss", "train", "decoder") in paths and ("sss", "calibrate", "projector") in paths
    assert missing_commands(html) == []


def test_missing_command_check_can_fail(site: Path):
    """The check above is not vacuous: a page without one command's section is caught."""
    html = (site / "reference/cli/index.html").read_text(encoding="utf-8")
    broken = html.replace('id="sss-train-pretrain"', 'id="gone"')
    assert missing_commands(broken) == ["sss train pretrain"]
