"""The simulator's light transport on a torch device (sssphase_core.sim_accel) renders what the numpy path
renders: the same footprints and images within float tolerance, on the CPU here and on CUDA where present."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from sssphase_core.errors import InputError
from sssphase_core.sim import SimScene, rig_preset
from sssphase_core.sim_accel import TorchTransport, transport_factory

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("obj", ["crab", "soap"])
def test_device_transport_renders_what_numpy_renders(obj, device):
    # the crab on the CPU preset; the soap before a wall (37,294 lit pixels), with 16 px footprints to keep it quick
    rig = rig_preset("cpu") if obj == "crab" else replace(rig_preset("cpu"), backdrop=90.0, patch=16)
    cpu = SimScene(obj, rig=rig)
    dev = SimScene(obj, rig=rig, transport_factory=transport_factory(device))
    assert isinstance(dev.transport, TorchTransport) and not isinstance(cpu.transport, TorchTransport)
    patterns = np.random.default_rng(0).uniform(0, 1, (1, 192, 256)).astype(np.float32)  # one pattern: the map is linear
    a, b = cpu.render(patterns), dev.render(patterns)
    assert a.shape == b.shape and a.max() > 0.1
    assert np.abs(a - b).max() <= 1e-5 * a.max()
    pixels = np.argwhere(cpu.lit)[::97]
    fa, fb = cpu.footprints(pixels), dev.footprints(pixels)
    assert np.abs(fa - fb).max() <= 1e-6 * fa.max()
    # the near rings clamped at the pixel's own disc are where a port goes wrong: they differ from the far field
    half = cpu.rig.patch // 2
    assert np.abs(fa[:, half - 1 : half + 2, half - 1 : half + 2] - fb[:, half - 1 : half + 2, half - 1 : half + 2]).max() \
        <= 1e-6 * fa.max()


def test_a_dot_frame_lights_only_its_dots_on_the_device():
    """Sparse light (a dot grid) splats only the lit sources, as on the CPU: black away from the dots."""
    from sssphase_core.processing.patterns import dot_grid

    cpu = SimScene("apple", rig=rig_preset("cpu"))
    dev = SimScene("apple", rig=rig_preset("cpu"), transport_factory=transport_factory("cpu"))
    dots = dot_grid(256, 192, 20, 3, 7)[None]
    a, b = cpu.render(dots), dev.render(dots)
    assert np.abs(a - b).max() <= 1e-5 * a.max()
    assert (a[0].sum(-1) > 0).mean() < 0.5  # most of the image stays (near) black


@pytest.mark.parametrize("device", DEVICES)
def test_a_batch_of_dot_grids_splats_each_source_only_under_its_own_grid(device, monkeypatch):
    """A batch of dot frames lights each source under one of its patterns: it is splatted pattern by pattern, and
    renders what numpy renders and what the every-pattern splat renders, frame for frame; a batch with a full-white
    pattern among the dots too."""
    from sssphase_core import sim_accel
    from sssphase_core.processing.patterns import dot_grid

    rig = rig_preset("cpu")
    cpu = SimScene("apple", rig=rig)
    dev = SimScene("apple", rig=rig, transport_factory=transport_factory(device))
    dots = np.stack([dot_grid(256, 192, 20, i, j) for i, j in ((0, 0), (7, 3), (13, 11), (19, 19))])
    dev.unit_white()  # (the first render would add the unit white's pattern to the batch)
    calls: list[int] = []  # the patterns of each splat
    splat_into = sim_accel.TorchTransport._splat_into

    def counted(self, canvas, src, light, progress):
        calls.append(light.shape[1])
        return splat_into(self, canvas, src, light, progress)

    monkeypatch.setattr(sim_accel.TorchTransport, "_splat_into", counted)
    for patterns in (dots, np.concatenate([dots, np.ones((1, 192, 256), np.float32)])):
        calls.clear()
        b = dev.render(patterns)
        assert calls == [1] * len(patterns)  # one pattern at a time
        a = cpu.render(patterns)
        assert np.abs(a - b).max() <= 1e-5 * a.max()
        with monkeypatch.context() as every:
            every.setattr(sim_accel, "COMPUTE_OVER_SPLAT", 1e9)  # every source under every pattern
            calls.clear()
            dense = dev.render(patterns)
        assert calls == [len(patterns)]
        assert np.abs(dense - b).max() <= 1e-5 * a.max()  # (float32 sums in another order)


def test_directional_dipole_stays_on_the_cpu_whatever_the_device():
    from sssphase_core.sim.rig import with_transport

    rig = with_transport(rig_preset("cpu"), "directional_dipole")
    scene = SimScene("star", rig=rig, transport_factory=transport_factory("cpu"))
    assert not isinstance(scene.transport, TorchTransport) and scene.transport.name == "directional_dipole"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(("obj", "g"), [("soap", 0.0), ("crab", 0.7)])
def test_the_radiative_transport_on_a_device_renders_what_numpy_renders(obj, g, device):
    from sssphase_core.sim.rig import with_transport
    from sssphase_core.sim_accel import TorchRadiativeTransport

    rig = with_transport(rig_preset("cpu"), "radiative", g)
    cpu, dev = SimScene(obj, rig=rig), SimScene(obj, rig=rig, transport_factory=transport_factory(device))
    assert isinstance(dev.transport, TorchRadiativeTransport) and not isinstance(cpu.transport, TorchTransport)
    patterns = np.random.default_rng(0).uniform(0, 1, (1, 192, 256)).astype(np.float32)  # one pattern: the map is linear
    a, b = cpu.render(patterns), dev.render(patterns)
    assert a.max() > 0.1 and np.abs(a - b).max() <= 1e-5 * a.max()
    pixels = np.argwhere(cpu.lit)[::97]
    fa, fb = cpu.footprints(pixels), dev.footprints(pixels)
    assert np.abs(fa - fb).max() <= 1e-5 * fa.max()


def test_the_sim_option_device_is_checked_before_any_work():
    from sssphase_plugins.sim_plugin import SimRigState

    assert SimRigState({"object": "star"}).transport_factory is None  # cpu: numpy, torch not needed
    assert SimRigState({"object": "star", "device": "cpu:0"}).transport_factory is None
    with pytest.raises(InputError, match="unknown device"):
        SimRigState({"object": "star", "device": "gpu"})
    with pytest.raises(InputError, match="must be a string"):
        SimRigState({"object": "star", "device": 1})
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="sees no CUDA device"):
            SimRigState({"object": "star", "device": "cuda"})
    state = SimRigState({"object": "star", "device": "auto"})
    if torch.cuda.is_available():
        assert isinstance(state.scene.transport, TorchTransport) and state.sensor is not None  # the sensor there too
        assert SimRigState({"object": "star", "device": "auto", "demosaic": "none"}).sensor is None  # three-chip
    else:  # auto on a machine without a GPU: the numpy path, faster there than torch on the CPU
        assert state.transport_factory is None and state.sensor is None
        assert not isinstance(state.scene.transport, TorchTransport)
    assert SimRigState({"object": "star"}).sensor is None


@pytest.mark.slow
def test_a_capture_on_the_device_equals_the_numpy_capture(sim_daemon, tmp_path):
    """`sss capture --device auto`: on a GPU the daemon renders the frames and the client the ground-truth
    references there: the same noise-free renders within float tolerance, captures that agree to within their
    noise (the same seeds, but a Poisson draw whose rate differs in its last bits can take another path through
    the generator), the same decoded correspondences, and it resumes across devices. Without a GPU, auto is the
    numpy path: the same frames, bit for bit."""
    from sssphase_core.capture import CaptureRequest, RigSpec, run_capture

    got = {}
    for device in ("cpu", "auto"):
        req = CaptureRequest.from_options("sand_rake", RigSpec(), views=1, references=["checkerboard"], device=device,
                                          out=tmp_path / device)
        got[device] = run_capture(sim_daemon, req)
    a, b = got["cpu"], got["auto"]
    assert b.manifest["rig"]["options"]["device"] == "auto"
    for name in ("gt/render/checkerboard", "gt/render/white"):
        x, y = np.asarray(a.load(0, name), np.float32), np.asarray(b.load(0, name), np.float32)
        assert x.shape == y.shape and np.abs(x - y).max() <= 1e-5 * np.abs(x).max(), name
    x, y = np.asarray(a.load(0, "psp"), np.float32), np.asarray(b.load(0, "psp"), np.float32)
    assert np.abs(x - y).mean() <= 2e-3 * x.max()  # below the shot noise (~1% of white)
    if not torch.cuda.is_available():
        np.testing.assert_array_equal(x, y)
    mask = a.load(0, "corr/mask").astype(bool) & b.load(0, "corr/mask").astype(bool)
    assert mask.sum() > 1000
    assert np.median(np.abs(a.load(0, "corr/xp")[mask] - b.load(0, "corr/xp")[mask])) < 0.05  # projector px
    again = CaptureRequest.from_options("sand_rake", RigSpec(), views=1, references=["checkerboard"], resume=True,
                                        out=tmp_path / "auto")
    assert run_capture(sim_daemon, again).views() == [0]  # the device is where it computes, not another rig


def test_sparse_patterns_are_looked_up_only_where_they_reach_with_the_same_values():
    from sssphase_core.processing.patterns import dot_grid
    from sssphase_core.processing.projector import sample_projector
    from sssphase_core.sim.scene import _sample_sparse

    rng = np.random.default_rng(3)
    light = np.stack([dot_grid(64, 48, 9, 2, 5), dot_grid(64, 48, 9, 8, 0)])[..., None].astype(np.float32)
    light[1, 0, 63] = 0.5  # a lit pixel in the corner: taps beyond the edge read 0
    xy = np.column_stack([rng.uniform(-1.5, 64.5, 5000), rng.uniform(-1.5, 48.5, 5000)]).astype(np.float32)
    xy[:50] = np.nan  # pixels without projector light
    xy[50:60] = [[63.4, -0.3]] * 10
    dense = sample_projector(light, xy[:, 0], xy[:, 1])
    sparse = _sample_sparse(light, xy)
    assert np.count_nonzero(dense) > 100
    np.testing.assert_array_equal(sparse, np.nan_to_num(dense))


@pytest.mark.slow
def test_bench_sim_times_the_plan_and_compares_the_paths(tmp_path, monkeypatch):
    """`sss bench sim` (the plumbing, on the CPU preset with torch on the CPU): every frame kind timed, the numpy
    baseline measured in the same run, and both paths' footprints and images compared."""
    import functools
    import json

    from typer.testing import CliRunner

    from sssphase_cli.main import app
    from sssphase_core.bench import sim_accel_bench

    out = tmp_path / "sim.json"  # fewer dot frames rendered and numpy pixels sampled than the bench's 200 and 20,000
    monkeypatch.setattr(sim_accel_bench, "run", functools.partial(sim_accel_bench.run, cpu_pixels=2000, dot_sample=20))
    result = CliRunner().invoke(app, ["bench", "sim", "--device", "cpu", "--preset", "cpu", "--object", "sand_rake",
                                      "--out", str(out)])
    assert result.exit_code == 0, result.output
    r = json.loads(out.read_text())
    assert r["frames"] == 426 and r["dot_frames"] == 400 and r["dot_frames_rendered"] == 20
    assert r["render_s"] >= r["render_psp_s"] > 0 and r["numpy_psp_white_s"] > 0 and r["sense_frame_s"] > 0
    assert r["device_sense_frame_s"] > 0
    assert r["footprint_max_rel_diff"] < 1e-6 and r["image_max_rel_diff"] < 1e-5
    assert "the numpy path" in out.with_suffix(".md").read_text()
    refused = CliRunner().invoke(app, ["bench", "sim", "--device", "cpu", "--transport", "directional_dipole",
                                       "--out", str(tmp_path / "dd.json")])
    assert isinstance(refused.exception, InputError) and "burley or radiative" in str(refused.exception)
    assert not (tmp_path / "dd.json").exists()  # refused before any work (`sss` prints it as one line)
    # the radiative transport through the same benchmark (the CLI's --transport is this call's), on fewer sampled
    # pixels and dot frames
    from sssphase_core.bench.sim_accel_bench import markdown, run

    r = run(device="cpu", preset="cpu", object_name="sand_rake", transport="radiative", cpu_pixels=2000, dot_sample=20)
    assert r["transport"] == "radiative" and r["dot_frames_rendered"] == 20
    assert r["footprint_max_rel_diff"] < 1e-5 and r["image_max_rel_diff"] < 1e-5
    assert "radiative transport" in markdown(r)


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_isp_equals_the_cameras(device):
    """Median per Bayer plane and Malvar demosaicing on the device give what processing.isp gives (OpenCV's median
    and Malvar), borders included."""
    from sssphase_core.processing.isp import demosaic, develop, median3_bayer
    from sssphase_core.sim_accel import DeviceSensor, malvar_rggb, median3_rggb

    cfa = np.random.default_rng(0).uniform(0, 4095, (38, 52)).round().astype(np.uint16)
    t = torch.tensor(cfa, dtype=torch.float64, device=device)[None]
    np.testing.assert_allclose(malvar_rggb(t)[0].cpu().numpy(), demosaic(cfa.astype(np.float32), "malvar"), atol=1e-3)
    np.testing.assert_array_equal(median3_rggb(t.float())[0].cpu().numpy(), median3_bayer(cfa).astype(np.float32))
    cfg = rig_preset("paper").sensor
    got = DeviceSensor(device).develop(t.float(), cfg, cfg.dn_per_unit(1.0))[0].cpu().numpy()
    want = develop(cfa, cfg.black_level, cfg.dn_per_unit(1.0), median=True, method="malvar")
    assert np.abs(got - want).max() <= 1e-6 * np.abs(want).max()


