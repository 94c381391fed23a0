"""Bad training options and unusable checkpoints are refused with one line, before any work or file."""

from __future__ import annotations

import importlib
import math
import re

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sssphase_core.errors import DataError, InputError

app = importlib.import_module("sssphase_cli.main").app
runner = CliRunner()


def _decoder_checkpoint(path, preset, *, poison: str | None = None) -> None:
    """A decoder checkpoint of fresh ``preset`` weights (no training); ``poison``: the part set to NaN."""
    from sssphase_core.learning.models import Decoder, Encoder
    from sssphase_core.learning.training import save_checkpoint

    torch.manual_seed(0)
    parts = {"encoder": Encoder(preset).state_dict(), "decoder": Decoder(preset, head="reciprocal").state_dict()}
    if poison is not None:
        for t in parts[poison].values():
            if t.is_floating_point():
                t.fill_(math.nan)
    save_checkpoint(path, {"kind": "decoder", "preset": preset.to_dict(), "config": {"head": "reciprocal"}, **parts})


@pytest.mark.parametrize("poison", ["decoder", "encoder"])
def test_a_checkpoint_with_non_finite_weights_is_refused_where_it_is_loaded(poison, tiny, tmp_path):
    """NaN weights made every footprint NaN, which relighting silently zeroed (then reported a PSNR)."""
    from sssphase_core.learning.backends.torch_backend import TorchBackend
    from sssphase_core.learning.training import load_decoder, load_encoder

    good, bad = tmp_path / "good.pt", tmp_path / "nan_dec.pt"
    _decoder_checkpoint(good, tiny)
    _decoder_checkpoint(bad, tiny, poison=poison)
    load_decoder(good)  # fresh finite weights load
    TorchBackend(checkpoint=good)
    expected = rf"{bad}: the {poison} weights are not all finite \(\d+ NaN or infinite values"
    with pytest.raises(DataError, match=expected):
        load_decoder(bad)
    with pytest.raises(DataError, match=expected):
        TorchBackend(checkpoint=bad)  # what `sss relight --backend torch --checkpoint` and eval footprints use
    if poison == "encoder":
        with pytest.raises(DataError, match=expected):
            load_encoder(bad)  # `--encoder`, `eval knn`, `viz pca`
        with pytest.raises(DataError, match=expected):
            runner.invoke(app, ["train", "decoder", "--encoder", str(bad), "--out", str(tmp_path / "dec")],
                          catch_exceptions=False)
        assert not (tmp_path / "dec").exists()


def test_a_warmup_saved_as_nan_is_refused_when_the_config_is_repeated(tmp_path):
    (tmp_path / "config.toml").write_text('command = "train pretrain"\n[options]\nwarmup_epochs = nan\n')
    with pytest.raises(InputError, match="--warmup-epochs must be a finite number >= 0, got nan"):
        runner.invoke(app, ["train", "pretrain", "--config", str(tmp_path), "--out", str(tmp_path / "run"),
                            "--cache", str(tmp_path / "cache")], catch_exceptions=False)
    assert not (tmp_path / "run").exists() and not (tmp_path / "cache").exists()


