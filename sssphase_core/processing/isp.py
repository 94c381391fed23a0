"""Camera raw processing, the paper's chain: 3x3 median per RGGB plane, Malvar-He-Cutler demosaicing,
black level and scaling to linear camera units; plus HDR merging of exposure brackets.

numpy at module level only; OpenCV is imported inside the functions.
Bayer layouts: RGGB (R at (even row, even col), B at (odd, odd)) and its shifts GRBG, GBRG, BGGR,
developed by re-phasing the mosaic to RGGB (one reflected row and/or column) and cutting it back.
"""

from __future__ import annotations

import numpy as np

from sssphase_core.errors import InputError

#: A sample counts as saturated from this fraction of its clipping level (demosaicing mixes
#: clipped neighbours into nearby samples).
SATURATION_MARGIN = 0.95


#: Bayer layouts -> where the red sample sits in each 2 x 2 cell (row, column).
BAYER_LAYOUTS = {"RGGB": (0, 0), "GRBG": (0, 1), "GBRG": (1, 0), "BGGR": (1, 1)}


def check_layout(layout: str) -> str:
    """``layout`` if it is a known Bayer layout (:data:`BAYER_LAYOUTS`), else one clear error."""
    if layout not in BAYER_LAYOUTS:
        raise InputError(f"unknown Bayer layout {layout!r}; use one of {', '.join(BAYER_LAYOUTS)}")
    return layout


#: :func:`detect_bayer_layout`: the noise of a demosaiced frame varies over the 2 x 2 sites by at least
#: this much (max |site / mean - 1|; 0.33-0.62 measured on the sim camera's, 0.01 on three-chip frames and
#: renders), the best layout's correlation reaches ``BAYER_MIN_CORR`` (Malvar's frames 0.87-0.99; OpenCV's
#: edge-aware demosaicing mixes the sites' noise: 0.3-0.7, declined, and the import says so) and beats the
#: next by ``BAYER_MARGIN``.
BAYER_SITE_SPREAD, BAYER_MIN_CORR, BAYER_MARGIN, BAYER_MIN_PIXELS = 0.15, 0.8, 0.2, 400
#: ... and the sites' pattern of each fringe set correlates with the others' by at least this much (Malvar's frames
#: 0.80 in the import tests; a noise-free render whose fringes alias along each set's direction: 0.00).
BAYER_SETS_AGREE = 0.5
#: The residual's squares are capped at this quantile over the mask before each site's mean: a path tracer's stray
#: sample (a firefly 10^4 times the light) made a render's sites differ by 3 and the import suggest ``--bayer``.
BAYER_CAP_QUANTILE = 0.999


