"""The layer order of pyproject's [tool.importlinter] contracts holds (import-linter, run as CI runs it)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _lint(config: Path) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    if exe is None:
        pytest.fail("lint-imports is missing: install the dev extra (pip install -e '.[dev]')")
    return subprocess.run([exe, "--config", str(config), "--no-cache"], capture_output=True, text=True, cwd=ROOT,
                          timeout=300)


def test_the_import_contracts_hold():
    proc = _lint(ROOT / "pyproject.toml")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


def test_a_broken_contract_is_reported(tmp_path):
    """The checker sees real imports: the CLI draws with rich, so forbidding it there must fail."""
    (tmp_path / "bad.toml").write_text(
        '[tool.importlinter]\nroot_packages = ["sssphase_cli", "sssphase_core"]\ninclude_external_packages = true\n'
        '[[tool.importlinter.contracts]]\nname = "no rich in the CLI"\ntype = "forbidden"\n'
        'source_modules = ["sssphase_cli"]\nforbidden_modules = ["rich"]\n')
    proc = _lint(tmp_path / "bad.toml")
    assert proc.returncode != 0 and "BROKEN" in proc.stdout


def test_cli_functions_only_parse_and_print():
    """The CLI is thin (each command parses, calls one function of the library, prints): no function in cli/
    runs over 60 lines, signature included; the work lives in core runners the web view and notebooks share."""
    import ast

    long = []
    for path in sorted((ROOT / "cli").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 60:
                long.append(f"{path.name}:{node.name} ({node.end_lineno - node.lineno + 1} lines)")
    assert long == [], long


def test_cli_imports_no_private_name_of_the_library():
    """The CLI calls the library's public API only (a `_name` import means logic that belongs in core)."""
    import ast

    private = []
    for path in sorted((ROOT / "cli").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(("sssphase_core", "sssphase_daemon",
                                                                                   "sssphase_plugins")):
                private += [f"{path.name}: {node.module}.{a.name}" for a in node.names
                            if a.name.startswith("_") and not a.name.endswith("__")]
    assert private == [], private