def test_a_boolean_where_a_config_wants_a_number_is_refused(tmp_path):
    (tmp_path / "config.toml").write_text('command = "train pretrain"\n[options]\nbatch_size = true\n')
    with pytest.raises(InputError, match="batch_size must be a whole number, got true"):  # it ran with a batch of 1
        runner.invoke(app, ["train", "pretrain", "--config", str(tmp_path), "--out", str(tmp_path / "run"),
                            "--cache", str(tmp_path / "cache")], catch_exceptions=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("line", "message"), [
    ('epochs = "three"', "epochs must be a whole number, got 'three'"),  # was "Invalid value for '--epochs'"
    ("epochs = 1.5", "epochs must be a whole number, got 1.5"),
    ('sessions = ["/x"]', "sessions must be a path (not empty), got ['/x']"),  # was "Input is not a valid path for ..."
    ('sessions = ""', "sessions must be a path (not empty), got ''"),  # was the current folder, read in silence
    ('out = ""', "out must be a path (not empty), got ''"),  # the run was written into the current folder
    ('cache = ""', "cache must be a path (not empty), got ''"),
    ('check_sessions = ["/x", ""]', "check_sessions must be a list of paths (none empty), got ['/x', '']"),
    ('objects = ["apple"]', "objects must be a string, got ['apple']"),  # was read as the session "['apple']"
    ('check_sessions = "/x"', "check_sessions must be a list of paths (none empty), got '/x'"),  # was "Value must be an iterable."
    ('lr = "fast"', "lr must be a number, got 'fast'"),
    ("end_to_end = 1", "end_to_end must be true or false, got 1"),
])
def test_a_config_value_of_the_wrong_type_is_named_in_the_files_terms(tmp_path, line, message):
    (tmp_path / "config.toml").write_text(f'command = "train decoder"\n[options]\n{line}\n')
    with pytest.raises(InputError, match=f"--config {tmp_path}/config.toml: " + re.escape(message)):
        runner.invoke(app, ["train", "decoder", "--config", str(tmp_path), "--out", str(tmp_path / "run")],
                      catch_exceptions=False)
    assert not (tmp_path / "run").exists()


def test_the_library_refuses_what_the_cli_refuses(dataset, tiny, tmp_path):
    """TorchBackend.pretrain/fit call these loops directly: same checks, before the run folder is made."""
    from sssphase_core.learning.training import DecoderConfig, PretrainConfig, pretrain, train_decoder

    for cfg, match in [(PretrainConfig(batch_size=1), "--batch-size must be at least 2"),
                       (PretrainConfig(warmup_epochs=float("nan")), "--warmup-epochs must be a finite number"),
                       (PretrainConfig(warmup_epochs=-1.0), "--warmup-epochs must be a finite number"),
                       (PretrainConfig(decorrelate=-1.0), "--decorrelate must be a finite number >= 0, got -1.0"),
                       (PretrainConfig(decorrelate=float("inf")), "--decorrelate must be a finite number >= 0")]:
        with pytest.raises(InputError, match=match):
            pretrain(cfg, dataset, tmp_path / "pre", preset=tiny, progress=False)
    with pytest.raises(InputError, match="--aux-classes must be 0"):
        train_decoder(DecoderConfig(aux_classes=-1), None, dataset, tmp_path / "dec", preset=tiny, progress=False)
    # the synthetic views' material labels are 0 and 1: one class is too few
    with pytest.raises(InputError, match="--aux-classes must be 0 .*got 1"):
        train_decoder(DecoderConfig(aux_classes=1), None, dataset, tmp_path / "dec", preset=tiny, progress=False)
    assert not (tmp_path / "pre").exists() and not (tmp_path / "dec").exists()


def test_aux_classes_must_cover_the_material_labels_of_the_training_data(synthetic):
    from sssphase_core.learning.data import PatchDataset, ViewData
    from sssphase_core.learning.training.decoder import check_aux_classes

    views = synthetic[0]
    ds = PatchDataset(views, 16, ["a", "b"], with_targets=True)  # labels 0 and 1
    check_aux_classes(2, ds)
    check_aux_classes(0, ds)
    wide = [ViewData(v.object, v.view, v.psp, v.pixels, v.materials + 16, v.footprints) for v in views]
    with pytest.raises(InputError, match="--aux-classes 3 is too few: the training data have material label 17 .*at least 18"):
        check_aux_classes(3, PatchDataset(wide, 16, ["a", "b"], with_targets=True))
    unlabelled = [ViewData(v.object, v.view, v.psp, v.pixels, np.full_like(v.materials, -1), v.footprints) for v in views]
    with pytest.raises(InputError, match="no material labels"):
        check_aux_classes(24, PatchDataset(unlabelled, 16, ["a", "b"], with_targets=True))


