"""Figures a person can read: every PNG the CLI writes as a figure has a title, and every value map in it
has a colour bar (category maps carry a legend)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner


@pytest.fixture
def saved_figures(monkeypatch):
    """Record every matplotlib figure saved: (path, titles, images mapped through a colour map without a bar, legends)."""
    from matplotlib.figure import Figure

    records = []
    original = Figure.savefig

    def spy(self, fname, *args, **kwargs):
        titles = [ax.get_title() for ax in self.axes if ax.get_title()] + ([self._suptitle.get_text()] if self._suptitle else [])
        images = [im for ax in self.axes for im in ax.get_images() if im.get_array().ndim == 2]
        barred = {id(im.norm) for im in images if im.colorbar is not None}  # panels may share one bar and norm
        unbarred = [im for im in images if id(im.norm) not in barred]
        legends = [ax.get_legend() for ax in self.axes if ax.get_legend() is not None]
        path = Path(str(fname))  # figures are saved under a temporary name and renamed (store.files.save_figure)
        final = re.fullmatch(r"\.(.+)\.\d+-[0-9a-f]+\.tmp\.\w+", path.name)
        records.append({"path": str(path.with_name(final.group(1)) if final else path), "titles": titles,
                        "unbarred": unbarred, "legends": legends})
        return original(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", spy)
    return records


def test_every_png_of_sss_sim_is_a_titled_figure_with_colour_bars_or_legends(saved_figures, tmp_path):
    app = importlib.import_module("sssphase_cli.main").app
    res = CliRunner().invoke(app, ["sim", "--object", "leaf", "--views", "1", "--out", str(tmp_path)], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    pngs = sorted(str(p) for p in tmp_path.rglob("*.png"))
    assert len(pngs) >= 19 and sorted(r["path"] for r in saved_figures) == pngs  # every PNG went through a figure
    for r in saved_figures:
        assert r["titles"], r["path"]
        assert not r["unbarred"], f"{r['path']}: a value map without a colour bar"
    by_name = {r["path"].rsplit("/", 1)[-1]: r for r in saved_figures}
    for name in ("material.png", "reason.png", "mask.png"):
        labels = [t.get_text() for t in by_name[name]["legends"][0].get_texts()]
        assert labels, name
    assert "leaf" in [t.get_text() for t in by_name["material.png"]["legends"][0].get_texts()]


def test_label_colours_follow_the_label_not_its_rank(tmp_path):
    from PIL import Image

    from sssphase_core.reporting.figures import label_figure

    names = {0: "valid", 3: "shadow", 5: "outside"}
    a = np.array([[0, 3], [3, 0]], np.int16).repeat(40, 0).repeat(40, 1)
    b = np.array([[3, 5], [5, 3]], np.int16).repeat(40, 0).repeat(40, 1)
    colours = []
    for labels, path in ((a, tmp_path / "a.png"), (b, tmp_path / "b.png")):
        label_figure(path, labels, names, "t")
        img = np.asarray(Image.open(path).convert("RGB"))
        colours.append({tuple(c) for c in img.reshape(-1, 3)})
    from matplotlib import colormaps

    shadow = tuple(int(round(v * 255)) for v in colormaps["tab10"](3)[:3])
    assert all(any(np.abs(np.subtract(c, shadow)).max() <= 1 for c in cs) for cs in colours)


def test_a_small_image_is_enlarged_without_smoothing(tmp_path):
    from PIL import Image

    from sssphase_core.reporting.figures import image_figure

    img = np.zeros((12, 16, 3), np.float32)
    img[::2, ::2] = 1.0  # a one-pixel checker: smoothing would make greys
    image_figure(tmp_path / "x.png", img, "checker")
    out = np.asarray(Image.open(tmp_path / "x.png").convert("L"))
    assert out.shape[1] >= 400
    core = out[out.shape[0] // 3: 2 * out.shape[0] // 3, out.shape[1] // 3: 2 * out.shape[1] // 3]
    assert ((core < 8) | (core > 247)).mean() > 0.97
