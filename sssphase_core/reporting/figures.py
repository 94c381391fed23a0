"""Figures a person can read: every PNG has a title; maps of values have a colour bar with units,
maps of categories a legend; small images are enlarged with nearest-neighbour (no smoothing).

Images are (H, W) value maps, (H, W) integer label maps or (H, W, 3) RGB in [0, 1]. NaN is drawn black.
Data images (patterns to project, relit images) are not figures and are written elsewhere as they are.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from sssphase_core.store.files import save_figure

MIN_WIDTH_IN = 4.0  # small images are enlarged to at least this width on the page
MAX_WIDTH_IN = 16.0
DPI = 110


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _panel_size(shape: tuple[int, ...], n: int = 1, *, side: float = 0.0) -> tuple[float, float]:
    """Figure size (inches) for ``n`` panels of ``shape`` plus ``side`` inches for a colour bar or legend."""
    h, w = shape[:2]
    panel = min(max(MIN_WIDTH_IN / min(n, 2), w / DPI), MAX_WIDTH_IN / n)
    return n * panel + side, panel * h / w + 0.9


def _title(text: str, width: int = 60) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)) or text


def _save(fig, path: Path | str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, dpi=DPI)
    _pyplot().close(fig)
    return path


def image_figure(path: Path | str, image: np.ndarray, title: str) -> Path:
    """An RGB (H, W, 3) image in [0, 1] (display-encoded) with a title."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=_panel_size(image.shape), constrained_layout=True)
    ax.imshow(np.clip(np.nan_to_num(np.asarray(image, np.float32)), 0, 1), interpolation="nearest")
    ax.set_title(_title(title, 45), fontsize=10)
    ax.axis("off")
    return _save(fig, path)


def value_figure(path: Path | str, values: np.ndarray, title: str, *, units: str, cmap: str = "viridis",
                 vmin: float | None = None, vmax: float | None = None, log: bool = False) -> Path:
    """A value map (H, W) through ``cmap`` with a colour bar labelled ``units`` (NaN black)."""
    import matplotlib.colors as mcolors

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=_panel_size(values.shape, side=1.3), constrained_layout=True)
    cm = plt.get_cmap(cmap).with_extremes(bad="black")
    finite = values[np.isfinite(values)]
    lo = vmin if vmin is not None else (float(finite.min()) if finite.size else 0.0)
    hi = vmax if vmax is not None else (float(finite.max()) if finite.size else 1.0)
    norm = mcolors.LogNorm(max(lo, 1e-12), max(hi, 2e-12)) if log else mcolors.Normalize(lo, hi if hi > lo else lo + 1)
    im = ax.imshow(np.ma.masked_invalid(values), cmap=cm, norm=norm, interpolation="nearest")
    ax.set_title(_title(title), fontsize=10)
    ax.axis("off")
    fig.colorbar(im, ax=ax, shrink=0.85, label=units)
    return _save(fig, path)


def label_figure(path: Path | str, labels: np.ndarray, names: Mapping[int, str], title: str, *,
                 other: str = "other") -> Path:
    """A label map (H, W) of integers; each label in ``names`` gets a colour and a legend entry, others black (in the
    legend as ``other`` where there are any)."""
    import matplotlib.patches as mpatches

    plt = _pyplot()
    palette = plt.get_cmap("tab10" if max(names, default=0) < 10 else "tab20")
    colour = {v: palette(v % palette.N)[:3] for v in names}  # by label value: the same colour in every figure
    shown = [int(v) for v in np.unique(labels) if int(v) in names]
    rgb = np.zeros((*labels.shape, 3))
    for value in shown:
        rgb[labels == value] = colour[value]
    fig, ax = plt.subplots(figsize=_panel_size(labels.shape, side=1.9), constrained_layout=True)
    ax.imshow(rgb, interpolation="nearest")
    ax.set_title(_title(title), fontsize=10)
    ax.axis("off")
    handles = [mpatches.Patch(color=colour[v], label=names[v]) for v in shown]
    if not np.isin(labels, list(names)).all():
        handles.append(mpatches.Patch(facecolor="black", edgecolor="grey", label=other))
    if handles:
        ax.legend(handles=handles, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8, frameon=False)
    return _save(fig, path)


