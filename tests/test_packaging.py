"""Packaging: every third-party module the code imports is declared in pyproject.toml.

A fresh virtual environment has only what pyproject.toml names; an import that a developer's machine
happens to have (click, once typer stopped installing it) passes locally and breaks every user.
"""

from __future__ import annotations

import ast
import importlib.metadata as md
import re
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIRST_PARTY = {"sssphase_core", "sssphase_cli", "sssphase_daemon", "sssphase_plugins", "sssphase_example_plugin"}
# Import names whose distribution differs and may not be installed where the test runs.
KNOWN = {"PIL": "pillow", "zmq": "pyzmq", "serial": "pyserial", "hid": "hidapi", "usb": "pyusb", "cv2": "opencv-contrib-python-headless",
         "yaml": "pyyaml", "OpenEXR": "openexr", "Imath": "openexr"}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _declared() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"]) + [r for extra in project["optional-dependencies"].values() for r in extra]
    return {_norm(re.split(r"[ <>=!~\[;]", r.strip())[0]) for r in reqs}


def _third_party_imports() -> dict[str, Path]:
    local = {p.stem for p in ROOT.rglob("*.py")}  # test helper modules (conftest, dev_fakes, ...)
    found: dict[str, Path] = {}
    for folder in ("sssphase_core", "cli", "daemon", "plugins", "tests"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split(".")[0]
                    if top not in sys.stdlib_module_names and top not in FIRST_PARTY and top not in local:
                        found.setdefault(top, path)
    return found


def test_every_third_party_import_is_declared() -> None:
    declared = _declared()
    dists = md.packages_distributions()
    missing = {}
    for top, path in _third_party_imports().items():
        candidates = {_norm(d) for d in dists.get(top, [])} | {_norm(KNOWN.get(top, top))}
        if not candidates & declared:
            missing[top] = str(path.relative_to(ROOT))
    assert not missing, f"imported but not declared in pyproject.toml: {missing}"


def test_scanner_sees_imports_of_the_cli() -> None:
    """The scan is not vacuous: it finds the CLI's own third-party imports."""
    found = _third_party_imports()
    assert {"typer", "rich", "numpy", "torch", "zmq"} <= set(found)


def test_torch_is_pinned_to_the_cpu_build() -> None:
    pins = (ROOT / "constraints.txt").read_text()
    assert re.search(r"^torch==2\.13\.0$", pins, re.M)
    assert "torchvision" not in (ROOT / "pyproject.toml").read_text()


def test_every_package_folder_is_listed_for_setuptools():
    """A wheel (not an editable install) holds only the listed packages: a missing one imports on a
    developer's machine and fails for every user who installs the wheel."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    dirs = {name: ROOT / folder for name, folder in tool.get("package-dir", {}).items()}
    dirs.setdefault("sssphase_core", ROOT / "sssphase_core")
    found = set()
    for top, folder in dirs.items():
        for init in folder.rglob("__init__.py"):
            found.add(".".join([top, *init.parent.relative_to(folder).parts]))
    assert found == set(tool["packages"]), found ^ set(tool["packages"])
