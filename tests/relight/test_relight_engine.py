"""Splat kernels, truncation, precision, the no-scattering baseline, the footprint cache and image IO."""

import warnings

import cv2
import numpy as np
import pytest
import torch

from sssphase_core.errors import InputError
from sssphase_core.relight import (
    FootprintCache,
    emitted_light,
    no_scattering_source,
    read_pattern,
    relight,
    sample_projector,
    write_images,
)


@pytest.fixture
def scene(make_projection):
    rng = np.random.default_rng(1)
    proj, k = make_projection(30, 36, 40, 34, scale=1.05, offset=(0.4, 0.2), radius_div=2.3, black=0.01), 7
    h, w = proj.shape
    fps = rng.random((h, w, k, k, 3)).astype(np.float32) * 0.05
    pats = rng.random((3, 34, 40)).astype(np.float32)
    return proj, k, fps, pats


def test_csc_index_and_fold_kernels_agree(scene, monkeypatch):
    proj, k, fps, pats = scene
    src = lambda px: fps[px[:, 0], px[:, 1]]  # noqa: E731
    a = relight(src, proj, pats, k, method="csc", chunk=50)
    b = relight(src, proj, pats, k, method="index", chunk=333)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    assert np.array_equal(a, relight(src, proj, pats, k, method="csc", chunk=50))  # deterministic
    monkeypatch.setattr("sssphase_core.relight.engine.FOLD_BAND_BYTES", 1)  # one image row per fold band
    f = relight(src, proj, pats, k, method="fold", chunk=77)
    np.testing.assert_allclose(f, a, rtol=1e-5, atol=1e-7)
    assert np.array_equal(f, relight(src, proj, pats, k, method="fold", chunk=77))


