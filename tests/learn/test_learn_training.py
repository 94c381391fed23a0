"""Training loops: exact resume, interrupted runs, checkpoints, frozen encoder, collapse monitor."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys

import numpy as np
import pytest
import torch

from sssphase_core.errors import DataError
from sssphase_core.learning.models import get_preset
from sssphase_core.learning.training import (
    CHECKPOINT,
    METRICS,
    DecoderConfig,
    PretrainConfig,
    TrainingCollapsed,
    effective_rank,
    initial_encoder,
    load_checkpoint,
    load_decoder,
    pretrain,
    projection_std,
    train_decoder,
    warmup_cosine,
)

PRE = PretrainConfig(epochs=2, batch_size=16, ckpt_every=3, warmup_epochs=1)


def interrupt_after(n: int):
    """A progress callback that interrupts a run after ``n`` steps, as Ctrl-C does."""
    start: list[int] = []

    def report(kind: str, done: int, total: int, info: str) -> None:
        if not start:
            start.append(done)
        elif done - start[0] >= n:
            raise KeyboardInterrupt

    return report


def states_equal(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_pretrain_writes_safe_checkpoints_and_metrics(pretrained, tiny):
    ckpt = torch.load(pretrained / CHECKPOINT, weights_only=True)
    assert ckpt["preset"]["name"] == "tiny" and ckpt["kind"] == "pretrain"
    assert "optimizer" in ckpt and ckpt["loop"]["epoch"] == 2
    rows = [json.loads(line) for line in (pretrained / METRICS).read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [1, 2]
    assert rows[1]["wall_s"] > rows[0]["wall_s"] > 0
    for r in rows:
        assert r["proj_std_healthy"] == pytest.approx(1 / tiny.proj_dim**0.5)
        assert r["proj_std"] > 0 and r["eff_rank"] > 1 and r["collapsed"] == 0


def test_run_interrupted_mid_epoch_resumes_to_the_same_state(pretrained, dataset, tiny, tmp_path):
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        pretrain(PRE, dataset, out, preset=tiny, progress=interrupt_after(7))
    mid = load_checkpoint(out)["loop"]
    assert mid["epoch"] == 0 and mid["step_in_epoch"] == 6  # last mid-epoch checkpoint
    pretrain(PRE, dataset, out, preset=tiny, progress=False)
    a, b = load_checkpoint(pretrained), load_checkpoint(out)
    assert states_equal(a["model"], b["model"])
    assert a["loop"]["epoch"] == b["loop"]["epoch"] == 2


def test_ctrl_c_saves_a_checkpoint_at_the_step_it_came_and_the_rerun_ends_where_one_run_does(pretrained, dataset, tiny,
                                                                                            tmp_path):
    """Ctrl-C lost every step since the last checkpoint (all of them before the first: `sss train pretrain` stopped
    at step 13 said it would continue from its checkpoint, and started again from zero). Now the loop saves at the
    step the signal came, stops, and puts back the process's own handler."""
    import signal

    from sssphase_core.learning.training import TrainingStopped

    asked: list[int] = []

    def ctrl_c_after(kind: str, done: int, total: int, info: str) -> None:
        if done == 7 and not asked:
            asked.append(done)
            signal.raise_signal(signal.SIGINT)  # as the terminal sends it

    handler = signal.getsignal(signal.SIGINT)
    out = tmp_path / "run"
    with pytest.raises(TrainingStopped, match=r"stopped at step 7 of \d+; saved .*last.pt"):
        pretrain(PRE, dataset, out, preset=tiny, progress=ctrl_c_after)
    assert signal.getsignal(signal.SIGINT) is handler
    mid = load_checkpoint(out)["loop"]
    assert (mid["epoch"], mid["step_in_epoch"]) == (0, 7)  # (the last periodic checkpoint was step 6)
    pretrain(PRE, dataset, out, preset=tiny, progress=False)
    a, b = load_checkpoint(pretrained), load_checkpoint(out)
    assert b["loop"]["epoch"] == 2 and states_equal(a["model"], b["model"])


def test_a_time_limit_ends_the_run_at_an_epoch_end_and_a_rerun_continues_it_exactly(pretrained, dataset, tiny, tmp_path):
    """``time_limit_s`` stops after the epoch at which another would pass it (here: after the first, whatever
    this machine's speed), with that epoch's checkpoint; the rerun without a limit ends where the uninterrupted
    run did, weights equal."""
    out = tmp_path / "run"
    pretrain(dataclasses.replace(PRE, time_limit_s=1e-3), dataset, out, preset=tiny, progress=False)
    assert load_checkpoint(out)["loop"]["epoch"] == 1
    assert [json.loads(line)["epoch"] for line in (out / METRICS).read_text().splitlines()] == [1]
    pretrain(PRE, dataset, out, preset=tiny, progress=False)
    a, b = load_checkpoint(pretrained), load_checkpoint(out)
    assert b["loop"]["epoch"] == 2 and states_equal(a["model"], b["model"])
    roomy = tmp_path / "roomy"  # a limit that is not reached changes nothing
    pretrain(dataclasses.replace(PRE, time_limit_s=3600.0), dataset, roomy, preset=tiny, progress=False)
    assert states_equal(a["model"], load_checkpoint(roomy)["model"])


