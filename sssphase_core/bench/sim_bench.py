"""Simulator speed: frames per second of noise-free rendering at the CPU and paper (1080p) presets,
and the scatter-add strategies compared on the same footprints."""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse

from sssphase_core.sim.materials import MATERIALS, dropped_fraction
from sssphase_core.sim.rig import TRANSPORTS, pixel_pitch_mm, rig_preset, with_transport
from sssphase_core.sim.scene import SimScene


def _psp_and_white(width: int, height: int) -> np.ndarray:
    from sssphase_core.processing.patterns import paper_inputs, psp_config_for

    pats = paper_inputs(width, height, period=psp_config_for(width, height).period)
    return np.concatenate([pats, np.ones((1, height, width), np.float32)])


def render_speed(preset: str, object_name: str = "apple", max_pixels: int | None = None, seed: int = 0,
                 transport: str | None = None) -> dict:
    """Time one view's 8 PSP + white render (as a scene's first render, without the footprint cache), with the
    rig's light transport or ``transport`` (:data:`sssphase_core.sim.TRANSPORTS`).

    With ``max_pixels``, random subsets of ``max_pixels / 2`` and ``max_pixels`` lit pixels are
    rendered and the time is extrapolated linearly (fixed + per-pixel cost) to the whole view.
    """
    rig = with_transport(rig_preset(preset), transport)
    t0 = time.perf_counter()
    scene = SimScene(object_name, rig=rig)
    build_s = time.perf_counter() - t0
    pats = _psp_and_white(rig.projector.width, rig.projector.height)
    # As in the scene's first render: the unit-white image (black level) rides along as one more pattern.
    light = np.concatenate([scene.emitted(pats), scene.emitted(pats[-1:]) / (1 - rig.projector.black)], axis=1)
    tr = scene.transport
    n_lit = len(tr.lit_index)
    sizes = [n_lit] if max_pixels is None or max_pixels >= n_lit else [max_pixels // 2, max_pixels]
    rng = np.random.default_rng(seed)
    times = []
    tr.cache_bytes = 0  # time the computation, as without a cache (the paper preset never has one)
    for n in sizes:
        sel = np.sort(rng.choice(n_lit, n, replace=False))
        t0 = time.perf_counter()
        tr.splat(tr.lit_index[sel], np.ascontiguousarray(light[sel]))
        times.append(time.perf_counter() - t0)
    if len(sizes) == 1:
        render_s = times[0]
    else:
        per_pixel = max(times[1] - times[0], 0.0) / (sizes[1] - sizes[0])
        render_s = times[1] + per_pixel * (n_lit - sizes[1])
    return {
        "preset": preset,
        "object": object_name,
        "transport": rig.transport,
        "resolution": [rig.camera.width, rig.camera.height],
        "patch": rig.patch,
        "frames": len(pats),
        "pixels_lit": n_lit,
        "pixels_rendered": sizes[-1],
        "extrapolated": len(sizes) > 1,
        "scene_build_s": build_s,
        "render_s": render_s,
        "frames_per_s": len(pats) / render_s,
    }


def cached_render_speed(object_name: str = "apple", repeats: int = 3) -> dict:
    """CPU preset: seconds per 8 PSP + white render once the view's footprints are cached."""
    scene = SimScene(object_name, rig=rig_preset("cpu"))
    pats = _psp_and_white(scene.rig.projector.width, scene.rig.projector.height)
    scene.render(pats)
    t0 = time.perf_counter()
    for _ in range(repeats):
        scene.render(pats)
    render_s = (time.perf_counter() - t0) / repeats
    return {"preset": "cpu", "object": object_name, "frames": len(pats), "render_s": render_s,
            "frames_per_s": len(pats) / render_s}


def scatter_strategies(object_name: str = "apple", n_pixels: int = 2000, n_patterns: int = 9) -> dict:
    """Seconds to splat the same CPU-preset footprints for ``n_patterns`` patterns three ways:
    sparse CSC matrix product (used), ``np.bincount`` per pattern and channel, ``np.add.at``."""
    scene = SimScene(object_name, rig=rig_preset("cpu"))
    tr = scene.transport
    src = tr.lit_index[:n_pixels]
    light = np.random.default_rng(0).random((len(src), n_patterns, 3), dtype=np.float32)
    w = tr.weights(src)
    y, x = np.divmod(src, tr.w)
    rows = ((y * tr.wpad + x)[:, None] + tr._offsets[None, :]).ravel()
    size, kk = tr.hpad * tr.wpad, tr.k * tr.k
    times = {}

    t0 = time.perf_counter()
    indptr = np.arange(0, len(src) * kk + 1, kk, dtype=np.int32)
    out = np.zeros((3, size, n_patterns), np.float32)
    for c in range(3):
        out[c] += scipy.sparse.csc_array((w[c].ravel(), rows.astype(np.int32), indptr), shape=(size, len(src))) @ light[:, :, c]
    times["sparse_csc"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ref = np.zeros((3, n_patterns, size))
    for c in range(3):
        wc = w[c].reshape(len(src), kk)
        for p in range(n_patterns):
            ref[c, p] = np.bincount(rows, weights=(wc * light[:, p, c, None]).ravel(), minlength=size)
    times["bincount"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    acc = np.zeros((3, size, n_patterns), np.float32)
    for c in range(3):
        np.add.at(acc[c], rows, (w[c].reshape(len(src), kk, 1) * light[:, None, :, c]).reshape(-1, n_patterns))
    times["add_at"] = time.perf_counter() - t0

    agree = bool(np.allclose(out, ref.transpose(0, 2, 1), rtol=1e-4, atol=1e-7) and np.allclose(out, acc, rtol=1e-4, atol=1e-7))
    return {"entries": int(len(src) * kk), "patterns": n_patterns, "seconds": times, "agree": agree}


def dropped_energy(preset: str = "cpu") -> dict[str, list[float]]:
    """Per catalogue material, the RGB share of subsurface energy beyond the preset's patch (flat
    fronto-parallel surface at the turntable centre)."""
    rig = rig_preset(preset)
    pitch = pixel_pitch_mm(rig)
    return {name: [round(float(v), 5) for v in dropped_fraction(m.rate(rig.sss_scale), pitch, rig.patch)]
            for name, m in MATERIALS.items()}


def simulator_speed(paper_pixels: int | None = 20000, object_name: str = "apple") -> dict:
    """Frames per second at both presets (render of 8 PSP patterns + white for one view).

    The CPU preset is rendered in full; the paper preset on ``paper_pixels`` random lit pixels,
    scaled to the whole view (``None`` renders it in full: about two minutes on two cores).
    """
    cpu = render_speed("cpu", object_name)  # the preset's own transport (Burley): not timed twice below
    return {
        "cpu": cpu,
        "cpu_transports": {t: cpu if t == cpu["transport"] else render_speed("cpu", object_name, transport=t)
                           for t in TRANSPORTS},
        "cpu_cached": cached_render_speed(object_name),
        "paper": render_speed("paper", object_name, max_pixels=paper_pixels),
        "scatter": scatter_strategies(object_name),
        "dropped_energy": {preset: dropped_energy(preset) for preset in ("cpu", "paper")},
    }
