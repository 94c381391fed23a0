"""Camera sensor: exposure, Poisson-Gaussian noise, RGGB Bayer mosaic, black level, bit depth, clipping."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sssphase_core.processing.isp import bayer_mosaic

#: The ``demosaic`` of a camera without a colour filter array (three sensors behind a prism, or one behind a
#: filter wheel): every pixel measures R, G and B, nothing is demosaiced.
THREE_CHIP = "none"


@dataclass(frozen=True)
class SensorConfig:
    """Linear value 1.0 (the reference white) collects ``white_fraction * full_well`` electrons at
    nominal exposure 1.0; the full well maps to the top DN code. ``read_noise`` in electrons."""

    bit_depth: int = 12
    full_well: float = 10000.0
    white_fraction: float = 0.6
    read_noise: float = 3.0
    black_level: int = 256  # DN
    #: The paper's 3x3 median per RGGB plane before demosaicing. It blurs fringes a few pixels wide,
    #: so presets whose high-frequency period is ~10 camera px turn it off (measured: median
    #: correspondence error 0.036 -> 0.25 px on the star at the CPU preset with it on).
    isp_median: bool = True
    #: The lens's point spread (the system MTF): a Gaussian of this sigma in camera px blurs the
    #: optical image before it is sampled (0: a perfect lens).
    lens_blur: float = 0.0
    #: The camera's demosaicing (``isp.demosaic`` methods: ``malvar`` or ``opencv``), or :data:`THREE_CHIP`
    #: for a camera without a colour filter array.
    demosaic: str = "malvar"

    @property
    def three_chip(self) -> bool:
        """Whether every pixel sees R, G and B (no colour filter array, nothing demosaiced)."""
        return self.demosaic == THREE_CHIP

    @property
    def max_dn(self) -> int:
        return 2**self.bit_depth - 1

    @property
    def electrons_per_unit(self) -> float:
        return self.white_fraction * self.full_well

    @property
    def dn_per_electron(self) -> float:
        return (self.max_dn - self.black_level) / self.full_well

    def dn_per_unit(self, exposure: float = 1.0) -> float:
        """DN above black per linear camera unit at ``exposure`` (the ``white_scale`` of isp.develop)."""
        return self.electrons_per_unit * exposure * self.dn_per_electron

    def noise_std(self, linear: np.ndarray, exposure: float = 1.0) -> np.ndarray:
        """Standard deviation of a raw sample in linear units: photon shot noise, read noise and
        quantisation (before demosaicing and the median, which lower it)."""
        k = self.electrons_per_unit * exposure
        quant = 1.0 / (self.dn_per_electron * k)
        return np.sqrt(np.clip(linear, 0, None) / k + (self.read_noise / k) ** 2 + quant**2 / 12)

    def saturation(self, exposure: float = 1.0) -> float:
        """Linear value at which a sample clips (full well) at ``exposure``."""
        return self.full_well / (self.electrons_per_unit * exposure)


def through_lens(linear: np.ndarray, config: SensorConfig) -> np.ndarray:
    """The optical image on the sensor, (..., H, W, 3): ``linear`` blurred by the lens's Gaussian PSF
    (``config.lens_blur`` px; reflected at the borders). Unchanged for a perfect lens."""
    if config.lens_blur <= 0:
        return linear
    import cv2

    arr = np.asarray(linear, np.float32)
    flat = arr.reshape(-1, *arr.shape[-3:])
    out = np.stack([cv2.GaussianBlur(f, (0, 0), float(config.lens_blur), borderType=cv2.BORDER_REFLECT) for f in flat])
    return out.reshape(arr.shape)


def _on_sensor(linear: np.ndarray, config: SensorConfig) -> np.ndarray:
    """What the photosites see, float64: the lens's image through the Bayer filter (..., H, W), or all three
    colours at every pixel for a three-chip camera (:data:`THREE_CHIP`, (..., H, W, 3))."""
    image = np.asarray(through_lens(linear, config), np.float64)
    return image if config.three_chip else bayer_mosaic(image)


def expose(linear: np.ndarray, config: SensorConfig, rng: np.random.Generator, exposure: float = 1.0) -> np.ndarray:
    """Noisy raw frames (uint16: Bayer (..., H, W), or (..., H, W, 3) for a three-chip camera) from linear RGB
    images (..., H, W, 3) in front of the lens."""
    mean_e = np.clip(_on_sensor(linear, config), 0.0, None) * (config.electrons_per_unit * exposure)
    electrons = rng.poisson(mean_e).astype(np.float64) + rng.normal(0.0, config.read_noise, mean_e.shape)
    electrons = np.minimum(electrons, config.full_well)
    dn = np.round(config.black_level + electrons * config.dn_per_electron)
    return np.clip(dn, 0, config.max_dn).astype(np.uint16)


def expose_noise_free(linear: np.ndarray, config: SensorConfig, exposure: float = 1.0) -> np.ndarray:
    """The mean raw Bayer frames (float32 DN, (..., H, W)) that :func:`expose` draws around: no photon or
    read noise, no rounding; clipped at the full well like a real exposure."""
    mean_e = np.clip(_on_sensor(linear, config), 0.0, None) * (config.electrons_per_unit * exposure)
    dn = config.black_level + np.minimum(mean_e, config.full_well) * config.dn_per_electron
    return np.minimum(dn, config.max_dn).astype(np.float32)


def develop(frames: np.ndarray, config: SensorConfig, dn_per_unit: float) -> np.ndarray:
    """Raw frames of :func:`expose` (P, H, W) Bayer or (P, H, W, 3) three-chip -> linear RGB float32
    (P, H, W, 3): the camera's ISP (median, demosaicing) for a Bayer camera; black level and scale only for a
    three-chip one, which has nothing to demosaic."""
    from sssphase_core.processing import isp

    if config.three_chip:
        return ((np.asarray(frames, np.float32) - np.float32(config.black_level)) / np.float32(dn_per_unit)).astype(np.float32)
    return np.stack([isp.develop(f, config.black_level, dn_per_unit, median=config.isp_median, method=config.demosaic)
                     for f in frames])
