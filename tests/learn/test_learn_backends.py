"""Model backends: the analytic physics baseline, the torch backend and plugin registration."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
import torch

from sssphase_core.bench.synthetic import synthetic_views
from sssphase_core.errors import InputError
from sssphase_core.learning.backends import FootprintBackend, available_backends, get_backend
from sssphase_core.learning.backends.analytic_backend import AnalyticBackend
from sssphase_core.learning.data import psp_patches
from sssphase_core.learning.evaluation import footprint_metrics, summarise


@pytest.fixture(scope="module")
def flat_scene():
    views, kernels = synthetic_views(("a", "b"), (0,), size=(64, 64), patch=32, period=8.0, pixels_per_view=20, noise=0.0)
    return views, kernels


def test_analytic_recovers_known_exponential_kernels(flat_scene):
    views, kernels = flat_scene
    be = AnalyticBackend(patch=32, black=0.0, profile="exponential")
    for v in views:
        est = be.estimate(psp_patches(v.psp, v.pixels, 32))
        k = kernels[v.object]
        assert np.allclose(est["energy"], k.sum(axis=(0, 1)), rtol=1e-3)
        # isotropic kernel: equal widths along x and y, consistent with the known per-channel widths
        assert np.allclose(est["widths"][..., 0], est["widths"][..., 1], rtol=1e-3)
        assert np.allclose(np.abs(est["freq"][:, 0, 0]), 2 * np.pi / 8, rtol=1e-3)
        pred = be.predict_footprints((v.psp, v.pixels))
        assert pred.shape == (20, 32, 32, 3)
        assert summarise(footprint_metrics(pred, np.asarray(v.footprints)))["ssim"] > 0.97


def test_analytic_detects_anisotropy():
    be = AnalyticBackend(patch=16, black=0.0, profile="exponential")
    # MTF per orientation for widths (dx, dy) = (2, 0.5) at k = 0.8 rad/px along x resp. y
    k2 = np.array([[[0.64, 0.0], [0.0, 0.64]]])
    u = np.stack([np.full(3, 0.64 * 4), np.full(3, 0.64 * 0.25)])[None]
    widths = be._solve_widths(k2, u)
    assert np.allclose(widths[0, :, 0], 2.0) and np.allclose(widths[0, :, 1], 0.5)
    fp = be.render(np.ones((1, 3)), widths)
    assert fp[0, 8, :, 0].sum() > 2 * fp[0, :, 8, 0].sum()  # wider along x than along y


def test_footprints_integrate_to_the_energy():
    be = AnalyticBackend(patch=32)
    fp = be.render(np.array([[0.5, 0.3, 0.1]]), np.full((1, 3, 2), 1.5))
    assert np.allclose(fp.sum(axis=(1, 2)), [0.5, 0.3, 0.1], rtol=1e-5)
    assert fp[0].argmax() // 3 == 16 * 32 + 16  # peak on the entry pixel


def _render_directly(widths: np.ndarray, k: int, s: int) -> np.ndarray:
    """The render rule pixel by pixel over the whole K x K grid in float64 (the reference the mirrored quadrant
    must match): supersampled within NEAR_PIXELS diagonals of the pole (width-scaled), the centre's value beyond."""
    from sssphase_core.learning.backends.analytic_backend import _MEAN_INV_R, NEAR_PIXELS

    burley = lambda r: (np.exp(-r) + np.exp(-r / 3)) / r  # noqa: E731
    sub = (np.arange(s) + 0.5) / s - 0.5
    out = np.zeros((len(widths), k, k, 3))
    for n, w in enumerate(widths):
        for c, (dx, dy) in enumerate(w):
            for y in range(k):
                for x in range(k):
                    oy, ox = y - k // 2, x - k // 2
                    if np.hypot(oy / dy, ox / dx) < NEAR_PIXELS * np.hypot(1 / dx, 1 / dy):
                        r = np.hypot((oy + sub)[:, None] / dy, (ox + sub)[None, :] / dx)
                        out[n, y, x, c] = burley(np.maximum(r, 1 / (s * _MEAN_INV_R * np.sqrt(dx * dy)))).sum()
                    else:
                        out[n, y, x, c] = s * s * burley(np.hypot(oy / dy, ox / dx))
    return out / out.sum(axis=(1, 2), keepdims=True)


