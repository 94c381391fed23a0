"""`sss bench sim`: one view's whole capture plan rendered by the simulator on a torch device (a GPU)
against its numpy path measured in the same run, the camera's sensor per frame, and the two paths'
footprints and images compared."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from sssphase_core.bench.sim_bench import render_speed
from sssphase_core.sim.rig import rig_preset, with_transport
from sssphase_core.sim.scene import SimScene

#: Frames rendered together, as the sim device plugin batches a 1080p plan (RENDER_BATCH_BYTES).
BATCH = 10


def _sync(device: Any) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def run(*, device: str, preset: str = "paper", object_name: str = "soap", cpu_pixels: int = 20000,
        compare_pixels: int = 256, dot_sample: int = 200, progress: Callable[[str], None] | None = None,
        transport: str = "burley") -> dict[str, Any]:
    """The benchmark's result: the plan's render time on ``device``, the sensor there and in numpy (PSP, unwrapping, white/black and the dot
    grids, noise-free; ``dot_sample`` dot frames rendered and the rest extrapolated: they cost the same each),
    the numpy path's time for the same view (extrapolated from ``cpu_pixels`` lit pixels), one frame through
    the sensor, and the largest differences between the paths, with light transport ``transport`` (burley or
    radiative: the ported ones)."""
    from sssphase_core.capture.plan import dot_spacing_for
    from sssphase_core.compute import compute_device
    from sssphase_core.processing.patterns import capture_plan
    from sssphase_core.sim_accel import transport_factory

    say = progress or (lambda _m: None)
    dev = compute_device(device)
    rig = with_transport(rig_preset(preset), transport)
    w, h = rig.projector.width, rig.projector.height
    plan = capture_plan(w, h, footprints=True, dot_spacing=dot_spacing_for(rig.patch), references=("white", "black"))
    say(f"tracing {object_name} at {rig.camera.width}x{rig.camera.height}")
    t0 = time.perf_counter()
    scene = SimScene(object_name, rig=rig, transport_factory=transport_factory(dev))
    trace_s = time.perf_counter() - t0
    cpu_scene = SimScene(object_name, rig=rig)  # the numpy path on the same geometry

    frames = list(plan.frames)
    n_dots = sum(f.kind == "dots" for f in frames)
    rendered = [f for f in frames if f.kind != "dots"] + [f for f in frames if f.kind == "dots"][:dot_sample]
    sampled = sum(f.kind == "dots" for f in rendered)
    say(f"rendering {len(rendered)} of the plan's {len(frames)} frames on {dev}")
    t0 = time.perf_counter()
    psp_s = dots_s = 0.0
    first: np.ndarray | None = None
    for start in range(0, len(rendered), BATCH):
        batch = rendered[start:start + BATCH]
        t1 = time.perf_counter()
        images = scene.render(np.stack([f.pattern() for f in batch]))
        _sync(dev)
        spent = time.perf_counter() - t1
        if all(f.kind == "dots" for f in batch):
            dots_s += spent
        else:
            psp_s += spent
        if first is None:
            first = images
    dots_s *= n_dots / max(sampled, 1)
    render_s = psp_s + dots_s

    say("the numpy path on the same view (extrapolated)")
    cpu = render_speed(preset, object_name, max_pixels=cpu_pixels, transport=transport)
    say("one frame through the sensor (CPU)")
    rng = np.random.default_rng(0)
    scene.sense(first[:1], rng)  # the first call imports the ISP's packages
    t0 = time.perf_counter()
    scene.sense(first[:1], rng)
    sense_s = time.perf_counter() - t0
    from sssphase_core.sim_accel import DeviceSensor

    device_sense_s = None
    if DeviceSensor.handles(rig.sensor):
        sensor = DeviceSensor(dev)
        sensor.sense(first[:1], rig.sensor, rng)  # warm-up
        _sync(dev)
        t0 = time.perf_counter()
        sensor.sense(first[:1], rig.sensor, rng)
        _sync(dev)
        device_sense_s = time.perf_counter() - t0

    say("comparing footprints and images with the numpy path")
    lit = np.argwhere(scene.lit)
    pick = lit[np.random.default_rng(1).choice(len(lit), min(compare_pixels, len(lit)), replace=False)]
    fa, fb = cpu_scene.footprints(pick), scene.footprints(pick)
    # images: the same sources splatted by both paths (a whole 1080p view takes minutes in numpy)
    src = cpu_scene.transport.lit_index[np.random.default_rng(2).choice(len(lit), min(4 * compare_pixels, len(lit)),
                                                                         replace=False)]
    light = cpu_scene.emitted(np.stack([f.pattern() for f in frames[:2]]), pixels=src)
    ia = cpu_scene.transport.splat(src, np.ascontiguousarray(light))
    ib = scene.transport.splat(src, np.ascontiguousarray(light))
    return {"device": str(dev), "preset": preset, "object": object_name, "transport": rig.transport, "camera": f"{rig.camera.width}x{rig.camera.height}",
            "patch": rig.patch, "frames": len(frames), "dot_frames": n_dots, "dot_frames_rendered": sampled,
            "lit_pixels": int(len(lit)), "trace_s": trace_s, "render_s": render_s, "render_psp_s": psp_s,
            "render_dots_s": dots_s, "numpy_psp_white_s": cpu["render_s"], "numpy_psp_white_frames": cpu["frames"],
            "numpy_extrapolated": cpu["extrapolated"], "sense_frame_s": sense_s, "device_sense_frame_s": device_sense_s,
            "footprint_max_rel_diff": float(np.abs(fa - fb).max() / max(float(np.abs(fa).max()), 1e-30)),
            "image_max_rel_diff": float(np.abs(ia - ib).max() / max(float(np.abs(ia).max()), 1e-30))}


def markdown(r: dict[str, Any]) -> str:
    per = r["render_psp_s"] / max(1, r["frames"] - r["dot_frames"])
    cpu_per = r["numpy_psp_white_s"] / r["numpy_psp_white_frames"]
    return "\n".join([
        f"`sss bench sim` on {r['device']}: {r['object']} at the `{r['preset']}` preset ({r['camera']}, K = {r['patch']}, "
        f"{r['lit_pixels']:,} lit pixels), {r.get('transport', 'burley')} transport", "",
        "| what | seconds |", "|---|---|",
        f"| trace the view (CPU) | {r['trace_s']:.1f} |",
        f"| render the whole plan, noise-free: {r['frames']:,} frames ({r['dot_frames']:,} dot grids) | {r['render_s']:.1f} |",
        f"| ... of which the fringe, white and black frames | {r['render_psp_s']:.1f} ({per:.3f} per frame) |",
        f"| ... of which the dot grids ({r['dot_frames_rendered']:,} rendered, the rest extrapolated) | {r['render_dots_s']:.1f} |",
        f"| the numpy path, 8 PSP + white frames (same run, extrapolated) | {r['numpy_psp_white_s']:.1f} ({cpu_per:.2f} per frame: "
        f"{cpu_per / per:.3g}x the device's) |",
        f"| one frame through the sensor (noise, Bayer, ISP; numpy on the CPU) | {r['sense_frame_s']:.2f} |",
        f"| ... through the sensor on {r['device']} (sim_accel.DeviceSensor; its frame back on the host) | "
        + (f"{r['device_sense_frame_s']:.3f} |" if r.get("device_sense_frame_s") is not None else "not this camera |"), "",
        f"Device against numpy: footprints differ by at most {r['footprint_max_rel_diff']:.1e} of their peak, images by "
        f"{r['image_max_rel_diff']:.1e}.", ""])
