"""`sss --help` stays fast: drawing the help imports no numpy, torch or plugin (the ≤ 0.5 s budget of the
front door; the figure itself is measured with farm-bench, see the docs' CLI page)."""

from __future__ import annotations

import subprocess
import sys

PROBE = """
import sys
sys.argv = ["sss", "--help"]
from sssphase_cli.main import main
try:
    main()
except SystemExit as exc:
    code = exc.code
heavy = sorted(m for m in ("numpy", "torch", "zmq", "scipy", "cv2", "pluggy", "sssphase_plugins.manager")
               if m in sys.modules)
print("HEAVY=" + ",".join(heavy), "CODE=" + str(code), file=sys.stderr)
"""


def _probe(argv: list[str]) -> tuple[str, str]:
    code = PROBE.replace('["sss", "--help"]', repr(["sss", *argv]))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    line = [ln for ln in proc.stderr.splitlines() if ln.startswith("HEAVY=")]
    assert line, proc.stderr[-2000:]
    return proc.stdout, line[-1]


def test_top_level_help_imports_nothing_heavy():
    out, probe = _probe(["--help"])
    assert "relight" in out and "capture" in out  # the help itself was drawn
    assert probe == "HEAVY= CODE=0", probe


def test_a_command_still_loads_the_plugins():
    """The plugin manager (model backends of plugins) is loaded once a command runs."""
    out, probe = _probe(["plugins"])
    assert "builtin" in out
    assert "sssphase_plugins.manager" in probe and "pluggy" in probe, probe


def test_usage_errors_are_answered_before_torch_is_imported():
    """A refused relight, geometry, evaluation, training or benchmark request answers in well under a second: the checks
    run before the modules that import torch (2 s on its own) are loaded."""
    for argv in (["eval", "relight", "s", "--backend", "blend", "--checkpoint", "/nonexistent/ck.pt"],
                 ["geometry", "no_session", "--device", "nonsense"],
                 ["relight", "no_session", "--pattern", "checkerboard", "--format", "tiff"],
                 ["eval", "knn", "--checkpoint", "root=/", "--n-views", "1"],
                 ["bench", "gpu", "--device", "nonsense"],
                 ["train", "pretrain", "--warmup-epochs", "nan", "--out", "/nonexistent/run"],
                 ["train", "decoder", "--end-to-end", "--aux-classes", "1", "--out", "/nonexistent/run"],
                 ["train", "decoder", "--encoder", "/nonexistent/pre", "--head", "nonsense", "--out", "/nonexistent/run"]):
        _, probe = _probe(argv)
        assert "torch" not in probe and "CODE=2" in probe, (argv, probe)
    _, probe = _probe(["eval", "relight", "/nonexistent/sessions", "--backend", "torch", "--checkpoint", __file__])
    assert "CODE=2" in probe, probe  # a file that is not a checkpoint: refused, also without torch
    assert "torch" not in probe, probe