@pytest.mark.parametrize("k", [9, 10])
def test_the_mirrored_quadrant_render_is_the_render_rule_over_the_whole_patch(k):
    """Footprints are integrated over one quadrant and mirrored (a stretched radial profile, symmetric
    sub-pixel samples): the same footprints, odd or even K, thin or wide, within float32."""
    # (widths off the near rule's ties: at 1 x 1 px the pixel (3, 3) lies exactly on its threshold, where float32
    # and float64 may choose differently, both right)
    widths = np.array([[[1.1, 0.9], [0.3, 2.0], [4.0, 0.5]], [[0.05, 0.05], [2.6, 2.4], [0.7, 6.0]]])
    fp = AnalyticBackend(patch=k, supersample=3).render(np.ones((2, 3)), widths)
    ref = _render_directly(widths, k, 3)
    assert fp.dtype == np.float32 and np.abs(fp - ref).max() < 2e-6


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_tensors_render_on_their_device_the_footprints_arrays_render(device):
    """The torch backend renders the analytic tail where its footprints are (a GPU's): tensors in give a tensor on
    the widths' device, the same footprints as NumPy's within float32, chunked or not, either profile."""
    from sssphase_core.learning.backends.analytic_backend import render_footprints

    rng = np.random.default_rng(3)
    energy, widths = rng.uniform(0.1, 2, (11, 3)), rng.uniform(0.05, 12, (11, 3, 2))
    for profile in ("burley", "exponential"):
        be = AnalyticBackend(patch=31, profile=profile, chunk=4)
        want = be.render(energy, widths)
        got = be.render(torch.as_tensor(energy, device=device), torch.as_tensor(widths, device=device))
        assert isinstance(want, np.ndarray) and torch.is_tensor(got) and got.device.type == device
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=2e-5, atol=1e-7 * want.max())
        whole = render_footprints(torch.as_tensor(energy), torch.as_tensor(widths), 31, profile=profile, chunk=64)
        np.testing.assert_allclose(whole.numpy(), want, rtol=1e-6, atol=1e-9)


def test_a_query_of_pixels_reads_only_the_window_the_estimate_needs(flat_scene):
    """(psp, pixels) queries are cropped to the estimate's window, not to K x K: the same footprints as from the
    full patches, at the image's border too."""
    views, _ = flat_scene
    psp = views[0].psp
    pixels = np.concatenate([views[0].pixels, [[0, 0], [63, 63], [1, 62]]])
    be = AnalyticBackend(patch=32)
    full = be.predict_footprints(psp_patches(psp, pixels, 32))
    assert np.array_equal(be.predict_footprints((psp, pixels)), full)
    from sssphase_core.relight.sources import backend_source

    # relighting crops the backend's input_patch (5), not K = 32
    assert be.input_patch == 5 and np.array_equal(backend_source(be, psp, chunk=7)(pixels), full)
    with pytest.raises(InputError, match="5x5 window"):
        be.estimate(psp_patches(psp, pixels[:2], 4))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"))])