def panels_figure(path: Path | str, images: Sequence[np.ndarray], titles: Sequence[str], title: str, *,
                  units: str | None = None, cmap: str = "magma", vmin: float | None = None,
                  vmax: float | None = None) -> Path:
    """Images side by side with one title each: RGB panels as they are, value panels through ``cmap``
    with a shared colour bar labelled ``units``."""
    import matplotlib.colors as mcolors

    plt = _pyplot()
    n = len(images)
    fig, axes = plt.subplots(1, n, figsize=_panel_size(images[0].shape, n, side=1.3 if units else 0.0),
                             constrained_layout=True, squeeze=False)
    im = None
    values = [np.asarray(i) for i in images if np.asarray(i).ndim == 2]
    if values:
        finite = np.concatenate([v[np.isfinite(v)] for v in values]) if values else np.zeros(1)
        norm = mcolors.Normalize(vmin if vmin is not None else float(finite.min(initial=0.0)),
                                 vmax if vmax is not None else float(finite.max(initial=1.0)))
    for ax, img, sub in zip(axes[0], images, titles, strict=True):
        img = np.asarray(img)
        if img.ndim == 2:
            cm = plt.get_cmap(cmap).with_extremes(bad="black")
            im = ax.imshow(np.ma.masked_invalid(img), cmap=cm, norm=norm, interpolation="nearest")
        else:
            ax.imshow(np.clip(np.nan_to_num(img.astype(np.float32)), 0, 1), interpolation="nearest")
        ax.set_title(sub, fontsize=8)
        ax.axis("off")
    fig.suptitle(_title(title, max(30, int(11 * fig.get_figwidth()))), fontsize=10)  # ~11 characters an inch at 10 pt
    if im is not None and units:
        fig.colorbar(im, ax=list(axes[0]), shrink=0.8, label=units)
    return _save(fig, path)


