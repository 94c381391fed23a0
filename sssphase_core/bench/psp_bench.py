"""``sss bench psp``: PSP decoding speed against OpenCV, accuracy against exact correspondences,
and error against run time for different numbers of shifts and fringe periods.

Speed baseline: OpenCV's ``cv2.structured_light`` SinusoidalPattern (PSP method) computing a 3-step
wrapped phase map from 1080p frames, measured in the same run; a numpy float32 implementation of our
own formula is reported too (the torch-versus-numpy choice of ``sssphase_core.processing.psp``).
Accuracy: synthetic fringes with an exact affine correspondence (Gaussian blur standing in for
subsurface scattering, additive noise), and the simulated rig per object and exposure when
``sssphase_core.sim`` is present. Scattering bias: decoded correspondences against the exact ones
under both transport models, before and after removing the predicted scattering shift.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from sssphase_core.bench.output import Table, interleaved_seconds, machine_info, median_seconds
from sssphase_core.processing.patterns import (
    PSPConfig,
    period_ladder,
    phase_shift_pattern,
    psp_config_for,
    psp_key,
)
from sssphase_core.processing.psp import Correspondence, decode, wrapped_phase

SPEED_SIZE = (1920, 1080)
SYNTH_SIZE = (256, 192)
Progress = Callable[[str], None]


# ------------------------------------------------------------------------------------------ metrics


def correspondence_errors(
    corr: Correspondence, gt_x: np.ndarray, gt_y: np.ndarray, period: float
) -> dict[str, float]:
    """Errors of decoded correspondences against exact ones (NaN where the truth has none).

    ``phase_rmse_rad``: RMS of the wrapped high-frequency phase error over x and y; ``median_px``,
    ``p99_px``: Euclidean error; ``wrong_order``: fraction of valid pixels off by more than half a
    period; ``coverage``: valid fraction of the pixels with a true correspondence; ``false_valid``:
    pixels decoded valid without a true correspondence.
    """
    truth = np.isfinite(gt_x) & np.isfinite(gt_y)
    ok = corr.mask & truth
    dx, dy = (corr.xp - gt_x)[ok].astype(np.float64), (corr.yp - gt_y)[ok].astype(np.float64)
    if not ok.any():
        nan = float("nan")
        return {"phase_rmse_rad": nan, "median_px": nan, "p99_px": nan, "wrong_order": nan, "coverage": 0.0,
                "false_valid": int((corr.mask & ~truth).sum())}
    phase_err = np.angle(np.exp(2j * np.pi * np.concatenate([dx, dy]) / period))
    err = np.hypot(dx, dy)
    return {
        "phase_rmse_rad": float(np.sqrt(np.mean(phase_err**2))),
        "median_px": float(np.median(err)),
        "p99_px": float(np.percentile(err, 99)),
        "wrong_order": float(np.mean(err > period / 2)),
        "coverage": float(ok.sum() / max(1, truth.sum())),
        "false_valid": int((corr.mask & ~truth).sum()),
    }


# ------------------------------------------------------------------------------------------ synthetic data


def synthetic_frames(
    config: PSPConfig,
    xp: np.ndarray,
    yp: np.ndarray,
    *,
    offset: float = 0.3,
    amplitude: float = 0.2,
    blur: float = 0.0,
    noise: float = 0.0,
    channels: tuple[float, ...] | None = None,
    rng: np.random.Generator | None = None,
    dtype: type = np.float32,
) -> dict[str, np.ndarray]:
    """Frames ``offset + amplitude cos(2π u / P - δ_n)`` at camera pixels seeing projector (xp, yp),
    Gaussian-blurred by ``blur`` px (an SSS stand-in whose symmetric kernel keeps the phase of a
    linear ramp), times per-channel gains ``channels`` (RGB frames) if given, with Gaussian noise
    ``noise``; uint8 output scales [0, 1] to 0..255."""
    from scipy.ndimage import gaussian_filter

    rng = rng or np.random.default_rng(0)
    frames = {}
    for o, u in (("x", xp), ("y", yp)):
        for p in config.periods:
            for n in range(config.n_shifts):
                img = offset + amplitude * np.cos(2 * np.pi * u / p - 2 * np.pi * n / config.n_shifts)
                if blur:
                    img = gaussian_filter(img, blur, mode="nearest")
                if channels is not None:
                    img = img[..., None] * np.asarray(channels)
                if noise:
                    img = img + rng.normal(0.0, noise, img.shape)
                if dtype == np.uint8:
                    frames[psp_key(o, p, n)] = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)
                else:
                    frames[psp_key(o, p, n)] = img.astype(dtype)
    return frames


def _affine_view(size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A camera seeing the projector slightly rotated and scaled (exact correspondence)."""
    w, h = size
    yy, xx = np.mgrid[:h, :w].astype(np.float64)
    return 0.92 * xx + 0.04 * yy + 6.3, 0.92 * yy - 0.04 * xx + 0.04 * w + 3.7