def test_prefetching_batches_on_a_worker_thread_changes_nothing_and_resumes_exactly(pretrained, dataset, tiny, tmp_path):
    """The worker thread builds the same batches in the same order: weights equal to the plain loop's, also
    after an interrupt that leaves a batch in flight; every epoch logs the time it waited for data."""
    out = tmp_path / "run"
    cfg = dataclasses.replace(PRE, prefetch=True)
    with pytest.raises(KeyboardInterrupt):
        pretrain(cfg, dataset, out, preset=tiny, progress=interrupt_after(7))
    pretrain(cfg, dataset, out, preset=tiny, progress=False)
    assert states_equal(load_checkpoint(pretrained)["model"], load_checkpoint(out)["model"])
    rows = [json.loads(line) for line in (out / METRICS).read_text().splitlines()]
    assert all(0 <= r["data_wait_s"] <= r["wall_s"] for r in rows)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_patches_cropped_on_the_device_equal_the_host_crops_and_training_gives_the_dataset_back(dataset, tiny, tmp_path):
    from sssphase_core.learning.training.loop import place_stacks

    idx = np.random.default_rng(0).permutation(len(dataset))[:40]
    host = dataset.batch(idx)
    assert host["psp"].device.type == "cpu"
    assert place_stacks(dataset, torch.device("cuda"), None)
    try:
        dev = dataset.batch(idx)
        assert dev["psp"].is_cuda and torch.equal(dev["psp"].cpu(), host["psp"])
    finally:
        dataset.place(None)
    pretrain(dataclasses.replace(PRE, epochs=1, device="cuda"), dataset, tmp_path / "run", preset=tiny, progress=False)
    assert dataset.batch(idx)["psp"].device.type == "cpu"  # the run's device copies are released


def test_stacks_stay_on_the_host_for_cpu_training(dataset):
    from sssphase_core.learning.training.loop import place_stacks

    assert not place_stacks(dataset, torch.device("cpu"), True)
    assert dataset.batch(np.arange(4))["psp"].device.type == "cpu"


def test_resume_off_restarts_from_scratch(pretrained, dataset, tiny, tmp_path):
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        pretrain(PRE, dataset, out, preset=tiny, progress=interrupt_after(4))
    cfg = PretrainConfig(epochs=1, batch_size=16, ckpt_every=0, warmup_epochs=1)
    pretrain(cfg, dataset, out, preset=tiny, progress=False, resume=False)
    assert load_checkpoint(out)["loop"]["epoch"] == 1
    assert len((out / METRICS).read_text().splitlines()) == 1


def test_collapse_stops_training_with_a_clear_message(dataset, tiny, tmp_path):
    cfg = PretrainConfig(epochs=3, batch_size=16, ckpt_every=0, collapse_std_frac=100.0)
    with pytest.raises(TrainingCollapsed, match="collapsed at epoch 1.*healthy"):
        pretrain(cfg, dataset, tmp_path / "run", preset=tiny, progress=False)
    assert load_checkpoint(tmp_path / "run")["loop"]["epoch"] == 1


def test_knn_monitor_is_logged_every_epoch_and_measures_the_right_patches(pretrained, dataset):
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.evaluation import knn_leave_one_view_out
    from sssphase_core.learning.training import knn_monitor, knn_monitor_indices

    rows = [json.loads(line) for line in (pretrained / METRICS).read_text().splitlines()]
    assert len(rows) == PRE.epochs and all(0.0 <= r["knn_acc"] <= 1.0 for r in rows)

    class MeanColour(torch.nn.Module):  # a stand-in encoder: the mean of each of the 24 channels
        def forward(self, x):
            return x.mean(dim=(2, 3))

    idx = knn_monitor_indices(dataset, 100, seed=0)
    assert len(idx) == 100 and len(np.unique(idx)) == 100
    emb = dataset.batch(idx)["psp"].mean(dim=(2, 3)).numpy()
    want = knn_leave_one_view_out(emb, dataset.labels("object")[idx], dataset.labels("view")[idx], k=5)["overall"]
    assert knn_monitor(MeanColour(), dataset, idx, 5, torch.device("cpu")) == want
    one_view = PatchDataset([v for v in dataset.views if v.view == 0], 16, ["a", "b"])
    assert knn_monitor_indices(one_view, 100, seed=0) is None  # leave-one-view-out needs two views
    one_object = PatchDataset([v for v in dataset.views if v.object == "a"], 16, ["a", "b"])
    assert knn_monitor_indices(one_object, 100, seed=0) is None  # a one-class vote is always right (it read 100%)
    crossed = PatchDataset([v for v in dataset.views if (v.object, v.view) in (("a", 0), ("b", 1))], 16, ["a", "b"])
    assert knn_monitor_indices(crossed, 100, seed=0) is None  # two views, two objects, but no object in both views


