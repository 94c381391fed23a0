"""The learning commands' core: data options and views (``learning.inputs``) and the session-level runners
(``reporting.learning_runs``), called directly as a notebook would, with a Report that records what they say."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest
from learn_sessions import synthetic_sessions

from sssphase_core.errors import InputError
from sssphase_core.learning.inputs import (
    Report,
    RunConfigFile,
    ViewOptions,
    chosen_views,
    decoder_view_choice,
    describe_views,
    load_views,
    parse_ints,
    parse_names,
    training_data_from_sessions,
    used_views,
)


class Said:
    """A Report that keeps its lines, its statuses and the kinds it styled."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self.statuses: list[str] = []

    def report(self) -> Report:
        @contextlib.contextmanager
        def status(text):
            self.statuses.append(text)
            yield

        return Report(say=self.lines.append, status=status, style=lambda text, kind: f"<{kind}>{text}</{kind}>")




def _decoder_checkpoint(path, preset) -> None:
    """A decoder checkpoint of fresh ``preset`` weights (no training)."""
    import torch

    from sssphase_core.learning.models import Decoder, Encoder
    from sssphase_core.learning.training import save_checkpoint

    torch.manual_seed(0)
    parts = {"encoder": Encoder(preset).state_dict(), "decoder": Decoder(preset, head="reciprocal").state_dict()}
    save_checkpoint(path, {"kind": "decoder", "preset": preset.to_dict(), "config": {"head": "reciprocal"}, **parts})


def test_names_and_views_are_parsed_once_each_and_echoed_as_given():
    assert parse_names("apple, apple,pear,apple", ()) == ["apple", "pear"]
    assert parse_names(["pear", "pear", "soap"], ()) == ["pear", "soap"]
    assert parse_names("", ("a", "b")) == ["a", "b"]
    assert parse_ints("3, 1,") == [3, 1]
    with pytest.raises(InputError, match="--k expects comma-separated integers, got 'x'"):
        parse_ints("x", "--k")
    assert chosen_views("1,1,0", "0,1,2,3", None) == [1, 0]
    assert chosen_views(None, "0,1,2,3", None) == [0, 1, 2, 3]  # the simulator's default
    assert chosen_views(None, "0,1,2,3", "sessions") is None  # every complete view of the sessions
    from sssphase_core.learning.inputs import decoder_view_choice

    with pytest.raises(InputError, match="--val-views expects comma-separated integers, got 'abc'"):  # said --views
        decoder_view_choice(["apple"], "0", "abc", None)
    assert chosen_views([2, 2], "0", None) == [2]


def test_views_are_read_from_sessions_and_described(synthetic, tmp_path):
    root = synthetic_sessions(tmp_path / "sessions", synthetic)
    said = Said()
    vds = load_views([], None, ViewOptions(sessions=root, pixels_per_view=5), footprints=False, report=said.report())
    assert [(v.object, v.view, len(v.pixels)) for v in vds] == [("one", 0, 5), ("three", 0, 5), ("three", 2, 5),
                                                                ("three", 5, 5)]
    assert said.statuses == [f"reading sessions under {root}"]
    assert said.lines == [f"data: captured sessions under {root}: one view 0; three view 0,2,5"]
    assert describe_views(vds) == "one view 0; three view 0,2,5"
    assert used_views(None, vds) == "0,2,5" and used_views("5, 0", vds) == "5, 0" and used_views([2, 0], vds) == "2,0"
    with pytest.raises(InputError, match=r"no complete session views under .*absent \(no such folder\)"):
        load_views([], None, ViewOptions(sessions=tmp_path / "absent"), footprints=False, report=said.report())


def test_simulated_views_beyond_the_turntable_are_refused_before_any_rendering(tmp_path):
    said = Said()
    with pytest.raises(InputError, match=r"views 0,4 need --n-views above 4 .* it is 4\): pass --views within 0..3"):
        load_views(["star"], [0, 4], ViewOptions(cache=tmp_path / "cache"), footprints=False, report=said.report())
    assert said.statuses == [] and not (tmp_path / "cache").exists()