def _affine_truth(xp: np.ndarray, yp: np.ndarray, size: tuple[int, int], border: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Exact correspondence where it is inside the projector, NaN elsewhere and on a ``border``-px
    frame of the camera image (where the blur of the synthetic data is one-sided and biases the phase)."""
    keep = (xp >= -0.5) & (xp < size[0] - 0.5) & (yp >= -0.5) & (yp < size[1] - 0.5)
    keep[:border], keep[-border:], keep[:, :border], keep[:, -border:] = False, False, False, False
    return np.where(keep, xp, np.nan), np.where(keep, yp, np.nan)


def _fringe_images(size: tuple[int, int], config: PSPConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A full 8-bit capture set at ``size`` (camera = projector pixels) for timing."""
    w, h = size
    frames = {}
    for o in ("x", "y"):
        for p in config.periods:
            for n in range(config.n_shifts):
                pat = phase_shift_pattern(w, h, period=p, shift=n, n_shifts=config.n_shifts, orientation=o, gamma=1.0)
                noisy = 20 + 200 * pat + rng.normal(0, 2, (1, w) if o == "y" else (h, 1))
                frames[psp_key(o, p, n)] = np.clip(noisy, 0, 255).astype(np.uint8)
    return frames


def _numpy_wrapped_phase(frames: list[np.ndarray]) -> np.ndarray:
    """Reference numpy float32 implementation of the same formula (speed baseline)."""
    n = len(frames)
    s = np.zeros(frames[0].shape, np.float32)
    c = np.zeros(frames[0].shape, np.float32)
    for k, f in enumerate(frames):
        v = f.astype(np.float32)
        s += v * np.float32(math.sin(2 * math.pi * k / n))
        c += v * np.float32(math.cos(2 * math.pi * k / n))
    return np.arctan2(s, c)


# ------------------------------------------------------------------------------------------ sections


def bench_speed(repeats: int, rgb: bool, progress: Progress) -> dict[str, Any]:
    """Milliseconds per phase map at 1080p: our full decode + unwrap against OpenCV's PSP."""
    import cv2

    w, h = SPEED_SIZE
    config = psp_config_for(w, h)
    n_maps = 2 * len(config.periods)
    rng = np.random.default_rng(0)
    progress("speed: rendering 1080p capture set")
    frames = _fringe_images(SPEED_SIZE, config, rng)
    three = [frames[psp_key("x", config.period, n)] for n in range(3)]  # any 3 frames: same work as OpenCV

    params = cv2.structured_light.SinusoidalPattern.Params()
    params.width, params.height = w, h
    params.nbrOfPeriods = int(round(w / config.period))
    params.methodId = cv2.structured_light.PSP
    params.setMarkers = False
    pattern = cv2.structured_light.SinusoidalPattern_create(params)
    ok, cv_images = pattern.generate()
    if not ok:
        raise RuntimeError("OpenCV could not generate its sinusoidal patterns")
    cv_images = [np.ascontiguousarray(im) for im in cv_images]

    progress("speed: ours, numpy and OpenCV, interleaved")
    times = interleaved_seconds(
        {
            "decode": lambda: decode(frames, config, SPEED_SIZE),
            "wrapped": lambda: wrapped_phase(three),
            "numpy": lambda: _numpy_wrapped_phase(three),
            "opencv": lambda: pattern.computePhaseMap(cv_images),
        },
        repeats,
    )
    med = {k: statistics.median(v) for k, v in times.items()}
    ours, ours_wrapped, numpy_wrapped, opencv = med["decode"], med["wrapped"], med["numpy"], med["opencv"]
    pair_ratio = statistics.median(c / (d / n_maps) for c, d in zip(times["opencv"], times["decode"], strict=True))

    result: dict[str, Any] = {
        "size": list(SPEED_SIZE),
        "config": {"period": config.period, "n_shifts": config.n_shifts, "unwrap_periods": list(config.unwrap_periods)},
        "frames": n_maps * config.n_shifts,
        "phase_maps": n_maps,
        "repeats": repeats,
        "ours_decode_ms_total": ours * 1e3,
        "ours_ms_per_phase_map": ours * 1e3 / n_maps,
        "ours_wrapped_3step_ms": ours_wrapped * 1e3,
        "numpy_wrapped_3step_ms": numpy_wrapped * 1e3,
        "opencv_psp_3step_ms": opencv * 1e3,
        "ratio_opencv_over_ours_per_map": opencv / (ours / n_maps),
        "ratio_opencv_over_ours_per_map_paired": pair_ratio,
        "ratio_opencv_over_ours_wrapped_3step": opencv / ours_wrapped,
        "ratio_numpy_over_torch_3step": numpy_wrapped / ours_wrapped,
    }
    if rgb:
        progress("speed: our decode of float32 RGB frames")
        rgb_frames = {k: np.repeat((v * np.float32(1 / 255))[..., None], 3, axis=-1) for k, v in frames.items()}
        del frames
        t = median_seconds(lambda: decode(rgb_frames, config, SPEED_SIZE), max(1, repeats // 2))
        result["ours_rgb_float32_ms_per_phase_map"] = t * 1e3 / n_maps
    return result


def bench_synthetic(noise_levels: tuple[float, ...], blur: float) -> list[dict[str, Any]]:
    """Accuracy on synthetic fringes (exact affine correspondence) across additive noise levels."""
    config = psp_config_for(*SYNTH_SIZE)
    xp, yp = _affine_view(SYNTH_SIZE)
    rows = []
    for noise in noise_levels:
        frames = synthetic_frames(config, xp, yp, blur=blur, noise=noise, rng=np.random.default_rng(1))
        corr = decode(frames, config, SYNTH_SIZE)
        gt_x, gt_y = _affine_truth(xp, yp, SYNTH_SIZE)
        errors = correspondence_errors(corr, gt_x, gt_y, config.period)
        errors.pop("false_valid")  # the excluded border is not "no correspondence" here
        rows.append({"noise": noise, "blur_px": blur, "snr_B_over_noise": 0.2 / noise if noise else float("inf"), **errors})
    return rows


class _SimFringes:
    """Fringe images of one sim view for any shift count, from 3 renders per (orientation, period).

    By linearity of light transport, with E_a, E_b the images of the shift-0 and quarter-shift
    sinusoids and E_c that of constant emitted light 0.5: ``I(δ) = E_c + cos δ (E_a - E_c) + sin δ (E_b - E_c)``
    equals the render of pattern shift δ exactly (black level included).
    """

    def __init__(self, scene: Any) -> None:
        self.scene = scene
        self.gamma = scene.rig.projector.gamma
        self.wp, self.hp = scene.rig.projector.width, scene.rig.projector.height
        self._basis: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = {}
        half = np.full((self.hp, self.wp), 0.5 ** (1 / self.gamma), np.float32)
        self._constant = scene.render(half[None])[0]

    def prepare(self, periods: set[tuple[str, float]]) -> None:
        todo = sorted(periods - self._basis.keys())
        if not todo:
            return
        pats = []
        for o, p in todo:
            for shift in (0, 1):
                pats.append(phase_shift_pattern(self.wp, self.hp, period=p, shift=shift, n_shifts=4, orientation=o, gamma=self.gamma))
        images = self.scene.render(np.stack(pats))
        for i, key in enumerate(todo):
            self._basis[key] = (images[2 * i], images[2 * i + 1])

    def clean(self, config: PSPConfig) -> dict[str, np.ndarray]:
        self.prepare({(o, p) for o in ("x", "y") for p in config.periods})
        frames = {}
        ec = self._constant
        for o in ("x", "y"):
            for p in config.periods:
                ea, eb = self._basis[(o, p)]
                for n in range(config.n_shifts):
                    d = 2 * math.pi * n / config.n_shifts
                    frames[psp_key(o, p, n)] = (ec + math.cos(d) * (ea - ec) + math.sin(d) * (eb - ec)).astype(np.float32)
        return frames

    def captured(self, clean: dict[str, np.ndarray], exposure: float, rng: np.random.Generator, median: bool) -> dict[str, np.ndarray]:
        """Noisy sensor frames (Poisson-Gaussian, RGGB, bit depth) developed by the ISP chain."""
        from sssphase_core.processing import isp
        from sssphase_core.sim.sensor import expose

        sensor = self.scene.rig.sensor
        keys = list(clean)
        raw = expose(np.stack([clean[k] for k in keys]), sensor, rng, exposure)
        scale = sensor.dn_per_unit(exposure)
        return {k: isp.develop(r, sensor.black_level, scale, median=median) for k, r in zip(keys, raw, strict=True)}


def bench_sim_objects(objects: tuple[str, ...], exposures: tuple[float, ...], progress: Progress) -> list[dict[str, Any]]:
    """Per object and exposure: decode simulated captures and compare with ``SimScene.proj_xy``."""
    from sssphase_core.sim import SimScene

    rows = []
    for name in objects:
        progress(f"sim accuracy: {name}")
        scene = SimScene(name)
        fringes = _SimFringes(scene)
        size = (fringes.wp, fringes.hp)
        config = psp_config_for(*size)
        clean = fringes.clean(config)
        gt_x, gt_y = scene.proj_xy[..., 0], scene.proj_xy[..., 1]
        base = {"object": name, "period": config.period, "n_shifts": config.n_shifts}
        rows.append({**base, "exposure": "noise-free", "isp_median": False,
                     **correspondence_errors(decode(clean, config, size), gt_x, gt_y, config.period)})
        for exposure in exposures:
            for median in (False, True):
                frames = fringes.captured(clean, exposure, np.random.default_rng(7), median)
                corr = decode(frames, config, size)
                rows.append({**base, "exposure": exposure, "isp_median": median,
                             **correspondence_errors(corr, gt_x, gt_y, config.period)})
    return rows


def bench_scattering_bias(objects: tuple[str, ...], progress: Progress,
                          transports: tuple[str, ...] | None = None) -> list[dict[str, Any]]:
    """Per transport model (``transports``; default every one) and object: bias of the decoded correspondence
    along the baseline (x) and across it (y) against ``SimScene.proj_xy``, from noise-free and from noisy
    (nominal exposure) fringes, and what is left once the scattering shift predicted from the exact footprints
    is removed (:func:`sssphase_core.relight.geometry.geometric_correspondence`)."""
    from sssphase_core.relight.engine import Projection
    from sssphase_core.relight.geometry import geometric_correspondence
    from sssphase_core.sim import TRANSPORTS, SimScene, rig_preset, with_transport

    rows = []
    for transport in transports or TRANSPORTS:
        for name in objects:
            progress(f"scattering bias: {name}, {transport}")
            t0 = time.perf_counter()
            scene = SimScene(name, rig=with_transport(rig_preset("cpu"), transport))
            fringes = _SimFringes(scene)
            size = (fringes.wp, fringes.hp)
            config = psp_config_for(*size)
            clean = fringes.clean(config)
            row: dict[str, Any] = {"transport": transport, "object": name, "render_s": time.perf_counter() - t0}
            gt = scene.proj_xy
            for noise, frames in (("", clean), ("noisy_", fringes.captured(clean, 1.0, np.random.default_rng(7), False))):
                corr = decode(frames, config, size)
                ok = corr.mask & np.isfinite(gt[..., 0])
                proj = Projection(corr.xp, corr.yp, corr.mask, size, scene.rig.projector.gamma, scene.rig.projector.black)
                t0 = time.perf_counter()
                geo = geometric_correspondence(scene.footprints, proj, scene.rig.patch, config.period)
                row[f"{noise}correct_s"] = time.perf_counter() - t0
                for label, (xp, yp) in (("decoded", (corr.xp, corr.yp)), ("corrected", (geo.xp, geo.yp))):
                    dx, dy = (xp - gt[..., 0])[ok].astype(np.float64), (yp - gt[..., 1])[ok].astype(np.float64)
                    row |= {f"{noise}{label}_bias_x": float(np.median(dx)), f"{noise}{label}_bias_y": float(np.median(dy)),
                            f"{noise}{label}_median_px": float(np.median(np.hypot(dx, dy)))}
            rows.append(row)
    return rows


def bench_tradeoff(
    shifts: tuple[int, ...], periods: tuple[float, ...], sim_object: str | None, repeats: int, progress: Progress
) -> list[dict[str, Any]]:
    """Error against run time: decode time of a full 1080p capture set with each (N, period) ladder,
    error on the sim object at nominal exposure (or on synthetic blurred fringes without the sim)."""
    rows = []
    fringes = None
    if sim_object is not None:
        from sssphase_core.sim import SimScene

        progress(f"trade-off: rendering {sim_object}")
        fringes = _SimFringes(SimScene(sim_object))
        size = (fringes.wp, fringes.hp)
        gt = fringes.scene.proj_xy
        gt_x, gt_y = gt[..., 0], gt[..., 1]
    else:
        size = SYNTH_SIZE
        xp, yp = _affine_view(size)
        gt_x, gt_y = _affine_truth(xp, yp, size)
    timing_rng = np.random.default_rng(3)
    for period in periods:
        for n in shifts:
            progress(f"trade-off: N={n}, period={period:g}")
            config = PSPConfig(period=period, n_shifts=n, unwrap_periods=period_ladder(period, max(size)))
            if fringes is not None:
                frames = fringes.captured(fringes.clean(config), 1.0, np.random.default_rng(11), median=False)
            else:
                frames = synthetic_frames(config, xp, yp, blur=1.0, noise=0.01, rng=np.random.default_rng(11))
            errors = correspondence_errors(decode(frames, config, size), gt_x, gt_y, period)
            if fringes is None:
                errors.pop("false_valid")
            scale = SPEED_SIZE[0] / size[0]  # the same ladder stretched to 1080p: same frame count
            big = PSPConfig(period=period * scale, n_shifts=n, unwrap_periods=tuple(p * scale for p in config.unwrap_periods))
            big_frames = _fringe_images(SPEED_SIZE, big, timing_rng)
            t = median_seconds(lambda c=big, f=big_frames: decode(f, c, SPEED_SIZE), repeats)
            del big_frames
            rows.append({"n_shifts": n, "period": period, "levels": len(config.periods),
                         "frames": 2 * n * len(config.periods), "decode_ms_1080p": t * 1e3, **errors})
    return rows


# ------------------------------------------------------------------------------------------ entry point


def run(quick: bool = False, progress: Progress | None = None) -> tuple[dict[str, Any], list[Table]]:
    """Run the PSP benchmark; ``quick`` keeps it well under a minute. Returns (JSON dict, tables)."""
    progress = progress or (lambda _msg: None)
    result: dict[str, Any] = {"benchmark": "psp", "quick": quick, "machine": machine_info(), "section_seconds": {}}

    def section(name: str, fn: Callable[[], Any]) -> None:
        t0 = time.perf_counter()
        value = fn()
        result["section_seconds"][name] = time.perf_counter() - t0
        if value is not None:
            result[name] = value

    section("speed", lambda: bench_speed(repeats=3 if quick else 7, rgb=not quick, progress=progress))
    progress("synthetic accuracy")
    noise = (0.0, 0.01, 0.04) if quick else (0.0, 0.0025, 0.005, 0.01, 0.02, 0.04, 0.08)
    section("synthetic", lambda: bench_synthetic(noise, blur=1.0))
    from sssphase_core.bench.sim_bench import simulator_speed
    from sssphase_core.sim import TRAIN_OBJECTS, UNSEEN_OBJECTS

    objects = ("star",) if quick else (*TRAIN_OBJECTS, *UNSEEN_OBJECTS)
    exposures = (1.0,) if quick else (1.0, 0.25, 0.0625)
    section("sim", lambda: bench_sim_objects(objects, exposures, progress))
    section("scattering_bias", lambda: bench_scattering_bias(("soap",) if quick else objects, progress,
                                                             ("burley",) if quick else None))  # the dipole: 5 s
    section("tradeoff", lambda: bench_tradeoff(
        shifts=(3, 4) if quick else (3, 4, 6, 8),
        periods=(11.0,) if quick else (8.0, 11.0, 16.0),
        sim_object="star",
        repeats=1 if quick else 5,
        progress=progress,
    ))
    if not quick:  # about half a minute: not part of the smoke-test run
        progress("simulator speed")
        section("simulator_speed", simulator_speed)
    return result, tables(result)


def tables(result: dict[str, Any]) -> list[Table]:
    """Markdown tables of a benchmark result."""
    s = result["speed"]
    speed = Table(
        "PSP decoding speed, 1920x1080 (ms per phase map, median of repeats)",
        ["method", "ms / phase map", "OpenCV / this"],
        [
            [f"ours: decode + unwrap, {s['frames']} uint8 frames ({s['phase_maps']} maps)", s["ours_ms_per_phase_map"],
             s["ratio_opencv_over_ours_per_map"]],
            ["ours: wrapped phase only, 3-step", s["ours_wrapped_3step_ms"], s["ratio_opencv_over_ours_wrapped_3step"]],
            ["numpy float32, same formula, 3-step", s["numpy_wrapped_3step_ms"], s["opencv_psp_3step_ms"] / s["numpy_wrapped_3step_ms"]],
            ["OpenCV SinusoidalPattern PSP, 3-step", s["opencv_psp_3step_ms"], 1.0],
        ],
        note=f"Measured interleaved ({s['repeats']} repeats); median of per-repeat ratios "
             f"{s['ratio_opencv_over_ours_per_map_paired']:.3g}x; 1-min load average at start "
             f"{result['machine'].get('load_average_1min', float('nan')):.2f} on {result['machine'].get('cpus')} CPUs "
             f"(other processes slow the 2-thread decoder more than single-threaded OpenCV).",
    )
    if "ours_rgb_float32_ms_per_phase_map" in s:
        speed.rows.insert(1, ["ours: decode + unwrap, float32 RGB frames", s["ours_rgb_float32_ms_per_phase_map"],
                              s["opencv_psp_3step_ms"] / s["ours_rgb_float32_ms_per_phase_map"]])
    acc_cols = ["phase RMSE (rad)", "median (px)", "p99 (px)", "wrong order", "coverage"]

    def acc(row: dict[str, Any]) -> list[Any]:
        return [row["phase_rmse_rad"], row["median_px"], row["p99_px"], row["wrong_order"], row["coverage"]]

    out = [speed]
    out.append(Table(
        "Synthetic fringes (exact affine correspondence, 1 px Gaussian blur, A = 0.3, B = 0.2)",
        ["noise σ", *acc_cols], [[r["noise"], *acc(r)] for r in result["synthetic"]],
    ))
    if "sim" in result:
        out.append(Table(
            "Simulated rig (CPU preset), correspondence error against SimScene.proj_xy",
            ["object", "exposure", "ISP 3x3 median", *acc_cols],
            [[r["object"], r["exposure"], "yes" if r["isp_median"] else "no", *acc(r)] for r in result["sim"]],
            note="Exposure 1 is nominal noise; lower exposures raise the relative noise. The paper's 3x3 median per "
                 "Bayer plane distorts fringes of ~11 camera px period, so decoding is best on frames developed without it.",
        ))
    if "scattering_bias" in result:
        out.append(Table(
            "Scattering bias of decoded correspondences (CPU preset; projector px; baseline along x)",
            ["transport", "object", "decoded bias x", "bias y", "median error",
             "corrected bias x", "bias y", "median error", "noisy: decoded error", "corrected error",
             "corrected bias x", "correction s"],
            [[r["transport"], r["object"], r["decoded_bias_x"], r["decoded_bias_y"], r["decoded_median_px"],
              r["corrected_bias_x"], r["corrected_bias_y"], r["corrected_median_px"], r["noisy_decoded_median_px"],
              r["noisy_corrected_median_px"], r["noisy_corrected_bias_x"], r["correct_s"]]
             for r in result["scattering_bias"]],
            note="Bias: median signed error of the decoded map against the exact projector point that lit each "
                 "pixel. Light entering obliquely re-emerges displaced (directional dipole), so the decoded point "
                 "shifts along the baseline; relighting keeps the decoded map (it is where light shows up). "
                 "Corrected: relight.geometry.geometric_correspondence with the exact footprints, the map for 3D "
                 "(`sss geometry SESSION` does it with a backend's footprints). Noise-free fringes first; 'noisy': "
                 "the nominal exposure's sensor noise (median error of the decoded map; the correction predicts the "
                 "shift from smoothed points, so noise is not amplified).",
        ))
    source = "sim object star, nominal exposure" if "sim" in result else "synthetic fringes, noise 0.01"
    out.append(Table(
        f"Error against run time (error: {source}; time: decode + unwrap of the full set at 1080p)",
        ["shifts", "period (px)", "frames", "decode ms", "median (px)", "p99 (px)", "coverage"],
        [[r["n_shifts"], r["period"], r["frames"], r["decode_ms_1080p"], r["median_px"], r["p99_px"], r["coverage"]]
         for r in result["tradeoff"]],
    ))
    return out