def test_knn_monitor_starts_from_the_initial_encoder_measured_in_the_same_run(pretrained, dataset, tiny, tmp_path):
    """The baseline every epoch is compared with: the monitor on the encoder before any step (its random
    initialisation, seeded by the run), in the first epoch's row and the checkpoint, kept across a resume."""
    from sssphase_core.learning.models.simsiam import SimSiam
    from sssphase_core.learning.training import knn_monitor, knn_monitor_indices

    rows = [json.loads(line) for line in (pretrained / METRICS).read_text().splitlines()]
    torch.manual_seed(PRE.seed)
    fresh = SimSiam(tiny).encoder
    idx = knn_monitor_indices(dataset, PRE.knn_monitor, PRE.seed)
    want = knn_monitor(fresh, dataset, idx, PRE.knn_k, torch.device("cpu"))
    assert rows[0]["knn_initial"] == want and load_checkpoint(pretrained)["knn_initial"] == want
    # rebuilt from the checkpoint alone (the demo's and `sss report`'s kNN baseline), leaving torch's RNG alone
    state = torch.random.get_rng_state()
    assert knn_monitor(initial_encoder(pretrained / CHECKPOINT), dataset, idx, PRE.knn_k, torch.device("cpu")) == want
    assert torch.equal(torch.random.get_rng_state(), state)
    assert rows[0]["knn_acc"] != want or rows[1]["knn_acc"] != want  # the monitor itself measures the trained encoder
    # interrupted in its first epoch and resumed: the initial figure is the one measured before the first step
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        pretrain(PRE, dataset, run, preset=tiny, progress=interrupt_after(4))
    assert load_checkpoint(run)["loop"]["epoch"] == 0 and load_checkpoint(run)["loop"]["step_in_epoch"] > 0
    pretrain(PRE, dataset, run, preset=tiny, progress=False)
    assert json.loads((run / METRICS).read_text().splitlines()[0])["knn_initial"] == want


def test_predictor_keeps_the_base_lr_by_default_while_the_rest_decays(pretrained):
    backbone, predictor = load_checkpoint(pretrained)["optimizer"]["param_groups"]
    assert PRE.fix_pred_lr and predictor["fix"] and not backbone["fix"]
    assert predictor["lr"] == PRE.lr and backbone["lr"] < 0.2 * PRE.lr  # cosine decay near its end


def test_the_decorrelation_term_is_logged_and_keeps_the_projections_apart(pretrained, dataset, tiny, tmp_path):
    """The default run adds the decorrelation term (logged per epoch); runs without it end with projections whose
    features move together more, measured on the same patches (the mean over three seeds: one tiny run can go
    either way)."""
    from sssphase_core.learning.models import SimSiam
    from sssphase_core.learning.models.simsiam import decorrelation_loss

    assert PRE.decorrelate > 0
    rows = [json.loads(line) for line in (pretrained / METRICS).read_text().splitlines()]
    assert all(0 < r["decorrelation"] < 1 for r in rows)

    def run(seed, weight):
        cfg = PretrainConfig(epochs=2, batch_size=16, ckpt_every=0, warmup_epochs=1, decorrelate=weight, seed=seed)
        return pretrain(cfg, dataset, tmp_path / f"s{seed}_w{weight}", preset=tiny, progress=False).parent

    plain = [run(seed, 0.0) for seed in (0, 1, 2)]
    assert "decorrelation" not in json.loads((plain[0] / METRICS).read_text().splitlines()[-1])

    def correlation_of(run):
        model = SimSiam(tiny)
        model.load_state_dict(load_checkpoint(run)["model"])
        with torch.no_grad():
            return float(decorrelation_loss(model.eval().projector(model.encoder(dataset.batch(range(len(dataset)))["psp"]))))

    with_term = np.mean([correlation_of(r) for r in (pretrained, run(1, PRE.decorrelate), run(2, PRE.decorrelate))])
    assert with_term < 0.8 * np.mean([correlation_of(r) for r in plain])  # 0.17 against 0.29 (seeds 0-2)