def grid_figure(path: Path | str, rows: Sequence[Sequence[np.ndarray]], row_titles: Sequence[str],
                col_titles: Sequence[str], title: str, *, units: str, cmap: str = "magma",
                vmin: float | None = None, vmax: float | None = None) -> Path:
    """Value maps in a grid (one row per method, one column per sample), one shared colour bar."""
    import matplotlib.colors as mcolors

    plt = _pyplot()
    n_rows, n_cols = len(rows), len(rows[0])
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(1.6 * n_cols + 1.8, 1.6 * n_rows + 0.8),
                             constrained_layout=True, squeeze=False)
    finite = np.concatenate([np.asarray(v)[np.isfinite(v)].ravel() for row in rows for v in row] or [np.zeros(1)])
    norm = mcolors.Normalize(vmin if vmin is not None else float(finite.min(initial=0.0)),
                             vmax if vmax is not None else float(finite.max(initial=1.0)))
    cm = plt.get_cmap(cmap).with_extremes(bad="black")
    im = None
    for r, row in enumerate(rows):
        for c, img in enumerate(row):
            ax = axes[r][c]
            im = ax.imshow(np.ma.masked_invalid(img), cmap=cm, norm=norm, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(col_titles[c], fontsize=8)
            if c == 0:
                ax.set_ylabel(row_titles[r], fontsize=9)
    fig.suptitle(_title(title, 30 * n_cols), fontsize=10)
    fig.colorbar(im, ax=axes, shrink=0.8, label=units)
    return _save(fig, path)


def profiles_figure(path: Path | str, curves: Mapping[str, np.ndarray], col_titles: Sequence[str], title: str, *,
                    xlabel: str, ylabel: str, log: bool = True) -> Path:
    """One subplot per sample, one line per method: ``curves[name]`` is (N samples, K points) centred on 0."""
    plt = _pyplot()
    n = len(col_titles)
    fig, axes = plt.subplots(1, n, figsize=(2.4 * n + 0.6, 2.8), constrained_layout=True, squeeze=False, sharey=True)
    for c, ax in enumerate(axes[0]):
        for name, values in curves.items():
            y = np.asarray(values[c], np.float64)
            x = np.arange(len(y)) - len(y) // 2
            # markers: a delta footprint (no scattering) is one point, and isolated positive samples of a noisy
            # crop between values <= 0 (not drawn on a log axis) stay visible
            ax.plot(x, np.where(y > 0, y, np.nan) if log else y, label=name, lw=1.2, marker=".", ms=3)
        ax.set_title(col_titles[c], fontsize=8)
        ax.set_xlabel(xlabel, fontsize=8)
        if log:
            ax.set_yscale("log")
    axes[0][0].set_ylabel(ylabel, fontsize=8)
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.suptitle(_title(title, 30 * n), fontsize=10)
    return _save(fig, path)


# --- training curves and footprint profiles ------------------------------------------------------


def plot_profiles(gt: np.ndarray, pred: np.ndarray, path: Path | str, *, title: str = "") -> None:
    """Centre row of one (K, K, 3) footprint per channel: GT solid, prediction dotted; and the difference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = gt.shape[0]
    x = np.arange(k) - k // 2
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.2))
    for c, colour in enumerate("rgb"):
        a.plot(x, gt[k // 2, :, c], "-", color=colour, label=f"GT {colour.upper()}")
        a.plot(x, pred[k // 2, :, c], ":", color=colour, lw=2, label=f"pred {colour.upper()}")
        b.plot(x, pred[k // 2, :, c] - gt[k // 2, :, c], color=colour)
    a.set(xlabel="offset (px)", ylabel="linear camera units", title=title or "footprint profile")
    b.set(xlabel="offset (px)", title="prediction - GT")
    a.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def plot_metric_vs_time(metrics_path: Path | str, keys: str | Sequence[str], out: Path | str, *, log: bool = True,
                        ylabel: str | None = None, right: Sequence[str] = (), right_label: str = "",
                        chance: float | None = None, title: str | None = None,
                        reference: tuple[str, float] | None = None, right_span: float = 0.0) -> None:
    """Error against run time: each of ``keys`` (and ``right`` on a second axis) of the metrics.jsonl rows
    against their cumulative ``wall_s``, with a legend; ``chance`` draws the chance level, ``reference``
    (label, value) a baseline measured in the same run. The second axis spans at least ``right_span`` (a change of
    0.01 dB was drawn corner to corner)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [keys] if isinstance(keys, str) else list(keys)
    from sssphase_core.errors import InputError
    from sssphase_core.learning.runlog import read_rows

    rows = read_rows(Path(metrics_path))
    if not any(keys[0] in r for r in rows):
        raise InputError(f"no {keys[0]!r} in {metrics_path}")
    fig, ax = plt.subplots(figsize=(6, 3.6))
    lines = []
    for key in keys:
        rs = [r for r in rows if key in r]
        lines += ax.plot([r["wall_s"] for r in rs], [r[key] for r in rs], "o-", label=key)
    if chance is not None:
        lines.append(ax.axhline(chance, color="grey", ls="--", label=f"chance ({chance:.3g})"))
    if reference is not None:
        lines.append(ax.axhline(reference[1], color="tab:green", ls=":", label=f"{reference[0]} ({reference[1]:.3g})"))
    ax.set(xlabel="run time (s)", ylabel=ylabel or ", ".join(keys), title=title or f"{', '.join(keys)} against run time")
    if log and all(r[k] > 0 for k in keys for r in rows if k in r):
        ax.set_yscale("log")
    if right:
        twin = ax.twinx()
        for key, colour in zip(right, ("tab:red", "tab:purple", "tab:brown"), strict=False):
            rs = [r for r in rows if key in r]
            lines += twin.plot([r["wall_s"] for r in rs], [r[key] for r in rs], "s--", color=colour, label=key)
        twin.set_ylabel(right_label or ", ".join(right))
        low, high = twin.get_ylim()
        if high - low < right_span:
            middle = (low + high) / 2
            twin.set_ylim(middle - right_span / 2, middle + right_span / 2)
    ax.legend(handles=lines, fontsize=8, loc="best")
    fig.tight_layout()
    save_figure(fig, out, dpi=120)
    plt.close(fig)