def test_decoder_views_hold_out_each_sessions_last_view_unless_it_trains(synthetic, tmp_path):
    root = synthetic_sessions(tmp_path / "sessions", synthetic, footprints=True)
    assert decoder_view_choice([], None, None, root) == ({"one": [0], "three": [0, 2]}, {"one": [], "three": [5]})
    assert decoder_view_choice([], "0", None, root) == ([0], {"one": [], "three": [5]})  # its last view, if not training
    assert decoder_view_choice(["three"], "0,2,5", None, root) == ([0, 2, 5], [])  # every view trains: none held out
    assert decoder_view_choice([], "0", "", root) == ([0], [])  # "" : no validation
    assert decoder_view_choice([], None, None, None) == ([0, 1, 2], [3])  # the simulator's
    said = Said()
    opts = ViewOptions(sessions=root, pixels_per_view=4)
    train, val = training_data_from_sessions([], opts, decoder_view_choice([], None, None, root), report=said.report())
    assert [(v.object, v.view) for v in train] == [("one", 0), ("three", 0), ("three", 2)]
    assert [(v.object, v.view) for v in val] == [("three", 5)] and all(v.footprints is not None for v in val)
    assert said.lines[1] == f"validation (held out): captured sessions under {root}: three view 5"
    with pytest.raises(InputError, match="--val-views: three view 2 is also a training view; validation views must be held out"):
        training_data_from_sessions(["three"], opts, ([0, 2], [2]), report=said.report())


def test_final_lines_name_the_last_epoch_and_the_kept_one(tmp_path):
    from sssphase_core.reporting.learning_runs import final_lines

    rows = [{"epoch": 1, "step": 4, "val_loss": 0.25, "val_psnr": 31.0, "best_epoch": 1},
            {"epoch": 2, "step": 8, "val_loss": 0.5, "val_psnr": 30.12345, "best_epoch": 1}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert final_lines(tmp_path / "metrics.jsonl", ("loss", "val_loss", "val_psnr"), "val_loss") == [
        "final (epoch 2): val_loss 0.5, val_psnr 30.12",
        f"best val_loss at epoch 1 (0.25): {tmp_path / 'best.pt'} (what backends load from this run folder)"]
    assert final_lines(tmp_path / "absent.jsonl", ("loss",), "loss") == []


def test_named_checkpoints_are_plain_distinct_and_present(tmp_path):
    from sssphase_core.reporting.learning_runs import named_checkpoints

    (tmp_path / "a").mkdir()
    (tmp_path / "enc.pt").write_bytes(b"")
    assert named_checkpoints([f"psp={tmp_path / 'a'}", str(tmp_path / "enc.pt")]) == {
        "psp": str(tmp_path / "a"), "enc": str(tmp_path / "enc.pt")}
    with pytest.raises(InputError, match="distinct name"):
        named_checkpoints([f"x={tmp_path / 'a'}", f"x={tmp_path / 'enc.pt'}"])
    with pytest.raises(InputError, match="no checkpoint at .*missing.pt"):
        named_checkpoints([str(tmp_path / "missing.pt")])


def test_an_empty_run_folder_names_both_checkpoints_it_looked_for(tmp_path):
    """It said "no checkpoint at RUN/last.pt" though a run folder's best.pt is what is loaded first."""
    from sssphase_core.errors import DataError
    from sssphase_core.learning.runlog import check_checkpoint_file

    with pytest.raises(DataError, match=rf"^no checkpoint in the run folder {tmp_path} \(neither best.pt nor last.pt\)"):
        check_checkpoint_file(tmp_path)


def test_run_pretrain_checks_the_config_before_the_data_and_saves_it_before_training(synthetic, tmp_path):
    from sssphase_core.reporting.learning_runs import PretrainOptions, run_pretrain

    root = synthetic_sessions(tmp_path / "sessions", synthetic, views_of={"one": [0, 2], "three": [0, 2, 5]})
    out = tmp_path / "run"
    calls: list[tuple[str, bool]] = []

    def refuse(path, resuming):
        raise InputError("changed options")

    said = Said()
    opts = PretrainOptions(out=out, sessions=root, pixels_per_view=8, batch_size=8, epochs=1, warmup_epochs=1,
                           knn_monitor=16, device="cpu")
    with pytest.raises(InputError, match="changed options"):  # refused before any session is read
        run_pretrain(opts, said.report(), config_file=RunConfigFile(refuse, lambda p, r: p))
    assert said.lines == [] and said.statuses == [] and not out.exists()

    def save(path, resuming):
        calls.append(("save", resuming))
        return path / "options.toml"

    result = run_pretrain(opts, said.report(),
                          config_file=RunConfigFile(lambda p, r: calls.append(("check", r)), save))
    assert calls == [("check", False), ("save", False)]
    assert result.checkpoint == out / "last.pt" and result.checkpoint.exists()
    assert [r["epoch"] for r in result.rows] == [1] and 0 <= result.rows[0]["knn_acc"] <= 1
    assert result.figures == [out / "knn_vs_time.png"] and result.figures[0].exists()
    assert said.lines[0] == f"data: captured sessions under {root}: one view 0,2; three view 0,2,5"
    assert said.lines[1].startswith("<note>note:</note> --warmup-epochs 1 is not shorter than --epochs 1")
    assert said.lines[2] == (f"pretraining <strong>lite</strong> on 40 patches of one, three -> {out} "
                             f"(options in {out / 'options.toml'})")
    first = result.rows[0]
    assert not any("monitor is off" in line for line in said.lines)
    trail = next(line for line in said.lines if line.startswith("kNN monitor"))
    assert trail == (f"kNN monitor (% per epoch, training patches): initial encoder {100 * first['knn_initial']:.1f} -> "
                     f"{100 * first['knn_acc']:.1f}; plot {out / 'knn_vs_time.png'}")
    below = [line for line in said.lines if "never raised the kNN monitor above" in line]
    assert len(below) == (first["knn_acc"] < first["knn_initial"])  # said exactly when training lost to the start
    assert said.lines[-1] == f"<done>done</done>: {out / 'last.pt'}"


def test_the_knn_monitor_is_off_and_says_so_when_only_one_object_has_two_views(synthetic, tmp_path):
    """'one' (view 0) left out had nothing of it to match: the monitor scored it 0% at every epoch."""
    from sssphase_core.reporting.learning_runs import PretrainOptions, run_pretrain

    said = Said()
    result = run_pretrain(PretrainOptions(out=tmp_path / "run", sessions=synthetic_sessions(tmp_path / "s", synthetic),
                                          pixels_per_view=8, batch_size=8, epochs=1, knn_monitor=16, device="cpu"),
                          said.report())
    assert "knn_acc" not in result.rows[0]
    assert any("the kNN monitor is off: it leaves one view out, so it needs two objects each seen in two or more views"
               in line for line in said.lines), said.lines


def test_run_pretrain_refuses_a_batch_larger_than_the_data_before_the_run_folder(synthetic, tmp_path):
    from sssphase_core.reporting.learning_runs import PretrainOptions, run_pretrain

    root = synthetic_sessions(tmp_path / "sessions", synthetic)
    with pytest.raises(InputError, match="--batch-size 64 is more than the 32 training patches"):
        run_pretrain(PretrainOptions(out=tmp_path / "run", sessions=root, pixels_per_view=8), Report(say=lambda s: None))
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("changes", "expected"), [
    ({"encoder": None}, "give either --encoder PATH"),
    ({"end_to_end": True}, "give either --encoder PATH"),
    ({"preset_given": True}, "--preset sets the model of an --end-to-end run"),
    ({"head": "wide"}, "unknown decoder head 'wide'"),
    ({"lr": 20.0}, "--lr must be at most 10, got 20"),
])
def test_run_decoder_refuses_bad_options_before_any_data(changes, expected, tmp_path):
    from sssphase_core.reporting.learning_runs import DecoderOptions, run_decoder

    said = Said()
    opts = DecoderOptions(**{"out": tmp_path / "dec", "encoder": tmp_path / "pre", **changes})
    with pytest.raises(InputError, match=expected):
        run_decoder(opts, said.report())
    assert said.lines == [] and not (tmp_path / "dec").exists()


