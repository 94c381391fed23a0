"""Ground-truth footprints from dot-grid captures (numpy + scipy).

Dot-grid frame ``(sx, sy)`` lights projector pixels ``(sx + i*s, sy + j*s)``. A camera pixel p whose
rounded projector coordinate is one of them receives light in that frame, and the ``K x K`` crop of
the frame centred on p, made to mean what relighting assumes, is p's footprint:

* **per camera pixel**: a dot is one *projector* pixel, which covers ``1 / |det J|`` camera pixels
  (J = d(xp, yp) / d(x, y), the camera->projector Jacobian of the decoded correspondence), while a
  footprint is the light that enters through one *camera* pixel. Each crop is multiplied by the
  pixel's ``|det J|`` (smoothed over 5x5 valid pixels), so a white pattern relit from the footprints
  gives the white image back. Without it, crops carry 1.1-1.7x the energy where the projector is
  spread over the camera view.
* **its own dot only**: where the projector pattern is compressed in the camera view, a K x K crop
  also holds neighbouring dots. Crop pixels whose projector coordinate is nearer to another dot of
  the same frame than to p's own dot are set to 0: the dot's Voronoi cell in projector space. Light
  that scatters further than half the dot spacing is lost there, which is why the spacing should
  exceed the footprint's width (the paper's 55 px for K = 90).

Frames arrive one at a time; only the crops are kept.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import uniform_filter

from sssphase_core.errors import InputError


def _dot_frame(shift_x: int, shift_y: int, frame: np.ndarray, spacing: int, shape: tuple[int, int],
               channels: int) -> np.ndarray:
    """A dot-grid frame checked against the extractor's shift range and image shape, as (H, W, C)."""
    if not (0 <= shift_x < spacing and 0 <= shift_y < spacing):
        raise InputError(f"dot-grid shift ({shift_x}, {shift_y}) outside [0, {spacing})")
    frame = frame[..., None] if frame.ndim == 2 else frame
    if frame.shape != (*shape, channels):
        raise InputError(f"dot-grid frame must be {(*shape, channels)}, got {frame.shape}")
    return frame


def _cell_labels(xp: np.ndarray, yp: np.ndarray, valid: np.ndarray, shift_x: int, shift_y: int,
                 spacing: int) -> np.ndarray:
    """The dot of frame ``(shift_x, shift_y)`` nearest to each projector coordinate, as one int64 label
    (its Voronoi cell in projector space); -2 where there is no coordinate."""
    gx = np.floor((xp - shift_x) / spacing + 0.5).astype(np.int64)
    gy = np.floor((yp - shift_y) / spacing + 0.5).astype(np.int64)
    return np.where(valid, gy * (1 << 20) + gx, -2)


def _isolated_windows(frame: np.ndarray, ys: np.ndarray, xs: np.ndarray, own: np.ndarray | None, patch: int,
                      corr: tuple[np.ndarray, np.ndarray, np.ndarray], shift_x: int, shift_y: int,
                      spacing: int) -> np.ndarray:
    """``(n, K, K, C)`` float32 windows of ``frame`` (H, W, C) centred on pixels ``(ys, xs)`` (zero beyond
    the image), each cut to its own dot's cell: pixels whose projector coordinate (``corr`` = xp, yp,
    valid) is nearest to another dot of frame ``(shift_x, shift_y)`` are 0 (``own`` (n,): each window's
    dot as a :func:`_cell_labels` label; None keeps everything). Cells follow the local Jacobian and need
    no lit camera pixel, so a dot between camera pixel centres on a grazing surface is still told apart;
    pixels without a coordinate (off the surface, outside the image) are kept. Only the bounding box of
    the pixels is padded, so the cost follows the object, not the image."""
    k, half = patch, patch // 2
    h, w = frame.shape[:2]
    y0, y1, x0, x1 = int(ys.min()), int(ys.max()), int(xs.min()), int(xs.max())
    sy0, sx0 = max(0, y0 - half), max(0, x0 - half)
    sy1, sx1 = min(h, y1 - half + k), min(w, x1 - half + k)
    oy, ox = sy0 - (y0 - half), sx0 - (x0 - half)
    region = np.zeros((y1 - y0 + k, x1 - x0 + k, frame.shape[2]), np.float32)
    region[oy:oy + sy1 - sy0, ox:ox + sx1 - sx0] = frame[sy0:sy1, sx0:sx1]
    out = sliding_window_view(region, (k, k), axis=(0, 1))[ys - y0, xs - x0].transpose(0, 2, 3, 1)  # (n, K, K, C)
    if own is None:
        return np.ascontiguousarray(out)
    xp, yp, valid = corr
    labels = np.full(region.shape[:2], -2, np.int64)  # -2: no projector coordinate (kept)
    labels[oy:oy + sy1 - sy0, ox:ox + sx1 - sx0] = _cell_labels(xp[sy0:sy1, sx0:sx1], yp[sy0:sy1, sx0:sx1],
                                                                 valid[sy0:sy1, sx0:sx1], shift_x, shift_y, spacing)
    cells = sliding_window_view(labels, (k, k))[ys - y0, xs - x0]
    return out * ((cells == own[:, None, None]) | (cells == -2))[..., None]