def test_precise_batchnorm_sets_the_running_statistics_to_those_of_the_patches_whatever_they_were(pretrained, dataset):
    """Each epoch's end replaces BatchNorm's exponential averages (the last augmented batches') with the average
    over training patches as captured: the first BatchNorm's running mean is its input's mean over them, and
    garbled running statistics before it change nothing."""
    from torch import nn

    from sssphase_core.learning.training import load_encoder
    from sssphase_core.learning.training.pretrain import precise_batchnorm

    encoder = load_encoder(pretrained)
    bns = [m for m in encoder.modules() if isinstance(m, nn.BatchNorm2d)]
    n = 16 * (len(dataset) // 16)
    seen: list[torch.Tensor] = []
    hook = bns[0].register_forward_hook(lambda m, args, out: seen.append(args[0].detach()))
    idx = np.random.default_rng(0 + 11).permutation(len(dataset))[:n]
    with torch.no_grad():
        encoder.eval()(dataset.batch(idx)["psp"])
    hook.remove()
    precise_batchnorm(encoder, dataset, n, 16, 0, torch.device("cpu"))
    first = {k: v.clone() for k, v in encoder.state_dict().items()}
    assert torch.allclose(bns[0].running_mean, seen[0].mean(dim=(0, 2, 3)), atol=1e-5)
    assert not encoder.training and bns[0].momentum == 0.1  # left as it was found
    for m in bns:  # garbled: another run's, or a resumed one's
        m.running_mean.fill_(3.0)
        m.running_var.fill_(7.0)
    precise_batchnorm(encoder, dataset, n, 16, 0, torch.device("cpu"))
    assert [k for k, v in encoder.state_dict().items() if not torch.equal(first[k], v)] == []


def test_collapse_statistics():
    torch.manual_seed(0)
    healthy = torch.randn(4096, 64)
    assert projection_std(healthy) == pytest.approx(1 / 8, rel=0.05)
    assert projection_std(torch.ones(100, 64) + 1e-6 * torch.randn(100, 64)) < 1e-3
    rank1 = torch.randn(500, 1) * torch.randn(1, 32)
    assert effective_rank(rank1) < 1.5
    assert effective_rank(healthy) > 50


def test_warmup_then_cosine_schedule_and_its_resumed_continuation():
    def rates(start: int, steps: int) -> list[tuple[float, float]]:
        w = [torch.nn.Parameter(torch.zeros(1)), torch.nn.Parameter(torch.zeros(1))]
        opt = torch.optim.SGD([{"params": [w[0]], "fix": False}, {"params": [w[1]], "fix": True}], lr=0.3)
        schedule = warmup_cosine(opt, 100, 10, 0.05, start=start)
        out = []
        for _ in range(steps):
            out.append((opt.param_groups[0]["lr"], opt.param_groups[1]["lr"]))
            opt.step()
            schedule.step()
        return out

    lrs = [a for a, _ in rates(0, 100)]
    assert lrs[0] == pytest.approx(0.005) and lrs[9] == pytest.approx(0.05)
    assert all(a >= b for a, b in zip(lrs[9:], lrs[10:], strict=False))
    assert lrs[-1] < 1e-4
    assert {b for _, b in rates(0, 100)} == {0.05}  # a fixed group keeps the base rate
    assert [a for a, _ in rates(37, 63)] == lrs[37:]  # a resumed run continues the same schedule


def test_decoder_training_keeps_the_encoder_frozen(pretrained, dataset, tmp_path):
    src = load_checkpoint(pretrained)
    cfg = DecoderConfig(epochs=1, batch_size=16, ckpt_every=0, aux_classes=2)
    train_decoder(cfg, pretrained, dataset, tmp_path / "dec", val=dataset, progress=False)
    ckpt = load_checkpoint(tmp_path / "dec")
    assert ckpt["kind"] == "decoder" and ckpt["preset"]["name"] == "tiny"
    with pytest.raises(DataError, match="not a pretraining checkpoint"):  # whose initial encoder is not its own
        initial_encoder(tmp_path / "dec" / CHECKPOINT)
    # BN running statistics (and every other encoder tensor) unchanged
    assert states_equal(src["encoder"], ckpt["encoder"])
    assert any(k.endswith("running_var") for k in ckpt["encoder"])
    rows = [json.loads(line) for line in (tmp_path / "dec" / METRICS).read_text().splitlines()]
    assert {"val_mse", "val_psnr", "wall_s", "aux", "ssim", "grad"} <= rows[0].keys()
    enc, dec = load_decoder(tmp_path / "dec")
    assert not enc.training and not dec.training


def test_a_decoder_records_what_it_was_trained_on_and_evaluations_say_when_they_score_it(pretrained, dataset, tmp_path):
    """`sss eval relight` and the training check scored a decoder on the very views it was fitted on as if they were
    unseen objects, without a word."""
    from sssphase_core.learning.data import PatchDataset
    from sssphase_core.learning.training.checkpoints import trained_views
    from sssphase_core.relight.evaluation import training_overlap

    view_0 = PatchDataset([v for v in dataset.views if v.view == 0], dataset.patch, dataset.classes, with_targets=True)
    train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), pretrained, view_0, tmp_path / "dec",
                  progress=False)
    assert trained_views(tmp_path / "dec") == {"a": [0], "b": [0]}
    note = training_overlap(tmp_path / "dec", [("a", 0), ("a", 1), ("c", 0), ("a", 0)])
    assert note == ("note: the decoder was trained on a view 0: the torch and blend figures there measure how it fits "
                    "what it saw, not relighting of unseen data; a view 1 is another view of its training objects, not "
                    "unseen objects")
    assert training_overlap(tmp_path / "dec", [("a", 1)], held_out=False) is None  # the held-out views it was asked for
    assert training_overlap(tmp_path / "dec", [("c", 0), ("d", 1)]) is None  # unseen objects: nothing to say
    _, _ = load_decoder(tmp_path / "dec")  # the record is plain data: the checkpoint still loads weights-only


@pytest.mark.parametrize("camera_augment", [0.0, 0.5])
def test_decoder_resume_is_exact(pretrained, dataset, tmp_path, camera_augment):
    cfg = DecoderConfig(epochs=1, batch_size=16, ckpt_every=2, camera_augment=camera_augment)
    train_decoder(cfg, pretrained, dataset, tmp_path / "a", progress=False)
    with pytest.raises(KeyboardInterrupt):
        train_decoder(cfg, pretrained, dataset, tmp_path / "b", progress=interrupt_after(5))
    train_decoder(cfg, pretrained, dataset, tmp_path / "b", progress=False)
    assert states_equal(load_checkpoint(tmp_path / "a")["decoder"], load_checkpoint(tmp_path / "b")["decoder"])
    assert load_checkpoint(tmp_path / "b")["config"]["camera_augment"] == camera_augment  # the run records it