def test_radius_truncation_equals_zeroing_the_outer_ring(scene):
    proj, k, fps, pats = scene
    cut = fps.copy()
    cut[..., [0, -1], :, :] = 0
    cut[..., :, [0, -1], :] = 0
    a = relight(lambda px: fps[px[:, 0], px[:, 1]], proj, pats, k, radius=k // 2 - 1)
    b = relight(lambda px: cut[px[:, 0], px[:, 1]], proj, pats, k)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_bf16_is_close_but_not_identical(scene):
    proj, k, fps, pats = scene
    src = lambda px: fps[px[:, 0], px[:, 1]]  # noqa: E731
    a = relight(src, proj, pats, k)
    b = relight(src, proj, pats, k, dtype=torch.bfloat16)
    assert not np.array_equal(a, b)
    np.testing.assert_allclose(a, b, rtol=2e-2, atol=1e-3 * a.max())


def test_no_scattering_keeps_each_pixels_light(make_projection):
    proj = make_projection(30, 36, 40, 34, scale=1.05, offset=(0.4, 0.2), radius_div=2.3, black=0.01)
    rng = np.random.default_rng(2)
    white = rng.random((*proj.shape, 3)).astype(np.float32)
    pats = rng.random((2, 34, 40)).astype(np.float32)
    out = relight(no_scattering_source(white), proj, pats, 1, white=white)
    ys, xs = np.nonzero(proj.mask)
    c = sample_projector(emitted_light(pats, proj.gamma), proj.xp[ys, xs], proj.yp[ys, xs]) * (1 - proj.black)
    expect = white[ys, xs][:, None] * c + proj.black * white[ys, xs][:, None]
    np.testing.assert_allclose(out[:, ys, xs].transpose(1, 0, 2), expect, rtol=1e-5, atol=1e-6)
    wide = relight(no_scattering_source(white, 5), proj, pats, 5, white=white)  # same image with a bigger patch
    np.testing.assert_allclose(wide, out, atol=1e-6)


def test_footprint_cache_skips_the_source_for_cached_pixels(tmp_path, scene):
    proj, k, fps, pats = scene
    calls = []

    def src(px):
        calls.append(len(px))
        return fps[px[:, 0], px[:, 1]]

    cache = FootprintCache(src, tmp_path / "fp.npz", proj.shape, k)
    first = relight(cache, proj, pats[:1], k)
    cache.save()
    n_first = sum(calls)
    again = FootprintCache(src, tmp_path / "fp.npz", proj.shape, k)
    second = relight(again, proj, pats[:1], k)
    assert sum(calls) == n_first and again.hits == n_first and again.misses == 0
    np.testing.assert_array_equal(second, first)  # the same image whether the footprints were cached or not
    direct = relight(src, proj, pats[:1], k)
    np.testing.assert_allclose(direct, first, rtol=2e-3, atol=1e-4)  # (float16 storage: close to the source's own)
    # what an evaluation calls "read from the cache": footprints an earlier run kept, not those this run computed and
    # read again (a view's calibration pass, then its relight: "read 50% of its footprints from cache" of a first run)
    assert cache.kept_read == 0 and again.kept_read == n_first
    fresh = FootprintCache(src, tmp_path / "fresh.npz", proj.shape, k)
    relight(fresh, proj, pats[:1], k)
    relight(fresh, proj, pats[1:2], k)
    assert fresh.hits == fresh.misses == n_first and fresh.kept_read == 0


def _cached_once(src, path, scene):
    """Relight ``scene``'s first pattern through a fresh cache of ``src`` at ``path`` and save it -> (the image, the
    file's arrays)."""
    proj, k, _, pats = scene
    cache = FootprintCache(src, path, proj.shape, k)
    first = relight(cache, proj, pats[:1], k)
    cache.save()
    with np.load(path) as z:
        return first, {name: z[name] for name in z.files}


@pytest.mark.parametrize("damage", ["truncated", "index_out_of_range", "negative_index", "object_array", "not_npz"])
def test_a_damaged_footprint_cache_is_ignored_and_rewritten(tmp_path, scene, damage):
    """The cache only saves time: a damaged or foreign file (truncated, indices off the view, pickled
    objects, not a zip) is ignored, every footprint computed again and right, and the file rewritten."""
    proj, k, fps, pats = scene

    def src(px):
        return fps[px[:, 0], px[:, 1]]

    path = tmp_path / "fp.npz"
    first, parts = _cached_once(src, path, scene)
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage == "not_npz":
        path.write_text("not a cache")
    else:
        index = parts["index"].copy()
        if damage == "object_array":
            parts["index"] = np.array([object()] * len(index), dtype=object)
        else:
            index[0] = 10**9 if damage == "index_out_of_range" else -5
            parts["index"] = index
        np.savez(path, **parts)
    again = FootprintCache(src, path, proj.shape, k)
    assert again.size == 0
    np.testing.assert_allclose(relight(again, proj, pats[:1], k), first, rtol=2e-3, atol=1e-4)
    again.save()
    assert FootprintCache(src, path, proj.shape, k).size == len(parts["data"])


def test_non_finite_footprints_in_a_cache_are_computed_again_not_blamed_on_the_model(tmp_path, scene):
    """A cache file whose footprints were damaged to NaN/inf (an edit, a bad disk) is not a broken model: those
    footprints are asked of the source again, the relight is the one without the damage, and the file is rewritten
    with them mended (the engine's "the model is broken" refusal is left for a model's own non-finite output)."""
    proj, k, fps, pats = scene
    calls = []

    def src(px):
        calls.append(len(px))
        return fps[px[:, 0], px[:, 1]]

    path = tmp_path / "fp.npz"
    first, parts = _cached_once(src, path, scene)
    parts["data"] = parts["data"].copy()
    parts["data"][: len(parts["data"]) * 3 // 4] = np.nan  # most of them: past the engine's broken-source share
    parts["data"][-1, 0, 0, 0] = np.inf
    np.savez(path, **parts)
    calls.clear()
    again = FootprintCache(src, path, proj.shape, k)
    np.testing.assert_array_equal(relight(again, proj, pats[:1], k), first)
    bad = len(parts["data"]) * 3 // 4 + 1
    assert sum(calls) == bad and again.hits == len(parts["data"]) - bad
    again.save()
    with np.load(path) as z:
        assert np.isfinite(z["data"]).all() and len(z["data"]) == len(parts["data"])


def test_footprint_cache_stays_within_its_memory_budget(tmp_path, scene):
    proj, k, fps, pats = scene
    calls = []

    def src(px):
        calls.append(len(px))
        return fps[px[:, 0], px[:, 1]]

    budget = 100 * k * k * 3 * 2  # 100 float16 footprints
    cache = FootprintCache(src, tmp_path / "fp.npz", proj.shape, k, max_bytes=budget)
    first = relight(cache, proj, pats[:1], k, chunk=64)
    n = sum(calls)
    assert cache.size == 100 and cache.data.nbytes <= budget and cache.uncached == n - 100
    cache.save()
    again = FootprintCache(src, tmp_path / "fp.npz", proj.shape, k, max_bytes=budget)
    np.testing.assert_allclose(relight(again, proj, pats[:1], k, chunk=64), first, rtol=2e-3, atol=1e-4)
    assert again.hits == 100 and sum(calls) == 2 * n - 100  # only the uncached ones ran again


@pytest.mark.parametrize("fmt", ["png", "exr"])
def test_an_image_that_cannot_be_written_is_an_error_not_a_wrote_line(tmp_path, fmt):
    """cv2.imwrite returns False (and OpenEXR raises) for a name over the file system's 255 bytes, a full
    disk or a read-only folder: one error naming the file, never a path reported as written."""
    with pytest.raises(InputError, match="could not write .*L{200}"):
        write_images(tmp_path / ("L" * 300), np.zeros((4, 5, 3), np.float32), formats=(fmt,))


def test_write_images_16bit_linear_and_display(tmp_path):
    import cv2

    img = np.zeros((8, 10, 3), np.float32)
    img[2:5, 3:6] = (0.25, 0.5, 1.5)
    paths = write_images(tmp_path / "x", img)
    lin = cv2.imread(str(paths[0]), cv2.IMREAD_UNCHANGED)
    assert lin.dtype == np.uint16 and lin.shape == (8, 10, 3)
    np.testing.assert_allclose(lin[3, 4, ::-1] / 65535, (0.25, 0.5, 1.0), atol=1e-4)  # clipped at 1
    disp = cv2.imread(str(paths[1]), cv2.IMREAD_UNCHANGED)
    assert disp.dtype == np.uint8 and disp.max() == 255 and disp[0, 0].max() == 0


def test_exr_output_is_the_linear_image_bit_exact_and_unclipped(tmp_path):
    from sssphase_core.store.exr import read_exr

    rng = np.random.default_rng(3)
    img = (rng.standard_normal((9, 11, 3)) * 2).astype(np.float32)  # negative and far above 1.0
    img[0, 0] = (np.inf, np.nan, 1e-30)
    paths = write_images(tmp_path / "x", img, formats=("exr",))
    assert [p.name for p in paths] == ["x.exr", "x_display.png"]
    back = read_exr(paths[0])
    assert back.dtype == np.float32 and back.tobytes() == img.tobytes()


def test_an_unknown_image_format_is_refused(tmp_path):
    with pytest.raises(InputError, match="unknown image format tiff"):
        write_images(tmp_path / "x", np.zeros((2, 2, 3), np.float32), formats=("tiff",))


def test_read_pattern_checks_size_and_resizes(tmp_path):
    from PIL import Image

    Image.fromarray((np.arange(20 * 30).reshape(20, 30) % 256).astype(np.uint8)).save(tmp_path / "p.png")
    with pytest.raises(InputError, match="--resize"):
        read_pattern(tmp_path / "p.png", (40, 34))
    pat = read_pattern(tmp_path / "p.png", (40, 34), resize=True)
    assert pat.shape == (34, 40) and 0 <= pat.min() and pat.max() <= 1


def test_fit_and_fill_keep_the_aspect_ratio(tmp_path):
    from PIL import Image

    Image.fromarray(np.full((20, 40), 255, np.uint8)).save(tmp_path / "wide.png")  # 2:1 white
    fit = read_pattern(tmp_path / "wide.png", (60, 60), resize="fit")
    assert fit.shape == (60, 60) and fit[:10].max() == 0 and fit[-10:].max() == 0 and fit[30].min() == 1  # letterboxed
    fill = read_pattern(tmp_path / "wide.png", (60, 60), resize="fill")
    assert fill.min() == 1  # covered, cropped
    assert read_pattern(tmp_path / "wide.png", (60, 60), resize="stretch").min() == 1
    with pytest.raises(InputError, match="--resize must be one of fit, fill, stretch"):
        read_pattern(tmp_path / "wide.png", (60, 60), resize="zoom")


def test_palette_and_16_bit_patterns_are_read_as_their_values(tmp_path):
    from PIL import Image

    pal = Image.new("P", (8, 6))
    pal.putpalette([0, 0, 0, 255, 255, 255] + [0] * 762)  # index 1 is white
    pal.putpixel((2, 3), 1)
    pal.save(tmp_path / "pal.png")
    got = read_pattern(tmp_path / "pal.png", (8, 6))
    assert got[3, 2] == 1.0 and got.sum() == 1.0  # the colour, not the palette index 1/255
    Image.fromarray(np.full((6, 8), 32768, np.uint16)).save(tmp_path / "p16.png")
    assert read_pattern(tmp_path / "p16.png", (8, 6)) == pytest.approx(np.full((6, 8), 32768 / 65535))


def test_transparency_animations_and_wide_integers_are_not_misread_in_patterns(tmp_path):
    """An RGBA checkerboard drawn with alpha relit as full white (alpha dropped); an animated GIF used its
    first frame; a 32-bit TIFF of 2**30 read as 1.0 everywhere (divided by 65535, clipped)."""
    from PIL import Image

    alpha = np.zeros((6, 8), np.uint8)
    alpha[:, :4] = 255  # left half opaque, right half transparent
    Image.fromarray(np.dstack([np.full((6, 8, 3), 200, np.uint8), alpha]), "RGBA").save(tmp_path / "rgba.png")
    with pytest.warns(UserWarning, match=r"50% of its pixels are not fully opaque \(50% fully transparent\)"):
        got = read_pattern(tmp_path / "rgba.png", (8, 6))
    assert got[:, :4] == pytest.approx(200 / 255) and (got[:, 4:] == 0).all()  # no light where transparent
    Image.fromarray(np.dstack([np.full((6, 8), 255, np.uint8), alpha]), "LA").save(tmp_path / "la.png")
    with pytest.warns(UserWarning, match="transparent"):
        got = read_pattern(tmp_path / "la.png", (8, 6))
    assert got.ndim == 2 and (got[:, :4] == 1).all() and (got[:, 4:] == 0).all()
    checker = np.where(alpha > 0, 0, 255).astype(np.uint8)  # a colour key (tRNS) marks white as transparent
    for mode, image, key in (("RGB", np.dstack([checker] * 3), (255, 255, 255)), ("L", checker, 255)):
        Image.fromarray(image, mode).save(tmp_path / f"key_{mode}.png", transparency=key)  # was projected opaque
        with pytest.warns(UserWarning, match=r"50% fully transparent"):
            assert (read_pattern(tmp_path / f"key_{mode}.png", (8, 6)) == 0).all()  # black, and no light where keyed
    Image.fromarray(np.dstack([np.full((6, 8, 3), 9, np.uint8), np.full((6, 8), 255, np.uint8)]), "RGBA").save(tmp_path / "opaque.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # opaque: no warning
        assert read_pattern(tmp_path / "opaque.png", (8, 6)) == pytest.approx(9 / 255)
    frames = [Image.fromarray(np.full((6, 8), v, np.uint8)) for v in (0, 255)]
    frames[0].save(tmp_path / "anim.gif", save_all=True, append_images=frames[1:], duration=100, loop=0)
    with pytest.raises(InputError, match="holds 2 frames"):
        read_pattern(tmp_path / "anim.gif", (8, 6))
    Image.fromarray(np.full((6, 8), 2**30, np.int32)).save(tmp_path / "i32.tif")
    with pytest.raises(InputError, match="8- or 16-bit unsigned"):
        read_pattern(tmp_path / "i32.tif", (8, 6))
    Image.fromarray(np.full((6, 8), -5, np.int32)).save(tmp_path / "neg.tif")
    with pytest.raises(InputError, match="from -5 to -5"):
        read_pattern(tmp_path / "neg.tif", (8, 6))


def test_a_large_rgba_image_is_composited_in_eight_bits_and_a_large_16_bit_one_is_resized_like_an_eight_bit_one(tmp_path):
    """A 250 kB 8000 x 8000 RGBA PNG (within the 64 MP a resize takes) was composited over black as float32: 3.5 GB
    of memory; a 3000 x 2000 16-bit PNG was refused as "far larger than the projector" with --resize fit, where the
    same image in 8 bits was relit."""
    import json
    import subprocess
    import sys

    from PIL import Image

    rgba = np.zeros((8000, 8000, 4), np.uint8)
    rgba[:, :4000] = (200, 100, 50, 255)  # the left half opaque, the right half transparent
    Image.fromarray(rgba, "RGBA").save(tmp_path / "big.png")
    del rgba
    script = ("import re, warnings, numpy as np; from sssphase_core.store.imageio import read_pattern; "
              "warnings.simplefilter('ignore'); "
              f"p = read_pattern({str(tmp_path / 'big.png')!r}, (256, 192), resize='stretch'); "
              # this process's own peak (VmHWM: ru_maxrss keeps the forking test worker's across exec)
              "peak = int(re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read()).group(1)) >> 10; "
              "print(peak, p[:, :120].mean((0, 1)).tolist(), float(p[:, 136:].max()))")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    peak_mb, left, right = done.stdout.split(" ", 1)[0], *done.stdout.split(" ", 1)[1].rsplit(" ", 1)
    assert int(peak_mb) < 1000, f"reading the 8K RGBA pattern peaked at {peak_mb} MB"
    assert json.loads(left) == pytest.approx([200 / 255, 100 / 255, 50 / 255], abs=1e-5) and float(right) == 0.0  # no light where clear
    wide = np.zeros((2000, 3000, 3), np.uint16)
    wide[:, :1500] = 65535
    cv2.imwrite(str(tmp_path / "wide16.png"), wide)
    got = read_pattern(tmp_path / "wide16.png", (256, 192), resize="fit")
    assert got.shape[:2] == (192, 256) and np.allclose(got[96, 10], 1.0) and not got[96, 250].any()
    with pytest.raises(InputError, match="far larger than the 256x192 projector"):
        read_pattern(tmp_path / "wide16.png", (256, 192))  # as it is, 4 MP at most: refused from its header


def test_a_pattern_tagged_with_an_exif_orientation_is_projected_as_viewers_show_it(tmp_path):
    """A phone's photo is stored sideways with an EXIF tag saying "rotate 90° clockwise": it was read as stored
    (relit sideways, or refused for its size) where every image viewer shows it upright."""
    from PIL import Image

    shown = np.zeros((6, 8), np.uint8)
    shown[0, :3] = 255  # a bar along the top left: where the user sees it
    stored = np.rot90(shown, k=1)  # what the camera wrote (8 tall, 6 wide); tag 6 turns it back clockwise
    exif = Image.Exif()
    exif[274] = 6
    for name in ("photo.jpg", "photo.png"):
        Image.fromarray(np.ascontiguousarray(stored)).save(tmp_path / name, exif=exif.tobytes(), quality=100)
        with pytest.warns(UserWarning, match="EXIF orientation tag says the stored image is shown rotated 90° clockwise"):
            got = read_pattern(tmp_path / name, (8, 6))
        assert got.shape == (6, 8)
        assert np.abs(got - shown / 255.0).max() < 0.1  # (JPEG's loss, on a bar of 3 pixels)
    Image.fromarray(shown).save(tmp_path / "plain.png")  # no tag: as stored, without a word
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert (read_pattern(tmp_path / "plain.png", (8, 6)) == shown / 255.0).all()
    # a 16-bit colour PNG (read by OpenCV, which ignores the tag) with the same eXIf chunk: turned the same way,
    # and `--resize`'s line names the size as shown (it said 6x8 -> 8x6 where nothing was resized)
    import struct
    import zlib

    from sssphase_core.relight.runner import resize_note

    cv2.imwrite(str(tmp_path / "deep.png"), np.repeat(np.ascontiguousarray(stored)[..., None], 3, -1).astype(np.uint16) * 257)
    data = (tmp_path / "deep.png").read_bytes()
    body = exif.tobytes().removeprefix(b"Exif\x00\x00")
    chunk = struct.pack(">I", len(body)) + b"eXIf" + body + struct.pack(">I", zlib.crc32(b"eXIf" + body))
    at = data.index(b"IDAT") - 4
    (tmp_path / "deep.png").write_bytes(data[:at] + chunk + data[at:])
    with pytest.warns(UserWarning, match="EXIF orientation tag says the stored image is shown rotated 90° clockwise"):
        got = read_pattern(tmp_path / "deep.png", (8, 6))
    assert got.shape == (6, 8, 3) and np.abs(got - shown[..., None] / 255.0).max() < 1e-6
    assert resize_note(str(tmp_path / "deep.png"), (8, 6), "fit") is None
    assert resize_note(str(tmp_path / "photo.jpg"), (16, 12), "fit")[0].endswith(": 8x6 -> 16x12 (fit)")


def test_non_finite_footprints_are_zeroed_with_a_warning(scene):
    proj, k, fps, pats = scene
    bad = fps.copy()
    ys, xs = np.nonzero(proj.mask)
    bad[ys[0], xs[0], 0, 0, 0] = np.inf
    bad[ys[1], xs[1], 2, 3, 1] = np.nan
    with pytest.warns(RuntimeWarning, match="2 non-finite"):
        out = relight(lambda px: bad[px[:, 0], px[:, 1]], proj, pats, k)
    assert np.isfinite(out).all()
    huge = fps.copy()  # finite values whose sum overflows float32 (the check's first reduction): kept, no warning
    huge[ys[0], xs[0], 0, 0, 0] = huge[ys[0], xs[0], k - 1, k - 1, 0] = 3e38
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = relight(lambda px: huge[px[:, 0], px[:, 1]], proj, pats, k)
    assert np.nanmax(out) > 1e37


def test_a_source_whose_footprints_are_mostly_not_finite_is_refused(scene):
    """A checkpoint of finite weights that overflow made 24% of the footprint values inf, and relit an image
    labelled with its backend, exit 0, after a warning. Beyond 1% of the pixels the source is refused."""
    from sssphase_core.errors import DataError

    proj, k, fps, pats = scene
    ys, xs = np.nonzero(proj.mask)
    broken = fps.copy()
    n = len(ys) // 50 + 2  # just over 2% of the lit pixels
    broken[ys[:n], xs[:n], k // 2, k // 2, 0] = np.inf
    with pytest.raises(DataError, match=rf"non-finite footprints for more than 1% of the {len(ys)} lit pixels"):
        relight(lambda px: broken[px[:, 0], px[:, 1]], proj, pats, k, chunk=max(1, len(ys) // 10))


def test_nearest_measured_source_rescales_the_nearest_captured_footprint():
    from sssphase_core.relight import nearest_measured_source

    white = np.ones((20, 20, 3), np.float32)
    white[:, 10:] = 2.0  # the right half reflects twice as much
    dots = np.array([[5, 5], [5, 17]])
    crops = np.stack([np.full((3, 3, 3), 1.0, np.float32), np.full((3, 3, 3), 4.0, np.float32)])
    fp = nearest_measured_source(dots, crops, white)(np.array([[6, 4], [4, 18], [5, 10]]))
    # (6, 4) and (4, 18): their own dot, same white; (5, 10): nearest dot (5, 5), white ratio 2 / 1
    np.testing.assert_allclose(fp[:, 1, 1, 0], [1.0, 4.0, 2.0])


def test_without_the_openexr_bindings_exr_says_what_to_install(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # as if not installed
    with pytest.raises(InputError, match=r"OpenEXR Python bindings, which are not installed: pip install 'sssphase\[exr\]'"):
        write_images(tmp_path / "x", np.zeros((2, 2, 3), np.float32), formats=("exr",))
    assert not list(tmp_path.iterdir())


def test_numpy_patterns_are_read_checked_and_resized(tmp_path):
    rgb = np.random.default_rng(0).random((34, 40, 3)).astype(np.float32)
    np.save(tmp_path / "rgb.npy", rgb)
    np.testing.assert_array_equal(read_pattern(tmp_path / "rgb.npy", (40, 34)), rgb)
    np.save(tmp_path / "u16.npy", np.full((34, 40), 65535, np.uint16))
    assert read_pattern(tmp_path / "u16.npy", (40, 34)).max() == 1.0
    np.save(tmp_path / "small.npy", np.ones((17, 20), np.float32))
    with pytest.raises(InputError, match="is 20x17 but the projector is 40x34"):
        read_pattern(tmp_path / "small.npy", (40, 34))
    assert read_pattern(tmp_path / "small.npy", (40, 34), resize="stretch").shape == (34, 40)
    assert read_pattern(tmp_path / "rgb.npy", (80, 40), resize="fit").shape == (40, 80, 3)
    for name, bad, message in [("nan", np.full((34, 40), np.nan, np.float32), "finite values in"),
                               ("bright", np.full((34, 40), 2.0), "finite values in"),
                               ("4d", np.zeros((2, 2, 2, 2), np.float32), "must be an"),
                               ("signed", np.zeros((34, 40), np.int16), "must be an"),
                               ("empty", np.zeros((0, 40), np.float32), r"has shape \(0, 40\): expected \(H, W\)"),
                               ("scalar", np.float32(0.5), r"has shape \(\): expected \(H, W\) or \(H, W, 3\)")]:
        np.save(tmp_path / f"{name}.npy", bad)
        with pytest.raises(InputError, match=message):
            read_pattern(tmp_path / f"{name}.npy", (40, 34))
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="cannot read"):  # never unpickled
        read_pattern(tmp_path / "objects.npy", (40, 34))


def test_float_tiff_and_exr_patterns_are_read_as_their_values(tmp_path):
    """Renderers and HDR tools write float32 RGB TIFF (which Pillow cannot decode) and EXR."""
    import cv2

    from sssphase_core.store.exr import write_exr

    rgb = np.random.default_rng(1).random((34, 40, 3)).astype(np.float32)
    cv2.imwrite(str(tmp_path / "p.tiff"), rgb[..., ::-1])  # OpenCV writes BGR
    np.testing.assert_array_equal(read_pattern(tmp_path / "p.tiff", (40, 34)), rgb)
    write_exr(tmp_path / "p.exr", rgb)
    np.testing.assert_array_equal(read_pattern(tmp_path / "p.exr", (40, 34)), rgb)
    assert read_pattern(tmp_path / "p.exr", (80, 68), resize="stretch").shape == (68, 80, 3)
    import OpenEXR  # an RGBA file, as compositors write it: the alpha is dropped

    rgba = np.concatenate([rgb, np.ones_like(rgb[..., :1])], axis=-1)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"RGBA": rgba}) as f:
        f.write(str(tmp_path / "rgba.exr"))
    np.testing.assert_array_equal(read_pattern(tmp_path / "rgba.exr", (40, 34)), rgb)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {c: np.ascontiguousarray(rgb[..., i]) for i, c in enumerate("rgb")}) as f:
        f.write(str(tmp_path / "lower.exr"))  # channels named in lower case (some writers): refused before
    np.testing.assert_array_equal(read_pattern(tmp_path / "lower.exr", (40, 34)), rgb)
    write_exr(tmp_path / "hdr.exr", rgb * 4)
    with pytest.raises(InputError, match="finite values in"):
        read_pattern(tmp_path / "hdr.exr", (40, 34))
    with pytest.raises(InputError, match="is 40x34 but the projector is 20x17"):
        read_pattern(tmp_path / "p.tiff", (20, 17))
    (tmp_path / "bad.tiff").write_bytes(b"II*\x00\x08\x00\x00\x00\x01\x00\x00\x01\x04\x00")  # a damaged directory
    with pytest.raises(InputError, match="a TIFF header without an image size"):
        read_pattern(tmp_path / "bad.tiff", (40, 34))


def test_sixteen_bit_alpha_float64_tiffs_and_cut_files_are_read_as_their_eight_bit_kin(tmp_path):
    """Found by hand: a 16-bit RGBA PNG relit as full white where its alpha said transparent (8-bit ones
    were composited); a float64 TIFF and a PNG cut within its header were internal errors; a cut EXR
    printed the library's own line, then blamed its channels."""
    import cv2

    from sssphase_core.errors import DataError
    from sssphase_core.store.exr import write_exr

    bgra = np.zeros((6, 8, 4), np.uint16)
    bgra[..., :3] = 65535
    bgra[:, :4, 3] = 65535  # left half opaque, right half transparent
    cv2.imwrite(str(tmp_path / "rgba16.png"), bgra)
    with pytest.warns(UserWarning, match=r"50% of its pixels are not fully opaque \(50% fully transparent\)"):
        got = read_pattern(tmp_path / "rgba16.png", (8, 6))
    assert (got[:, :4] == 1).all() and (got[:, 4:] == 0).all()
    rgb = np.random.default_rng(2).random((6, 8, 3))
    cv2.imwrite(str(tmp_path / "f64.tif"), rgb[..., ::-1])
    np.testing.assert_allclose(read_pattern(tmp_path / "f64.tif", (8, 6)), rgb, atol=1e-6)
    (tmp_path / "cut.png").write_bytes((tmp_path / "rgba16.png").read_bytes()[:20])
    with pytest.raises(InputError, match="cannot read pattern"):
        read_pattern(tmp_path / "cut.png", (8, 6))
    write_exr(tmp_path / "whole.exr", np.random.default_rng(3).random((64, 80, 3)).astype(np.float32))
    data = (tmp_path / "whole.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 3])
    with pytest.raises(DataError, match="damaged or truncated"):
        read_pattern(tmp_path / "cut.exr", (80, 64))


def test_a_full_disk_leaves_no_half_written_image_under_its_name(tmp_path):
    """`sss relight --format exr` on a disk that filled left a truncated, unreadable EXR under the final name;
    each image is now written under a temporary name and renamed once complete. The disk fills here by a
    file-size limit on the writing process (RLIMIT_FSIZE)."""
    import subprocess
    import sys

    code = """
import resource, signal, sys
import numpy as np
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead of killing us
resource.setrlimit(resource.RLIMIT_FSIZE, (30000, 30000))
from sssphase_core.errors import InputError
from sssphase_core.relight.images import write_images
image = np.random.default_rng(0).random((200, 200, 3), dtype=np.float32)
for fmt in ("exr", "png"):
    try:
        write_images(sys.argv[1] + "_" + fmt, image, formats=(fmt,))
    except InputError as exc:
        print("refused", fmt, exc)
"""
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "relit")], capture_output=True, text=True, timeout=120)
    assert res.stdout.count("refused") == 2, res.stdout + res.stderr
    # the file and the cause, in one line each (not libpng's "Write Error" on stderr, nor the temporary's name)
    assert f"refused png could not write {tmp_path / 'relit_png.png'}: File too large" in res.stdout
    assert f"refused exr could not write {tmp_path / 'relit_exr.exr'}: Failed to write pixel data. File too large" \
        in res.stdout, res.stdout
    assert not res.stderr and ".tmp" not in res.stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == [], list(tmp_path.iterdir())  # nothing, not even temporaries


def test_write_npz_is_an_npz_numpy_reads_back_bit_for_bit_and_compressed(tmp_path):
    from sssphase_core.relight.cache import write_npz

    rng = np.random.default_rng(0)
    data = np.zeros((64, 16, 16, 3), np.float16)
    data[:, 6:10, 6:10] = rng.random((64, 4, 4, 3)).astype(np.float16)  # footprints: a core, zeros around it
    write_npz(tmp_path / "c.npz", data=data, index=np.arange(64), shape=np.asarray((8, 8)))
    with np.load(tmp_path / "c.npz", allow_pickle=False) as z:
        assert sorted(z.files) == ["data", "index", "shape"]
        assert z["data"].dtype == np.float16 and np.array_equal(z["data"], data)
        assert np.array_equal(z["index"], np.arange(64)) and z["shape"].tolist() == [8, 8]
    assert (tmp_path / "c.npz").stat().st_size < data.nbytes / 4


def test_the_mean_over_a_box_of_projector_pixels_is_exact_and_one_pixel_wide_it_is_the_bilinear_lookup():
    from sssphase_core.processing.projector import area_sample_projector

    rng = np.random.default_rng(3)
    light = rng.random((2, 30, 40, 3)).astype(np.float32)
    xp, yp = rng.uniform(-2, 42, 400), rng.uniform(-2, 32, 400)  # some outside the projector: no light there
    np.testing.assert_allclose(area_sample_projector(light, xp, yp, np.ones(400), np.ones(400)),
                               sample_projector(light, xp, yp), atol=1e-6)
    got = area_sample_projector(light, np.array([10.0, 0.0]), np.array([12.0, 0.0]), np.array([3.0, 2.0]),
                                np.array([3.0, 2.0]))
    np.testing.assert_allclose(got[0], light[:, 11:14, 9:12].mean(axis=(1, 2)), rtol=1e-5)  # a 3 x 3 block
    corner = light[:, 0, 0] + 0.5 * light[:, 0, 1] + 0.5 * light[:, 1, 0] + 0.25 * light[:, 1, 1]
    np.testing.assert_allclose(got[1], corner / 4, rtol=1e-5)  # [-1, 1] x [-1, 1]: a quarter of it is off the projector


def test_a_camera_coarser_than_the_projector_receives_the_mean_of_the_pixels_it_sees():
    """A 192 x 144 camera seeing a 640 x 360 projector (2-3 projector px per camera px) relit a plain wall at 24 dB
    from the light at each pixel's point; a camera pixel records the mean over its footprint (a session of our
    simulator, whose pinhole samples a point, keeps the lookup)."""
    from dataclasses import replace

    from sssphase_core.relight.engine import Projection

    h, w, s = 20, 24, 3  # each camera pixel sees s x s projector pixels
    yy, xx = np.mgrid[:h, :w].astype(np.float32)
    proj = Projection(s * xx + 1, s * yy + 1, np.ones((h, w), bool), (s * w, s * h), gamma=1.0, pixel_area=True)
    pats = np.random.default_rng(4).random((2, s * h, s * w)).astype(np.float32)
    relit = relight(no_scattering_source(np.ones((h, w, 3), np.float32)), proj, pats, 1)
    truth = pats.reshape(2, h, s, w, s).mean(axis=(2, 4))  # what the camera records of a white wall
    np.testing.assert_allclose(relit[..., 0], truth, atol=1e-5)
    pinhole = relight(no_scattering_source(np.ones((h, w, 3), np.float32)), replace(proj, pixel_area=False), pats, 1)
    assert np.abs(pinhole[..., 0] - truth).max() > 0.1  # our simulator's camera: the light at the decoded point
    near = Projection(1.2 * xx + 1, 1.2 * yy + 1, np.ones((h, w), bool), (s * w, s * h), gamma=1.0,
                      pixel_area=True)  # 1.2 px: a lookup
    looked_up = relight(no_scattering_source(np.ones((h, w, 3), np.float32)), near, pats, 1)
    np.testing.assert_allclose(looked_up[..., 0].reshape(2, -1).T, sample_projector(
        pats[..., None].repeat(3, -1), near.xp.ravel(), near.yp.ravel())[..., 0], atol=1e-6)


def test_variants_are_splatted_from_one_call_of_the_source_each_as_its_own_relight(scene):
    from sssphase_core.relight.engine import widened

    proj, k, fps, pats = scene
    calls = []

    def src(px):
        calls.append(len(px))
        return fps[px[:, 0], px[:, 1]]

    both = relight(src, proj, pats, k, chunk=100, variants=(lambda f: widened(f, 1.5),))
    assert both.shape == (2, len(pats), *proj.shape, 3) and sum(calls) <= proj.mask.sum()
    np.testing.assert_allclose(both[0], relight(lambda px: fps[px[:, 0], px[:, 1]], proj, pats, k), rtol=1e-5, atol=1e-7)
    stretched = lambda px: widened(torch.from_numpy(fps[px[:, 0], px[:, 1]]), 1.5).numpy()  # noqa: E731
    np.testing.assert_allclose(both[1], relight(stretched, proj, pats, k), rtol=1e-5, atol=1e-7)


def test_widened_footprints_keep_their_energy_and_spread_by_the_factor():
    from sssphase_core.relight.engine import widened

    k = 31
    off = torch.arange(k, dtype=torch.float32) - k // 2
    r2 = off[:, None] ** 2 + off[None, :] ** 2
    sigma = torch.tensor([1.5, 2.0, 2.5])
    fp = torch.exp(-r2[None, :, :, None] / (2 * sigma ** 2))  # (1, K, K, 3) Gaussians
    np.testing.assert_allclose(widened(fp, 1.0), fp, atol=1e-6)  # factor 1: the footprints themselves
    for factor in (1.3, 2.0, 0.7):
        out = widened(fp, factor)
        np.testing.assert_allclose(out.sum(dim=(1, 2)), fp.sum(dim=(1, 2)), rtol=1e-5)  # energy per colour kept
        spread = (out * r2[None, :, :, None]).sum(dim=(1, 2)) / out.sum(dim=(1, 2))
        np.testing.assert_allclose(spread.sqrt() / (2 ** 0.5 * sigma), factor, rtol=0.08)  # rms radius x factor
    assert widened(torch.zeros(2, 5, 5, 3), 1.5).abs().sum() == 0 and torch.isfinite(widened(torch.zeros(2, 5, 5, 3), 1.5)).all()


def test_footprints_stretched_along_one_axis_widen_only_along_it():
    """``widened(f, (sx, sy))``: x is the footprint's second (column) axis; one factor is both; the calibration's
    members (``axis_stretches``) are stretched along x, y and both."""
    from sssphase_core.relight.engine import axis_stretches, widened

    k = 31
    off = torch.arange(k, dtype=torch.float32) - k // 2
    sigma = torch.tensor([1.5, 2.0, 2.5])
    fp = torch.exp(-(off[:, None, None] ** 2 + off[None, :, None] ** 2) / (2 * sigma ** 2))[None]  # (1, K, K, 3)
    rms = lambda f, axis: ((f * (off ** 2).reshape((k, 1) if axis == "y" else (1, k))[None, :, :, None]).sum(dim=(1, 2))  # noqa: E731
                           / f.sum(dim=(1, 2))).sqrt() / sigma
    assert axis_stretches(1.4) == ((1.4, 1.0), (1.0, 1.4), (1.4, 1.4))
    np.testing.assert_allclose(widened(fp, (1.4, 1.4)), widened(fp, 1.4), atol=1e-7)
    along_x, along_y, _ = (widened(fp, s) for s in axis_stretches(1.4))
    for out, wide, narrow in ((along_x, "x", "y"), (along_y, "y", "x")):
        np.testing.assert_allclose(out.sum(dim=(1, 2)), fp.sum(dim=(1, 2)), rtol=1e-5)
        np.testing.assert_allclose(rms(out, wide), 1.4, rtol=0.06)
        np.testing.assert_allclose(rms(out, narrow), 1.0, rtol=0.03)


def test_softened_footprints_keep_their_width_and_energy_and_lose_their_sharp_core():
    """``softened``: the one-pixel box (1/8, 3/4, 1/8 per axis); a delta becomes the box itself, a wide footprint
    barely changes, a footprint's rms radius grows by the box's own (1/4 px^2 per axis) and no more; the calibration's
    fourth member is it, energy kept."""
    from sssphase_core.relight.engine import calibration_members, softened

    k = 31
    delta = torch.zeros(1, k, k, 3)
    delta[0, k // 2, k // 2] = 1.0
    box = softened(delta)[0, :, :, 0]
    taps = torch.tensor([0.125, 0.75, 0.125])
    np.testing.assert_allclose(box[k // 2 - 1 : k // 2 + 2, k // 2 - 1 : k // 2 + 2], taps[:, None] * taps[None, :], atol=1e-7)
    assert float(box.sum()) == pytest.approx(1.0) and float(box[k // 2, k // 2]) == pytest.approx(0.5625)
    off = torch.arange(k, dtype=torch.float32) - k // 2
    r2 = off[:, None] ** 2 + off[None, :] ** 2
    sigma = torch.tensor([0.7, 1.5, 3.0])
    fp = torch.exp(-r2[None, :, :, None] / (2 * sigma ** 2))
    out = softened(fp)
    var = lambda f: (f * r2[None, :, :, None]).sum(dim=(1, 2)) / f.sum(dim=(1, 2))  # noqa: E731  (x and y together)
    np.testing.assert_allclose(var(out) - var(fp), 0.5, rtol=0.02)  # 2 axes x 1/4 px^2: the box's variance added
    peak = (out / fp)[0, k // 2, k // 2]
    assert float(peak[2]) > 0.95 and float(peak[0]) < 0.75  # the 3 px footprint hardly moves, the 0.7 px one loses its core
    soft = calibration_members(1.3)[-1](fp * 2)
    np.testing.assert_allclose(soft.sum(dim=(1, 2)), (fp * 2).sum(dim=(1, 2)), rtol=1e-5)
    np.testing.assert_allclose(soft, softened(fp * 2) * (fp.sum(dim=(1, 2)) / softened(fp).sum(dim=(1, 2)))[:, None, None], rtol=1e-5)


def test_a_relight_of_variants_only_leaves_the_plain_footprints_out(scene):
    from sssphase_core.relight.engine import widened

    proj, k, fps, pats = scene
    src = lambda px: fps[px[:, 0], px[:, 1]]  # noqa: E731
    both = relight(src, proj, pats, k, variants=(lambda f: widened(f, (1.5, 1.0)),))
    only = relight(src, proj, pats, k, variants=(lambda f: widened(f, (1.5, 1.0)),), plain=False)
    assert only.shape == (1, *both.shape[1:])
    np.testing.assert_allclose(only[0], both[1], rtol=1e-6, atol=1e-8)
    with pytest.raises(ValueError, match="nothing to splat"):
        relight(src, proj, pats, k, plain=False)


def test_a_cache_seeded_onto_a_full_disk_leaves_no_cut_file_and_costs_no_image(tmp_path, monkeypatch):
    """The training check's cache was copied straight to its final name on another file system: a full disk left a
    cut .npz there and ended the relight with "<the run's cache file>: No space left on device"."""
    import errno
    import os
    import shutil

    from sssphase_core.relight import cache as cache_module

    run = tmp_path / "run"
    (run / cache_module.CHECK_FOLDER / "cache").mkdir(parents=True)
    seed = run / cache_module.CHECK_FOLDER / "cache" / "soap_v0_x_torch.npz"
    seed.write_bytes(b"PK" + bytes(4096))

    def other_file_system(src, dst):
        raise OSError(errno.EXDEV, "Invalid cross-device link")

    def disk_full(src, dst):
        with open(dst, "wb") as f:
            f.write(b"PK" + bytes(100))  # part of it, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "link", other_file_system)
    monkeypatch.setattr(shutil, "copyfile", disk_full)
    target = tmp_path / "out" / "cache" / seed.name
    with pytest.warns(UserWarning, match=r"was not started from .*soap_v0_x_torch.npz \(No space left on device\)"):
        cache_module.seed_cache(target, run / "best.pt")
    assert not target.exists() and not [p for p in target.parent.iterdir()]  # nothing cut under any name
    monkeypatch.undo()
    cache_module.seed_cache(target, run / "best.pt")
    assert target.read_bytes() == seed.read_bytes()


def test_a_16_bit_grey_png_with_alpha_keeps_its_16_bits(tmp_path):
    """A 16-bit grey+alpha PNG (colour type 4) went through Pillow, which reads it at 8 bits: a ramp of 300 levels
    kept 5 per row segment."""
    import struct
    import zlib

    h, w = 4, 300
    row = np.empty(2 * w, ">u2")
    row[0::2], row[1::2] = np.arange(w) * 200, 65535  # grey ramp, opaque
    raw = b"".join(b"\0" + row.tobytes() for _ in range(h))

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    (tmp_path / "la16.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 16, 4, 0, 0, 0))
                                        + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
    got = read_pattern(tmp_path / "la16.png", (w, h))
    np.testing.assert_allclose(got[0, :, 0] if got.ndim == 3 else got[0], np.arange(w) * 200 / 65535, atol=1e-6)
