"""The white a full-colour view's relighting is made consistent with (`calibration.exit_white`): the white capture
and the 8 PSP frames' offset, averaged. A textured object with shot noise in every capture: the estimate keeps the
texture and carries less of the capture's noise; where the fringes are lost it is the white capture."""

from types import SimpleNamespace

import numpy as np

from sssphase_core.relight.calibration import exit_white


def _view(rng, lost_rows=0):
    h, w = 48, 64
    texture = 0.2 + 0.6 * rng.random((h, w, 3)).astype(np.float32)  # a different albedo at every pixel
    photons = 3000.0

    def shot(x):
        return (rng.poisson(x * photons) / photons).astype(np.float32)

    phases = np.arange(4) * np.pi / 2
    xs = np.arange(w)[None, :, None] * 2 * np.pi / 8
    frames = [shot(texture * 0.5 * (1 + 0.6 * np.cos(xs + p))) for p in phases]
    frames += [shot(texture * 0.5 * (1 + 0.6 * np.cos(np.arange(h)[:, None, None] * 2 * np.pi / 8 + p))) for p in phases]
    psp = np.stack(frames)
    lost = np.zeros((h, w), bool)
    lost[:lost_rows] = True
    mask = np.ones((h, w), bool)
    rv = SimpleNamespace(white=shot(texture), psp=psp, saturation=None, white_saturation=None,
                         proj=SimpleNamespace(mask=mask, black=0.0), _model_inputs=(psp, lost))
    return rv, texture


def test_the_nine_capture_white_keeps_the_texture_with_less_noise():
    rv, texture = _view(np.random.default_rng(0))
    est = exit_white(rv)
    err_capture = np.sqrt(np.mean((rv.white - texture) ** 2))
    err_both = np.sqrt(np.mean((est - texture) ** 2))
    assert err_both < 0.6 * err_capture  # ~1/sqrt(5) of the capture's noise
    assert np.corrcoef(est.ravel(), texture.ravel())[0, 1] > 0.99  # the per-pixel texture stays


def test_where_the_fringes_are_lost_the_white_capture_is_kept():
    rv, _ = _view(np.random.default_rng(1), lost_rows=5)
    est = exit_white(rv)
    np.testing.assert_array_equal(est[:5], rv.white[:5])
    assert not np.allclose(est[5:], rv.white[5:])
