"""The learning commands end to end on the simulated rig (tiny sizes)."""

from __future__ import annotations

import importlib
import json

import pytest
from sss_process import run_sss
from typer.testing import CliRunner

app = importlib.import_module("sssphase_cli.main").app  # the installed `sss` app (cli/ folder)
runner = CliRunner()


def invoke(*args: str):
    result = runner.invoke(app, list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result


def test_commands_are_registered():
    for group, cmd in [("train", "pretrain"), ("train", "decoder"), ("eval", "knn"), ("eval", "footprints"), ("viz", "pca")]:
        assert runner.invoke(app, [group, cmd, "--help"]).exit_code == 0


def test_missing_checkpoint_is_a_one_line_error(tmp_path):
    from sssphase_core.errors import DataError

    with pytest.raises(DataError, match="no checkpoint"):
        runner.invoke(app, ["viz", "pca", "--checkpoint", str(tmp_path / "none.pt")], catch_exceptions=False)


@pytest.mark.parametrize("args", [[], ["--encoder", "runs/pre", "--end-to-end"]])
def test_decoder_needs_exactly_one_of_encoder_or_end_to_end(args, tmp_path):
    from sssphase_core.errors import InputError

    with pytest.raises(InputError, match="--encoder PATH .* or --end-to-end"):
        runner.invoke(app, ["train", "decoder", *args, "--out", str(tmp_path / "dec")], catch_exceptions=False)
    assert not (tmp_path / "dec").exists()


def _tensorboard_scalars(logdir) -> dict[str, list[float]]:
    """Scalars of a run's event files, read by TensorBoard's own reader."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(logdir))
    acc.Reload()
    return {tag: [e.value for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_a_config_of_another_command_is_refused(tmp_path):
    from sssphase_core.errors import InputError

    (tmp_path / "config.toml").write_text('command = "train decoder"\n[options]\nepochs = 2\n')
    with pytest.raises(InputError, match="configuration of `sss train decoder`, not of `sss train pretrain`"):
        runner.invoke(app, ["train", "pretrain", "--config", str(tmp_path)], catch_exceptions=False)
    (tmp_path / "config.toml").write_text('command = "train pretrain"\n[options]\nepochs = 2\nepoch = 3\n')
    with pytest.raises(InputError, match="unknown option.* epoch for"):
        runner.invoke(app, ["train", "pretrain", "--config", str(tmp_path / "config.toml")], catch_exceptions=False)


@pytest.mark.slow
def test_train_eval_viz_on_the_simulator(tmp_path):
    pytest.importorskip("sssphase_core.sim")
    cache = str(tmp_path / "cache")
    common = ["--objects", "star,shovel", "--views", "0,1", "--pixels-per-view", "64", "--cache", cache]
    pre, dec = tmp_path / "pre", tmp_path / "dec"
    invoke("train", "pretrain", "--out", str(pre), "--epochs", "1", "--batch-size", "32", *common)
    assert (pre / "last.pt").exists() and (pre / "metrics.jsonl").exists() and (pre / "knn_vs_time.png").exists()
    tb = _tensorboard_scalars(pre / "tb")
    assert {"step/loss", "step/lr", "epoch/knn_acc", "epoch/eff_rank"} <= tb.keys()
    first = json.loads((pre / "metrics.jsonl").read_text().splitlines()[0])
    assert tb["epoch/knn_acc"] == pytest.approx([first["knn_acc"]]) and len(tb["step/loss"]) == first["step"]
    assert (pre / "metrics.csv").read_text().splitlines()[0].startswith("epoch,step,loss,lr")
    again = tmp_path / "pre_again"  # the saved configuration repeats the run; a flag overrides it
    invoke("train", "pretrain", "--config", str(pre / "config.toml"), "--out", str(again))
    repeat = json.loads((again / "metrics.jsonl").read_text().splitlines()[0])
    for name in ("loss", "lr", "knn_acc", "eff_rank", "step"):
        assert repeat[name] == pytest.approx(first[name], rel=1e-6, abs=1e-9), name
    elsewhere = tmp_path / "elsewhere"  # `--config RUN` from another folder continues that run, not a new one there
    elsewhere.mkdir()
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(elsewhere)
        resumed = invoke("train", "pretrain", "--config", "../pre", "--epochs", "2")
    assert [json.loads(r)["epoch"] for r in (pre / "metrics.jsonl").read_text().splitlines()] == [1, 2]
    assert f"resuming from {pre / 'last.pt'}: 1 epoch done, 0 steps into the next" in " ".join(resumed.output.split())
    assert not list(elsewhere.iterdir())
    invoke("eval", "knn", "--checkpoint", f"psp={pre}", "--k", "5,1", "--seed", "0", "--out", str(tmp_path / "knn.json"), *common)
    knn = json.loads((tmp_path / "knn.json").read_text())
    psp = knn["results"]["psp"]
    assert knn["k"] == 5 and psp["k"] == 5 and 0 <= psp["overall"] <= 1 and psp["overall_by_k"]["5"] == psp["overall"]
    assert set(psp["overall_by_k"]) == {"5", "1"}
    assert "| star |" in (tmp_path / "knn.md").read_text() and "against k" in (tmp_path / "knn.md").read_text()
    import torch

    from sssphase_core.learning.training import save_checkpoint

    unfinished = torch.load(pre / "last.pt", weights_only=False)  # (as a pretraining stopped after 2 of 3 epochs)
    unfinished["config"]["epochs"] = 3
    save_checkpoint(tmp_path / "unfinished" / "last.pt", unfinished)
    fitted = invoke("train", "decoder", "--encoder", str(tmp_path / "unfinished"), "--out", str(dec), "--epochs", "1",
                    "--batch-size", "32", "--views", "0", "--val-views", "1", "--objects", "star", "--pixels-per-view",
                    "64", "--cache", cache)
    assert "is from an unfinished pretraining (2 of its 3 epochs done)" in " ".join(fitted.output.split())
    finished = torch.load(pre / "last.pt", weights_only=False)  # a finished run whose best kNN came at epoch 1 of 2:
    save_checkpoint(tmp_path / "finished" / "last.pt", finished)  # its best.pt was taken for an unfinished run's
    finished["loop"]["epoch"] = 1
    save_checkpoint(tmp_path / "finished" / "best.pt", finished)
    quiet = invoke("train", "decoder", "--encoder", str(tmp_path / "finished"), "--out", str(tmp_path / "dec2"),
                   "--epochs", "1", "--batch-size", "32", "--views", "0", "--val-views", "", "--objects", "star",
                   "--pixels-per-view", "64", "--cache", cache)
    assert "unfinished" not in quiet.output, quiet.output
    assert (dec / "error_vs_time.png").exists()
    assert {"step/loss", "step/lr", "epoch/val_loss", "epoch/val_psnr"} <= _tensorboard_scalars(dec / "tb").keys()
    e2e = tmp_path / "e2e"  # the supervised U-Net baseline: no SSL, encoder trained with the decoder
    invoke("train", "decoder", "--end-to-end", "--out", str(e2e), "--epochs", "1", "--batch-size", "32",
           "--views", "0", "--val-views", "", "--objects", "star", "--pixels-per-view", "64", "--cache", cache)
    invoke("eval", "footprints", "--checkpoint", str(dec), "--compare", f"unet={e2e}", "--objects", "soap", "--views", "0",
           "--pixels-per-view", "16", "--plots", str(tmp_path / "plots"), "--out", str(tmp_path / "fp.json"), "--cache", cache,
           "--precision", "fp32")
    assert json.loads((tmp_path / "fp.json").read_text())["precision"] == "fp32"
    assert "the decoders inferred in fp32" in (tmp_path / "fp.md").read_text()
    fp = json.loads((tmp_path / "fp.json").read_text())["results"]["soap"]
    assert {"torch", "unet", "analytic"} == fp.keys() and min(r["psnr"] for r in fp.values()) > 0
    assert "unet PSNR" in (tmp_path / "fp.md").read_text()
    assert (tmp_path / "plots" / "soap_torch.png").exists()
    invoke("viz", "pca", "--checkpoint", str(pre), "--objects", "star", "--stride", "8", "--out", str(tmp_path / "pca.png"),
           "--cache", cache)
    from PIL import Image

    img = Image.open(tmp_path / "pca.png")
    assert img.size[0] >= 400  # a 32x24 map (stride 8) enlarged into a titled figure


def test_a_run_folder_of_another_kind_or_a_session_is_never_overwritten(tmp_path):
    """`--no-resume` starts over in a folder of the same kind only: a pretraining run (or a session) given as
    a decoder's --out is refused before anything is read or written, its files untouched."""
    from sssphase_core.errors import DataError, InputError
    from sssphase_core.learning.training import save_checkpoint

    run = tmp_path / "pre"
    save_checkpoint(run / "last.pt", {"kind": "pretrain", "preset": {}, "encoder": {}})
    (run / "metrics.jsonl").write_text('{"epoch": 1}\n')
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    for resume in ("--resume", "--no-resume"):
        with pytest.raises(DataError, match="holds a pretrain run, not decoder"):
            runner.invoke(app, ["train", "decoder", "--end-to-end", "--out", str(run), resume, "--epochs", "1"],
                          catch_exceptions=False)
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    session = tmp_path / "session"
    session.mkdir()
    (session / "manifest.json").write_text("{}")
    with pytest.raises(InputError, match="would write into the session"):
        runner.invoke(app, ["train", "pretrain", "--out", str(session), "--no-resume"], catch_exceptions=False)
    assert sorted(p.name for p in session.iterdir()) == ["manifest.json"]


def test_a_folder_of_the_user_s_files_is_no_run_folder(tmp_path):
    """`--out ~/notes` (or a received config.toml's out) deleted the tb/ folder and best.pt it held, and replaced
    metrics.csv: a folder without a run of this kind keeps its files; a run stopped before its first checkpoint
    (its config.toml says what it was) starts over."""
    from sssphase_core.errors import DataError
    from sssphase_core.learning.training import check_run_folder, save_checkpoint

    notes = tmp_path / "notes"
    (notes / "tb").mkdir(parents=True)
    (notes / "tb" / "events.1").write_text("logs")
    (notes / "best.pt").write_text("mine")
    before = {p.relative_to(notes): p.read_bytes() for p in notes.rglob("*") if p.is_file()}
    with pytest.raises(DataError, match=r"notes holds best.pt, tb but no decoder run of sssphase .*give a new or empty"):
        runner.invoke(app, ["train", "decoder", "--end-to-end", "--out", str(notes), "--no-resume"], catch_exceptions=False)
    assert {p.relative_to(notes): p.read_bytes() for p in notes.rglob("*") if p.is_file()} == before
    (notes / "config.toml").write_text('command = "train pretrain"\n[options]\n')  # another kind's config: still refused
    with pytest.raises(DataError, match="no decoder run of sssphase"):
        check_run_folder(notes, "decoder")
    assert check_run_folder(notes, "pretrain") is None  # a pretraining run stopped before its first checkpoint
    (notes / "config.toml").unlink()
    save_checkpoint(notes / "best.pt", {"kind": "decoder", "preset": {}, "encoder": {}})  # a decoder run's best.pt: its own
    assert check_run_folder(notes, "decoder") is None


@pytest.mark.parametrize("text", ["[tool.mine]\nkeep = 1\n", 'command = "train pretrain"\n[options]\n', "not toml ["])
def test_a_config_toml_that_is_not_this_commands_run_options_is_never_replaced(tmp_path, text):
    """`--out ~/project` replaced the project's own config.toml (it is not among the run files checked above)."""
    from sssphase_core.errors import InputError

    project = tmp_path / "project"
    project.mkdir()
    (project / "config.toml").write_text(text)
    with pytest.raises(InputError, match="is not the options file of a `sss train decoder` run: refusing to replace"):
        runner.invoke(app, ["train", "decoder", "--end-to-end", "--out", str(project), "--no-resume"],
                      catch_exceptions=False)
    assert (project / "config.toml").read_text() == text and sorted(p.name for p in project.iterdir()) == ["config.toml"]


def test_a_run_resumed_with_other_data_or_model_options_is_refused(tmp_path):
    """config.toml says what the run is: resuming it with an option that shaped it changed (here the pixels
    per view) is refused before any data is read; the epochs may grow."""
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import save_checkpoint

    run = tmp_path / "dec"
    save_checkpoint(run / "last.pt", {"kind": "decoder", "preset": {}, "encoder": {}})
    (run / "config.toml").write_text('command = "train decoder"\n[options]\nend_to_end = true\npixels_per_view = 50\n'
                                     'epochs = 1\n')
    saved = (run / "config.toml").read_text()
    with pytest.raises(InputError, match="made with --pixels-per-view 50, not 60.*--no-resume"):
        runner.invoke(app, ["train", "decoder", "--config", str(run), "--out", str(run), "--pixels-per-view", "60"],
                      catch_exceptions=False)
    assert (run / "config.toml").read_text() == saved


@pytest.mark.parametrize(("args", "expected"), [
    (["--device", "tpu"], "unknown device 'tpu'"),  # it was saved in config.toml, then refused
    (["--epochs", "2"], r"has trained 3 epochs: --epochs 2 would train none; pass --epochs above 3"),  # trained none,
])  # and config.toml said 2
def test_a_refused_run_leaves_the_finished_run_s_config_as_it_was(args, expected, tmp_path):
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import save_checkpoint

    run = tmp_path / "dec"
    save_checkpoint(run / "last.pt", {"kind": "decoder", "preset": {}, "encoder": {}, "loop": {"epoch": 3}})
    (run / "config.toml").write_text('command = "train decoder"\n[options]\nend_to_end = true\npixels_per_view = 50\n'
                                     'epochs = 3\n')
    saved = (run / "config.toml").read_text()
    with pytest.raises(InputError, match=expected):
        runner.invoke(app, ["train", "decoder", "--config", str(run), "--out", str(run), *args], catch_exceptions=False)
    assert (run / "config.toml").read_text() == saved


def test_a_copied_run_continued_with_its_config_stays_in_the_copy(tmp_path):
    """A run folder copied, then continued with `--config COPY`, trained into the original: its config.toml
    records the original's --out. It now continues in the copy, with a warning; --out still chooses."""
    from sssphase_core.learning.training import save_checkpoint

    original, copy = tmp_path / "dec", tmp_path / "copy"
    save_checkpoint(original / "last.pt", {"kind": "decoder", "preset": {}, "encoder": {}})
    (original / "config.toml").write_text(f'command = "train decoder"\n[options]\nend_to_end = true\n'
                                          f'pixels_per_view = 50\nepochs = 1\nout = "{original}"\n')
    import shutil

    shutil.copytree(original, copy)
    before = {p.name: p.read_bytes() for p in original.iterdir()}
    with pytest.warns(UserWarning, match=f"--config {copy}: this run was recorded at {original}; it continues here, in {copy}"):
        runner.invoke(app, ["train", "decoder", "--config", str(copy), "--pixels-per-view", "60"])
    assert {p.name: p.read_bytes() for p in original.iterdir()} == before


@pytest.mark.parametrize("config", [None, "garbage [[[", 'command = "train decoder"\noptions = 5\n'])
def test_a_run_whose_options_are_unknown_is_not_resumed_with_new_ones(config, tmp_path):
    """A checkpoint without a readable config.toml (the demo's runs, a damaged file) resumed with any options:
    epochs 1-2 on one data set, epoch 3 on another, and config.toml then described only the last."""
    from sssphase_core.errors import InputError
    from sssphase_core.learning.training import save_checkpoint

    run = tmp_path / "dec"
    save_checkpoint(run / "last.pt", {"kind": "decoder", "preset": {}, "encoder": {}})
    if config is not None:
        (run / "config.toml").write_text(config)
    with pytest.raises(InputError, match="no readable config.toml.*--no-resume"):
        runner.invoke(app, ["train", "decoder", "--end-to-end", "--out", str(run), "--epochs", "3"], catch_exceptions=False)
    assert (run / "config.toml").exists() == (config is not None)


def test_outputs_inside_a_session_or_among_sessions_are_refused(tmp_path):
    from sssphase_core.errors import InputError

    session = tmp_path / "sessions" / "shovel"
    (session / "view_000").mkdir(parents=True)
    (session / "manifest.json").write_text("{}")
    for out, message in ((session / "view_000", "inside the session|into the session"), (tmp_path / "sessions", "holds sessions")):
        with pytest.raises(InputError, match=message):
            runner.invoke(app, ["train", "pretrain", "--out", str(out), "--no-resume"], catch_exceptions=False)
    assert sorted(p.name for p in (session / "view_000").iterdir()) == []
    with pytest.raises(InputError, match="--plots"):
        runner.invoke(app, ["eval", "footprints", "--checkpoint", str(tmp_path / "none"), "--plots", str(session / "plots")],
                      catch_exceptions=False)
    assert not (session / "plots").exists()


def test_validation_views_that_are_training_views_and_a_mistyped_check_session_are_refused_before_training(tmp_path):
    from sssphase_core.errors import InputError

    common = ["train", "decoder", "--end-to-end", "--objects", "star", "--pixels-per-view", "4", "--batch-size", "2",
              "--epochs", "1", "--cache", str(tmp_path / "cache")]
    with pytest.raises(InputError, match="star view 0 is also a training view; validation views must be held out"):
        runner.invoke(app, [*common, "--views", "0,1", "--val-views", "0", "--out", str(tmp_path / "a")], catch_exceptions=False)
    with pytest.raises(InputError, match="typo does not exist"):  # it was found after the whole training
        runner.invoke(app, [*common, "--views", "0", "--val-views", "1", "--out", str(tmp_path / "b"),
                            "--check-sessions", str(tmp_path / "typo")], catch_exceptions=False)
    assert not (tmp_path / "a" / "last.pt").exists() and not (tmp_path / "b" / "last.pt").exists()


def test_a_preset_typed_beside_an_encoder_is_refused_not_recorded(tmp_path):
    from sssphase_core.errors import InputError

    with pytest.raises(InputError, match="--preset sets the model of an --end-to-end run"):
        runner.invoke(app, ["train", "decoder", "--encoder", str(tmp_path / "pre"), "--preset", "paper", "--out",
                            str(tmp_path / "d")], catch_exceptions=False)
    assert not (tmp_path / "d").exists()


def test_an_unknown_precision_is_refused_before_the_checkpoint_is_read(tmp_path):
    from sssphase_core.errors import InputError

    with pytest.raises(InputError, match="unknown precision 'half': use auto, fp32, bf16"):
        runner.invoke(app, ["eval", "footprints", "--checkpoint", str(tmp_path / "none.pt"), "--precision", "half",
                            "--out", str(tmp_path / "o.json")], catch_exceptions=False)
    assert not (tmp_path / "o.json").exists()


@pytest.mark.parametrize("item", ["../../x=run", "/abs=run", "a/b=run", "torch=run", "norun"])
def test_compare_names_that_are_not_plain_or_new_are_refused_first(item, tmp_path):
    """--compare NAME names output files: a name with a path in it (or taken, or missing) is refused before
    any checkpoint or data is read."""
    from sssphase_core.errors import InputError

    with pytest.raises(InputError, match="--compare takes NAME=PATH with a new name"):
        runner.invoke(app, ["eval", "footprints", "--checkpoint", str(tmp_path / "none.pt"), "--compare", item,
                            "--out", str(tmp_path / "o")], catch_exceptions=False)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("args", "expected"), [
    (["train", "decoder", "--end-to-end", "--pixels-per-view", "-5"], "Invalid value for '--pixels-per-view'"),
    (["train", "pretrain", "--pixels-per-view", "0"], "Invalid value for '--pixels-per-view'"),
    (["eval", "footprints", "--checkpoint", "ck.pt", "--pixels-per-view", "-1"], "Invalid value for '--pixels-per-view'"),
    (["eval", "knn", "--checkpoint", "ck.pt", "--pixels-per-view", "0"], "Invalid value for '--pixels-per-view'"),
    (["train", "decoder", "--end-to-end", "--lr", "-1"], "error: --lr must be a finite number > 0, got -1.0"),
    (["train", "decoder", "--end-to-end", "--lr", "nan"], "error: --lr must be a finite number > 0, got nan"),
    (["train", "pretrain", "--lr", "0"], "error: --lr must be a finite number > 0, got 0.0"),
    # SimSiam's BatchNorm1d cannot normalise a batch of one ("Expected more than 1 value per channel")
    (["train", "pretrain", "--batch-size", "1", "--knn-monitor", "0"],
     "error: --batch-size must be at least 2 for pretraining, got 1: SimSiam's projector and predictor normalise"),
    # NaN/inf crashed after config.toml was written (so --config repeated the crash); -1 meant no warmup, silently
    (["train", "pretrain", "--warmup-epochs", "nan"], "error: --warmup-epochs must be a finite number >= 0, got nan"),
    (["train", "pretrain", "--warmup-epochs", "inf"], "error: --warmup-epochs must be a finite number >= 0, got inf"),
    (["train", "pretrain", "--warmup-epochs", "-1"], "error: --warmup-epochs must be a finite number >= 0, got -1.0"),
    # -1 silently meant no auxiliary head; 1 is a one-class "classification" that never learns anything
    (["train", "decoder", "--end-to-end", "--aux-classes", "-1"],
     "error: --aux-classes must be 0 (no auxiliary material head) or a number of material classes from 2 to 25"),
    (["train", "decoder", "--end-to-end", "--aux-classes", "1"], "the simulator's materials, which label the data), got 1"),
    (["train", "decoder", "--end-to-end", "--aux-classes", "1000000000000"], "got 1000000000000"),  # was: out of memory
    (["train", "pretrain", "--lr", "1e12"], "error: --lr must be at most 10, got 1e+12"),  # a silent no-op run (decoder)
    (["train", "decoder", "--end-to-end", "--lr", "11"], "error: --lr must be at most 10, got 11"),
    # a negative count silently meant "off" or "every step"; a negative seed crashed numpy's generator
    (["train", "pretrain", "--knn-monitor", "-1"], "Invalid value for '--knn-monitor'"),
    (["train", "pretrain", "--ckpt-every", "-1"], "Invalid value for '--ckpt-every'"),
    (["train", "decoder", "--end-to-end", "--ckpt-every", "-5"], "Invalid value for '--ckpt-every'"),
    (["train", "decoder", "--end-to-end", "--seed", "-1"], "Invalid value for '--seed'"),
    (["eval", "knn", "--checkpoint", "ck.pt", "--seed", "-1"], "Invalid value for '--seed'"),
    (["eval", "footprints", "--checkpoint", "ck.pt", "--seed", "99999999999999999999"], "Invalid value for '--seed'"),
    (["train", "pretrain", "--n-views", "0"], "Invalid value for '--n-views'"),
    (["eval", "footprints", "--checkpoint", "ck.pt", "--n-views", "-1"], "Invalid value for '--n-views'"),
    (["viz", "pca", "--checkpoint", "ck.pt", "--stride", "0"], "Invalid value for '--stride'"),
    (["viz", "pca", "--checkpoint", "ck.pt", "--view", "-1"], "Invalid value for '--view'"),
    (["train", "pretrain", "--epochs", "100000000000000000000"], "Invalid value for '--epochs'"),  # it started a run
])
def test_bad_sample_counts_and_learning_rates_are_refused_before_any_work(args, expected, tmp_path):

    out_args = ["--out", str(tmp_path / "run")] if args[0] == "train" else []
    res = run_sss([*args, *out_args, "--cache", str(tmp_path / "cache")], timeout=120, cwd=tmp_path)
    out = res.stdout + res.stderr
    assert res.returncode == 2 and "Traceback" not in out and "internal error" not in out, out
    assert [line for line in out.splitlines() if expected in line] == [out.strip().splitlines()[-1]], out
    assert not (tmp_path / "run").exists() and not (tmp_path / "cache").exists()


