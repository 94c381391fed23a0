"""`sss sim`, the torch-free import rule, and the simulator benchmark helpers."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import typer
from PIL import Image
from typer.testing import CliRunner

from sssphase_cli import cmd_sim
from sssphase_core.errors import UnknownObjectError
from sssphase_core.reporting.sim_views import VIEW_FILES


def test_sim_and_isp_never_import_torch():
    code = ("import sys, numpy as np, sssphase_core.sim, sssphase_core.bench.sim_bench\n"
            "from sssphase_core.processing import isp\n"
            "isp.develop(np.zeros((8, 8), np.uint16), 0, 1.0)  # loads OpenCV\n"
            "assert 'torch' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.fixture(scope="module")
def app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:  # a group, as in the real CLI
        pass

    cmd_sim.register({"root": app, "bench": typer.Typer()})
    return app


def test_sim_command_writes_viewable_pngs(app, tmp_path):
    result = CliRunner().invoke(app, ["sim", "--object", "apple", "--views", "2", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    info = json.loads((tmp_path / "scene.json").read_text())
    assert info["object"]["name"] == "apple" and len(info["views"]) == 2
    assert {"apple_flesh", "apple_red"} <= set(info["object"]["materials_seen"])
    for view in (0, 1):
        vdir = tmp_path / f"view{view}"
        names = {p.stem for p in vdir.glob("*.png")}
        expected = {f"psp_{o}_s{n}" for o in "xy" for n in range(4)} | {"white", "mask", "proj_x", "proj_y", "material", "footprints"}
        assert expected <= names
        assert all(VIEW_FILES.fullmatch(f.name) for f in vdir.iterdir())  # a later run here removes them all
        psp = np.asarray(Image.open(vdir / "psp_x_s0.png").convert("L")).astype(float)
        assert psp.shape[1] >= 400  # the 256x192 frame enlarged into a titled figure
        h, w = psp.shape
        assert psp[h // 3: 2 * h // 3, w // 3: 2 * w // 3].std() > 20  # fringes visible on the object
        assert np.asarray(Image.open(vdir / "footprints.png").convert("L")).max() > 200
        decoded = info["views"][view]["decode"]
        assert decoded["valid_fraction"] > 0.9
        assert decoded["median_error_px"] < 0.2  # noisy capture decoded against the exact correspondences
        maps = np.load(vdir / "decoded.npz")
        assert np.isfinite(maps["xp"][maps["mask"]]).all() and np.isnan(maps["xp"][~maps["mask"]]).all()
        assert (maps["reason"][~maps["mask"]] > 0).all()


def test_sim_command_rejects_unknown_objects(app, tmp_path):
    result = CliRunner().invoke(app, ["sim", "--object", "banana", "--out", str(tmp_path)])
    assert isinstance(result.exception, UnknownObjectError)
    assert "apple" in str(result.exception)


def test_scatter_strategies_agree():
    from sssphase_core.bench.sim_bench import scatter_strategies

    out = scatter_strategies(n_pixels=200, n_patterns=3)
    assert out["agree"] and set(out["seconds"]) == {"sparse_csc", "bincount", "add_at"}