def test_a_decoder_is_not_resumed_on_an_encoder_that_changed_since(pretrained, dataset, tmp_path):
    """Continuing the pretraining run and then resuming a decoder fitted on it swapped the frozen encoder
    between the decoder's epochs, without a word."""
    import shutil

    from sssphase_core.learning.training.checkpoints import save_checkpoint

    shutil.copytree(pretrained, tmp_path / "pre")
    enc = tmp_path / "pre" / CHECKPOINT
    train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), enc, dataset, tmp_path / "dec", progress=False)
    train_decoder(DecoderConfig(epochs=2, batch_size=16, ckpt_every=0), enc, dataset, tmp_path / "dec", progress=False)
    ckpt = load_checkpoint(enc)  # the same encoder resumes; now it changes
    first = next(k for k, v in ckpt["encoder"].items() if v.is_floating_point())
    ckpt["encoder"][first] = ckpt["encoder"][first] + 0.01  # "trained further"
    save_checkpoint(enc, ckpt)
    with pytest.raises(DataError, match="other encoder weights"):
        train_decoder(DecoderConfig(epochs=3, batch_size=16, ckpt_every=0), enc, dataset, tmp_path / "dec", progress=False)


def test_a_decoder_is_not_resumed_on_training_data_that_changed_since(pretrained, dataset, tmp_path):
    """A decoder run stopped, its sessions captured again, and resumed: it finished fitted on both, without a word."""
    from sssphase_core.bench.synthetic import synthetic_views
    from sssphase_core.learning.data import PatchDataset

    train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), pretrained, dataset, tmp_path / "dec", progress=False)
    recaptured = PatchDataset(synthetic_views(("a", "b"), (0, 1), size=(48, 48), patch=16, pixels_per_view=64,
                                              seed=5)[0], 16, ["a", "b"], with_targets=True)
    with pytest.raises(DataError, match=r"was fitted on other training data than it is given now \(sessions captured "
                                        r"again, or other views or pixels\)"):
        train_decoder(DecoderConfig(epochs=2, batch_size=16, ckpt_every=0), pretrained, recaptured, tmp_path / "dec",
                      progress=False)
    train_decoder(DecoderConfig(epochs=2, batch_size=16, ckpt_every=0), pretrained, dataset, tmp_path / "dec",
                  progress=False)  # the same data resumes
    assert load_checkpoint(tmp_path / "dec" / CHECKPOINT)["loop"]["epoch"] == 2


def test_end_to_end_baseline_trains_the_encoder_too(dataset, tiny, tmp_path):
    from sssphase_core.learning.models import Encoder

    cfg = DecoderConfig(epochs=1, batch_size=16, ckpt_every=0)
    train_decoder(cfg, None, dataset, tmp_path / "e2e", progress=False, preset=tiny)
    ckpt = load_checkpoint(tmp_path / "e2e")
    assert ckpt["config"]["end_to_end"] and ckpt["config"]["preset"] == "tiny"
    torch.manual_seed(cfg.seed)
    init = Encoder(tiny).state_dict()  # the run's starting weights (same seed)
    moved = [k for k in init if k.endswith("weight") and not torch.equal(init[k], ckpt["encoder"][k])]
    assert len(moved) > 0.9 * sum(k.endswith("weight") for k in init)
    bn = [k for k in init if k.endswith("running_var")]
    assert bn and all(not torch.equal(init[k], ckpt["encoder"][k]) for k in bn)  # trained in train mode
    enc, dec = load_decoder(tmp_path / "e2e")  # the torch backend loads it like any decoder run
    assert not enc.training and not dec.training


def test_end_to_end_resume_is_exact_and_not_mixed_with_a_frozen_run(pretrained, dataset, tiny, tmp_path):
    from sssphase_core.errors import DataError

    cfg = DecoderConfig(epochs=1, batch_size=16, ckpt_every=2)
    train_decoder(cfg, None, dataset, tmp_path / "a", progress=False, preset=tiny)
    with pytest.raises(KeyboardInterrupt):
        train_decoder(cfg, None, dataset, tmp_path / "b", progress=interrupt_after(3), preset=tiny)
    train_decoder(cfg, None, dataset, tmp_path / "b", progress=False, preset=tiny)
    a, b = load_checkpoint(tmp_path / "a"), load_checkpoint(tmp_path / "b")
    assert states_equal(a["encoder"], b["encoder"]) and states_equal(a["decoder"], b["decoder"])
    with pytest.raises(DataError, match="end-to-end"):
        train_decoder(cfg, pretrained, dataset, tmp_path / "a", progress=False)


def test_decoder_rejects_a_pretraining_run_as_its_own_output(pretrained, dataset):
    from sssphase_core.errors import DataError

    with pytest.raises(DataError, match="pretrain"):
        train_decoder(DecoderConfig(epochs=1, batch_size=16), pretrained, dataset, pretrained, progress=False)


def test_resume_refuses_another_preset(pretrained, dataset):
    from dataclasses import replace

    from sssphase_core.errors import DataError

    other = replace(get_preset(load_checkpoint(pretrained)["preset"]), stem=4)
    with pytest.raises(DataError, match="preset"):
        pretrain(PRE, dataset, pretrained, preset=other, progress=False)


