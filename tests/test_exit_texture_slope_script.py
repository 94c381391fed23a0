"""The exit-texture diagnostic (benchmarks/exit_texture_slope.py) reads fringe modulation as the PSP frames hold it."""


import numpy as np
from benchmark_script import load_benchmark

script = load_benchmark("exit_texture_slope")


def test_modulation_is_the_fringes_amplitude_whatever_their_phase_and_offset():
    rng = np.random.default_rng(0)
    offset, amplitude = rng.uniform(0.2, 1.0, (2, 5, 4, 3)), rng.uniform(0.0, 0.2, (2, 5, 4, 3))
    phase = rng.uniform(0, 2 * np.pi, (2, 5, 4, 3))
    frames = np.stack([offset[o] + amplitude[o] * np.cos(phase[o] + n * np.pi / 2) for o in (0, 1) for n in range(4)])
    np.testing.assert_allclose(script.modulation(frames), amplitude.mean(axis=0), rtol=1e-6)
    textured = frames * 1.7  # a texture where light leaves the surface scales the modulation with the light
    np.testing.assert_allclose(script.modulation(textured), 1.7 * amplitude.mean(axis=0), rtol=1e-6)
