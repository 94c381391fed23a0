"""How a dot-grid crop records a footprint (learning.camera), and what decoder training gains from modelling it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from sssphase_core.errors import InputError
from sssphase_core.learning.camera import (
    NO_CAMERA,
    CaptureModel,
    as_captured,
    bayer_demosaic,
    crop_codes,
    rebayer,
    shift_subpixel,
    spread_dot,
    through_camera,
)
from sssphase_core.processing import isp


def _crop(img: np.ndarray, p: tuple[int, int], k: int) -> np.ndarray:
    return img[p[0] - k // 2 : p[0] - k // 2 + k, p[1] - k // 2 : p[1] - k // 2 + k]


@pytest.mark.parametrize("layout", ["RGGB", "GRBG", "GBRG", "BGGR"])
@pytest.mark.parametrize("median", [False, True])
def test_a_crop_through_the_camera_is_the_crop_of_the_camera_image(layout, median):
    """Crops of an image, passed through their camera at their own Bayer phase, equal the crops of the whole
    image developed by the ISP (Malvar and the per-plane median, both via OpenCV)."""
    rng = np.random.default_rng(0)
    img = rng.random((40, 46, 3)).astype(np.float32)
    developed = isp.through_camera(img, demosaic="malvar", median=median, layout=layout)
    k, border = 14, 4 if median else 2  # the crop's edge lacks the neighbours the whole image had
    pixels = np.array([[20, 23], [21, 23], [20, 24], [21, 24]])  # all four Bayer phases
    codes = crop_codes({"bayer": layout, "demosaic": "malvar", "median": median}, pixels, k)
    assert len(set(codes.tolist())) == 4
    crops = torch.tensor(np.stack([_crop(img, p, k) for p in pixels])).permute(0, 3, 1, 2)
    out = through_camera(crops, codes).permute(0, 2, 3, 1).numpy()
    for p, o in zip(pixels, out, strict=True):
        inner = (slice(border, -border), slice(border, -border))
        np.testing.assert_allclose(o[inner], _crop(developed, p, k)[inner], atol=2e-6)


@pytest.mark.parametrize("method", ["malvar", "bilinear"])
def test_demosaicing_models_keep_a_flat_colour(method):
    flat = torch.tensor([0.7, 0.2, 0.05]).view(1, 3, 1, 1).expand(2, 3, 10, 10).clone()
    for phase in range(4):
        out = bayer_demosaic(flat, phase, method)
        torch.testing.assert_close(out[..., 2:-2, 2:-2], flat[..., 2:-2, 2:-2], atol=1e-6, rtol=0)


def test_views_without_a_bayer_pipeline_are_left_alone():
    fp = torch.rand(3, 3, 8, 8)
    for isp_record in (None, {"bayer": "RGGB", "demosaic": "other"}, {}):
        codes = crop_codes(isp_record, np.array([[5, 5], [6, 7], [9, 2]]), 8)
        assert (codes == NO_CAMERA).all()
        assert through_camera(fp, codes) is fp
    assert as_captured(fp, np.full(3, NO_CAMERA)) is fp


def test_shift_subpixel_moves_a_dot_bilinearly_and_keeps_its_light():
    dot = torch.zeros(1, 1, 7, 7)
    dot[0, 0, 3, 3] = 1.0
    moved = shift_subpixel(dot, torch.tensor([[-0.25, 0.5]]))[0, 0]  # (dy, dx): up a quarter, right a half
    expect = torch.zeros(7, 7)
    expect[3, 3], expect[3, 4], expect[2, 3], expect[2, 4] = 0.375, 0.375, 0.125, 0.125
    torch.testing.assert_close(moved, expect, atol=1e-6, rtol=0)
    assert shift_subpixel(dot, torch.zeros(1, 2)) is dot


def _dots(n: int, jac: np.ndarray) -> torch.Tensor:
    """(n, 7, 7) dot kernels of n pixels under an affine correspondence of Jacobian ``jac`` [[dxp/dx, dxp/dy],
    [dyp/dx, dyp/dy]]: their projector coordinates, and so their dots' offsets, differ from pixel to pixel."""
    from sssphase_core.processing.footprints import dot_kernels

    yy, xx = np.mgrid[:60, :60].astype(np.float64)
    xp, yp = jac[0, 0] * xx + jac[0, 1] * yy + 0.37, jac[1, 0] * xx + jac[1, 1] * yy - 0.21
    pixels = np.array([[8 + (5 * i) % 44, 8 + (7 * i) % 44] for i in range(n)])
    return torch.as_tensor(dot_kernels(xp, yp, np.ones(xp.shape, bool), pixels))


