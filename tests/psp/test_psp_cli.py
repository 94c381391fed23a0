"""`sss patterns`, `sss decode` and `sss bench psp --quick` end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from sss_process import run_sss
from typer.testing import CliRunner

runner = CliRunner()


def _app():
    from sssphase_cli.main import app  # the installed CLI (cli/ folder), imported like the entry point does

    return app


def _run(*args: str):
    result = runner.invoke(_app(), list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result


def test_patterns_writes_plan_pngs(tmp_path):
    _run("patterns", "--projector", "64x48", "--out", str(tmp_path), "--footprints", "--dot-spacing", "4",
         "--reference", "checkerboard")
    plan = json.loads((tmp_path / "plan.json").read_text())
    keys = [f["key"] for f in plan["frames"]]
    assert sum(k.startswith("dots/") for k in keys) == 16
    assert "ref/checkerboard" in keys and "black" in keys
    for key in keys:
        img = np.asarray(Image.open(tmp_path / f"{key}.png"))
        assert img.dtype == np.uint8 and img.shape == (48, 64)
    lit = sum(np.asarray(Image.open(tmp_path / f"dots/{sx}_{sy}.png")) // 255 for sx in range(4) for sy in range(4))
    assert (lit == 1).all()


def test_patterns_without_footprints_has_no_dot_grids_but_the_white_and_black_an_import_needs(tmp_path):
    """A lab that captured exactly what `sss patterns` wrote was refused by `sss import` (no white, no black)."""
    _run("patterns", "--projector", "64x48", "--out", str(tmp_path))
    assert not (tmp_path / "dots").exists()
    frames = json.loads((tmp_path / "plan.json").read_text())["frames"]
    assert {f["kind"] for f in frames} == {"psp", "white", "black"}
    assert (tmp_path / "white.png").is_file() and (tmp_path / "black.png").is_file()


def test_decode_folder_of_captures(tmp_path):
    """Patterns -> 'captures' (camera = projector, gamma applied, 16-bit PNG) -> correspondence maps."""
    pat_dir, cap_dir, out_dir = tmp_path / "patterns", tmp_path / "captures", tmp_path / "decoded"
    _run("patterns", "--projector", "80x60", "--out", str(pat_dir))
    plan = json.loads((pat_dir / "plan.json").read_text())
    cap_dir.mkdir()
    (cap_dir / "plan.json").write_text(json.dumps(plan))
    for frame in plan["frames"]:
        value = np.asarray(Image.open(pat_dir / f"{frame['key']}.png")).astype(np.float64) / 255
        emitted = 0.05 + 0.8 * value ** plan["gamma"]
        name = frame["key"].replace("/", "__")
        Image.fromarray(np.round(emitted * 65535).astype(np.uint16)).save(cap_dir / f"{name}.png")
    _run("decode", str(cap_dir), "--out", str(out_dir))
    xp, yp, mask = (np.load(out_dir / f"{n}.npy") for n in ("xp", "yp", "mask"))
    yy, xx = np.mgrid[:60, :80]
    assert mask.all()
    assert np.abs(xp - xx).max() < 0.15 and np.abs(yp - yy).max() < 0.15  # 8-bit pattern quantisation
    for png in ("phase_x", "phase_y", "xp", "yp", "mask", "reason", "modulation"):
        assert (out_dir / f"{png}.png").is_file()
    assert json.loads((out_dir / "decode.json").read_text())["coverage"]["VALID"] == 80 * 60
    _run("decode", str(cap_dir), "--out", str(out_dir))  # its own folder: decoded again in place
    # a folder of the user's that holds these names is not written to, and a symlink is not written through
    from sssphase_core.errors import InputError

    mine, target = tmp_path / "mine", tmp_path / "target.npy"
    mine.mkdir()
    (mine / "mask.png").write_bytes(b"my mask")
    target.write_bytes(b"keep")
    (mine / "xp.npy").symlink_to(target)
    with pytest.raises(InputError, match=r"--out .*mine holds xp.npy, mask.png, which sss decode did not write"):
        runner.invoke(_app(), ["decode", str(cap_dir), "--out", str(mine)], catch_exceptions=False)
    assert (mine / "mask.png").read_bytes() == b"my mask" and target.read_bytes() == b"keep"
    assert sorted(p.name for p in mine.iterdir()) == ["mask.png", "xp.npy"]
    (out_dir / "xp.npy").unlink()
    (out_dir / "xp.npy").symlink_to(target)  # in a decoded folder too
    with pytest.raises(InputError, match="which sss decode did not write"):
        runner.invoke(_app(), ["decode", str(cap_dir), "--out", str(out_dir)], catch_exceptions=False)
    assert target.read_bytes() == b"keep"
    # one frame re-saved at 8 bits among 16-bit ones: another pipeline's frame, decoded in silence; refused as
    odd = sorted(cap_dir.glob("psp__y__*__s1.png"))[0]  # `sss import` refuses it
    Image.fromarray((np.asarray(Image.open(odd)) >> 8).astype(np.uint8)).save(odd)
    with pytest.raises(InputError, match=rf"holds 16-bit codes but .*{odd.name} holds 8-bit ones"):
        runner.invoke(_app(), ["decode", str(cap_dir), "--out", str(tmp_path / "mixed")], catch_exceptions=False)
    assert not (tmp_path / "mixed").exists()


def _captures_of(pat_dir, scale: float):
    """Every PSP pattern of a `sss patterns` folder as the linear light a camera would record."""
    plan = json.loads((pat_dir / "plan.json").read_text())
    for frame in plan["frames"]:
        value = np.asarray(Image.open(pat_dir / f"{frame['key']}.png")).astype(np.float32) / 255
        yield frame["key"], scale * (0.05 + 0.8 * value ** plan["gamma"])


def test_decode_reads_exr_in_the_patterns_folder_layout_and_never_calls_float_light_saturated(tmp_path):
    """Frames as `sss patterns` lays them out (``psp/x/p20/s0``), written as EXR with values above 1:
    EXR has no top code, so bright light decodes; the same light in 8-bit PNGs clips and is refused."""
    from sssphase_core.store import exr

    assert exr.available(), "OpenEXR is a dependency of sssphase"
    pat_dir = tmp_path / "patterns"
    _run("patterns", "--projector", "80x60", "--out", str(pat_dir))
    exr_dir, png_dir = tmp_path / "exr", tmp_path / "png"
    for key, light in _captures_of(pat_dir, scale=3.0):
        for folder in (exr_dir, png_dir):
            (folder / key).parent.mkdir(parents=True, exist_ok=True)
        exr.write_exr(exr_dir / f"{key}.exr", np.repeat(light[..., None], 3, -1))
        Image.fromarray(np.round(np.clip(light, 0, 1) * 255).astype(np.uint8)).save(png_dir / f"{key}.png")
    for folder in (exr_dir, png_dir):
        (folder / "plan.json").write_text((pat_dir / "plan.json").read_text())
    _run("decode", str(exr_dir), "--out", str(tmp_path / "out_exr"))
    res = runner.invoke(_app(), ["decode", str(png_dir), "--out", str(tmp_path / "out_png")])
    assert "no camera pixel decoded (100% saturated)" in str(res.exception), res.output
    xp, mask = (np.load(tmp_path / "out_exr" / f"{n}.npy") for n in ("xp", "mask"))
    assert mask.all() and np.abs(xp - np.mgrid[:60, :80][1]).max() < 0.15
    coverage = json.loads((tmp_path / "out_png" / "decode.json").read_text())["coverage"]
    assert coverage["SATURATED"] > 0.3 * 80 * 60  # 3x over-exposed 8-bit frames clip at their top code


def test_decode_reports_missing_frames_as_one_line(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "plan.json").write_text(json.dumps({"projector": [32, 24], "gamma": 2.2,
                                                  "psp": {"period": 8, "n_shifts": 4, "unwrap_periods": [40]}}))
    from sssphase_core.errors import DataError

    with pytest.raises(DataError, match="psp/x/p40/s0"):
        runner.invoke(_app(), ["decode", str(frames), "--out", str(tmp_path / "o")], catch_exceptions=False)


@pytest.mark.parametrize("inside", [".", "decoded"])
def test_decode_refuses_to_write_among_its_frames(tmp_path, inside):
    """Its maps (xp.npy, mask.npy, ...) written into the frames folder were read back as frames: a later
    `sss import` of the folder failed on them ("'mask' is no frame name")."""
    from sssphase_core.errors import InputError

    frames = tmp_path / "frames"
    _run("patterns", "--projector", "32x24", "--out", str(frames))
    before = sorted(p.relative_to(frames) for p in frames.rglob("*"))
    with pytest.raises(InputError, match="would write among the frames of"):
        runner.invoke(_app(), ["decode", str(frames), "--out", str(frames / inside)], catch_exceptions=False)
    assert sorted(p.relative_to(frames) for p in frames.rglob("*")) == before


@pytest.mark.slow
def test_bench_psp_quick_smoke(tmp_path):
    out, md = tmp_path / "psp.json", tmp_path / "psp.md"
    _run("bench", "psp", "--quick", "--out", str(out), "--md", str(md))
    data = json.loads(out.read_text())
    speed = data["speed"]
    assert speed["ours_ms_per_phase_map"] > 0 and speed["opencv_psp_3step_ms"] > 0
    assert [r["noise"] for r in data["synthetic"]] == [0.0, 0.01, 0.04]
    assert data["synthetic"][0]["median_px"] < 0.01  # noise-free synthetic fringes decode exactly
    assert {r["n_shifts"] for r in data["tradeoff"]} == {3, 4}
    (bias,) = data["scattering_bias"]  # quick: the soap under Burley transport only
    assert bias["transport"] == "burley" and abs(bias["corrected_bias_x"]) < abs(bias["decoded_bias_x"])
    assert "OpenCV" in md.read_text()


def test_decode_names_the_odd_frame_ignores_other_images_and_refuses_nan_thresholds(tmp_path):
    from sssphase_core.errors import DataError, InputError

    pat_dir = tmp_path / "patterns"
    _run("patterns", "--projector", "64x48", "--out", str(pat_dir))
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(tmp_path / "patterns" / "holiday.png")  # not a frame: skipped
    _run("decode", str(pat_dir), "--out", str(tmp_path / "dec"))  # a rerun into the same folder replaces its maps
    _run("decode", str(pat_dir), "--out", str(tmp_path / "dec"))
    with pytest.raises(InputError, match="--min-modulation must be a finite number"):
        runner.invoke(_app(), ["decode", str(pat_dir), "--out", str(tmp_path / "o"), "--min-modulation", "nan"],
                      catch_exceptions=False)
    odd = next((pat_dir / "psp" / "y").rglob("s2.png"))
    Image.fromarray(np.zeros((10, 12), np.uint8)).save(odd)
    with pytest.raises(DataError, match=rf"{odd.name} is 12x10, but .* is 64x48"):
        runner.invoke(_app(), ["decode", str(pat_dir), "--out", str(tmp_path / "o")], catch_exceptions=False)


@pytest.mark.parametrize(("option", "value", "expected"), [
    ("--period", "0", "--period must be a finite fringe period of at least 2 projector px, got 0.0"),
    ("--period", "nan", "--period must be a finite fringe period of at least 2 projector px, got nan"),
    ("--period", "-3", "--period must be a finite fringe period of at least 2 projector px, got -3.0"),
    ("--shifts", "100000", "--shifts must be 3 to 32, got 100000"),  # ran for minutes
    ("--gamma", "nan", "--gamma must be a number in [0.3, 5] (as a rig file's), got nan"),
    ("--projector", "3x2", "a 3x2 projector is smaller than one fringe period (4 px): PSP needs a few periods across it"),
])
def test_patterns_refuses_bad_fringe_options_in_one_line(tmp_path, option, value, expected):

    args = [option, value] if option == "--projector" else ["--projector", "64x48", option, value]
    res = run_sss(["patterns", "--out", str(tmp_path / "p"), *args], timeout=60)
    out = res.stdout + res.stderr
    assert res.returncode == 2 and "Traceback" not in out and "internal error" not in out, out
    assert out.strip().splitlines() == [f"error: {expected}"], out
    assert not (tmp_path / "p").exists()


def test_decode_with_bayer_drops_the_silhouette_pixels_only_demosaicing_lit(tmp_path):
    """A bright disk on black seen through a Bayer camera (Malvar): `sss decode` takes the background pixels
    beside it as surface; with --bayer it drops them (reason demosaic bleed) and keeps the disk."""
    from sssphase_core.processing.isp import through_camera

    pat_dir, cap_dir = tmp_path / "patterns", tmp_path / "captures"
    _run("patterns", "--projector", "80x60", "--out", str(pat_dir))
    cap_dir.mkdir()
    (cap_dir / "plan.json").write_text((pat_dir / "plan.json").read_text())
    yy, xx = np.mgrid[:60, :80]
    disk = np.hypot(yy - 29.5, xx - 40.2) < 18
    for key, light in _captures_of(pat_dir, 1.0):
        seen = np.where(disk, light, 0.0)[..., None] * np.float32([0.8, 0.45, 0.3])
        np.save(cap_dir / (key.replace("/", "__") + ".npy"), through_camera(seen.astype(np.float32)))
    masks = {}
    for name, extra in (("plain", []), ("bayer", ["--bayer", "rggb"])):
        _run("decode", str(cap_dir), "--out", str(tmp_path / name), *extra)
        masks[name] = np.load(tmp_path / name / "mask.npy")
    assert (masks["plain"] & ~disk).sum() > 20
    assert (masks["bayer"] & ~disk).sum() <= 0.1 * (masks["plain"] & ~disk).sum()
    assert (masks["bayer"] & disk).sum() >= (masks["plain"] & disk).sum() - 2
    coverage = json.loads((tmp_path / "bayer" / "decode.json").read_text())["coverage"]
    assert coverage["DEMOSAIC_BLEED"] == (masks["plain"] & ~masks["bayer"]).sum()
    res = runner.invoke(_app(), ["decode", str(cap_dir), "--out", str(tmp_path / "x"), "--bayer", "RGBG"])
    assert res.exit_code != 0 and "unknown Bayer layout 'RGBG'" in str(res.exception)


@pytest.mark.parametrize(("text", "expected"), [
    ("{not json", "is not valid JSON (Expecting property name"),
    ("[" * 100000 + "]" * 100000, "nests deeper than 32 levels"),
    ("[]", "plan is not a table"),
    ('{"psp": {}}', "it names no projector size"),
    ('{"projector": [64, 48, 3]}', "plan.projector must be [width, height]"),
    ('{"projector": [-64, 48]}', "plan.projector must be [width, height]"),
    ('{"projector": [80, 60], "psp": {"period": 11, "n_shifts": 4}}', "its psp configuration is incomplete"),
    # a billion shifts built a billion frame names before anything was refused (hours, or out of memory)
    ('{"projector": [80, 60], "psp": {"period": 11, "n_shifts": 1000000000, "unwrap_periods": [88]}}',
     "plan.json: phase shifting takes at most 32 shifts, got 1000000000"),
    ('{"projector": [80, 60], "psp": {"period": 11, "n_shifts": 4.5, "unwrap_periods": [88]}}',
     "plan.json: the number of phase shifts must be an integer, got 4.5"),
    (json.dumps({"projector": [80, 60], "psp": {"period": 11, "n_shifts": 4, "unwrap_periods": list(range(12, 112, 5))}}),
     "plan.json: at most 16 unwrapping periods, got 20"),
])
def test_decode_names_a_broken_plan_json_in_one_line(tmp_path, text, expected):
    """A hand-edited plan.json was an internal error (KeyError, JSONDecodeError ...) or decoded nothing."""
    from sssphase_core.errors import InputError

    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "plan.json").write_text(text)
    res = runner.invoke(_app(), ["decode", str(frames), "--out", str(tmp_path / "out")])
    assert isinstance(res.exception, InputError) and expected in str(res.exception), res.output
    assert str(frames / "plan.json") in str(res.exception)


def test_decode_refuses_frames_smaller_than_a_camera_frame_as_import_does(tmp_path):
    """`sss decode` took 1 x 1 frames ("decoded 0 of 1") where `sss import` refuses them."""
    from sssphase_core.errors import InputError

    pat_dir = tmp_path / "patterns"
    _run("patterns", "--projector", "80x60", "--out", str(pat_dir))
    (tmp_path / "cap").mkdir()
    for key, light in _captures_of(pat_dir, 1.0):
        np.save(tmp_path / "cap" / (key.replace("/", "__") + ".npy"), light[:1, :1])
    res = runner.invoke(_app(), ["decode", str(tmp_path / "cap"), "--projector", "80x60", "--out", str(tmp_path / "o")])
    assert isinstance(res.exception, InputError) and "is 1x1: smaller than a camera frame (at least 16 px" in str(res.exception)


def test_decode_without_a_plan_reads_the_shift_count_from_the_names_and_scales_float_frames(tmp_path):
    """5-step frames in a renderer's units (1e-3 of the camera's), no plan.json: decoded as 4-step they gave
    389 of 19,200 pixels at 0.83 px, and at 1e-3 nothing (all "shadow"), exit code 0 both times."""
    pat_dir, cap_dir, out_dir = tmp_path / "patterns", tmp_path / "captures", tmp_path / "decoded"
    _run("patterns", "--projector", "80x60", "--out", str(pat_dir), "--shifts", "5")
    cap_dir.mkdir()
    for key, light in _captures_of(pat_dir, scale=1e-3):
        np.save(cap_dir / (key.replace("/", "__") + ".npy"), light.astype(np.float32))
    result = _run("decode", str(cap_dir), "--out", str(out_dir), "--projector", "80x60")
    assert "scaled to 1" in result.output
    xp, yp, mask = (np.load(out_dir / f"{n}.npy") for n in ("xp", "yp", "mask"))
    yy, xx = np.mgrid[:60, :80]
    assert mask.all() and np.abs(xp - xx).max() < 0.15 and np.abs(yp - yy).max() < 0.15
    assert json.loads((out_dir / "decode.json").read_text())["psp"]["n_shifts"] == 5


def test_decode_where_nothing_decodes_keeps_its_figures_and_says_why(tmp_path):
    """Frames with no fringe left (all at one level) decoded "0 of N pixels" with exit code 0, where
    `sss import` refuses the same frames; a threshold above every modulation likewise."""
    pat_dir = tmp_path / "patterns"
    _run("patterns", "--projector", "80x60", "--out", str(pat_dir))
    for name in ("flat", "lit"):
        (tmp_path / name).mkdir()
    for key, light in _captures_of(pat_dir, 1.0):
        np.save(tmp_path / "flat" / (key.replace("/", "__") + ".npy"), np.full_like(light, 0.5))
        np.save(tmp_path / "lit" / (key.replace("/", "__") + ".npy"), light)
    for folder, extra in ((tmp_path / "flat", []), (tmp_path / "lit", ["--min-modulation", "1e9"])):
        out = tmp_path / f"out_{folder.name}"
        done = run_sss(["decode", str(folder), "--projector", "80x60", "--out", str(out), *extra])
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stdout + done.stderr
        line = done.stderr.strip().splitlines()[-1]
        assert "no camera pixel decoded (100% low modulation)" in line and f"figures in {out}" in line, line
        assert (out / "reason.png").is_file() and (out / "decode.json").is_file()