def test_a_decoder_run_given_as_encoder_is_said(synthetic, tiny, tmp_path):
    """A decoder run's checkpoint as --encoder trained on its encoder without a word."""
    from sssphase_core.reporting.learning_runs import DecoderOptions, run_decoder

    root = synthetic_sessions(tmp_path / "sessions", synthetic, footprints=True)
    _decoder_checkpoint(tmp_path / "dec.pt", tiny)
    said = Said()
    run_decoder(DecoderOptions(out=tmp_path / "run", encoder=tmp_path / "dec.pt", sessions=root, pixels_per_view=8,
                               batch_size=8, epochs=1), said.report())
    assert any(f"--encoder {tmp_path / 'dec.pt'} is a decoder run: its encoder is used, frozen" in line
               for line in said.lines), said.lines


def test_check_against_baselines_without_sessions_says_so():
    from sssphase_core.reporting.learning_runs import check_against_baselines

    said = Said()
    assert check_against_baselines(None, [], None, "cpu", said.report()) is None  # type: ignore[arg-type]
    assert said.lines == ["no --check-sessions: relighting against the baselines was not checked"]


def test_evaluate_knn_returns_the_results_and_tables_it_measured(synthetic, tiny, tmp_path):
    from sssphase_core.reporting.learning_runs import KnnOptions, evaluate_knn

    root = synthetic_sessions(tmp_path / "sessions", synthetic, views_of={"one": [0], "two": [0, 2], "three": [0, 2, 5]})
    _decoder_checkpoint(tmp_path / "enc.pt", tiny)
    said = Said()
    ev = evaluate_knn(KnnOptions(checkpoints=[f"fresh={tmp_path / 'enc.pt'}"], sessions=root, pixels_per_view=8, k="1,3"),
                      said.report())
    res = ev.payload["results"]["fresh"]
    assert ev.payload["k"] == 1 and ev.payload["views"] == "0,2,5" and ev.payload["label"] == "object"
    assert set(res["overall_by_k"]) == {1, 3} and res["overall_by_k"][1] == res["overall"]
    assert 0 <= res["overall"] <= 1
    assert said.statuses == [f"reading sessions under {root}", "embedding 48 patches with fresh"]
    assert "| three |" in ev.markdown() and "against k" in ev.markdown()
    # 'one' is in view 0 only: leaving view 0 out leaves none of it to match, so it is not scored (it read 0%)
    assert set(res["per_class"]) == {"two", "three"} and res["unscored"] == {"one": 8}
    assert "| one | n/a |" in ev.markdown() and "one in one view only" in ev.markdown()
    with pytest.raises(InputError, match=r"--k 24 is not smaller than the 24 patches .*\(48 read, 24 of them in one view\)"):
        evaluate_knn(KnnOptions(checkpoints=[str(tmp_path / "enc.pt")], sessions=root, pixels_per_view=8, k="24"),
                     said.report())
    with pytest.raises(InputError, match="the views read are all view 0, so no patch has another view"):  # was: lower --k
        evaluate_knn(KnnOptions(checkpoints=[str(tmp_path / "enc.pt")], sessions=root, pixels_per_view=8, k="1",
                                views="0"), said.report())
    with pytest.raises(InputError, match="needs two or more objects to tell apart; the views read hold only three"):
        evaluate_knn(KnnOptions(checkpoints=[str(tmp_path / "enc.pt")], sessions=root / "three", pixels_per_view=8,
                                k="1"), said.report())
    lone = synthetic_sessions(tmp_path / "lone", synthetic)  # 'one' in view 0, 'three' in views 0, 2, 5
    with pytest.raises(InputError, match="scores only objects seen in two or more views, and needs two of them to tell "
                                         "apart; of the views read, three has two or more"):
        evaluate_knn(KnnOptions(checkpoints=[str(tmp_path / "enc.pt")], sessions=lone, pixels_per_view=8, k="1"),
                     said.report())