def test_the_capture_model_is_differentiable():
    fp = torch.rand(4, 3, 10, 10, requires_grad=True)
    codes = crop_codes({"bayer": "RGGB", "demosaic": "opencv", "median": True}, np.array([[5, 5], [5, 6], [6, 5], [6, 6]]), 10)
    dots = _dots(4, np.array([[0.6, 0.1], [0.0, 1.0]]))
    out = as_captured(fp, codes, dots)
    assert torch.equal(CaptureModel()(fp, torch.as_tensor(codes), dots), out)  # the module form
    out.square().sum().backward()
    assert fp.grad is not None and torch.isfinite(fp.grad).all() and fp.grad.abs().sum() > 0


def test_fitting_through_the_capture_model_recovers_the_footprint_the_crops_blur():
    """Crops of one footprint recorded at the four Bayer phases by dots of varied offsets, the projector magnified
    1.4 x along x on the camera: their mean is a blurred footprint (the red centre share drops to under 3/4 of
    the true one), while a footprint fitted through the capture model is the true one."""
    k = 12
    r2 = (np.mgrid[:k, :k] - k // 2).astype(np.float32) ** 2
    true = np.stack([np.exp(-(r2[0] + r2[1]) / (2 * s * s)) for s in (0.6, 0.8, 1.2)], 0)
    true = torch.tensor(true / true.sum(axis=(1, 2), keepdims=True) * np.array([0.5, 0.3, 0.2])[:, None, None],
                        dtype=torch.float32)
    rng = np.random.default_rng(1)
    n = 64
    pixels = rng.integers(20, 60, size=(n, 2))
    codes = crop_codes({"bayer": "RGGB", "demosaic": "malvar", "median": False}, pixels, k)
    dots = _dots(n, np.array([[0.7, 0.0], [0.0, 1.1]]))
    crops = as_captured(true.expand(n, -1, -1, -1).contiguous(), codes, dots)
    logits = torch.zeros(3, k * k, requires_grad=True)
    opt = torch.optim.Adam([logits], lr=0.05)
    energy = true.sum(dim=(1, 2))
    for _ in range(400):
        fit = torch.softmax(logits, dim=-1).view(3, k, k) * energy[:, None, None]
        loss = (as_captured(fit.expand(n, -1, -1, -1), codes, dots) - crops).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    fit = (torch.softmax(logits, dim=-1).view(3, k, k) * energy[:, None, None]).detach()
    c = k // 2
    share = lambda f: (f[:, c, c] / f.sum(dim=(1, 2))).numpy()  # noqa: E731
    mean_crop = crops.mean(dim=0)
    assert share(mean_crop)[0] < 0.75 * share(true)[0]  # what a decoder fitted to the crops themselves learns
    np.testing.assert_allclose(share(fit), share(true), atol=0.03)
    assert float((fit - true).abs().sum()) < 0.25 * float((mean_crop - true).abs().sum())


def test_dot_kernels_are_the_bilinear_move_where_the_projector_meets_the_camera_one_to_one():
    """J the identity: the dot lights the four pixels around it as :func:`shift_subpixel` moves a one-pixel box."""
    from sssphase_core.processing.footprints import dot_kernels, dot_offsets

    yy, xx = np.mgrid[:30, :30].astype(np.float64)
    xp, yp = xx + 0.3, yy - 0.45  # each pixel's dot (its rounded coordinate) 0.3 px left of it and 0.45 px below
    valid, pixels = np.ones(xp.shape, bool), np.array([[10, 12], [20, 5]])
    ker = torch.as_tensor(dot_kernels(xp, yp, valid, pixels))
    box = torch.zeros(2, 1, 7, 7)
    box[:, 0, 3, 3] = 1.0
    moved = shift_subpixel(box, dot_offsets(xp, yp, valid, pixels))[:, 0]
    torch.testing.assert_close(ker, moved, atol=1e-6, rtol=0)


def test_dot_kernels_cover_the_pixels_a_magnified_sheared_dot_lights():
    """Where one projector pixel covers 2 camera pixels along x (fringes twice as far apart) and is sheared, the dot
    spreads over them, its weights sum to 1, its centroid is where :func:`dot_offsets` puts the dot, and its
    spread along x is twice the identity's; a singular or unknown correspondence gives the pixel itself."""
    from sssphase_core.processing.footprints import dot_kernels, dot_offsets

    yy, xx = np.mgrid[:40, :40].astype(np.float64)
    jac = np.array([[0.5, 0.15], [0.0, 1.0]])
    xp, yp = jac[0, 0] * xx + jac[0, 1] * yy + 0.37, jac[1, 1] * yy - 0.21
    valid, pixels = np.ones(xp.shape, bool), np.array([[10, 12], [15, 20], [22, 31], [30, 7]])
    ker = dot_kernels(xp, yp, valid, pixels)
    assert ker.shape == (4, 7, 7) and (ker >= 0).all()
    np.testing.assert_allclose(ker.sum(axis=(1, 2)), 1.0, atol=1e-6)
    d = np.arange(-3, 4)
    cy, cx = (ker * d[None, :, None]).sum(axis=(1, 2)), (ker * d[None, None, :]).sum(axis=(1, 2))
    np.testing.assert_allclose(np.stack([cy, cx], 1), dot_offsets(xp, yp, valid, pixels), atol=0.02)
    var_x = (ker * (d[None, None, :] - cx[:, None, None]) ** 2).sum(axis=(1, 2))
    var_y = (ker * (d[None, :, None] - cy[:, None, None]) ** 2).sum(axis=(1, 2))
    # a unit tent's variance is 1/6 projector px^2, (1/6)/0.5^2 = 2/3 camera px^2 along x; sampling adds some
    assert (var_x > 0.55).all() and (var_y < 0.35).all()
    centre_only = np.zeros((7, 7), np.float32)
    centre_only[3, 3] = 1.0
    flat = np.zeros_like(xp)  # singular: no dot can be placed, the pixel's own light
    assert np.isfinite(dot_kernels(flat, flat, valid, pixels)).all()
    unknown = dot_kernels(np.full_like(xp, np.nan), np.full_like(yp, np.nan), valid, pixels)
    np.testing.assert_array_equal(unknown, np.broadcast_to(centre_only, unknown.shape))
    with pytest.raises(InputError, match="dot kernels"):
        spread_dot(torch.zeros(2, 3, 9, 9), torch.zeros(2, 4, 4))


def test_dot_kernels_explain_the_simulators_dot_crops():
    """Noise-free simulator crops against its exact footprints: summed over the pixels each dot lit they match the
    crops far better than moved bilinearly, above all where the projector is magnified on the camera."""
    from sssphase_core.processing.footprints import DotGridExtractor, dot_kernels, dot_offsets
    from sssphase_core.processing.patterns import dot_grid
    from sssphase_core.sim.scene import SimScene

    scene = SimScene("soap")
    hp, wp = scene.shape_projector
    xp, yp = scene.proj_xy[..., 0], scene.proj_xy[..., 1]
    valid = scene.object_mask & np.isfinite(xp) & np.isfinite(yp)
    xp, yp = np.where(valid, xp, np.nan), np.where(valid, yp, np.nan)
    extractor = DotGridExtractor(xp, yp, valid, 20, scene.rig.patch)
    shifts = [(0, 0), (10, 10)]
    frames = scene.render(np.stack([dot_grid(wp, hp, 20, sx, sy) for sx, sy in shifts]))
    for (sx, sy), frame in zip(shifts, frames - np.float32(scene.rig.projector.black) * scene.unit_white(), strict=True):
        extractor.add(sx, sy, frame)
    pixels, crops = extractor.result()
    exact = torch.as_tensor(scene.footprints(pixels)).permute(0, 3, 1, 2)
    target = torch.as_tensor(crops).permute(0, 3, 1, 2)

    def error(pred: torch.Tensor) -> np.ndarray:
        return ((pred - target).square().sum(dim=(1, 2, 3)).sqrt() / target.square().sum(dim=(1, 2, 3)).sqrt()).numpy()

    spread = error(spread_dot(exact, dot_kernels(xp, yp, valid, pixels)))
    moved = error(shift_subpixel(exact, dot_offsets(xp, yp, valid, pixels)))
    assert len(pixels) > 30
    assert np.median(spread) < 0.6 * np.median(moved) and np.median(spread) < 0.2


def test_dot_offsets_of_an_affine_correspondence():
    from sssphase_core.processing.footprints import MAX_DOT_OFFSET, dot_offsets

    yy, xx = np.mgrid[:30, :40].astype(np.float64)
    jac = np.array([[1.3, 0.2], [-0.1, 0.9]])  # [[dxp/dx, dxp/dy], [dyp/dx, dyp/dy]]
    xp, yp = jac[0, 0] * xx + jac[0, 1] * yy + 0.37, jac[1, 0] * xx + jac[1, 1] * yy - 0.21
    valid = np.ones(xp.shape, bool)
    pixels = np.array([[10, 12], [15, 20], [22, 31]])
    got = dot_offsets(xp, yp, valid, pixels)
    for (y, x), (dy, dx) in zip(pixels, got, strict=True):
        err = np.array([round(xp[y, x]) - xp[y, x], round(yp[y, x]) - yp[y, x]])
        np.testing.assert_allclose([dx, dy], np.linalg.solve(jac, err), atol=1e-5)
        # the dot's projector pixel is where the pixel plus its offset maps to
        np.testing.assert_allclose(jac @ [x + dx, y + dy] + [0.37, -0.21], np.round([xp[y, x], yp[y, x]]), atol=1e-5)
    dots = np.array([[18.6, 8.2], [28.9, 11.9], [45.8, 16.0]])  # any projector points near them: J^-1 (dot - p)
    placed = dot_offsets(xp, yp, valid, pixels, dots=dots)
    for (y, x), (dy, dx), dot in zip(pixels, placed, dots, strict=True):
        np.testing.assert_allclose(jac @ [x + dx, y + dy] + [0.37, -0.21], dot, atol=1e-5)
    with pytest.raises(InputError, match="2 dots for 3 pixels"):
        dot_offsets(xp, yp, valid, pixels, dots=dots[:2])
    flat = np.zeros_like(xp)  # a singular correspondence: no offset can be read, none is made up
    assert np.isfinite(dot_offsets(flat, flat, valid, pixels)).all()
    grazing = dot_offsets(xp * 1e-3, yp, valid, pixels)
    assert np.abs(grazing).max() <= MAX_DOT_OFFSET


def test_even_amplitude_window_reads_the_same_modulation_at_every_bayer_phase():
    """A uniform red surface under fringes, through a Malvar camera: the modulation features of its pixels
    must not depend on where they sit in the Bayer pattern (a 5 x 5 window read log-modulations 0.2 apart)."""
    from sssphase_core.learning.data import psp_patches
    from sssphase_core.learning.models.physics import modulation_features

    yy, xx = np.mgrid[:48, :48].astype(np.float32)
    frames = []
    for coord in (xx, yy):
        for s in range(4):
            pattern = 0.5 + 0.5 * np.cos(2 * np.pi * coord / 6.0 + s * np.pi / 2)
            frames.append(np.stack([cv2.GaussianBlur(pattern, (0, 0), sigma) * r
                                    for sigma, r in ((1.2, 0.8), (0.8, 0.3), (0.5, 0.1))], -1))
    psp = isp.through_camera(np.array(frames, np.float32), demosaic="malvar")
    pixels = np.array([[24, 24], [24, 25], [25, 24], [25, 25]])
    patches = torch.tensor(psp_patches(psp, pixels, 16))
    features = modulation_features(patches).numpy()
    assert np.ptp(features[:, :, :2], axis=0).max() < 1e-3
    odd = modulation_features(patches, even=False).numpy()  # the window decoders before it were trained with
    assert np.ptp(odd[:, :, :2], axis=0).max() > 0.05


def test_a_decoder_trained_before_the_even_window_runs_with_its_own(tmp_path):
    """Checkpoints are read as trained: a decoder from before the capture model (no capture_model in its
    config) read the modulation over a 5 x 5 window; run with the 6 x 6 one its profile would be off."""
    from sssphase_core.learning.models import Decoder, Encoder
    from sssphase_core.learning.training.checkpoints import load_decoder, save_checkpoint

    enc, dec = Encoder("lite"), Decoder("lite", head="reciprocal")
    for name, config in (("old", {"head": "reciprocal"}), ("new", {"head": "reciprocal", "capture_model": True})):
        save_checkpoint(tmp_path / f"{name}.pt", {"kind": "decoder", "preset": "lite", "config": config,
                                                  "encoder": enc.state_dict(), "decoder": dec.state_dict()})
    assert not load_decoder(tmp_path / "old.pt")[1].even_window and load_decoder(tmp_path / "new.pt")[1].even_window


def test_the_capture_model_is_deterministic_where_training_asks_for_it():
    """Decoder training runs CUDA with deterministic kernels by default (`loop.deterministic_kernels`): every op
    of the capture model must have a deterministic backward there (grid_sample's and scatter's do not)."""
    device = "cuda" if torch.cuda.is_available() else "cpu"
    rng = np.random.default_rng(3)
    codes = crop_codes({"bayer": "RGGB", "demosaic": "malvar", "median": True}, rng.integers(0, 50, (16, 2)), 12)
    dots = _dots(16, np.array([[0.5, 0.2], [-0.1, 0.9]]))
    grads = []
    previous = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        for _ in range(2):
            fp = torch.rand(16, 3, 12, 12, generator=torch.Generator().manual_seed(0)).to(device).requires_grad_()
            as_captured(fp, torch.as_tensor(codes, device=device), dots.to(device)).pow(2).sum().backward()
            grads.append(fp.grad.cpu())
    finally:
        torch.use_deterministic_algorithms(previous)
    assert torch.equal(grads[0], grads[1]) and grads[0].abs().sum() > 0



@pytest.mark.parametrize("phase, layout", [(0, "RGGB"), (2, "GBRG")])
def test_rebayer_is_the_isps_development_of_the_mosaic_without_a_dark_rim(phase, layout):
    """Full-colour frames through :func:`rebayer` equal the ISP's development of their mosaic (its
    Malvar) away from the border, and its mirrored border keeps the frame's brightness there."""
    rng = np.random.default_rng(1)
    frames = rng.random((8, 30, 34, 3)).astype(np.float32)
    seen = rebayer(torch.from_numpy(frames).permute(0, 3, 1, 2), phase).permute(0, 2, 3, 1).numpy()
    developed = isp.through_camera(frames, demosaic="malvar", layout=layout)
    np.testing.assert_allclose(seen[:, 2:-2, 2:-2], developed[:, 2:-2, 2:-2], atol=2e-6)
    assert abs(float(seen[:, :2].mean() / frames[:, :2].mean()) - 1) < 0.05
