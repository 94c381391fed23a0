"""The measured light transport of a captured view: one crop per projector dot (:class:`DotTransport`,
the ``measured`` backend), denoised by the mask that relights the view's own fringe captures best
(:func:`denoised_transport`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sssphase_core.relight.engine import relight
from sssphase_core.relight.views import RelightView


class DotTransport:
    """The measured light transport of a captured view (``transport/`` arrays of a session): crop ``i``
    (K, K, 3) is the camera's response to projector pixel ``dots[i]`` (x, y), centred on camera pixel
    ``pixels[i]`` (y, x). :func:`relight` splats ``sum_i L(dots[i]) crop_i`` with the pattern's light at
    each dot exactly.

    With ``noise`` > 0 (the crops' noise std, ``footprints.crop_noise``) crops are denoised as they are
    read by the mask of ``smoothing`` px (``footprints.above_noise``; :func:`denoised_transport` picks it
    per view); crops whose noise floor was zeroed with a single mask pass 0.
    """

    def __init__(self, pixels: np.ndarray, dots: np.ndarray, crops: object, noise: float, smoothing: float = 1.0) -> None:
        self.pixels, self.dots, self.crops, self.noise = np.asarray(pixels, np.int64), np.asarray(dots, np.int64), crops, noise
        self.smoothing = float(smoothing)
        self.fit: dict[float, float] = {}  # PSNR (dB) of each candidate mask on the view's fringe captures, when chosen

    def lit(self, light: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Dots lit by some pattern: (camera pixels (N, 2), light (N, P, C), rows into the crops (N,))."""
        c = light[:, self.dots[:, 1], self.dots[:, 0], :].transpose(1, 0, 2)
        rows = np.nonzero((c > 0).any(axis=(1, 2)))[0]
        return self.pixels[rows], c[rows], rows

    def crops_at(self, rows: np.ndarray) -> np.ndarray:
        """Denoised crops (n, K, K, 3) float32 of ``rows`` (ascending, as :meth:`lit` gives them)."""
        if len(rows) == 0:
            return np.zeros((0, *self.crops.shape[1:]), np.float32)  # type: ignore[attr-defined]
        from sssphase_core.processing.footprints import above_noise

        lo, hi = int(rows.min()), int(rows.max()) + 1
        if hi - lo <= 4 * len(rows) or not hasattr(self.crops, "oindex"):  # one contiguous read of the chunks
            crops = np.asarray(self.crops[lo:hi])[rows - lo].astype(np.float32)  # type: ignore[index]
        else:  # a sparse pattern lights few of the rows in between: read only theirs
            crops = np.asarray(self.crops.oindex[rows]).astype(np.float32)  # type: ignore[attr-defined]
        if self.noise > 0 and len(crops):
            crops = crops * above_noise(crops, self.noise, smoothing=self.smoothing)[..., None]
        return crops


def denoised_transport(rv: RelightView, pixels: np.ndarray, dots: np.ndarray, crops: object, noise: float,
                       smoothings: Sequence[float]) -> DotTransport:
    """The captured transport of a view denoised by the mask (one of ``smoothings`` px, see
    ``footprints.DENOISE_SMOOTHING``) that relights the view's own 8 fringe captures best: no ground
    truth, and the crops are camera images like the captures, so they are compared as they are. Its
    ``fit`` records each candidate's PSNR (dB) on those captures. Without the view's PSP patterns, the
    first candidate."""
    from sssphase_core.learning.metrics import psnr
    candidates = [DotTransport(pixels, dots, crops, noise, s) for s in smoothings]
    if rv.psp_patterns is None or noise <= 0 or len(candidates) == 1:
        return candidates[0]
    m = rv.proj.mask & np.isfinite(rv.psp).all(axis=(0, -1))
    k = int(crops.shape[1])  # type: ignore[attr-defined]
    fit = {t.smoothing: psnr(float(np.mean((relight(t, rv.proj, rv.psp_patterns, k, white=rv.white)[:, m] - rv.psp[:, m]) ** 2)))
           for t in candidates}
    best = next(t for t in candidates if t.smoothing == max(fit, key=fit.__getitem__))
    best.fit = fit
    return best