def test_the_analytic_model_gives_tensor_patches_footprints_on_its_device(flat_scene, device):
    """Tensor patches (the relight's, cut on a GPU) give a tensor on the backend's device: the footprints of the same
    patches as arrays. On the CPU the relight keeps NumPy; on a GPU it hands the model windows cut there."""
    from sssphase_core.relight.sources import backend_source

    views, _ = flat_scene
    psp, pixels = views[0].psp, np.concatenate([views[0].pixels, [[0, 0], [63, 63]]])
    be = AnalyticBackend(patch=32, device=device)
    want = be.predict_footprints((psp, pixels))
    for size in (5, 32):  # the window the estimate reads, or whole patches
        got = be.predict_footprints(torch.as_tensor(psp_patches(psp, pixels, size), device=device))
        assert torch.is_tensor(got) and got.device.type == device
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=1e-6, atol=1e-9)
    assert be.accepts_tensors == (device != "cpu")
    relit = backend_source(be, psp, chunk=7)(pixels)
    assert torch.is_tensor(relit) == (device != "cpu")
    np.testing.assert_allclose(relit.cpu().numpy() if torch.is_tensor(relit) else relit, want, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("k", [5, 90])
def test_the_render_is_finite_and_keeps_the_energy_at_extreme_widths(k):
    """Widths from a thousandth of a pixel (a sharp, nearly black object) to far beyond the patch, each axis alone
    (a line) or both, and energies from 0 to 1e4: finite footprints that sum to their energy (float32)."""
    ws = np.array([1e-3, 1e-2, 0.3, 5.0, 45.0, 1e3, 1e6], np.float32)
    wx, wy = (a.ravel() for a in np.meshgrid(ws, ws))
    widths = np.repeat(np.stack([wx, wy], -1)[:, None], 3, axis=1)  # (49, 3, 2)
    for e in (0.0, 1e-30, 1.0, 1e4):
        fp = AnalyticBackend(patch=k).render(np.full((len(widths), 3), e, np.float32), widths)
        assert np.isfinite(fp).all() and (fp >= 0).all()
        np.testing.assert_allclose(fp.sum(axis=(1, 2), dtype=np.float64), e, rtol=1e-5, atol=0)


@pytest.mark.parametrize("supersample", [1, 2, 3, 8])
def test_burley_render_is_finite_at_any_supersampling(supersample):
    """Odd supersampling puts a sample on the profile's 1/r pole (it used to give NaN)."""
    be = AnalyticBackend(patch=32, supersample=supersample)
    widths = np.array([[[1.0, 1.0]] * 3, [[0.3, 2.0]] * 3, [[0.01, 0.01]] * 3])
    fp = be.render(np.ones((3, 3)), widths)
    assert np.isfinite(fp).all()
    assert np.allclose(fp.sum(axis=(1, 2)), 1.0, rtol=1e-5)
    ref = AnalyticBackend(patch=32, supersample=16).render(np.ones((3, 3)), widths)
    assert np.abs(fp - ref).sum(axis=(1, 2)).max() < 0.3  # the pole's share converges with supersampling


def test_backends_are_registered_and_follow_the_protocol():
    found = available_backends()
    assert {"torch", "analytic"} <= found.keys()
    assert isinstance(get_backend("analytic"), FootprintBackend)
    with pytest.raises(InputError, match="analytic"):
        get_backend("nope")


def test_backend_hookspec_is_loaded_by_the_plugin_manager():
    pytest.importorskip("sssphase_plugins.manager")
    from sssphase_plugins.manager import build_plugin_manager

    pm = build_plugin_manager()
    assert hasattr(pm.hook, "sssphase_model_backends")
    import sssphase_core.learning.backends as builtin

    if not pm.is_registered(builtin):
        pm.register(builtin, name="builtin-test")
    merged = {k: v for d in pm.hook.sssphase_model_backends() for k, v in d.items()}
    assert isinstance(merged["analytic"](patch=16), AnalyticBackend)


@contextlib.contextmanager
def _backend_plugins(tmp_path, monkeypatch, **modules: str):
    """The plugin manager loaded with ``modules`` (name -> source) as $SSS_PLUGINS, and reloaded without them after."""
    from sssphase_plugins import manager

    for name, source in modules.items():
        (tmp_path / f"{name}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("SSS_PLUGINS", ",".join(modules))
    try:
        yield manager.get_plugin_manager(refresh=True)
    finally:
        monkeypatch.delenv("SSS_PLUGINS")
        manager.get_plugin_manager(refresh=True)


def test_a_plugin_backend_reaches_core_through_the_plugin_manager(tmp_path, monkeypatch):
    """Core does not import the plugin layer: the manager hands it the plugins' backends when loaded."""
    from sssphase_core.learning import backends
    from sssphase_plugins import manager

    mine = ("from sssphase_core.learning.backends import hookimpl\n"
            "from sssphase_core.learning.backends.analytic_backend import AnalyticBackend\n"
            "@hookimpl\n"
            "def sssphase_model_backends():\n"
            "    return {'mine': lambda **o: AnalyticBackend(patch=8, **o)}\n")
    with _backend_plugins(tmp_path, monkeypatch, my_backend_plugin=mine):
        try:
            assert isinstance(get_backend("mine"), AnalyticBackend) and "torch" in available_backends()
            backends.use_plugin_backends(None)
            with pytest.raises(InputError, match="unknown model backend 'mine'"):
                get_backend("mine")
        finally:
            backends.use_plugin_backends(manager._plugin_model_backends)


def test_a_backend_plugin_that_raises_or_takes_a_taken_name_is_left_out_not_the_others(tmp_path, monkeypatch):
    """A plugin whose backend hook raised made every relight "internal error: RuntimeError", built-in backends too;
    a plugin's `analytic` replaced the built-in one without a word."""
    import warnings

    from sssphase_core.learning import backends

    crashing = ("from sssphase_core.learning.backends import hookimpl\n"
                "@hookimpl\n"
                "def sssphase_model_backends():\n"
                "    raise RuntimeError('gauss backend hook crashed')\n")
    impostor = ("from sssphase_core.learning.backends import hookimpl\n"
                "from sssphase_core.learning.backends.analytic_backend import AnalyticBackend\n"
                "@hookimpl\n"
                "def sssphase_model_backends():\n"
                "    return {'analytic': lambda **o: None, 'mine': lambda **o: AnalyticBackend(patch=8, **o)}\n")
    intkey = ("from sssphase_core.learning.backends import hookimpl\n"
              "@hookimpl\n"
              "def sssphase_model_backends():\n"
              "    return {3: lambda **o: None}\n")
    uncallable = intkey.replace("{3: lambda **o: None}", "{'weird': 42}")
    with _backend_plugins(tmp_path, monkeypatch, crashing_backends=crashing, impostor_backends=impostor,
                          intkey_backends=intkey, uncallable_backends=uncallable):
        backends._told.clear()
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            found = available_backends()
        lines = [str(w.message) for w in said]
        assert {"torch", "analytic", "mine"} <= set(found)
        assert isinstance(get_backend("analytic", patch=16), AnalyticBackend)  # the built-in, not the impostor's
        from sssphase_plugins.manager import plugin_provides

        provides = plugin_provides()  # `sss plugins` listed a backend plugin as "backend", never which backends
        assert provides["builtin"] == ["backends torch, analytic"] and provides["sim"] == ["cameras", "projectors",
                                                                                            "turntables"]
        assert provides["impostor_backends"] == ["backends mine"]
        # (a key of 3 crashed `sss plugins` with "internal error: TypeError"; {'weird': 42} was listed as provided)
        for plugin in ("crashing_backends", "intkey_backends", "uncallable_backends"):
            assert provides[plugin] == ["no backend (see the warning)"], provides
        assert "weird" not in found
    assert "model backend plugin intkey_backends returned a backend named 3: names are non-empty text: its backends " \
           "are left out" in lines, lines
    assert "model backend plugin uncallable_backends returned backend 'weird' as int '42', not a factory (callable): " \
           "its backends are left out" in lines, lines
    assert any(line.startswith("model backend plugin crashing_backends failed (RuntimeError: gauss backend hook "
                               "crashed)") for line in lines), lines
    assert "backend 'analytic' of plugin impostor_backends is left out: 'analytic' is a built-in backend " \
           "(rename it)" in lines, lines


def test_a_plugin_backend_is_given_what_its_factory_takes_of_the_view(tmp_path, monkeypatch):
    """A plugin's factory was called with no options: a trained plugin backend never got its checkpoint, nor the
    session's patch size, and --checkpoint was "not used" by it."""
    from sssphase_core.learning.backends import accepted_options
    from sssphase_core.relight.runner import _plugin_takes_checkpoint

    taking = ("from sssphase_core.learning.backends import hookimpl\n"
              "def named(patch, checkpoint=None):\n    return (patch, checkpoint)\n"
              "def anything(**options):\n    return options\n"
              "def nothing():\n    return None\n"
              "@hookimpl\n"
              "def sssphase_model_backends():\n"
              "    return {'named': named, 'anything': anything, 'nothing': nothing}\n")
    offered = {"patch": 16, "black": 0.01, "device": "cpu", "checkpoint": "weights.pt"}
    with _backend_plugins(tmp_path, monkeypatch, taking_backends=taking):
        assert accepted_options("named", offered) == {"patch": 16, "checkpoint": "weights.pt"}
        assert accepted_options("anything", offered) == offered and accepted_options("nothing", offered) == {}
        assert _plugin_takes_checkpoint("named") and not _plugin_takes_checkpoint("nothing")
        assert not _plugin_takes_checkpoint("analytic")


def test_loading_the_backend_registry_does_not_import_torch():
    import subprocess
    import sys

    code = "import sys, sssphase_core.learning.backends as b; b.sssphase_model_backends(); print('torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_torch_backend_fits_and_predicts(dataset, tiny, tmp_path, synthetic):
    from sssphase_core.learning.training import DecoderConfig, PretrainConfig

    views = synthetic[0]
    be = get_backend("torch")
    with pytest.raises(InputError):
        be.predict_footprints(np.zeros((1, 24, 16, 16), np.float32))
    enc = be.pretrain(views, tmp_path / "pre", config=PretrainConfig(epochs=1, batch_size=16, ckpt_every=0), preset=tiny, progress=False)
    be.fit(views, tmp_path / "dec", encoder=enc, config=DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), progress=False)
    v = views[0]
    a = be.predict_footprints((v.psp, v.pixels[:5]))
    b = be.predict_footprints(psp_patches(v.psp, v.pixels[:5], 16))
    assert a.shape == (5, 16, 16, 3) and np.allclose(a, b, atol=1e-6)
    with pytest.raises(InputError, match="N, 24, K, K"):
        be.predict_footprints(np.zeros((2, 8, 16, 16), np.float32))


def test_auto_precision_is_bf16_only_where_the_cpu_computes_it_natively(monkeypatch, tmp_path, synthetic, tiny):
    """``auto``: bf16 on a CPU with AVX512-BF16 or AMX, float32 on one without (emulated bf16 is slower); the
    backend's footprints under bf16 are float32's within bf16's rounding."""
    import torch

    from sssphase_core.compute import inference_precision
    from sssphase_core.learning.backends.torch_backend import TorchBackend
    from sssphase_core.learning.training import DecoderConfig, PretrainConfig

    for avx512_bf16, amx, said in ((False, False, "fp32"), (True, False, "bf16"), (False, True, "bf16")):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda v=avx512_bf16: v)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda v=amx: v)
        assert inference_precision("cpu") == said
        assert TorchBackend(precision="auto").precision == said
    assert inference_precision("cpu", "fp32") == "fp32" and inference_precision("cpu", "bf16") == "bf16"
    with pytest.raises(InputError, match="unknown precision 'half'"):
        TorchBackend(precision="half")
    views = synthetic[0]
    be = get_backend("torch")
    enc = be.pretrain(views, tmp_path / "pre", config=PretrainConfig(epochs=1, batch_size=16, ckpt_every=0), preset=tiny,
                      progress=False)
    path = be.fit(views, tmp_path / "dec", encoder=enc, config=DecoderConfig(epochs=1, batch_size=16, ckpt_every=0),
                  progress=False)
    query = (views[0].psp, views[0].pixels[:16])
    fp32 = TorchBackend(path, precision="fp32").predict_footprints(query)
    bf16 = TorchBackend(path, precision="bf16").predict_footprints(query)
    assert bf16.dtype == np.float32 and 0 < np.abs(bf16 - fp32).mean() < 0.02 * np.abs(fp32).mean()


