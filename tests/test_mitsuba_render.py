"""The Mitsuba benchmark's scene (benchmarks/mitsuba_render.py): its meshes are closed and face outward (Mitsuba's
interior medium is the side the normals point away from), and its grey extinction keeps each colour's measured
absorption. (Mitsuba itself is not installed by the suite.)"""

from pathlib import Path

import numpy as np
import pytest
from benchmark_script import load_benchmark

mr = load_benchmark("mitsuba_render")


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    lines = path.read_text().splitlines()
    v = np.array([[float(t) for t in ln.split()[1:]] for ln in lines if ln.startswith("v ")])
    f = np.array([[int(t) - 1 for t in ln.split()[1:]] for ln in lines if ln.startswith("f ")])
    return v, f


@pytest.mark.parametrize(("radii", "lumps"), [((58.0, 36.0, 40.0), 0), ((45.0, 45.0, 45.0), 4)])
def test_meshes_are_closed_and_face_outward(tmp_path, radii, lumps):
    path = tmp_path / "m.obj"
    mr.sphere_obj(path, radii, lumps, seed=3)
    v, f = _read_obj(path)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    directed = {tuple(e) for e in edges.tolist()}
    assert len(directed) == len(edges)  # no directed edge twice: consistently oriented
    assert all((b, a) in directed for a, b in directed)  # every edge has its twin: closed
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6  # > 0 when the normals point outward
    if lumps == 0:
        assert volume == pytest.approx(4 / 3 * np.pi * np.prod(radii), rel=0.01)
    else:
        assert volume > 0.5 * 4 / 3 * np.pi * np.prod(radii)


@pytest.mark.parametrize("name", sorted(mr.MEDIA))
def test_grey_extinction_keeps_each_channels_measured_absorption(name):
    sigma_s, sigma_a = (np.asarray(v) for v in mr.MEDIA[name])
    sigma_t, albedo = mr.medium_coefficients(name, 1.5, 0.5)
    assert sigma_t == pytest.approx(1.5 * max(np.mean(sigma_s / 0.5 + sigma_a), 1.02 * sigma_a.max()))
    assert np.allclose(sigma_t * (1 - np.asarray(albedo)), 1.5 * sigma_a)
    assert all(0 < a < 1 for a in albedo)


def test_converged_references_need_the_test_render_they_converge(tmp_path):
    """The converged references take the object, medium and exposure of an earlier --test render; without its
    record, or from a --train one (no reference patterns), the script says so before building any scene."""
    import argparse
    import json

    args = argparse.Namespace(out=tmp_path, name="egg", spp=4, groups=3)
    with pytest.raises(SystemExit, match="no record of a --test render of egg"):
        mr.converged_references(None, args, None)
    (tmp_path / "egg.json").write_text(json.dumps({"test": False, "train": True}))
    with pytest.raises(SystemExit, match="not rendered with --test"):
        mr.converged_references(None, args, None)


@pytest.mark.parametrize("extra", [["--test", "--groups", "2"], ["--converged", "--groups", "1"]])
def test_groups_below_three_are_refused_before_any_render(monkeypatch, tmp_path, extra):
    """A trimmed mean drops each pixel's highest and lowest render, so it needs 3 (one render, the default for the
    capture plan, needs none)."""
    monkeypatch.setattr("sys.argv", ["mitsuba_render.py", str(tmp_path), "egg", *extra])
    with pytest.raises(SystemExit, match="--groups must be at least 3"):
        mr.main()


def test_the_trimmed_mean_leaves_out_one_firefly():
    renders = [np.full((2, 2, 3), 0.1, np.float32) for _ in range(4)]
    renders[2][0, 0] = 19.0  # a firefly in one render
    out = mr.trimmed(renders)
    assert np.allclose(out, 0.1)
    assert np.allclose(mr.trimmed(renders[:2]), np.mean(renders[:2], axis=0))  # fewer than 3: the plain mean


def test_converged_references_outsample_the_captures_by_default(capsys):
    """--converged without --spp rendered 8 x 64 spp whatever the captures had: below a 1,024-spp test render, whose
    own Monte-Carlo error then outweighed the truth's. By default it now takes 4 x the captures' samples."""
    assert mr.converged_spp({"spp": 1024}, 8, None) == 512
    assert mr.converged_spp({"spp": 64, "groups": 5}, 8, None) == 160
    assert mr.converged_spp({"spp": 32}, 8, None) == 64  # at least 64 per group
    assert mr.converged_spp({"spp": 1024}, 8, 64) == 64 and "less than twice the 1024 spp" in capsys.readouterr().out
    assert mr.converged_spp({"spp": 64}, 8, 128) == 128 and capsys.readouterr().out == ""


def test_a_coat_is_a_medium_of_its_own():
    """A layered object's coat is Jensen et al.'s medium scaled as asked (isotropic), beside the core's."""
    coat = mr.medium_dict("wholemilk", 2.0, 0.0)
    sigma_t, albedo = mr.medium_coefficients("wholemilk", 2.0, 0.0)
    assert coat["sigma_t"] == pytest.approx(sigma_t) and coat["albedo"]["value"] == albedo
    assert coat["phase"] == {"type": "isotropic"}
    assert mr.medium_dict("apple", 1.0, 0.5)["phase"] == {"type": "hg", "g": 0.5}


@pytest.mark.parametrize("extra", [["--coat-mm", "0"], ["--coat-mm", "30"], ["--coat-scale", "-1"]])
def test_a_coat_thinner_than_nothing_or_past_the_core_is_refused(monkeypatch, tmp_path, extra):
    monkeypatch.setattr("sys.argv", ["mitsuba_render.py", str(tmp_path), "egg", "--test", "--coat", "marble", *extra])
    with pytest.raises(SystemExit, match="--coat-mm in"):
        mr.main()
    assert not (tmp_path / "egg").exists()