def test_a_config_is_recognised_whatever_the_program_is_called(tmp_path):
    """`python -m sssphase_cli.main train decoder --config RUN` reads RUN's config like `sss` does (the command
    name was taken from the program's path, so every config was 'of another command')."""

    (tmp_path / "config.toml").write_text('command = "train decoder"\n[options]\nepochs = 2\n')
    res = run_sss(["train", "decoder", "--config", str(tmp_path), "--out", str(tmp_path / "o")], timeout=120)
    assert res.returncode == 2 and "give either --encoder PATH" in res.stderr, res.stderr  # past the config


@pytest.mark.parametrize("args", [["--checkpoint", "psp=a.pt", "--checkpoint", "psp=b.pt"],
                                  ["--checkpoint", "a/last.pt", "--checkpoint", "b/last.pt"],
                                  ["--checkpoint", "../x=a.pt"]])
def test_eval_knn_columns_have_distinct_plain_names(args):
    """Two checkpoints of one name dropped a column silently; '../x' was taken as a column name."""

    res = run_sss(["eval", "knn", *args], timeout=120)
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 2 and len(out.splitlines()) == 1, out
    assert "--checkpoint takes NAME=PATH (or PATH) with a distinct name" in out, out


def test_a_run_on_sessions_records_no_simulator_options(tmp_path):
    """`--rig paper --sessions DIR` warned that --rig is not used, then recorded `rig = "paper"` in config.toml,
    which then said the run was trained on the paper rig. The simulator's options are left out of a run on
    sessions, and kept for one on the simulator."""
    import tomllib
    from types import SimpleNamespace

    from sssphase_cli.run_config import save_run_config

    sim = {"rig": "paper", "n_views": 4, "cache": tmp_path / "cache", "epochs": 2, "sessions": None}
    saved = lambda params: tomllib.loads(save_run_config(SimpleNamespace(params=params, parent=None), tmp_path)  # noqa: E731
                                         .read_text())["options"]
    assert saved(sim) == {"rig": "paper", "n_views": 4, "cache": str(tmp_path / "cache"), "epochs": 2}
    assert saved({**sim, "sessions": tmp_path / "s"}) == {"epochs": 2, "sessions": str(tmp_path / "s")}


def test_a_run_folder_takes_one_training_at_a_time(tmp_path):
    """Two `sss train decoder` into one --out both trained to the end; the folder then held the second run only."""
    import os
    from types import SimpleNamespace

    from sssphase_core.errors import InputError
    from sssphase_core.reporting.learning_runs import one_training_per_folder, run_decoder, run_pretrain
    from sssphase_core.store.locks import folder_lock

    calls = []

    @one_training_per_folder
    def train(opts):
        calls.append(opts.out)
        return "trained"

    opts = SimpleNamespace(out=tmp_path / "runs" / "dec")
    with folder_lock(opts.out, "held by {holder}"):  # another training of that folder is running
        with pytest.raises(InputError, match=rf"run folder {opts.out} is being trained by pid {os.getpid()}: wait for "
                                             "it to end, or give another --out"):
            train(opts)
    assert train(opts) == "trained" and calls == [opts.out] and not list((tmp_path / "runs").iterdir())
    assert run_decoder.__wrapped__ and run_pretrain.__wrapped__  # (the commands' own runners hold it)
