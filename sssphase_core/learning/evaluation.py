"""Evaluation of what was learned: kNN with view-level leave-one-out, footprint metrics, PCA-RGB maps.

Plots of them are in :mod:`sssphase_core.reporting.figures`; throughput in :mod:`sssphase_core.bench.learn_bench`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from sssphase_core.errors import InputError
from sssphase_core.learning.data import crop_patches, pad_for_patches, to_channels_first
from sssphase_core.learning.losses import ssim_map
from sssphase_core.learning.metrics import MSE_FLOOR, psnr
from sssphase_core.tables import Table

# --- embeddings ----------------------------------------------------------------------------------


@torch.no_grad()
def embed_pixels(encoder: torch.nn.Module, psp: np.ndarray, pixels: np.ndarray, *, batch_size: int = 256,
                 device: str | torch.device = "cpu") -> np.ndarray:
    """(N, D) frozen-encoder embeddings of the patches around ``pixels`` of one (8, H, W, 3) PSP stack."""
    encoder = encoder.eval().to(device)
    k = encoder.preset.patch
    stack = pad_for_patches(to_channels_first(psp), k)  # once, not per batch
    out = [encoder(crop_patches(stack, pixels[i : i + batch_size], k, padded=True).to(device)).float().cpu()
           for i in range(0, len(pixels), batch_size)]
    return torch.cat(out).numpy() if out else np.zeros((0, encoder.preset.embed_dim), np.float32)


# --- kNN -----------------------------------------------------------------------------------------


def knn_predict(query: torch.Tensor, db: torch.Tensor, db_labels: torch.Tensor, n_classes: int, k: int,
                vote: str, temperature: float = 0.07, chunk: int = 2048) -> torch.Tensor:
    """Labels of L2-normalised ``query`` rows by cosine kNN over ``db``.

    ``majority``: most frequent label among the k nearest (ties go to the larger summed similarity);
    ``weighted``: votes weighted by exp(similarity / temperature) (Wu et al. 2018).
    """
    if vote not in ("majority", "weighted"):
        raise InputError(f"unknown vote {vote!r} (majority or weighted)")
    k = min(k, len(db))
    preds = []
    for i in range(0, len(query), chunk):
        sim, nn_idx = (query[i : i + chunk] @ db.T).topk(k, dim=1)
        labels = db_labels[nn_idx]
        w = torch.ones_like(sim) + 1e-3 * sim if vote == "majority" else torch.exp(sim / temperature)
        scores = torch.zeros(len(sim), n_classes, dtype=w.dtype).scatter_add_(1, labels, w)
        preds.append(scores.argmax(dim=1))
    return torch.cat(preds)


def scorable_classes(labels: np.ndarray, views: np.ndarray) -> np.ndarray:
    """The classes of ``labels`` (N,) non-negative ints with patches in two or more of ``views`` (N,): the only
    ones view-level leave-one-out can score (an object's only view left out leaves nothing of it to match)."""
    labels, views = np.asarray(labels, np.int64), np.asarray(views, np.int64)
    span = int(views.max(initial=0)) + 1
    class_of_each_view = np.unique(labels * span + views) // span  # one entry per (class, view) pair
    return np.flatnonzero(np.bincount(class_of_each_view) > 1)


def knn_leave_one_view_out(embeddings: np.ndarray, labels: np.ndarray, views: np.ndarray, *, k: int = 20,
                           vote: str = "majority", class_names: Sequence[str] | None = None) -> dict:
    """View-level leave-one-out: all patches of one view are queries, the other views the database.

    A query whose class has no patch in its fold's database (an object seen in only one view) cannot be
    classified by any embedding: it is left out of every score and counted in ``unscored`` ({class: patches}).
    Returns overall accuracy (over the scored held-out patches), mean per-view accuracy, per-view and
    per-class accuracy (keys are ``class_names`` when given), ``unscored`` and every patch's prediction.
    """
    emb = torch.nn.functional.normalize(torch.as_tensor(embeddings, dtype=torch.float32), dim=1)
    lab = torch.as_tensor(labels, dtype=torch.long)
    labels, views = np.asarray(labels), np.asarray(views)
    uniq = np.unique(views)
    if len(uniq) < 2:
        raise InputError("view-level leave-one-out needs patches from at least two views")
    n_classes = int(lab.max()) + 1
    pred = torch.empty_like(lab)
    for v in uniq:
        q = views == v
        pred[torch.as_tensor(q)] = knn_predict(emb[q], emb[~q], lab[~q], n_classes, k, vote)
    scored = np.isin(labels, scorable_classes(labels, views))
    name = (lambda c: class_names[c]) if class_names is not None else (lambda c: int(c))
    unscored = {name(c): int(np.count_nonzero(~scored & (labels == c))) for c in np.unique(labels[~scored])}
    if len(np.unique(labels[scored])) < 2:  # one scored class: each fold's vote is all but always right
        raise InputError("view-level leave-one-out scores only classes seen in two or more views and needs two of them "
                         f"to tell apart; these patches have {len(np.unique(labels[scored]))}")
    correct = (pred.numpy() == labels) & scored
    per_view = {int(v): float(correct[views == v].sum() / scored[views == v].sum())
                for v in uniq if scored[views == v].any()}
    per_class = {name(c): float(correct[labels == c].mean()) for c in np.unique(labels[scored])}
    return {"overall": float(correct.sum() / scored.sum()), "mean_per_view": float(np.mean(list(per_view.values()))),
            "per_view": per_view, "per_class": per_class, "unscored": unscored, "k": k, "vote": vote,
            "pred": pred.numpy()}


def knn_of_views(encoder: torch.nn.Module, views: Sequence, objects: Sequence[str], *, label: str = "object",
                 material_names: Sequence[str] | None = None, ks: Sequence[int] = (20,),
                 vote: str = "majority", device: str | torch.device = "cpu") -> dict[int, dict]:
    """The kNN table of frozen embeddings of every pixel of ``views`` (``data.View``), per k.

    ``label``: ``object`` (classes ``objects``, the paper's Table 2) or ``material`` (classes
    ``material_names``; pixels of no known material are left out). Views are the leave-one-out unit
    (:func:`knn_leave_one_view_out`); predictions are dropped from the results. ``device``: where the
    encoder embeds the patches.
    """
    from sssphase_core.learning.data import PatchDataset

    if label not in ("object", "material"):
        raise InputError(f"the kNN label must be object or material, got {label!r}")
    class_names = list(objects) if label == "object" else material_names
    ds = PatchDataset(views, encoder.preset.patch, objects)
    emb = np.concatenate([embed_pixels(encoder, v.psp, v.pixels, device=device) for v in views])
    labels = ds.labels(label)
    keep = labels >= 0
    if class_names is not None and keep.any() and int(labels[keep].max()) >= len(class_names):
        from sssphase_core.errors import DataError

        bad = sorted({v.object for v in views if v.materials.size and int(v.materials.max()) >= len(class_names)})
        raise DataError(f"the material labels (gt/labels) of {', '.join(bad) or 'the views'} reach "
                        f"{int(labels[keep].max())}, past the {len(class_names)} known materials: the sessions' labels "
                        "are damaged (kNN by --label object needs none)")
    out = {}
    for k in ks:
        res = knn_leave_one_view_out(emb[keep], labels[keep], ds.labels("view")[keep], k=k, vote=vote,
                                     class_names=class_names)
        res.pop("pred")
        out[k] = res
    return out


# --- footprint metrics ---------------------------------------------------------------------------


def footprint_metrics(pred: np.ndarray, target: np.ndarray, *, data_range: float = 1.0) -> dict[str, np.ndarray]:
    """Per-footprint metrics of (N, K, K, 3) arrays in linear camera units.

    ``mse``; ``psnr`` = 10 log10(data_range^2 / mse) with ``data_range`` 1 (the paper's convention:
    a white reference reads 1.0); ``ssim`` with data range = the footprint's own GT peak (see
    ``losses.ssim_map``); ``ssim_r1`` with data range 1 like the authors' code (nearly blind on
    footprints that peak at ~0.04, reported only for comparison); ``lpips`` (each footprint shown with
    its GT peak as white) when the LPIPS weights are on this machine.
    """
    p = torch.as_tensor(np.asarray(pred, np.float32)).permute(0, 3, 1, 2)
    t = torch.as_tensor(np.asarray(target, np.float32)).permute(0, 3, 1, 2)
    mse = ((p - t) ** 2).mean(dim=(1, 2, 3))
    from kornia.metrics import ssim as kornia_ssim

    out = {
        "mse": mse.numpy(),
        "psnr": psnr(mse.clamp_min(MSE_FLOOR).numpy(), data_range),
        "ssim": ssim_map(p, t).mean(dim=(1, 2, 3)).numpy(),
        "ssim_r1": kornia_ssim(p, t, 11, max_val=data_range).mean(dim=(1, 2, 3)).numpy(),
    }
    from sssphase_core.learning import lpips

    if lpips.available()[0]:  # with the weights on this machine (see sssphase_core.learning.lpips)
        out["lpips"] = lpips.lpips_footprints(np.asarray(pred, np.float32), np.asarray(target, np.float32))
    return out


def summarise(metrics: dict[str, np.ndarray]) -> dict[str, float]:
    """Means; PSNR is recomputed from the mean MSE (aggregate PSNR, as for a whole test set)."""
    out = {k: float(np.mean(v)) for k, v in metrics.items()}
    out["psnr"] = psnr(max(out["mse"], MSE_FLOOR))
    return out


# --- PCA-RGB -------------------------------------------------------------------------------------


def pca_rgb(embeddings: Sequence[np.ndarray], *, percentiles: tuple[float, float] = (1.0, 99.0)) -> list[np.ndarray]:
    """Joint PCA of several images' (N_i, D) embeddings; first 3 components -> RGB in [0, 1] (N_i, 3).

    Each component is stretched between the given percentiles over all images jointly, so colours
    are comparable across the images shown together. The sign of each component is fixed so its
    largest-magnitude loading is positive (deterministic colours).
    """
    x = torch.as_tensor(np.concatenate(embeddings), dtype=torch.float64)
    if len(x) < 3:
        raise InputError("PCA-RGB needs at least 3 embedded pixels")
    x = x - x.mean(dim=0)
    _, _, vt = torch.linalg.svd(x, full_matrices=False)
    comps = vt[:3]
    comps = comps * torch.sign(comps.gather(1, comps.abs().argmax(dim=1, keepdim=True)))
    proj = (x @ comps.T).numpy()
    if proj.shape[1] < 3:
        proj = np.pad(proj, ((0, 0), (0, 3 - proj.shape[1])))
    lo, hi = np.percentile(proj, percentiles, axis=0)
    rgb = np.clip((proj - lo) / np.maximum(hi - lo, 1e-12), 0, 1).astype(np.float32)
    return np.split(rgb, np.cumsum([len(e) for e in embeddings])[:-1])


def paint(shape: tuple[int, int], pixels: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """(H, W, 3) image, black except at ``pixels``."""
    img = np.zeros((*shape, 3), np.float32)
    img[pixels[:, 0], pixels[:, 1]] = colours
    return img


def pca_maps(encoder, views: Sequence[tuple[np.ndarray, np.ndarray]], stride: int) -> list[np.ndarray]:
    """PCA-RGB maps of several views embedded together: ``views`` = (psp (8, H, W, 3), pixels (N, 2) y, x)
    -> one (ceil(H/stride), ceil(W/stride), 3) map per view, black where no pixel was embedded."""
    grids = [px[(px[:, 0] % stride == 0) & (px[:, 1] % stride == 0)] for _, px in views]
    embs = [embed_pixels(encoder, psp, px) for (psp, _), px in zip(views, grids, strict=True)]
    maps = []
    for (psp, _), px, rgb in zip(views, grids, pca_rgb(embs), strict=True):
        h, w = psp.shape[1:3]
        maps.append(paint((-(-h // stride), -(-w // stride)), px // stride, rgb))
    return maps


PCA_TITLE = "PCA-RGB of encoder embeddings: components 1-3 as R, G, B, one joint PCA over the objects shown"


# --- tables --------------------------------------------------------------------------------------


def knn_tables(results: dict[str, dict], *, label: str, ks: Sequence[int], vote: str, views: str) -> list[Table]:
    """The paper's Table 2 from :func:`knn_of_views` results per run (``{run: result at ks[0]}``, each with
    ``overall_by_k``): accuracy (%) per class, overall and mean per view; with several k, overall against k."""
    runs = list(results)
    unscored = sorted({c for r in results.values() for c in r.get("unscored", {})}, key=str)
    classes = sorted({c for r in results.values() for c in r["per_class"]} | set(unscored), key=str)
    pct = lambda v: f"{100 * v:.2f}"  # noqa: E731
    note = (f"n/a: {', '.join(map(str, unscored))} in one view only; leaving that view out leaves no patch of its "
            f"{label} to match, so {'it is' if len(unscored) == 1 else 'they are'} left out of every score"
            if unscored else "")
    main = Table(f"kNN accuracy (%), k={ks[0]}, {vote} vote, view-level leave-one-out over views {views}",
                 [label.capitalize(), *runs], note=note)
    main.rows += [[c, *("n/a" if c not in r["per_class"] else pct(r["per_class"][c]) for r in results.values())]
                  for c in classes]
    main.rows.append(["**overall**", *(pct(r["overall"]) for r in results.values())])
    main.rows.append(["**mean per view**", *(pct(r["mean_per_view"]) for r in results.values())])
    tables = [main]
    if len(ks) > 1:
        tables.append(Table("Overall accuracy (%) against k", ["k", *runs],
                            [[kk, *(pct(r["overall_by_k"][kk]) for r in results.values())] for kk in ks]))
    return tables


def footprint_table(results: dict[str, dict[str, dict[str, float]]], *, views: str, note: str = "") -> Table:
    """The paper's Table 1 from ``{object: {source: summarise(...)}}``: MSE x 1e-5, PSNR, SSIM (and LPIPS
    when every entry has it) per object and footprint source."""
    sources = list(next(iter(results.values()), {}))
    with_lpips = all("lpips" in r for res in results.values() for r in res.values())
    metrics = [("MSE×1e-5", "mse", 1e5, ".2f"), ("PSNR", "psnr", 1, ".2f"), ("SSIM", "ssim", 1, ".3f")]
    metrics += [("LPIPS", "lpips", 1, ".3f")] if with_lpips else []
    table = Table(f"Footprint reconstruction on views {views}", ["Object"] + [f"{b} {m[0]}" for b in sources for m in metrics],
                  note=note)
    table.rows += [[obj, *(format(res[b][key] * scale, fmt) for b in sources for _n, key, scale, fmt in metrics)]
                   for obj, res in results.items()]
    return table