def test_evaluate_footprints_measures_each_backend_and_plots_it(synthetic, tiny, tmp_path):
    from sssphase_core.reporting.learning_runs import FootprintOptions, evaluate_footprints

    root = synthetic_sessions(tmp_path / "sessions", synthetic, footprints=True)
    with pytest.raises(InputError, match="--compare takes NAME=PATH with a new name"):  # before the checkpoint is read
        evaluate_footprints(FootprintOptions(checkpoint=tmp_path / "none.pt", compare=["torch=x"], sessions=root))
    _decoder_checkpoint(tmp_path / "dec.pt", tiny)
    with pytest.raises(InputError, match="--baseline torch is the model --checkpoint gives"):
        evaluate_footprints(FootprintOptions(checkpoint=tmp_path / "dec.pt", baseline="torch", sessions=root))
    said = Said()
    ev = evaluate_footprints(FootprintOptions(checkpoint=tmp_path / "dec.pt", compare=[f"again={tmp_path / 'dec.pt'}"],
                                              baseline="", objects="three", views="0,2", pixels_per_view=4,
                                              sessions=root, plots=tmp_path / "plots"), said.report())
    res = ev.payload["results"]["three"]
    assert ev.payload["objects"] == ["three"] and ev.payload["views"] == "0,2" and set(res) == {"torch", "again"}
    assert res["torch"] == res["again"] and np.isfinite(res["torch"]["psnr"]) and res["torch"]["mse"] >= 0
    assert said.statuses[1:] == ["torch: predicting 8 footprints of three", "again: predicting 8 footprints of three"]
    assert said.lines[1].startswith("LPIPS") and ev.payload["note"].endswith(said.lines[1] + ".")
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == ["three_again.png", "three_torch.png"]
    assert "again PSNR" in ev.markdown()
    from dataclasses import replace

    _decoder_checkpoint(tmp_path / "dec24.pt", replace(tiny, patch=24))  # the sessions' crops are 16 px: an internal
    with pytest.raises(InputError, match=r"--compare wide predicts 24px footprints \(preset tiny\); the sessions under "
                                         r".* hold 16px footprint crops"):  # size error in the metrics before
        evaluate_footprints(FootprintOptions(checkpoint=tmp_path / "dec.pt", compare=[f"wide={tmp_path / 'dec24.pt'}"],
                                             baseline="", pixels_per_view=4, sessions=root))