def detect_bayer_layout(fringe_sets: list[np.ndarray], white: np.ndarray, mask: np.ndarray) -> tuple[str | None, str]:
    """``(layout, why)``: the Bayer layout a camera demosaiced these frames from, read from their noise, or
    ``(None, why not)``.

    With an even number N of shifts, ``I_n + I_{n+N/2}`` is the same for every n, so
    ``(I_0 + I_{N/2}) - (I_1 + I_{1+N/2})`` holds noise only. Each photosite's noise is its own colour's shot
    noise, and demosaicing carries it into the other colours, so the residual's variance per 2 x 2 site
    (colours summed) follows the brightness of the colour that site samples: a layout is the assignment of
    colours to sites whose brightness (the white over ``mask``) correlates with it. Frames made without a
    colour filter array (three-chip cameras, renders) have the same noise at every site.
    ``fringe_sets``: each (N, H, W, 3) one orientation's shifts; ``white`` (H, W, 3); ``mask`` (H, W)."""
    residuals = [s[0] + s[len(s) // 2] - s[1] - s[1 + len(s) // 2] for s in fringe_sets if len(s) >= 4 and len(s) % 2 == 0]
    if not residuals:
        return None, "needs fringe sets of an even number of shifts"
    squares = [(np.asarray(r, np.float64) ** 2).mean(axis=-1) for r in residuals]  # (H, W): colours averaged
    if mask.any():  # a renderer's firefly would outweigh every other pixel of its site: capped with the brightest 0.1%
        squares = [np.minimum(q, np.quantile(q[mask], BAYER_CAP_QUANTILE)) for q in squares]
    site_noise, site_white = np.zeros((len(residuals), 2, 2)), np.zeros((2, 2, 3))  # per fringe set
    for i in range(2):
        for j in range(2):
            sel = np.zeros(mask.shape, bool)
            sel[i::2, j::2] = True
            sel &= mask
            if sel.sum() < BAYER_MIN_PIXELS:
                return None, f"too few decoded pixels ({int(mask.sum())})"
            site_noise[:, i, j] = [float(np.mean(q[sel])) for q in squares]
            site_white[i, j] = np.asarray(white, np.float64)[sel].mean(axis=0)
    each, site_noise = site_noise, site_noise.sum(axis=0)
    if not site_noise.mean() > 0:
        return None, "the frames hold no noise to read a layout from"
    spread = float(np.abs(site_noise / site_noise.mean() - 1).max())
    if spread < BAYER_SITE_SPREAD:
        return None, f"the noise is alike at every 2 x 2 site (spread {spread:.2f}): no colour filter array"
    colour = site_white.mean(axis=(0, 1))
    if not np.ptp(colour) > 0.05 * np.abs(colour).max():
        return None, "the object's colours are alike: the sites' noise cannot tell them apart"
    corr = {}
    for layout, (ry, rx) in BAYER_LAYOUTS.items():
        sample = np.ones((2, 2), int)  # green, then red and blue on the other diagonal
        sample[ry, rx], sample[1 - ry, 1 - rx] = 0, 2
        corr[layout] = float(np.corrcoef(colour[sample].ravel(), site_noise.ravel())[0, 1])
    ranked = sorted(corr, key=lambda k: -np.nan_to_num(corr[k], nan=-2.0))
    best, second = ranked[0], ranked[1]
    if not corr[best] >= BAYER_MIN_CORR or corr[best] - corr[second] < BAYER_MARGIN:
        return None, (f"the 2 x 2 sites' noise varies (spread {spread:.2f}) but matches no layout clearly "
                      f"({best} {corr[best]:.2f}, {second} {corr[second]:.2f})")
    # A sensor's pattern is the same in every fringe set; a residual that is not noise (the fringes aliased by a
    # camera pixel of 1.5 projector pixels: a render without noise) varies along each set's own fringe direction
    agree = min(float(np.corrcoef(a.ravel(), b.ravel())[0, 1]) for a, b in zip(each, each[1:], strict=False)) \
        if len(each) > 1 else 1.0
    if not agree >= BAYER_SETS_AGREE:
        return None, (f"the 2 x 2 sites' residual differs between the fringe sets (correlation {agree:.2f}): the fringes' "
                      "own structure, not a colour filter array's noise")
    return best, f"the noise of its 2 x 2 sites follows {best}'s colours (correlation {corr[best]:.2f}, spread {spread:.2f})"


#: :func:`detect_raw_mosaic`: a grey frame is a colour camera's raw Bayer samples when its 2 x 2 sites' levels (each
#: site's median over lit blocks of its sample over the block's mean) spread by at least this factor (max / min: an
#: RGGB mosaic of the exported sim crab's white 4.7, sites 1.99 0.79 0.80 0.42; the grey of that white, as a
#: monochrome camera would see it, 1.02, sites 0.99 0.99 1.01 1.01) ...
RAW_SITE_SPREAD = 1.08
#: ... and one diagonal's two sites (the greens) agree within this factor of each other's level (the crab's 1.015).
RAW_GREEN_AGREE = 1.04
#: Which sites hold green, by layout: the anti-diagonal ((0, 1) and (1, 0)) or the main one ((0, 0) and (1, 1)).
GREEN_DIAGONAL = {"RGGB": "anti", "BGGR": "anti", "GRBG": "main", "GBRG": "main"}


#: ... over at least this many lit 2 x 2 blocks (blocks whose mean is above RAW_LIT of the brightest's, the 99th
#: percentile).
RAW_MIN_BLOCKS, RAW_LIT = 64, 0.25


def raw_site_levels(grey: np.ndarray) -> np.ndarray | None:
    """(2, 2) levels of a grey (H, W) frame's 2 x 2 sites: each site's median, over the lit 2 x 2 blocks (their mean
    above :data:`RAW_LIT` of the 99th percentile of the blocks' means), of its sample over its block's mean (1 at
    every site for a monochrome camera); None with fewer than :data:`RAW_MIN_BLOCKS` such blocks."""
    h, w = (grey.shape[0] // 2) * 2, (grey.shape[1] // 2) * 2
    sites = np.asarray(grey[:h, :w], np.float64).reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3).reshape(-1, 2, 2)
    means = sites.mean(axis=(1, 2))
    finite = np.isfinite(means)
    if not finite.any():
        return None
    lit = finite & (means > RAW_LIT * float(np.percentile(means[finite], 99)))
    if lit.sum() < RAW_MIN_BLOCKS:
        return None
    return np.median(sites[lit] / means[lit, None, None], axis=0)


def detect_raw_mosaic(grey: np.ndarray) -> tuple[str | None, str]:
    """``(diagonal, why)``: where a grey (H, W) frame that is a colour camera's raw Bayer mosaic holds its greens
    (``"anti"``: RGGB or BGGR, ``"main"``: GRBG or GBRG; :data:`GREEN_DIAGONAL`), or ``(None, why not)`` for a
    monochrome camera's (its sites alike). Read from the sites' levels (:func:`raw_site_levels`; a white capture
    shows them best); which of the two non-green sites is red the frame cannot tell."""
    levels = raw_site_levels(grey)
    if levels is None:
        return None, "too few lit 2 x 2 blocks"
    said = f"site levels {' '.join(f'{v:.2f}' for v in levels.ravel())}"
    spread = float(levels.max() / max(levels.min(), 1e-12))
    pairs = {"anti": (levels[0, 1], levels[1, 0]), "main": (levels[0, 0], levels[1, 1])}
    agree = {d: max(a, b) / max(min(a, b), 1e-12) for d, (a, b) in pairs.items()}
    diagonal = min(agree, key=agree.__getitem__)
    if spread < RAW_SITE_SPREAD:
        return None, f"its 2 x 2 sites are alike ({said})"
    if agree[diagonal] > RAW_GREEN_AGREE:
        return None, f"no diagonal's two sites agree as a mosaic's greens do ({said})"
    return diagonal, f"its 2 x 2 sites hold different colours' light, greens on the {diagonal} diagonal ({said})"


def _check_mosaic(raw: np.ndarray) -> np.ndarray:
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.shape[0] % 2 or raw.shape[1] % 2:
        raise InputError(f"a Bayer mosaic must be 2-D with even sides, got shape {raw.shape}")
    return raw


def median3_bayer(raw: np.ndarray) -> np.ndarray:
    """3x3 median filter applied to each of the four RGGB planes separately (same dtype and shape)."""
    import cv2

    raw = _check_mosaic(raw)
    work = raw if raw.dtype in (np.uint8, np.uint16, np.float32) else raw.astype(np.float32)
    out = np.empty_like(work)
    for dy in (0, 1):
        for dx in (0, 1):
            out[dy::2, dx::2] = cv2.medianBlur(np.ascontiguousarray(work[dy::2, dx::2]), 3)
    return out.astype(raw.dtype, copy=False)


#: Malvar, He and Cutler 2004, "High-quality linear interpolation for demosaicing of Bayer-patterned colour images":
#: the 5 x 5 kernels (x 1/8) of what ``demosaic(method="malvar")`` computes, for the models of it elsewhere
#: (learning.camera, the sim's device sensor): green at red / blue sites; a colour at a green site whose row
#: holds that colour ("row") or whose column does ("col"); a colour at the opposite colour's site ("cross").
MALVAR_KERNELS: dict[str, list[list[float]]] = {
    "green": [[0, 0, -1, 0, 0], [0, 0, 2, 0, 0], [-1, 2, 4, 2, -1], [0, 0, 2, 0, 0], [0, 0, -1, 0, 0]],
    "row": [[0, 0, 0.5, 0, 0], [0, -1, 0, -1, 0], [-1, 4, 5, 4, -1], [0, -1, 0, -1, 0], [0, 0, 0.5, 0, 0]],
    "cross": [[0, 0, -1.5, 0, 0], [0, 2, 0, 2, 0], [-1.5, 0, 6, 0, -1.5], [0, 2, 0, 2, 0], [0, 0, -1.5, 0, 0]],
}
MALVAR_KERNELS["col"] = [list(r) for r in zip(*MALVAR_KERNELS["row"], strict=True)]


def malvar(raw: np.ndarray) -> np.ndarray:
    """RGGB mosaic (H, W) -> RGB (H, W, 3) float64, Malvar-He-Cutler 2004: each missing colour is the 5 x 5
    linear filter of :data:`MALVAR_KERNELS` for its site (OpenCV ``filter2D`` in float64, borders mirrored with the
    edge sample repeated, ``d c b a | a b c d``); measured samples are kept."""
    import cv2

    mosaic = np.ascontiguousarray(raw, np.float64)
    # the kernels are symmetric, so filter2D's correlation is the convolution; BORDER_REFLECT: d c b a | a b c d
    green, row, col, cross = (cv2.filter2D(mosaic, cv2.CV_64F, np.array(MALVAR_KERNELS[k], np.float64) / 8,
                                           borderType=cv2.BORDER_REFLECT) for k in ("green", "row", "col", "cross"))
    rgb = np.empty(mosaic.shape + (3,), np.float64)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    # red sites (even, even); green in red rows (even, odd); green in blue rows (odd, even); blue sites (odd, odd)
    for (dy, dx), red, grn, blu in (((0, 0), mosaic, green, cross), ((0, 1), row, mosaic, col),
                                    ((1, 0), col, mosaic, row), ((1, 1), cross, green, mosaic)):
        r[dy::2, dx::2], g[dy::2, dx::2], b[dy::2, dx::2] = red[dy::2, dx::2], grn[dy::2, dx::2], blu[dy::2, dx::2]
    return rgb


def demosaic(raw: np.ndarray, method: str = "malvar") -> np.ndarray:
    """RGGB mosaic (H, W) -> RGB (H, W, 3) float32 in the mosaic's units.

    ``malvar``: Malvar-He-Cutler 2004 (:func:`malvar`); ``opencv``: OpenCV's edge-aware (``COLOR_Bayer*_EA``).
    """
    raw = _check_mosaic(raw)
    if method == "malvar":
        return malvar(raw).astype(np.float32)
    if method == "opencv":
        import cv2

        # OpenCV names Bayer layouts by the second row's last two pixels: RGGB is its "BayerBG".
        scale = 65535.0 / max(float(raw.max()), 1e-12)
        as16 = np.clip(raw.astype(np.float64) * scale, 0, 65535).astype(np.uint16)
        return (cv2.cvtColor(as16, cv2.COLOR_BayerBG2RGB_EA).astype(np.float64) / scale).astype(np.float32)
    raise InputError(f"unknown demosaicing method {method!r}; use 'malvar' or 'opencv'")


def bayer_mosaic(rgb: np.ndarray, layout: str = "RGGB") -> np.ndarray:
    """Bayer mosaic of (..., H, W, 3) -> (..., H, W); RGGB: R at (even, even), B at (odd, odd), G elsewhere."""
    dy, dx = BAYER_LAYOUTS[check_layout(layout)]
    h, w = rgb.shape[-3:-1]
    yy, xx = np.mgrid[dy : h + dy, dx : w + dx]
    channel = np.where((yy % 2 == 0) & (xx % 2 == 0), 0, np.where((yy % 2 == 1) & (xx % 2 == 1), 2, 1))
    return np.take_along_axis(rgb, np.broadcast_to(channel[..., None], rgb.shape[:-1] + (1,)), axis=-1)[..., 0]


#: A demosaiced frame is a fixed point of its method: sampling it at its Bayer sites and demosaicing again gives it
#: back (but where the camera clipped it). A method is named when that redo departs from the fringe frames by less
#: than DEMOSAIC_MATCH of their light (the exported sim crab's finest fringes: Malvar 0.001 as floats, 0.005 as 8-bit
#: codes; noisy synthetic fringes: Malvar 0.000-0.003, OpenCV 0.007-0.010; OpenCV's bilinear 0.039 from OpenCV's
#: edge-aware, three-chip frames 0.17-0.21) and by less than DEMOSAIC_MARGIN of the other method's (0.07-0.21).
DEMOSAIC_MATCH, DEMOSAIC_MARGIN = 0.02, 0.3
DEMOSAIC_METHODS = ("malvar", "opencv")


def detect_demosaic(frames: np.ndarray, layout: str, mask: np.ndarray) -> tuple[str | None, str]:
    """``(method, why)``: which of :data:`DEMOSAIC_METHODS` made these frames from a ``layout`` mosaic, or
    ``(None, why not)``. Each method redoes the frames (:func:`through_camera`), on the ``mask``'s bounding box
    (even-aligned, so the layout keeps its phase); the one whose redo is (nearly) the frames is theirs.
    ``frames`` (N, H, W, 3): high-contrast ones tell the methods apart best (the finest fringes); ``mask`` (H, W)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size < 8 or cols.size < 8:
        return None, "too few lit pixels"
    box = (slice(rows[0] - rows[0] % 2, rows[-1] + 1), slice(cols[0] - cols[0] % 2, cols[-1] + 1))
    crop = np.asarray(frames, np.float32)[:, box[0], box[1]]
    # values a camera clipped (a filled colour below 0 beside a bright edge, or at the top) are no fixed point
    kept = mask[box][None, ..., None] & (crop > 0) & (crop < 0.999 * float(crop.max()))
    light = float(np.abs(crop[kept]).mean()) if kept.any() else 0.0
    if not light > 0:
        return None, "the frames hold no light"
    departs = {m: float(np.abs(through_camera(crop, demosaic=m, layout=layout) - crop)[kept].mean()) / light
               for m in DEMOSAIC_METHODS}
    best, other = sorted(departs, key=departs.__getitem__)
    said = ", ".join(f"{m} {v:.3f}" for m, v in departs.items())
    if departs[best] < DEMOSAIC_MATCH and departs[best] < DEMOSAIC_MARGIN * departs[other]:
        return best, (f"its fringe frames come back from {best} demosaicing of their own Bayer samples (departures "
                      f"{said})")
    return None, f"neither method gives its fringe frames back from their Bayer samples (departures {said})"


def through_camera(images: np.ndarray, *, demosaic: str = "malvar", median: bool = False, layout: str = "RGGB") -> np.ndarray:
    """What a camera whose raw frames this ISP develops records of linear images, noise aside:
    (..., H, W, 3) -> (..., H, W, 3) float32 in the same units (Bayer sampling in ``layout``, the 3x3
    median per Bayer plane if ``median``, demosaicing by ``demosaic``). Images made by light transport (a relit
    image, a render) become comparable with the camera's captures this way: demosaicing alone moves a
    dim colour's fringe contrast by several percent (measured: blue 0.93 -> 0.99 on a red object).
    Odd sides are padded by one reflected row or column for the mosaic and cut back."""
    arr = np.asarray(images, np.float32)
    h, w = arr.shape[-3:-1]
    pad = [(0, 0)] * (arr.ndim - 3) + [(0, h % 2), (0, w % 2), (0, 0)]
    flat = np.pad(arr, pad, mode="reflect" if min(h, w) > 1 else "edge").reshape(-1, h + h % 2, w + w % 2, 3)
    out = np.stack([develop(bayer_mosaic(f, layout), 0.0, 1.0, median=median, method=demosaic, layout=layout)
                    for f in flat])
    return out[:, :h, :w].reshape(arr.shape)


def develop(raw: np.ndarray, black_level: float, white_scale: float, *, median: bool = True, method: str = "malvar",
            layout: str = "RGGB") -> np.ndarray:
    """Raw Bayer frame (H, W) in ``layout`` -> linear RGB (H, W, 3) float32: median, demosaic,
    ``(x - black) / white_scale``.

    ``white_scale`` is the DN above black that one linear camera unit produces at the frame's exposure.
    """
    if not white_scale > 0:
        raise InputError(f"white_scale must be positive, got {white_scale}")
    dy, dx = BAYER_LAYOUTS[check_layout(layout)]
    raw = _check_mosaic(raw)
    if dy or dx:  # re-phase to RGGB: one reflected row / column before (and after, to keep the sides even)
        raw = np.pad(raw, ((dy, dy), (dx, dx)), mode="reflect")
    mosaic = median3_bayer(raw) if median else raw
    rgb = demosaic(mosaic, method)[dy : dy + raw.shape[0] - 2 * dy, dx : dx + raw.shape[1] - 2 * dx]
    return ((rgb - np.float32(black_level)) / np.float32(white_scale)).astype(np.float32)


#: A share of a bracket's longest frame at one bright value above which that value is a clipping level (clipped
#: samples, and the interior of a clipped area after demosaicing, all read the same number).
FLAT_TOP_SHARE = 0.002


def clipping_below(frames: np.ndarray, exposures, saturation: float) -> float | None:
    """The level (at exposure 1, as ``saturation``) where the longest frame of a bracket ``frames`` (E, ...) visibly
    clips when that is below ``SATURATION_MARGIN`` x ``saturation``, else None: the value that most of its brightest
    tenth share exactly, when they are more than :data:`FLAT_TOP_SHARE` of the frame, 5x the next lower value and more
    than all above it (a spike at the top, not one of a dim 8-bit scene's codes). A rig file whose saturation was too high (4095, a sensor's top
    code, where developed frames clip at 1.67) made :func:`hdr_merge` trust clipped samples without a word."""
    longest = int(np.argmax(np.asarray(exposures, float)))
    on_sensor = (np.asarray(frames[longest], np.float32) * np.float32(exposures[longest])).ravel()
    bright = on_sensor[on_sensor >= np.percentile(on_sensor, 90)]
    if bright.size == 0:
        return None
    values, counts = np.unique(bright, return_counts=True)
    i = int(np.argmax(counts))
    level, at_level = float(values[i]), int(counts[i])
    if not np.isfinite(level) or level <= 0 or level >= SATURATION_MARGIN * saturation:
        return None
    next_below = int(counts[i - 1]) if i > 0 else 0  # (a quantised scene's neighbouring code is about as common)
    above = int(counts[i + 1:].sum())  # (demosaicing's overshoot around a clipped area: fewer than its interior)
    spike = at_level > FLAT_TOP_SHARE * on_sensor.size and at_level > 5 * next_below and above < at_level
    return level if spike else None


def hdr_merge(
    frames: np.ndarray,
    exposures,
    saturation: float,
    *,
    electrons_per_unit: float | None = None,
    read_noise: float = 0.0,
    spread: int = 2,
) -> np.ndarray:
    """Merge an exposure bracket into one linear image.

    ``frames`` (E, ...) are developed images each already in linear camera units (as
    ``SimScene.capture`` returns them); frame i was taken at relative exposure ``exposures[i]`` and
    clips at ``saturation / exposures[i]`` (``saturation``: clipping level at exposure 1). Samples
    at or above ``SATURATION_MARGIN`` of their clipping level are ignored, and so is every colour of
    every pixel within ``spread`` px of one in that frame, for images ``(E, H, W[, 3])``:
    demosaicing (a 5 x 5 kernel: 2 px; 4 px with the paper's 3 x 3 median per Bayer plane) carries
    a clipped sample into its neighbours' values, in every colour, below the clipping level (measured
    on a red crab under a checkerboard: the merged red 0.008 low on average, 34 dB against the camera's
    noise-free image, 44 dB with the spread). Weights are inverse
    variances under Poisson-Gaussian noise: with photon noise only they are proportional to the
    exposure (the merge is then the maximum-likelihood sum of counts over sum of times); with
    ``electrons_per_unit`` (at exposure 1) and ``read_noise`` (electrons) the read noise is included.
    Where every sample is saturated, the shortest exposure's (clipped) value is kept.
    """
    x = np.asarray(frames, np.float64)
    t = np.asarray(exposures, np.float64).reshape((-1,) + (1,) * (x.ndim - 1))
    if x.shape[0] != t.shape[0] or x.shape[0] == 0:
        raise InputError(f"need one exposure per frame, got {x.shape[0]} frames and {t.shape[0]} exposures")
    if not (t > 0).all() or not saturation > 0:
        raise InputError("exposures and saturation must be positive")
    ok = x < SATURATION_MARGIN * saturation / t
    if spread > 0 and x.ndim >= 3:
        from scipy.ndimage import binary_dilation

        clipped = ~ok if x.ndim == 3 else ~ok.all(axis=-1)  # (E, H, W): any colour of the pixel
        reach = np.ones((1, 2 * spread + 1, 2 * spread + 1), bool)
        near = binary_dilation(clipped, structure=reach)
        ok = ~near if x.ndim == 3 else ~near[..., None] & ok
    w = np.where(ok, t, 0.0)
    total = w.sum(axis=0)
    merged = np.where(total > 0, (w * x).sum(axis=0) / np.where(total > 0, total, 1.0), 0.0)
    if electrons_per_unit is not None and read_noise > 0:
        k = electrons_per_unit * t  # electrons per unit at each exposure
        var = (np.clip(merged, 0, None) * k + read_noise**2) / k**2
        w = np.where(ok, 1.0 / var, 0.0)
        total = w.sum(axis=0)
        merged = np.where(total > 0, (w * x).sum(axis=0) / np.where(total > 0, total, 1.0), merged)
    shortest = x[np.argmin(t.ravel())]
    return np.where(ok.any(axis=0), merged, shortest).astype(np.float32)


#: A frame under a pattern no brighter than full white exceeds the robust white image by at most noise.
#: Values above ``OUTLIER_GAIN x white + OUTLIER_FLOOR x (the white's 99.9th percentile)`` are outliers.
OUTLIER_GAIN, OUTLIER_FLOOR = 1.5, 0.05


def robust_white(white: np.ndarray, psp_sets: list[list[np.ndarray]]) -> np.ndarray:
    """(H, W, C) the white image, robust to an outlier in any one frame: the median of the white capture and
    each PSP set's ``2 x mean over its shifts`` (N frames (H, W, C) each; the shifted fringes average to half
    the white light, whatever the scattering), so a firefly in one frame moves it by nothing. The sets are
    summed frame by frame (a 1080p set is 100 MB stacked)."""
    estimates = [np.asarray(white, np.float32)]
    for frames in psp_sets:
        total = np.zeros_like(estimates[0])
        for frame in frames:
            total += frame
        estimates.append(total * np.float32(2 / max(len(frames), 1)))
    return np.median(np.stack(estimates), axis=0).astype(np.float32)


def outlier_bound(white: np.ndarray) -> np.ndarray:
    """(H, W, 1) the largest value a frame under any pattern (no brighter than full white) may hold at each
    pixel, in any colour, from a :func:`robust_white` (H, W, C): its brightest colour over the 3 x 3
    neighbourhood, since demosaicing moves a sparse pattern's light between colours and neighbours (a dot
    frame's blue on the red sim crab reaches 2.5x the white's blue there)."""
    import cv2

    w = np.asarray(white, np.float32)
    top = float(np.percentile(w, 99.9)) if w.size else 0.0
    brightest = cv2.dilate(np.maximum(w.max(axis=-1), 0), np.ones((3, 3), np.uint8))
    return (OUTLIER_GAIN * brightest + OUTLIER_FLOOR * max(top, 0.0))[..., None].astype(np.float32)


#: A pixel is hot where its black frame exceeds its neighbours' by this many noise sigmas (robust, from the
#: whole frame) plus this fraction of the white's 99.9th percentile, and every lit frame shows at least half
#: that excess too (or the pixel is stuck: it answers light by less than STUCK_RESPONSE of its neighbours'
#: answer); more than HOT_MAX_FRACTION of the pixels so marked is no sensor defect but content (nothing is
#: then changed).
HOT_SIGMAS, HOT_FLOOR, HOT_MAX_FRACTION, STUCK_RESPONSE = 8.0, 1e-3, 0.01, 0.1


def hot_pixel_offsets(black: np.ndarray, lit: list[np.ndarray]) -> np.ndarray:
    """(H, W, C) float32: what hot pixels (sensor defects that add the same value to every frame) add, 0
    elsewhere; subtract it from every frame.

    A hot pixel survives the smoothed black that the dot grids subtract
    (:func:`~sssphase_core.processing.footprints.dark_reference`) and so sits in every footprint crop around
    it: 60 of them (0.02-0.3 each) in a 200 x 150 import took its captured transport from 32 to 0.9 dB.
    Found in ``black`` (H, W, C) as an excess over the 3 x 3 median beyond what the projector's black light
    on the texture gives (``r x`` the white's excess, ``r`` the black / white ratio), confirmed by the
    median excess of the ``lit`` frames (the white, each PSP set's mean over its shifts: a defect adds to
    all alike; a firefly in the black frame alone is not one) or by a white no brighter than the black
    where the neighbours answer light (a stuck pixel, the same value in every frame: subtracting its
    offset leaves it dark, and decoding leaves it out). Subtracting the offset keeps a hot pixel's signal
    (its fringe phase), which replacing it by its neighbours would not."""
    import cv2

    black = np.asarray(black, np.float32)
    lit = [np.asarray(f, np.float32) for f in lit]
    if not lit or black.ndim != 3 or min(black.shape[:2]) < 3 or any(f.shape != black.shape for f in lit):
        return np.zeros(black.shape, np.float32)
    white = lit[0]
    top = max(float(np.percentile(white, 99.9)), 0.0)
    on = white > 0.05 * top
    ratio = float(np.clip(np.median(black[on] / white[on]), 0.0, 0.5)) if on.any() else 0.0
    offsets = np.zeros(black.shape, np.float32)
    for c in range(black.shape[-1]):
        b = black[..., c]
        excess_b = b - cv2.medianBlur(b, 3)
        excess_each = [f[..., c] - cv2.medianBlur(np.ascontiguousarray(f[..., c]), 3) for f in lit]  # white first
        excess_lit = np.median(excess_each, axis=0)
        excess = excess_b - ratio * excess_each[0]
        sigma = 1.4826 * float(np.median(np.abs(excess - np.median(excess))))
        response = white[..., c] - b  # what light adds; ~0 at a stuck pixel whatever its value
        around = cv2.medianBlur(np.ascontiguousarray(response), 3)
        stuck = (np.abs(response) < STUCK_RESPONSE * around) & (around > HOT_SIGMAS * sigma + HOT_FLOOR * top)
        hot = (excess > HOT_SIGMAS * sigma + HOT_FLOOR * top) & ((excess_lit > 0.5 * excess) | stuck)
        offsets[..., c] = np.where(hot, excess_b, 0.0)
    return offsets if (offsets > 0).any(axis=-1).mean() <= HOT_MAX_FRACTION else np.zeros(black.shape, np.float32)


def repair_outliers(frame: np.ndarray, bound: np.ndarray) -> tuple[np.ndarray, int]:
    """``(frame, n)``: the (H, W, C) frame with the values above ``bound`` (fireflies of a path tracer, cosmic
    rays: isolated values brighter than full white could make them) replaced by the median of their 3 x 3
    neighbourhood; ``n`` the number replaced. A frame without any is returned as it is."""
    import cv2

    frame = np.asarray(frame, np.float32)
    bad = frame > bound
    n = int(bad.sum())
    if not n:
        return frame, 0
    out = frame.copy()
    for c in range(frame.shape[-1]):
        if bad[..., c].any():
            med = cv2.medianBlur(np.where(bad[..., c], 0, frame[..., c]).astype(np.float32), 3)
            out[..., c] = np.where(bad[..., c], med, frame[..., c])
    return out, n


#: Non-finite values a frame may hold and still be imported (repaired): path tracers leave a few NaN or inf
#: pixels (a degenerate sample); more is a broken file or pipeline, refused.
NONFINITE_LIMIT = 1e-3


def repair_nonfinite(frame: np.ndarray) -> tuple[np.ndarray, int]:
    """``(frame, n)``: the (H, W, C) frame with its NaN / inf values replaced by the median of the finite
    values of their 3 x 3 neighbourhood (wider, up to 17 x 17, where none is finite, else 0); ``n`` the number
    replaced."""
    frame = np.asarray(frame, np.float32)
    bad = ~np.isfinite(frame)
    n = int(bad.sum())
    if not n:
        return frame, 0
    out = frame.copy()
    for y, x, c in zip(*np.nonzero(bad), strict=True):
        for r in (1, 2, 4, 8):
            window = frame[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1, c]
            finite = window[np.isfinite(window)]
            if finite.size:
                out[y, x, c] = np.median(finite)
                break
        else:
            out[y, x, c] = 0.0
    return out, n