def test_best_checkpoint_is_the_best_monitored_epoch_and_what_a_run_folder_loads(pretrained):
    from sssphase_core.learning.training import BEST, resolve_checkpoint

    rows = [json.loads(line) for line in (pretrained / METRICS).read_text().splitlines()]
    assert all("knn_acc" in r for r in rows)
    best = max(rows, key=lambda r: (r["knn_acc"], -r["epoch"]))  # the first epoch reaching the maximum
    assert rows[-1]["best_epoch"] == best["epoch"]
    assert (pretrained / BEST).exists() and resolve_checkpoint(pretrained) == pretrained / BEST
    assert torch.load(pretrained / BEST, weights_only=True)["loop"]["epoch"] == best["epoch"]
    assert load_checkpoint(pretrained)["loop"]["epoch"] == best["epoch"]
    assert load_checkpoint(pretrained / CHECKPOINT)["loop"]["epoch"] == 2  # last.pt stays the resume point


def test_decoder_keeps_the_epoch_with_the_lowest_validation_loss(pretrained, dataset, tmp_path, monkeypatch):
    import sssphase_core.learning.training as training

    losses = iter([0.5, 0.2, 0.4])  # epoch 2 is the best, epoch 3 is the last
    monkeypatch.setattr(training.decoder, "validate_decoder", lambda *a, **k: {"val_loss": next(losses), "val_mse": 1e-4,
                                                                          "val_psnr": 40.0})
    out = tmp_path / "dec"
    train_decoder(DecoderConfig(epochs=3, batch_size=16, ckpt_every=0), pretrained, dataset, out, val=dataset, progress=False)
    assert torch.load(out / training.BEST, weights_only=True)["loop"]["epoch"] == 2
    assert torch.load(out / CHECKPOINT, weights_only=True)["loop"]["epoch"] == 3
    assert load_checkpoint(out)["loop"]["epoch"] == 2


def test_noise_floor_of_footprints_and_the_log_offset_it_sets(pretrained, dataset, tmp_path):
    from sssphase_core.learning.losses import LOG_EPS, noise_floor

    rng = np.random.default_rng(0)
    clean = torch.zeros(64, 3, 16, 16)
    clean[:, :, 6:10, 6:10] = 0.02
    assert noise_floor(clean) == 0.0
    noisy = clean + torch.from_numpy(rng.normal(0, 7e-4, clean.shape).astype(np.float32))
    assert noise_floor(noisy) == pytest.approx(7e-4, rel=0.1)
    out = tmp_path / "dec"
    train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0), pretrained, dataset, out, progress=False)
    eps = torch.load(out / CHECKPOINT, weights_only=True)["config"]["log_eps"]
    assert eps >= LOG_EPS  # recorded, so a resumed run uses the same offset


class _Pickled:  # torch.save pickles this; weights_only loading must refuse it
    pass


@pytest.mark.parametrize(("content", "expected"), [
    (None, "the file is empty"),
    ([1, 2, 3], "not a sssphase checkpoint (list)"),
    ({"kind": "pretrain", "encoder": {}}, "without preset"),
    (_Pickled(), "pickled Python objects"),
    (b"PK\x03\x04truncated", "cannot read checkpoint"),
    ("zip", "it is a zip archive, but not one torch saved"),  # said "[enforce fail at inline_container.cc:180] ..."
    ("bomb", "its member 'archive/data.pkl' is compressed"),  # 64 MB unpacked from 64 kB (gigabytes from 5 MB)
    (b"# a text file\n", "not a checkpoint file"),
    (b"\x89PNG\r\n\x1a\n" + bytes(64), "not a checkpoint file"),  # another program's file (torch says "101")
])
def test_bad_checkpoints_are_refused_with_one_clear_line(tmp_path, content, expected):
    from sssphase_core.errors import DataError
    from sssphase_core.learning.training import load_encoder

    path = tmp_path / "bad.pt"
    if content is None:
        path.write_bytes(b"")
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "zip":
        import zipfile

        with zipfile.ZipFile(path, "w") as z:
            z.writestr("hello.txt", "hi")
    elif content == "bomb":
        import zipfile

        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("archive/data.pkl", bytes(64 << 20))
            z.writestr("archive/version", "3\n")
    else:
        torch.save(content, path)
    with pytest.raises(DataError) as err:
        load_encoder(path)
    message = str(err.value)
    assert expected in message and "\n" not in message, message