def test_pca_figure_draws_every_session_view_and_returns_them(synthetic, tiny, tmp_path):
    from PIL import Image

    from sssphase_core.reporting.learning_runs import pca_figure

    root = synthetic_sessions(tmp_path / "sessions", synthetic)
    _decoder_checkpoint(tmp_path / "enc.pt", tiny)
    said = Said()
    vds = pca_figure(tmp_path / "enc.pt", "", 0, ViewOptions(sessions=root), 4, tmp_path / "pca.png", said.report())
    assert [(v.object, v.view) for v in vds] == [("one", 0), ("three", 0)]
    assert len(vds[0].pixels) == len({tuple(p) for p in synthetic[0][0].pixels.tolist()})  # every masked pixel
    assert said.statuses[-1] == "embedding one pixel in 4 along x and y of 2 view(s)"
    assert Image.open(tmp_path / "pca.png").size[0] > 100


def test_learn_bench_tables_set_each_preset_against_the_paper_one(monkeypatch):
    from sssphase_core.bench import learn_bench as lb

    speed = {"paper": 10.0, "lite": 40.0}
    monkeypatch.setattr(lb, "measure_throughput", lambda name, **kw: {
        "encoder_params": 2e6, "decoder_params": 1e6, "infer_patches_s": 2 * speed[name], "train_patches_s": speed[name]})
    monkeypatch.setattr(lb, "loader_throughput", lambda name, **kw: {
        "camera": name, "patch": 90 if name == "paper" else 32, "loader_psp_patches_s": 100.0, "loader_patches_s": 80.0})
    measured: list[str] = []

    @contextlib.contextmanager
    def status(text):
        measured.append(text)
        yield

    results, (table, loader) = lb.learn_bench(repeats=1, status=status)
    assert measured == ["measuring the paper preset (batch 8)", "measuring the lite preset (batch 64)"]
    assert results["lite"]["batch"] == 64 and results["lite"]["train_patches_s"] == 40.0
    assert table.rows[1] == ["lite", 64, "2.00M", "1.00M", 80.0, 4.0, 40.0, 4.0]
    assert loader.rows[0] == ["paper", "paper", 90, 100.0, 80.0, 10.0, 8.0, 4.0]


def test_sss_bench_learn_prints_and_writes_the_tables_learn_bench_returns(monkeypatch, tmp_path):
    import importlib

    from typer.testing import CliRunner

    from sssphase_core.bench import learn_bench as lb
    from sssphase_core.bench.output import Table

    table = Table("Speeds", ["preset", "inference"])
    table.rows.append(["lite", 12.5])
    monkeypatch.setattr(lb, "learn_bench", lambda **kw: ({"lite": {"batch": 64, "seen": kw["device"]}}, [table]))
    app = importlib.import_module("sssphase_cli.main").app
    res = CliRunner().invoke(app, ["bench", "learn", "--out", str(tmp_path / "b.json"), "--md", str(tmp_path / "b.md")],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "Speeds" in res.output and "| lite |" in res.output
    assert json.loads((tmp_path / "b.json").read_text())["results"] == {"lite": {"batch": 64, "seen": "cpu"}}
    assert "| lite |" in (tmp_path / "b.md").read_text()


def test_a_rig_preset_beside_sessions_is_said_to_be_unused(tmp_path):
    """`--rig paper --sessions DIR` trained on the sessions at their own size, and --rig was ignored without a word."""
    from sssphase_core.errors import SssError
    from sssphase_core.learning.inputs import ViewOptions, load_views

    with pytest.warns(UserWarning, match="--rig paper chooses the simulated rig.*--rig is not used"), \
            pytest.raises(SssError):  # (no sessions there: the data then fail as they would have)
        load_views(["apple"], None, ViewOptions(rig="paper", sessions=tmp_path / "none"), footprints=False)
    with pytest.warns(UserWarning, match=r"--cache .* holds simulated views; the data come from --sessions .*: --cache is "
                                         "not used"), pytest.raises(SssError):  # (it was ignored without a word)
        load_views(["apple"], None, ViewOptions(cache=tmp_path / "c", sessions=tmp_path / "none"), footprints=False)