def test_a_backend_returning_footprints_of_the_wrong_shape_is_named():
    """A plugin backend's (31, 32, 3) footprints were "the footprint source returned ... footprints": which backend?"""
    from sssphase_core.relight.sources import backend_source

    class Skewed:
        patch = 8

        def predict_footprints(self, patches):
            return np.zeros((len(patches), 7, 8, 3), np.float32)

    source = backend_source(Skewed(), np.zeros((8, 20, 30, 3), np.float32))
    with pytest.raises(InputError, match=r"model backend Skewed \(.*\) returned footprints of shape \(2, 7, 8, 3\) for 2 "
                                         r"pixels: expected \(2, 8, 8, 3\)"):
        source(np.array([[5, 10], [6, 11]]))


def test_weights_with_a_key_the_model_lacks_say_which():
    """A checkpoint with an extra key said only "(Error(s) in loading state_dict for Decoder:)"."""
    import torch

    from sssphase_core.errors import DataError
    from sssphase_core.learning.training.checkpoints import _load_weights

    module = torch.nn.Linear(2, 2)
    with pytest.raises(DataError, match=r"x.pt: the decoder weights do not fit the checkpoint's preset \(Unexpected "
                                        r"key\(s\) in state_dict: \"extra\"\)"):
        _load_weights(module, {**module.state_dict(), "extra": torch.zeros(1)}, "x.pt", "decoder")