def _by_shift(shift: np.ndarray, spacing: int) -> list[np.ndarray]:
    """Indices grouped by the dot-grid frame (shift index ``sy * spacing + sx``; -1: no frame) that lights them."""
    order = np.argsort(shift, kind="stable")
    bounds = np.searchsorted(shift[order], np.arange(spacing * spacing + 1))
    return [order[bounds[i]:bounds[i + 1]] for i in range(spacing * spacing)]


class DotGridExtractor:
    """Collects the ``K x K x C`` footprint of every valid camera pixel from streamed dot-grid frames.

    ``xp, yp, mask``: the correspondence maps ``(H, W)``; ``spacing``: dot spacing s in projector
    pixels; ``patch``: K. Crops are centred on the pixel (index ``K // 2``), zero-padded at the
    image border, scaled to one camera pixel's light (``|det J|``) and cut to the pixel's own dot
    (``isolate``; see the module docstring). Storage is preallocated (``np.zeros``) as
    ``(N, K, K, C)`` ``dtype``.
    """

    def __init__(
        self,
        xp: np.ndarray,
        yp: np.ndarray,
        mask: np.ndarray,
        spacing: int,
        patch: int,
        *,
        channels: int = 3,
        dtype: np.dtype = np.float32,
        per_camera_pixel: bool = True,
        isolate: bool = True,
    ) -> None:
        if xp.shape != yp.shape or xp.shape != mask.shape or xp.ndim != 2:
            raise InputError(f"xp, yp and mask must share one (H, W) shape, got {xp.shape}, {yp.shape}, {mask.shape}")
        if spacing < 1 or patch < 1:
            raise InputError(f"spacing and patch must be >= 1, got {spacing}, {patch}")
        self.shape, self.spacing, self.patch, self.channels = xp.shape, int(spacing), int(patch), int(channels)
        valid = mask & np.isfinite(xp) & np.isfinite(yp)
        ys, xs = np.nonzero(valid)
        self.pixels = np.stack([ys, xs], axis=1).astype(np.int64)
        rx = np.floor(xp[ys, xs].astype(np.float64) + 0.5).astype(np.int64)
        ry = np.floor(yp[ys, xs].astype(np.float64) + 0.5).astype(np.int64)
        inside = (rx >= 0) & (ry >= 0)
        self.isolate = bool(isolate)
        self._valid = valid
        self._xp, self._yp = np.where(valid, xp, 0.0).astype(np.float64), np.where(valid, yp, 0.0).astype(np.float64)
        self.scale = (jacobian_area(xp, yp, valid)[ys, xs] if per_camera_pixel else np.ones(len(ys))).astype(np.float32)
        # shift index of the frame that lights each pixel (-1: never lit)
        self._shift = np.where(inside, (ry % spacing) * spacing + rx % spacing, -1)
        self._groups = _by_shift(self._shift, spacing)
        self.dtype = np.dtype(dtype)
        self._footprints: np.ndarray | None = None  # allocated by the first ``add`` (``crops`` streams)
        self._lit = np.zeros(len(ys), bool)

    def add(self, shift_x: int, shift_y: int, frame: np.ndarray) -> int:
        """Crop and keep the footprints lit by dot-grid frame ``(shift_x, shift_y)``; returns how many."""
        idx, crops = self.crops(shift_x, shift_y, frame)
        if self._footprints is None:
            self._footprints = np.zeros((len(self.pixels), self.patch, self.patch, self.channels), self.dtype)
        self._footprints[idx] = crops
        return len(idx)

    def crops(self, shift_x: int, shift_y: int, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(idx (n,), crops (n, K, K, C) float32)`` of the pixels lit by dot-grid frame ``(shift_x,
        shift_y)`` (``self.pixels[idx]``), without keeping them: a caller that streams them to disk holds
        one frame's crops at a time. Marks the pixels as lit."""
        frame = _dot_frame(shift_x, shift_y, frame, self.spacing, self.shape, self.channels)
        idx = self._groups[shift_y * self.spacing + shift_x]
        if len(idx) == 0:
            return idx, np.zeros((0, self.patch, self.patch, self.channels), np.float32)
        ys, xs = self.pixels[idx, 0], self.pixels[idx, 1]
        own = (_cell_labels(self._xp[ys, xs], self._yp[ys, xs], np.ones(len(idx), bool), shift_x, shift_y, self.spacing)
               if self.isolate else None)
        crops = _isolated_windows(frame, ys, xs, own, self.patch, (self._xp, self._yp, self._valid), shift_x, shift_y,
                                  self.spacing)
        crops *= self.scale[idx, None, None, None]
        self._lit[idx] = True
        return idx, crops

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels (N, 2) int yx, footprints (N, K, K, C))`` of the pixels lit so far by ``add``."""
        if self._footprints is None:
            return self.pixels[:0], np.zeros((0, self.patch, self.patch, self.channels), self.dtype)
        if self._lit.all():
            return self.pixels, self._footprints
        return self.pixels[self._lit], self._footprints[self._lit]

    def missing(self) -> np.ndarray:
        """Valid pixels ``(M, 2)`` yx that no added frame has lit yet."""
        return self.pixels[~self._lit]


def _valid_deriv(a: np.ndarray, valid: np.ndarray, axis: int) -> np.ndarray:
    """Central differences of ``a`` along ``axis`` between ``valid`` neighbours (one-sided at a gap; NaN where
    neither neighbour is valid)."""
    a = np.where(valid, a.astype(np.float64), np.nan)
    fwd = np.diff(a, axis=axis, append=np.nan)
    bwd = np.diff(a, axis=axis, prepend=np.nan)
    return np.where(np.isfinite(fwd) & np.isfinite(bwd), 0.5 * (fwd + bwd), np.where(np.isfinite(fwd), fwd, bwd))


def _valid_mean(a: np.ndarray, smooth: int) -> np.ndarray:
    """``a`` averaged over its finite values in ``smooth x smooth`` windows (NaN where a window has none)."""
    ok = np.isfinite(a)
    num = uniform_filter(np.where(ok, a, 0.0), smooth, mode="constant")
    den = uniform_filter(ok.astype(np.float64), smooth, mode="constant")
    return np.where(den > 1e-9, num / np.maximum(den, 1e-9), np.nan)


def jacobian_area(xp: np.ndarray, yp: np.ndarray, valid: np.ndarray | None = None, smooth: int = 5) -> np.ndarray:
    """``|det J|`` ``(H, W)`` float32: projector area seen by each camera pixel, J = d(xp, yp)/d(x, y).

    Central differences between valid neighbours (one-sided at a gap), averaged over ``smooth x smooth``
    valid pixels to tame the decoding noise; pixels with no estimate take the median over the view
    (1 where nothing is valid, e.g. a one-row image). Differences across a depth edge are clipped to
    8x the view's median first.
    """
    valid = np.isfinite(xp) & np.isfinite(yp) if valid is None else valid & np.isfinite(xp) & np.isfinite(yp)
    if min(xp.shape) < 2 or not valid.any():
        return np.ones(xp.shape, np.float32)
    d = lambda a, axis: _valid_deriv(a, valid, axis)  # noqa: E731
    det = np.abs(d(xp, 1) * d(yp, 0) - d(xp, 0) * d(yp, 1))
    ok = np.isfinite(det)
    if not ok.any():
        return np.ones(xp.shape, np.float32)
    typical = float(np.median(det[ok]))
    det = np.where(ok, np.clip(det, typical / 8, typical * 8), np.nan)  # depth edges: a correspondence jump is no area
    out = _valid_mean(det, smooth)
    return np.where(np.isfinite(out), out, typical).astype(np.float32)


#: :func:`dot_offsets` are clipped to this many camera px (a grazing surface's J is near singular).
MAX_DOT_OFFSET = 1.5


def _local_jacobian(xp: np.ndarray, yp: np.ndarray, valid: np.ndarray, px: np.ndarray,
                    smooth: int) -> np.ndarray:
    """(N, 2, 2) J = d(xp, yp)/d(x, y) = [[dxp/dx, dxp/dy], [dyp/dx, dyp/dy]] at pixels ``px`` (N, 2) yx, each
    element averaged over ``smooth x smooth`` valid pixels (NaN where no neighbour is valid)."""
    rows = [[_valid_mean(_valid_deriv(a, valid, axis), smooth)[px[:, 0], px[:, 1]] for axis in (1, 0)] for a in (xp, yp)]
    return np.asarray(rows, np.float64).transpose(2, 0, 1).reshape(-1, 2, 2)


def dot_offsets(xp: np.ndarray, yp: np.ndarray, valid: np.ndarray, pixels: np.ndarray, smooth: int = 5,
                dots: np.ndarray | None = None) -> np.ndarray:
    """(N, 2) float32 (dy, dx) camera px: where the dot whose crop is pixel ``pixels[i]``'s footprint lit the
    surface, relative to that pixel's centre. The crop comes from the dot at the pixel's rounded projector
    coordinate, so its light enters ``J^-1 (round(p) - p)`` away (J = d(xp, yp)/d(x, y), each element averaged
    over ``smooth x smooth`` valid pixels); measured on the demo's diffuse star, the crops' 5 x 5 centroids
    follow it with slope 1.0-1.1 (correlation 0.80). ``dots``: (N, 2) projector (x, y) of other dots to place
    (``J^-1 (dot - p)``; default: each pixel's rounded coordinate). Clipped to :data:`MAX_DOT_OFFSET`; 0 where J
    is unknown. Where the dot's whole image matters (its size and shape, not only its place), see
    :func:`dot_kernels`."""
    px = np.asarray(pixels, np.int64).reshape(-1, 2)
    valid = valid & np.isfinite(xp) & np.isfinite(yp)
    if not len(px) or min(xp.shape) < 2:
        return np.zeros((len(px), 2), np.float32)
    jac = _local_jacobian(xp, yp, valid, px, smooth)
    (a, b), (c, d) = jac[:, 0].T, jac[:, 1].T
    at_x, at_y = xp[px[:, 0], px[:, 1]], yp[px[:, 0], px[:, 1]]
    to = np.round(np.stack([at_x, at_y], axis=1)) if dots is None else np.asarray(dots, np.float64).reshape(-1, 2)
    if len(to) != len(px):
        raise InputError(f"{len(to)} dots for {len(px)} pixels")
    ex, ey = to[:, 0] - at_x, to[:, 1] - at_y
    det = a * d - b * c
    with np.errstate(divide="ignore", invalid="ignore"):
        dx, dy = (d * ex - b * ey) / det, (a * ey - c * ex) / det
    out = np.stack([dy, dx], axis=1)
    out = np.where(np.isfinite(out), out, 0.0)
    return np.clip(out, -MAX_DOT_OFFSET, MAX_DOT_OFFSET).astype(np.float32)


#: :func:`dot_kernels` spans camera offsets -R..R: a dot lights 2 projector px of tent a side, so R = 3 holds it
#: whole where the projector is magnified up to ~2x on the camera (J's smaller singular value >= 0.5).
DOT_KERNEL_RADIUS = 3


def pixel_alone_kernel(radius: int = DOT_KERNEL_RADIUS) -> np.ndarray:
    """(2R+1, 2R+1) float32: a dot that lit only the crop's own pixel (weight 1 at the centre), as
    :func:`dot_kernels` gives where nothing is known about the dot's image."""
    kernel = np.zeros((2 * radius + 1, 2 * radius + 1), np.float32)
    kernel[radius, radius] = 1.0
    return kernel


def dot_kernels(xp: np.ndarray, yp: np.ndarray, valid: np.ndarray, pixels: np.ndarray, smooth: int = 5,
                radius: int = DOT_KERNEL_RADIUS) -> np.ndarray:
    """(N, 2R+1, 2R+1) float32: the image of the dot whose crop is pixel ``pixels[i]``'s footprint, as weights
    on the camera pixels at offsets (dy, dx) in -R..R from it, summing to 1.

    A dot is one projector pixel; relighting (and the simulator) give a camera pixel the projector's light
    looked up bilinearly at its projector coordinate, so the dot at q lights the camera pixel at offset d with
    ``tent(J d - e)`` (J = d(xp, yp)/d(x, y) as in :func:`dot_offsets`, ``e = q - p`` the dot's projector
    offset from the pixel's own coordinate, tent(u) = prod max(0, 1 - |u_i|)), and the crop holds the sum of
    those pixels' footprints. Where the projector is magnified on the camera (a singular value of J below 1,
    fringes wide apart) the dot spans several pixels, where it is sheared, a slanted patch: a shape that
    follows the fringes' density and that a decoder fitted to the crops would otherwise learn as part of every
    footprint. With J the identity the weights are the bilinear move of :func:`dot_offsets`. J unknown: the
    identity. Measured on noise-free simulator crops (the apple, 215 pixels, exact correspondences): the exact
    footprints through these kernels are 4.2% (median relative L2) from the crops, through the bilinear move
    18%, and 49% where J's smaller singular value is below 0.6."""
    px = np.asarray(pixels, np.int64).reshape(-1, 2)
    side = 2 * radius + 1
    valid = valid & np.isfinite(xp) & np.isfinite(yp)
    if not len(px):
        return np.zeros((0, side, side), np.float32)
    jac = (_local_jacobian(xp, yp, valid, px, smooth) if min(xp.shape) >= 2
           else np.full((len(px), 2, 2), np.nan))
    jac = np.where(np.isfinite(jac).all(axis=(1, 2))[:, None, None], jac, np.eye(2))
    at = np.stack([xp[px[:, 0], px[:, 1]], yp[px[:, 0], px[:, 1]]], axis=1).astype(np.float64)
    e = np.where(np.isfinite(at), np.round(at) - at, 0.0)  # (N, 2) projector (x, y)
    d = np.arange(-radius, radius + 1, dtype=np.float64)
    dy, dx = np.meshgrid(d, d, indexing="ij")
    offsets = np.stack([dx.ravel(), dy.ravel()], axis=1)  # (M, 2) camera (x, y)
    u = np.einsum("nij,mj->nmi", jac, offsets) - e[:, None, :]  # (N, M, 2) projector px from the dot
    w = np.clip(1 - np.abs(u[..., 0]), 0, None) * np.clip(1 - np.abs(u[..., 1]), 0, None)
    total = w.sum(axis=1, keepdims=True)
    centre = pixel_alone_kernel(radius).ravel().astype(np.float64)
    w = np.where(total > 1e-9, w / np.maximum(total, 1e-9), centre)  # (no weight at all: the pixel itself)
    return w.reshape(-1, side, side).astype(np.float32)


def dark_reference(black: np.ndarray, white: np.ndarray, *, window: int = 7, floor: float = 0.02) -> np.ndarray:
    """A low-noise estimate ``(H, W, C)`` of the black frame, to subtract from every dot-grid frame.

    Each camera pixel lies in the crops of ~K^2 footprints, so the noise of one black frame would be
    subtracted ~K^2 times at the same place (coherently) when footprints are splatted: on the CPU
    preset it cost relit soap 6 dB. The projector's black light is a smooth fraction of the white
    image, so the estimate is ``(box(black) / box(white)) * white`` over ``window x window`` pixels
    where the white image is above ``floor``, and ``box(black)`` elsewhere.
    """
    black = np.asarray(black, np.float32)
    white = np.asarray(white, np.float32)
    size = (window, window) + (1,) * (black.ndim - 2)
    bb, ww = uniform_filter(black, size), uniform_filter(white, size)
    lit = ww > floor
    return np.where(lit, bb / np.where(lit, ww, 1.0) * white, bb).astype(np.float32)


def transport_weights(pixels: np.ndarray, xp: np.ndarray, yp: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(N,)`` weights that turn per-camera-pixel crops back into the light transport, each dot once.

    Every camera pixel whose rounded projector coordinate is dot d stores d's response scaled by
    ``|det J|``; where the camera is finer than the projector, d is stored by n(d) > 1 pixels (1 or 2
    on the CPU preset, in a moire pattern). Relighting with the crops as camera-pixel footprints
    then counts each dot ``n(d) |det J|`` times, ~1 only on average. With these weights,
    ``1 / (n(d) |det J|)``, the splat is ``sum_d L(d) response_d`` over the captured dots: the
    measured transport applied to the pattern, whatever the rig's light model.
    """
    pixels = np.asarray(pixels, np.int64)
    rx = np.floor(xp[pixels[:, 0], pixels[:, 1]].astype(np.float64) + 0.5).astype(np.int64)
    ry = np.floor(yp[pixels[:, 0], pixels[:, 1]].astype(np.float64) + 0.5).astype(np.int64)
    _, inverse, counts = np.unique(ry * (1 << 20) + rx, return_inverse=True, return_counts=True)
    area = jacobian_area(xp, yp, mask)[pixels[:, 0], pixels[:, 1]]
    return (1.0 / (counts[inverse.ravel()] * np.maximum(area, 1e-6))).astype(np.float32)


class DotTransportExtractor:
    """The measured light transport, one column per projector dot: ``K x K x C`` crops of each dot-grid
    frame around the camera pixel that sees the dot, for *every* dot that lands on the object.

    Relighting with it is ``sum_d L(d) crop_d`` placed at the dot's camera pixel, with ``L(d)`` the
    pattern's light at projector pixel d exactly: no Jacobian, no per-camera-pixel assumption. Unlike
    :class:`DotGridExtractor` (one crop per camera pixel, for training), a camera pixel that sees
    several projector pixels (grazing surfaces) gets one crop per dot, and a dot seen by several camera
    pixels is stored once. A dot belongs to the valid camera pixel whose projector coordinate is
    nearest, within :data:`DOT_REACH` projector px. That includes dots that land where the camera has
    no decoded coordinate (a silhouette seen at grazing angles, the side just out of view) but whose
    light scatters into pixels it does see: keeping only dots within a pixel's own extent lost 16% of
    the crab's dots, all at the silhouette (``measured`` 40.2 -> 47.9 dB against the camera's image
    once kept). Dots whose crop holds no light above the noise (:func:`holds_light`) are left out of
    :meth:`result`. Crops are cut to their dot's Voronoi cell in projector space (as
    ``DotGridExtractor.isolate``).
    """

    def __init__(self, xp: np.ndarray, yp: np.ndarray, mask: np.ndarray, spacing: int, patch: int,
                 projector_size: tuple[int, int], *, channels: int = 3, dtype: np.dtype = np.float16) -> None:
        from scipy.spatial import cKDTree

        if xp.shape != yp.shape or xp.shape != mask.shape or xp.ndim != 2:
            raise InputError(f"xp, yp and mask must share one (H, W) shape, got {xp.shape}, {yp.shape}, {mask.shape}")
        if spacing < 1 or patch < 1:
            raise InputError(f"spacing and patch must be >= 1, got {spacing}, {patch}")
        self.shape, self.spacing, self.patch, self.channels, self.dtype = xp.shape, int(spacing), int(patch), channels, dtype
        valid = mask & np.isfinite(xp) & np.isfinite(yp)
        self._valid = valid
        self._xp, self._yp = np.where(valid, xp, 0.0).astype(np.float64), np.where(valid, yp, 0.0).astype(np.float64)
        vy, vx = np.nonzero(valid)
        wp, hp = projector_size
        gy, gx = np.mgrid[0:hp, 0:wp]
        dots = np.stack([gx.ravel(), gy.ravel()], axis=1)
        if len(vy) == 0:
            self.dots, self.pixels = np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64)
        else:
            dist, nearest = cKDTree(np.stack([self._xp[vy, vx], self._yp[vy, vx]], axis=1)).query(
                dots.astype(np.float64), distance_upper_bound=DOT_REACH)
            found = np.isfinite(dist)
            self.dots = dots[found].astype(np.int64)
            self.pixels = np.stack([vy[nearest[found]], vx[nearest[found]]], axis=1).astype(np.int64)
        self._groups = _by_shift((self.dots[:, 1] % spacing) * spacing + self.dots[:, 0] % spacing, spacing)
        self._crops: np.ndarray | None = None  # allocated by the first ``add`` (``crops`` streams)
        self._lit = np.zeros(len(self.dots), bool)

    def add(self, shift_x: int, shift_y: int, frame: np.ndarray) -> int:
        """Crop and keep the dots of dot-grid frame ``(shift_x, shift_y)`` (black already subtracted)."""
        idx, crops = self.crops(shift_x, shift_y, frame)
        if self._crops is None:  # pages are touched as dots arrive
            self._crops = np.zeros((len(self.dots), self.patch, self.patch, self.channels), self.dtype)
        self._crops[idx] = crops
        return len(idx)

    def crops(self, shift_x: int, shift_y: int, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(idx (n,), crops (n, K, K, C) float32)`` of the dots of frame ``(shift_x, shift_y)``
        (``self.dots[idx]``, seen at ``self.pixels[idx]``), without keeping them. Marks them as lit."""
        s, k = self.spacing, self.patch
        frame = _dot_frame(shift_x, shift_y, frame, s, self.shape, self.channels)
        idx = self._groups[shift_y * s + shift_x]
        if len(idx) == 0:
            return idx, np.zeros((0, k, k, self.channels), np.float32)
        own = _cell_labels(self.dots[idx, 0].astype(np.float64), self.dots[idx, 1].astype(np.float64),
                           np.ones(len(idx), bool), shift_x, shift_y, s)
        crops = _isolated_windows(frame, self.pixels[idx, 0], self.pixels[idx, 1], own, k,
                                  (self._xp, self._yp, self._valid), shift_x, shift_y, s)
        self._lit[idx] = True
        return idx, crops

    def result(self, *, drop_noise: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(pixels (N, 2) yx, dots (N, 2) projector xy, crops (N, K, K, C))`` of the dots seen so far;
        with ``drop_noise`` the crop values below the noise floor (:func:`above_noise`) are 0, which the
        relighting would drop anyway and which makes the store ~4x smaller. ``self.noise`` is then the
        crops' noise std before the drop (record it: it cannot be estimated from dropped crops)."""
        crops = self._crops[self._lit] if self._crops is not None else np.zeros((0, self.patch, self.patch, self.channels), self.dtype)
        pixels, dots = self.pixels[self._lit], self.dots[self._lit]
        self.noise = crop_noise(crops[:NOISE_SAMPLE]) if len(crops) else 0.0  # of the crops as captured
        if drop_noise and len(crops):
            crops = drop_below_noise(crops, self.noise)
            seen = holds_light(crops)
            pixels, dots, crops = pixels[seen], dots[seen], crops[seen]
        return pixels, dots, crops


#: How far (projector px) a dot may land from the nearest decoded camera pixel and still be kept
#: (its light is looked for in the K x K window around that pixel).
DOT_REACH = 8.0

#: Crops whose outer ring measures the noise floor of a view's transport (the first ones captured).
NOISE_SAMPLE = 512


#: Smoothings (px) of the candidate noise masks (:func:`above_noise`). A stored transport keeps what any of
#: them keeps, and relighting uses, per view, the one whose transport relights the view's own fringe captures
#: best (``relight.transport.denoised_transport``). Neither wins everywhere (measured, relit checkerboard):
#: the sim crab 41.1 dB with 1 px against 38.4 with 2 px, while a frame-filling wide scatterer with
#: shot noise and a clean black frame 25.6 against 29.3 (1 px drops its faint tails, which add up).
DENOISE_SMOOTHING = (1.0, 2.0)


def drop_below_noise(crops: np.ndarray, noise: float, smoothings: tuple[float, ...] = DENOISE_SMOOTHING) -> np.ndarray:
    """``crops`` (N, K, K, C) with the values that no mask of ``smoothings`` keeps (:func:`above_noise`) set to 0."""
    keep = np.zeros(np.shape(crops)[:3], bool)
    for s in smoothings:
        keep |= above_noise(crops, noise, smoothing=s)
    return crops * keep[..., None].astype(crops.dtype)


def holds_light(crops: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the crops (N, K, K, C) with any value left after :func:`drop_below_noise` (a dot
    whose light reached the camera)."""
    return np.asarray(crops).reshape(len(crops), -1).any(axis=1)


#: Ring values below which :func:`crop_noise` measures the noise inside the crops' own cells instead.
RING_SAMPLES = 256
#: Footprint crop sizes K a rig or an import takes: the crop's noise is read from its outer 2 px
#: (:func:`crop_noise`), so below 9 px that ring is the footprint itself and every crop reads as noise;
#: the paper's rig uses 90, and past 256 a relight chunk of crops alone needs gigabytes.
PATCH_RANGE = (9, 256)


def crop_noise(crops: np.ndarray, border: int = 2) -> float:
    """Robust noise std of captured crops ``(N, K, K, C)`` (0 for exact footprints and noise-free renders).

    Where the light of the dot has decayed: 1.4826 x the median absolute value of the outer ``border`` rows
    and columns, zeros (pixels cut to another dot's cell) left out. Where the surface fills the crops, every
    ring pixel belongs to another dot's cell and that ring is empty (a slab filling the view, a render of a
    large object): then the outer half of each crop's own cell (by distance from its centre), from its
    negative values alone: light is not negative, so after black subtraction those are noise, while the
    positive ones may be the footprint's tail (a noise-free render has none and reads 0). Without this the
    noise read 0 on such captures and nothing was denoised (the captured transport of a frame-filling
    scene with noise std 0.01 relit a checkerboard at 23.2 dB, 26.8 with it)."""
    crops = np.asarray(crops, np.float32)
    if crops.ndim == 3:
        crops = crops[..., None]
    k = crops.shape[1]
    ring = np.ones((k, k), bool)
    ring[border:k - border, border:k - border] = False
    values = crops[:, ring].ravel()
    values = values[values != 0]
    if values.size >= RING_SAMPLES or not len(crops):
        return float(1.4826 * np.median(np.abs(values))) if values.size else 0.0
    kept = (crops != 0).any(axis=-1)  # (N, K, K): the crop's own cell (and pixels off the surface)
    r = np.hypot(*np.meshgrid(np.arange(k) - k // 2, np.arange(k) - k // 2, indexing="ij"))
    reach = np.where(kept, r, 0).reshape(len(crops), -1).max(axis=1)  # (N,) the cell's extent
    outer = crops[kept & (r >= 0.5 * reach[:, None, None])]
    negative = outer[outer < 0]
    if negative.size < max(RING_SAMPLES // 4, 0.05 * outer.size):  # (almost) none: no noise to speak of
        return 0.0
    return float(1.4826 * np.median(-negative))


def above_noise(crops: np.ndarray, noise: float, sigmas: float = 3.0, smoothing: float = 1.0) -> np.ndarray:
    """``(N, K, K)`` bool: where a crop's luminance, smoothed by a Gaussian of ``smoothing`` px, is above
    ``sigmas`` times the noise of that smoothed map. Each camera pixel lies in ~K^2 crops, so their noise
    would add up; a wider smoothing finds fainter (wide) tails, whose light adds up too."""
    from scipy.ndimage import gaussian_filter

    smooth = gaussian_filter(np.asarray(crops, np.float32).mean(axis=-1), (0, smoothing, smoothing))
    return smooth > sigmas * noise / (2 * np.sqrt(np.pi) * smoothing)