def test_a_session_folder_given_as_sessions_is_a_one_session_set(one_and_three_sessions, synthetic, tmp_path):
    """`--sessions S/obj` said "no complete session views under S/obj"; --check-sessions already took it."""
    from sssphase_core.learning.data import held_out_split, session_views

    root = one_and_three_sessions(tmp_path / "sessions")
    one = root / "three"
    assert held_out_split(one) == ({"three": [0, 2]}, {"three": [5]}) == held_out_split(root, ["three"])
    got = [(d.object, d.view, d.pixels.tolist()) for d in session_views(one, pixels_per_view=5)]
    assert got == [(d.object, d.view, d.pixels.tolist()) for d in session_views(root, ["three"], pixels_per_view=5)]
    assert [d.object for d in session_views(one, ["three"], [2], pixels_per_view=5)] == ["three"]
    with pytest.raises(DataError, match="no session for \\['one'\\]"):
        session_views(one, ["one"])


def test_eval_knn_reads_a_session_folder_given_as_sessions(one_and_three_sessions, tiny, tmp_path):
    """A session folder is a one-object data set: kNN by object over it would score every patch 100%, so it
    is refused by name (as is one without material labels by material); the folder of sessions is read."""
    import json

    root = one_and_three_sessions(tmp_path / "sessions")
    ckpt = tmp_path / "enc.pt"
    _decoder_checkpoint(ckpt, tiny)
    for label, why in (("object", "needs two or more objects to tell apart; the views read hold only three"),
                       ("material", "no material labels")):
        res = runner.invoke(app, ["eval", "knn", "--checkpoint", f"fresh={ckpt}", "--sessions", str(root / "three"),
                                  "--pixels-per-view", "8", "--k", "1", "--label", label, "--out", str(tmp_path / "knn.json")])
        assert isinstance(res.exception, InputError) and why in str(res.exception), res.output
    assert not (tmp_path / "knn.json").exists()
    root = one_and_three_sessions(tmp_path / "both", views_of={"two": [0, 2], "three": [0, 2, 5]})
    res = runner.invoke(app, ["eval", "knn", "--checkpoint", f"fresh={ckpt}", "--sessions", str(root),
                              "--pixels-per-view", "8", "--k", "1", "--out", str(tmp_path / "knn.json")],
                        catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "captured sessions under" in res.output and "three view 0,2,5" in res.output
    assert json.loads((tmp_path / "knn.json").read_text())["views"] == "0,2,5"


def test_a_batch_or_k_larger_than_the_data_is_refused_before_the_run_folder_is_written(one_and_three_sessions, tiny, tmp_path):
    """Too few patches for one batch failed inside the loop, after config.toml was written; a k of at least
    the patches read made every kNN prediction the majority label, silently."""
    root = one_and_three_sessions(tmp_path / "sessions")
    with pytest.raises(InputError, match=r"--batch-size 1000 is more than the \d+ training patches"):
        runner.invoke(app, ["train", "pretrain", "--sessions", str(root), "--pixels-per-view", "8", "--batch-size", "1000",
                            "--out", str(tmp_path / "run")], catch_exceptions=False)
    assert not (tmp_path / "run").exists()
    ckpt = tmp_path / "enc.pt"
    _decoder_checkpoint(ckpt, tiny)
    # a k the smallest leave-one-view-out database cannot give was clamped to it and reported as given
    both = one_and_three_sessions(tmp_path / "both", views_of={"two": [0, 2], "three": [0, 2, 5]})
    with pytest.raises(InputError, match=r"--k 24 is not smaller than the 24 patches of the smallest leave-one-view-out "
                                         r"database \(40 read, 16 of them in one view\)"):
        runner.invoke(app, ["eval", "knn", "--checkpoint", str(ckpt), "--sessions", str(both), "--pixels-per-view", "8",
                            "--k", "5,24", "--out", str(tmp_path / "knn.json")], catch_exceptions=False)
    assert not (tmp_path / "knn.json").exists()


def test_figure_and_evaluation_options_are_refused_before_any_work(one_and_three_sessions, tiny, tmp_path):
    """viz pca ran the whole embedding before "Format 'txt' is not supported" (an internal error), wrote FOLDER.png
    for a folder and figures into a session; eval footprints --baseline torch said "call fit()" after reading
    the data; eval knn read an object named twice twice (its accuracies changed)."""
    from sssphase_core.learning.inputs import parse_names

    root = one_and_three_sessions(tmp_path / "sessions")
    ckpt = tmp_path / "enc.pt"
    _decoder_checkpoint(ckpt, tiny)
    for out, expected in ((tmp_path / "pca.txt", r"give a \.png file name \(e\.g\. .*pca\.png\)"),
                          (tmp_path, r"give a \.png file name \(e\.g\. .*pca_rgb\.png\)"),
                          (root / "one" / "pca.png", "would write into the session")):
        with pytest.raises(InputError, match=expected):
            runner.invoke(app, ["viz", "pca", "--checkpoint", str(tmp_path / "absent.pt"), "--sessions", str(root),
                                "--out", str(out)], catch_exceptions=False)
    assert not (root / "one" / "pca.png").exists() and not (tmp_path.parent / f"{tmp_path.name}.png").exists()
    with pytest.raises(InputError, match="--baseline torch is the model --checkpoint gives"):
        runner.invoke(app, ["eval", "footprints", "--checkpoint", str(ckpt), "--sessions", str(root), "--baseline", "torch",
                            "--out", str(tmp_path / "fp.json")], catch_exceptions=False)
    assert parse_names("apple, apple,pear,apple", ()) == ["apple", "pear"]


@pytest.mark.parametrize("command", [["train", "pretrain"], ["train", "decoder", "--end-to-end"]])
def test_a_cache_folder_inside_a_session_or_on_a_file_is_refused_before_any_simulation(command, tmp_path):
    """``--cache`` is written to like ``--out``: it wrote simulated views into a session folder (which then held a
    file its manifest does not list), and an existing file gave "File exists" without naming the option."""
    from sssphase_core.store.session import Session

    session = Session.create(tmp_path / "sessions", "apple", n_views=1)
    afile = tmp_path / "afile"
    afile.write_text("mine\n")
    for cache, expected in ((session.path, "--cache .* would write into the session"),
                            (session.path / "deeper", "--cache .* would write into the session"),
                            (afile, "--cache .*afile is a file: give a folder")):
        with pytest.raises(InputError, match=expected):
            runner.invoke(app, [*command, "--objects", "apple", "--n-views", "1", "--views", "0", "--epochs", "1",
                                "--cache", str(cache), "--out", str(tmp_path / "run")], catch_exceptions=False)
        assert not (tmp_path / "run").exists()
    assert sorted(p.name for p in session.path.iterdir()) == ["manifest.json"] and afile.read_text() == "mine\n"


def test_report_refuses_a_decoder_run_given_as_its_pretraining(tiny, tmp_path):
    """`sss report S --pretrain DECODER_RUN` was accepted, and its configuration table listed the decoder's
    learning rate and epochs as pretraining's."""
    ckpt = tmp_path / "dec.pt"
    _decoder_checkpoint(ckpt, tiny)
    with pytest.raises(InputError, match=r"--pretrain .*dec.pt is a decoder checkpoint: give the run of `sss train "
                                         r"pretrain` \(and this one as --decoder\)"):
        runner.invoke(app, ["report", str(tmp_path / "sessions"), "--pretrain", str(ckpt), "--backend", "none",
                            "--out", str(tmp_path / "report")], catch_exceptions=False)
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize(("env", "message"), [
    ({"WORLD_SIZE": "two"}, "WORLD_SIZE='two': give a whole number >= 1"),  # was an internal ValueError
    ({"WORLD_SIZE": "0"}, "WORLD_SIZE='0': give a whole number >= 1"),
    ({"WORLD_SIZE": "2", "RANK": "-1"}, "RANK='-1': give a whole number >= 0"),
    ({"WORLD_SIZE": "2", "RANK": "2"}, "RANK=2 is not below WORLD_SIZE=2"),
])
def test_torchrun_variables_that_are_not_a_process_group_are_one_line_naming_them(monkeypatch, env, message):
    from sssphase_core.learning.training.loop import init_distributed

    for name, value in env.items():
        monkeypatch.setenv(name, value)
    with pytest.raises(InputError, match=re.escape(message)):
        init_distributed("cpu")