def test_a_real_checkpoint_cut_anywhere_is_called_damaged_or_truncated(pretrained, tmp_path):
    """Cut past its first kilobytes, torch failed with a bare "[Errno 22] Invalid argument"."""
    from sssphase_core.errors import DataError
    from sssphase_core.learning.training import load_encoder

    whole = (pretrained / CHECKPOINT).read_bytes()
    for keep in (100, 5000, len(whole) // 3, len(whole) - 100):
        cut = tmp_path / f"cut{keep}.pt"
        cut.write_bytes(whole[:keep])
        with pytest.raises(DataError, match="damaged or truncated"):
            load_encoder(cut)


def test_a_checkpoint_whose_weights_do_not_fit_its_preset_is_refused(pretrained, tmp_path):
    from sssphase_core.errors import DataError
    from sssphase_core.learning.training import load_encoder

    ckpt = load_checkpoint(pretrained)
    ckpt["encoder"] = {k: v[..., :1] if v.ndim else v for k, v in ckpt["encoder"].items()}
    torch.save(ckpt, tmp_path / "cut.pt")
    with pytest.raises(DataError, match="do not fit"):
        load_encoder(tmp_path / "cut.pt")


def test_a_preset_for_a_huge_model_without_its_weights_is_refused_before_any_memory(pretrained, tmp_path):
    """Widths within the preset's limits (16,384) but weights of the lite model: the encoder was built first and
    asked for 38 GB. Under a 3 GB address-space limit the checkpoint is now refused by the shape of its weights."""
    ckpt = load_checkpoint(pretrained)
    ckpt["preset"] = {**ckpt["preset"], "stem": 16384, "stages": [16384] * 3, "bottleneck": 16384}
    torch.save({**ckpt, "kind": "decoder", "decoder": {}}, tmp_path / "huge.pt")
    code = ("import resource, sys\n"
            "resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))\n"
            "from sssphase_core.learning.training import load_decoder\n"
            "from sssphase_core.errors import DataError\n"
            "try:\n    load_decoder(sys.argv[1])\nexcept DataError as exc:\n    print(exc)\n")
    done = subprocess.run([sys.executable, "-c", code, str(tmp_path / "huge.pt")], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-1500:]
    assert "the encoder weights do not fit the checkpoint's preset (stem" in done.stdout and "16384x24" in done.stdout


@pytest.mark.parametrize(("edit", "expected"), [
    ({"stem": -1}, "stem must be a whole number from 1 to 16384, got -1"),  # was torch's "negative dimension"
    ({"patch": 0}, "patch must be a whole number from 9 to 256, got 0"),
    ({"patch": 10**6}, "patch must be a whole number from 9 to 256, got 1000000"),  # asked for 12 TB
    ({"stem": "x"}, "stem must be a whole number"),
    ({"stages": [8, 8]}, "stages must be 3 channel widths"),
    ({"dropout": 2.0}, "dropout must be a number in [0, 1)"),
])
def test_a_checkpoint_whose_preset_was_edited_is_refused_before_any_tensor(pretrained, tmp_path, edit, expected):
    from sssphase_core.errors import DataError
    from sssphase_core.learning.training import load_encoder

    ckpt = load_checkpoint(pretrained)
    ckpt["preset"] = {**ckpt["preset"], **edit}
    torch.save(ckpt, tmp_path / "edited.pt")
    with pytest.raises(DataError, match="its model preset cannot be read") as err:
        load_encoder(tmp_path / "edited.pt")
    assert expected in str(err.value)


def test_a_decoder_checkpoint_whose_config_was_edited_is_refused(pretrained, tmp_path):
    from sssphase_core.errors import DataError
    from sssphase_core.learning.training import load_decoder

    ckpt = {**load_checkpoint(pretrained), "kind": "decoder", "decoder": {}}  # its config is read before its weights
    for config, expected in (({"head": "reciprocal", "aux_classes": "abc"}, "aux_classes 'abc'"),
                             ([1, 2], "its config is a list, not a table")):
        torch.save({**ckpt, "config": config}, tmp_path / "edited.pt")
        with pytest.raises(DataError, match=re.escape(expected)):  # were an internal ValueError, and "weights do not fit"
            load_decoder(tmp_path / "edited.pt")


def test_the_energy_gain_stays_at_one_unless_asked(pretrained, dataset, tmp_path):
    for learn, moved in ((False, False), (True, True)):
        out = tmp_path / f"gain_{learn}"
        train_decoder(DecoderConfig(epochs=1, batch_size=16, ckpt_every=0, lr=1e-2, learn_gain=learn), pretrained, dataset,
                      out, progress=False)
        gain = torch.load(out / CHECKPOINT, weights_only=True)["decoder"]["log_gain"]
        assert bool(gain.abs().max() > 0) == moved, gain


def test_an_epoch_row_written_again_after_a_resume_replaces_the_first(tmp_path):
    """The row is written before the epoch's checkpoint (an interrupt between the two lost the row: the
    curves silently missed an epoch); a resumed run that writes it again replaces it."""
    from sssphase_core.learning.runlog import RunLog, read_rows

    log = RunLog(tmp_path, enabled=True)
    for epoch, loss in ((1, 3.0), (2, 2.0), (2, 1.5), (3, 1.0)):
        log.epoch({"epoch": epoch, "step": 10 * epoch, "loss": loss, "wall_s": float(epoch)})
    log.close()
    assert [(r["epoch"], r["loss"]) for r in read_rows(tmp_path / METRICS)] == [(1, 3.0), (2, 1.5), (3, 1.0)]
    assert (tmp_path / "metrics.csv").read_text().count("\n") == 4  # header + three rows


def test_damaged_rows_of_a_runs_metrics_are_left_out_with_a_warning_not_a_crash_after_the_epoch(tmp_path):
    """A resumed run crashed on a damaged line after training its epoch (and again on every rerun)."""
    from sssphase_core.learning.runlog import RunLog, read_rows

    (tmp_path / METRICS).write_text('{"epoch": 1, "step": 10, "loss": 3.0}\ngarbage{{{\n{"epoch": "x"}\n[1, 2]\n')
    with pytest.warns(UserWarning, match=r"lines 2, 3, 4 not an epoch's row"):
        RunLog(tmp_path, enabled=True).epoch({"epoch": 2, "step": 20, "loss": 2.0})
    assert [r["epoch"] for r in read_rows(tmp_path / METRICS)] == [1, 2]  # rewritten without them


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_paper_preset_runs_resume_exactly_on_cuda_with_the_default_kernels(tmp_path):
    """The claim behind each stage's default ``deterministic``, at the paper's size, in bf16 autocast."""
    from sssphase_core.bench.gpu_bench import _dataset

    ds = _dataset(get_preset("paper").patch, 12 * 16)
    pre = PretrainConfig(preset="paper", epochs=1, batch_size=16, ckpt_every=4, knn_monitor=0, warmup_epochs=0.5)
    dec = DecoderConfig(epochs=1, batch_size=16, ckpt_every=4, val_samples=0)
    assert not pre.deterministic and dec.deterministic
    pretrain(pre, ds, tmp_path / "pa", progress=False)
    with pytest.raises(KeyboardInterrupt):
        pretrain(pre, ds, tmp_path / "pb", progress=interrupt_after(6))
    pretrain(pre, ds, tmp_path / "pb", progress=False)
    assert states_equal(load_checkpoint(tmp_path / "pa")["model"], load_checkpoint(tmp_path / "pb")["model"])
    train_decoder(dec, tmp_path / "pa", ds, tmp_path / "da", progress=False)
    with pytest.raises(KeyboardInterrupt):
        train_decoder(dec, tmp_path / "pa", ds, tmp_path / "db", progress=interrupt_after(6))
    train_decoder(dec, tmp_path / "pa", ds, tmp_path / "db", progress=False)
    assert states_equal(load_checkpoint(tmp_path / "da")["decoder"], load_checkpoint(tmp_path / "db")["decoder"])


def test_deterministic_kernels_are_asked_of_cuda_for_the_run_only():
    """Without deterministic kernels a resumed decoder run ended with other weights than an uninterrupted one
    on an H200 (with them it did not); other code in the process must not inherit the setting."""
    from sssphase_core.learning.training.loop import deterministic_kernels

    before = torch.are_deterministic_algorithms_enabled()
    assert not before  # the test process runs with PyTorch's default
    with deterministic_kernels(torch.device("cuda"), True):  # only the flag is set: no CUDA needed here
        assert torch.are_deterministic_algorithms_enabled() and torch.is_deterministic_algorithms_warn_only_enabled()
    assert torch.are_deterministic_algorithms_enabled() is before
    for device, enabled in ((torch.device("cpu"), True), (torch.device("cuda"), False)):
        with deterministic_kernels(device, enabled):  # the CPU's kernels are deterministic already
            assert not torch.are_deterministic_algorithms_enabled()
    with pytest.raises(KeyboardInterrupt), deterministic_kernels(torch.device("cuda"), True):
        raise KeyboardInterrupt  # an interrupted run leaves the process as it found it
    assert not torch.are_deterministic_algorithms_enabled()


@pytest.mark.parametrize("moved", [True, False])
def test_the_fringe_phase_move_is_on_by_default_and_can_be_left_out(dataset, tiny, tmp_path, monkeypatch, moved):
    """``PretrainConfig.phase_shift`` (``--no-phase-shift``) decides whether the strong view moves the fringes."""
    from sssphase_core.learning import augment

    calls, original = [], augment.phase_shift
    monkeypatch.setattr(augment, "phase_shift", lambda x, p: calls.append(p) or original(x, p))
    cfg = PretrainConfig(epochs=1, batch_size=64, ckpt_every=0, warmup_epochs=0, knn_monitor=0, **({} if moved else {"phase_shift": False}))
    pretrain(cfg, dataset, tmp_path / "run", preset=tiny, progress=False)
    assert calls and set(calls) == ({1.0} if moved else {0.0})


def test_the_cli_passes_no_phase_shift_to_the_run(tmp_path, monkeypatch):
    import importlib

    from typer.testing import CliRunner

    app = importlib.import_module("sssphase_cli.main").app  # the installed `sss` app (cli/ folder)

    seen = []
    monkeypatch.setattr("sssphase_core.reporting.learning_runs.run_pretrain", lambda opts, *a, **k: seen.append(opts))
    for flag, expected in (([], True), (["--no-phase-shift"], False)):
        result = CliRunner().invoke(app, ["train", "pretrain", "--out", str(tmp_path / "pre"), *flag], catch_exceptions=False)
        assert result.exit_code == 0 and seen.pop().phase_shift is expected


@pytest.mark.parametrize("kind", ["device", "fifo"])
def test_a_runs_metrics_that_is_no_file_is_refused_by_name(tmp_path, kind):
    """A received run folder whose metrics.jsonl links to /dev/zero read it without end (4 GB in seconds); a
    FIFO hung the resumed run."""
    import os

    from sssphase_core.errors import InputError
    from sssphase_core.learning.runlog import read_rows

    path = tmp_path / METRICS
    os.symlink("/dev/zero", path) if kind == "device" else os.mkfifo(path)
    with pytest.raises(InputError, match=f"the run's metrics {path} is a {'device' if kind == 'device' else 'FIFO'}"):
        read_rows(path)