@pytest.mark.parametrize("device", DEVICES)
def test_the_device_sensor_draws_the_cameras_noise(device):
    """Photon and read noise drawn on the device: the numpy path's mean and spread per colour (another draw, so
    statistics, not samples), the same frame again from the same seed, raw frames as uint16 Bayer."""
    from sssphase_core.sim.sensor import expose
    from sssphase_core.sim_accel import DeviceSensor

    cfg = rig_preset("cpu").sensor
    img = np.full((2, 64, 64, 3), 0.3, np.float32)
    img[..., 2] = 0.05
    sensor = DeviceSensor(device)
    a = expose(img, cfg, np.random.default_rng(0)).astype(np.float64)
    b = sensor.expose(img, cfg, np.random.default_rng(0)).cpu().numpy()
    for y, x in ((0, 0), (1, 1), (0, 1)):  # R, B, G sites
        pa, pb = a[:, y::2, x::2], b[:, y::2, x::2]
        assert abs(pa.mean() - pb.mean()) < 0.01 * pa.mean() and abs(pa.std() - pb.std()) < 0.1 * pa.std()
    assert (b == np.round(b)).all() and b.max() <= cfg.max_dn
    again = sensor.sense(img, cfg, np.random.default_rng(5))
    np.testing.assert_array_equal(again, sensor.sense(img, cfg, np.random.default_rng(5)))  # resumable captures
    raw = sensor.sense(img, cfg, np.random.default_rng(5), raw=True)
    assert raw.dtype == np.uint16 and raw.shape == (2, 64, 64)
    assert DeviceSensor.handles(cfg) and not DeviceSensor.handles(rig_preset("cpu").sensor.__class__(demosaic="none"))
