"""`sss repro paper`: the paper's Tables 1-2 at its scale (1080p, K = 90, the 32M + 22M-parameter model),
within a time budget on one machine, through the user's path, with the paper's numbers beside ours.

Steps (each recorded in ``<out>/steps/<name>.json`` and skipped when rerun, like ``sss demo``):

1. ``train_sessions``  the paper's five training objects, captured as ``sss capture`` does (the sim rig at
   the ``paper`` preset, rendering on ``device``; dot grids every ``dot_stride``-th shift: footprints for
   1 / stride^2 of the pixels, what the decoder samples from);
2. ``test_sessions``   unseen objects with reference patterns;
3. ``pretrain_psp`` and ``pretrain_imagenet``  SimSiam with the paper's PSP augmentations and with
   ImageNet's (Table 2 compares them);
4. ``decoder``         the footprint decoder (SBH loss) on the frozen PSP encoder, from the captured crops;
5. ``footprints``      Table 1: footprint MSE / PSNR / SSIM (/ LPIPS with its weights) of unseen objects
   against the simulator's exact footprints (evaluation only);
6. ``knn``             Table 2: kNN accuracy per object, view-level leave-one-out, both augmentations;
7. ``relight``         relit PSNR / SSIM against the reference captures for none / analytic / torch / blend;
8. ``report``          ``<out>/report.md`` and ``report.json``: our figures beside the paper's, the
   seconds each step took of the budget, and what was scaled down to fit.

The budget (of this run: a rerun skips the finished steps and gets a budget of its own) is kept by sizing,
not by cutting runs short: the training epochs are chosen from the time left
after the captures (:func:`epochs_within`, with the throughput ``sss bench gpu`` measured), and a step
that would start with the budget spent is recorded as not run. The report is rewritten after every step,
so a run stopped from outside still leaves what it finished.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from sssphase_core.errors import InputError
from sssphase_core.relight.choices import BLENDS
from sssphase_core.reporting.demo import Demo, DemoConfig, NotAvailable
from sssphase_core.store.files import write_text

#: The paper's Table 1 (unseen test objects; MSE x 1e-5, LPIPS x 1e-2 there; plain units here).
PAPER_TABLE1: dict[str, dict[str, float]] = {
    "apple": {"mse": 4.1e-5, "psnr": 44.67, "ssim": 0.96, "lpips": 8.4e-2},
    "orange": {"mse": 4.9e-5, "psnr": 43.84, "ssim": 0.94, "lpips": 8.6e-2},
    "crab": {"mse": 3.5e-5, "psnr": 47.98, "ssim": 0.98, "lpips": 6.5e-2},
    "hand": {"mse": 3.8e-5, "psnr": 42.51, "ssim": 0.96, "lpips": 6.5e-2},
}
#: The paper's Table 2: kNN accuracy (%) per training object, PSP against ImageNet augmentations.
PAPER_TABLE2: dict[str, dict[str, float]] = {
    "apple": {"psp": 99.6, "imagenet": 99.04}, "pear": {"psp": 99.99, "imagenet": 98.74},
    "orange": {"psp": 99.99, "imagenet": 98.92}, "star": {"psp": 99.95, "imagenet": 99.93},
    "shovel": {"psp": 91.43, "imagenet": 84.91},
}
#: What the paper trained with, for the report's "scaled down" table.
PAPER_SCALE = {"train views per object": "about 40 (a turntable)", "pretraining epochs": 200,
               "decoder epochs": "not stated", "batch": 128, "patches": "every surface pixel"}

#: Training throughput (patches/s, all time counted) the epoch planner assumes per (device type, model preset):
#: `sss bench gpu` on one H200 measured 988 (SimSiam) and 947 (decoder) at batch 128 with the paper preset.
PLANNED_RATE = {("cuda", "paper"): 800.0, ("cuda", "lite"): 4000.0, ("cpu", "paper"): 3.0, ("cpu", "lite"): 150.0}


@dataclass(frozen=True)
class ReproConfig(DemoConfig):
    rig_preset: str = "paper"
    dot_stride: int = 11
    augments: tuple[str, ...] = ("psp", "imagenet")
    #: shares of the training time left after the captures and the evaluation reserve
    train_shares: tuple[float, float, float] = (0.3, 0.3, 0.4)  # pretrain psp, pretrain imagenet, decoder
    eval_reserve_s: float = 150.0  # kept for footprints, kNN and relighting


PRESETS = {
    # One lent H200 (16 cores) in about 8 minutes: the paper's objects, 2 views each (kNN's leave-one-view-out
    # needs two), 1080p, K = 90, the paper model; epochs fitted to the time the captures leave.
    "paper": ReproConfig(("apple", "pear", "orange", "star", "shovel"), ("crab", "hand"), train_views=2,
                         pixels_per_view=1000, pretrain_epochs=20, pretrain_batch=128, decoder_epochs=20,
                         decoder_batch=128, backends=("none", "torch", "analytic", "blend"), footprint_pixels=256,
                         model="paper", analytic_supersample=2, eval_reserve_s=150.0),
    # The test suite's: the CPU rig preset and the lite model, seconds per step.
    "tiny": ReproConfig(("apple", "star"), ("sand_rake",), train_views=2, pixels_per_view=12, pretrain_epochs=1,
                        pretrain_batch=8, decoder_epochs=1, decoder_batch=8, backends=("none", "analytic", "torch"),
                        footprint_pixels=16, model="lite", rig_preset="cpu", dot_stride=4, eval_reserve_s=0.0),
}

#: A relight is started only with at least this many seconds of the budget left, or as many as it is estimated
#: to take (a 1080p view with four backends outgrew a fixed reserve on the H200, and a 1080p torch relight the
#: time of the relight with no scattering before it).
RELIGHT_MIN_S = 20.0
#: A whole relight's seconds per lit pixel over its model's seconds per footprint in the footprints step (the
#: splat, the white-consistent calibration and the scoring besides the footprints), by device kind. On 2 cores for
#: the analytic model on a 1080p crab 1.35 (130 s for 182,018 pixels at 0.53 ms per footprint), and 1.04 once its
#: render moved to torch (54.6 s at 0.29 ms, the step's timing of 2,048 scattered pixels). On the H100 0.74 for the
#: decoder (98.4 s for 182,020 pixels at 0.73 ms: the step times batches of ~250 footprints, the relight's are
#: larger), which 1.5 had estimated at 199 s.
RELIGHT_OVER_FOOTPRINTS = {"cpu": 1.5, "cuda": 1.0}
BUDGET_SPENT = "the budget was spent"

STEPS = ("train_sessions", "test_sessions", "pretrain_psp", "pretrain_imagenet", "decoder", "footprints", "knn",
         "relight", "report")

#: ``capture(requests) -> session paths``: captures the requests as ``sss capture`` does (the CLI runs them
#: through daemons, several at once).
Capture = Callable[[Sequence[Any]], list[str]]


def epochs_within(seconds: float, patches: int, rate: float, most: int) -> int:
    """Epochs of ``patches`` that ``seconds`` allow at ``rate`` patches/s: 1 to ``most``."""
    if patches <= 0 or rate <= 0:
        return 1
    return int(max(1, min(most, math.floor(seconds * rate / patches))))


class PaperRepro(Demo):
    """The paper's experiments at its scale, within ``budget_s`` seconds (see the module docstring)."""

    report_title = "sssphase: the paper's Tables 1-2 reproduced"

    def __init__(self, out: Path, config: ReproConfig, capture: Capture, *, device: str, budget_s: float,
                 fresh: bool = False, log: Callable[[str], None] = print,
                 progress: Callable[[str, int, int, str], None] | None = None):
        super().__init__(out, config, client=None, fresh=fresh, log=log, progress=progress)
        self.cfg: ReproConfig = config
        self.capture, self.device, self.budget_s = capture, device, float(budget_s)  # (device: Demo's, the models')
        self.t0 = time.perf_counter()
        self._relit: dict[str, list[dict[str, Any]]] = {}  # the relights finished so far, "object/backend": rows

    # --- budget ------------------------------------------------------------------------------------

    def spent_s(self) -> float:
        """Seconds of this run's budget spent (a rerun resumes with a budget of its own; the steps it skips
        keep the seconds they took in the report)."""
        return time.perf_counter() - self.t0

    def left_s(self) -> float:
        return self.budget_s - self.spent_s()

    def step(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        if name != "report" and self._done(name) is None and self.left_s() <= 0:
            result = {"status": "not available", "seconds": 0.0, "skipped": "budget",
                      "reason": f"not run: the budget of {self.budget_s:.0f} s was spent ({self.spent_s():.0f} s)"}
            self.results[name] = result
            self.log(f"[{name}] {result['reason']}")
            return result
        result = super().step(name, fn)
        if name != "report":
            self.write_report()  # what is finished is on disk even if the run is stopped from outside
        return result

    def _device_kind(self) -> str:
        """``"cuda"`` or ``"cpu"``: the kind of device the models run on, which the run's planning constants are by."""
        from sssphase_core.compute import compute_device

        return "cuda" if compute_device(self.device).type == "cuda" else "cpu"

    def _plan(self, stage: int, patches: int, most: int) -> tuple[int, float]:
        """(epochs, seconds) for training stage ``stage`` (0: pretrain psp, 1: imagenet, 2: decoder): its share of
        the time left, and the epochs that fit in it at the throughput a pretraining of this run reached (before
        any: :data:`PLANNED_RATE`). The seconds also bound the training loop (``time_limit_s``): the rate is a
        guess (the decoder ran at 0.63 of pretraining's patches/s on the H200), the deadline is kept."""
        measured = [r["patches_s"] for n, r in self.results.items() if n.startswith("pretrain_") and r.get("patches_s")
                    and not r.get("resumed")]  # this run's own throughput, once a stage has run
        rate = min(measured) if measured else PLANNED_RATE.get((self._device_kind(), self.cfg.model), 100.0)
        shares = self.cfg.train_shares[stage:]
        seconds = max(0.0, self.left_s() - self.cfg.eval_reserve_s) * shares[0] / sum(shares)
        return epochs_within(seconds, patches, rate, most), seconds

    @staticmethod
    def _time_left(deadline: float) -> float:
        """Seconds until ``deadline`` (a perf_counter time), at least one: the loop always runs one epoch."""
        return max(1.0, deadline - time.perf_counter())

    # --- steps -------------------------------------------------------------------------------------

    def _request(self, obj: str, root: Path, views: int, **kw: Any) -> Any:
        from sssphase_core.capture import CaptureRequest

        sim = {"device": self.device} if self.device != "cpu" else {}
        return CaptureRequest(obj, views=views, resume=True, out=root, seed=self.cfg.seed, preset=self.cfg.rig_preset,
                              sim_options=sim, **kw)

    def _test_requests(self) -> list[Any]:
        root = self.out / "sessions" / "test"
        return [self._request(o, root, self.cfg.test_view + 1, references=self.cfg.references) for o in self.cfg.test_objects]

    def train_sessions(self) -> dict[str, Any]:
        """The training sessions, and the unseen ones captured at the same time (the captures run side by side)."""
        root = self.out / "sessions" / "train"
        reqs = [self._request(o, root, self.cfg.train_views, footprints=True, dot_stride=self.cfg.dot_stride)
                for o in self.cfg.train_objects]
        tests = self._test_requests() if self._done("test_sessions") is None else []
        paths = self.capture(reqs + tests)
        self._tests_captured = paths[len(reqs):]
        return {"root": str(root), "sessions": paths[: len(reqs)]}

    def test_sessions(self) -> dict[str, Any]:
        reqs = self._test_requests()
        paths = getattr(self, "_tests_captured", None) or self.capture(reqs)
        return {"root": str(self.out / "sessions" / "test"), "sessions": paths}

    def _pretrain(self, augment: str, stage: int) -> dict[str, Any]:
        from sssphase_core.learning.backends import get_backend
        from sssphase_core.learning.training import PretrainConfig

        c, t0 = self.cfg, time.perf_counter()
        views = self.train_views(footprints=False)
        patches = sum(len(v.pixels) for v in views)
        epochs, seconds = self._plan(stage, patches, c.pretrain_epochs)
        cfg = PretrainConfig(epochs=epochs, batch_size=min(c.pretrain_batch, patches), seed=c.seed, preset=c.model,
                             augment=augment, warmup_epochs=min(1.0, epochs / 2), device=self.device, knn_monitor=0,
                             time_limit_s=self._time_left(t0 + seconds))
        run = self.out / "runs" / f"pretrain_{augment}"
        path = get_backend("torch").pretrain(views, run, config=cfg, progress=self.progress)
        return {"checkpoint": str(path), **self._trained(run, "pretrain", epochs, patches, cfg.batch_size)}

    def pretrain_psp(self) -> dict[str, Any]:
        return self._pretrain("psp", 0)

    def pretrain_imagenet(self) -> dict[str, Any]:
        return self._pretrain("imagenet", 1)

    def decoder(self) -> dict[str, Any]:
        self._need("pretrain_psp")
        from sssphase_core.learning.backends import get_backend
        from sssphase_core.learning.training import DecoderConfig

        c, t0 = self.cfg, time.perf_counter()
        views = self.train_views()
        patches = sum(len(v.pixels) for v in views)
        epochs, seconds = self._plan(2, patches, c.decoder_epochs)
        cfg = DecoderConfig(epochs=epochs, batch_size=min(c.decoder_batch, patches), seed=c.seed, device=self.device,
                            time_limit_s=self._time_left(t0 + seconds))
        run = self.out / "runs" / "decoder"
        path = get_backend("torch").fit(views, run, encoder=self.results["pretrain_psp"]["checkpoint"], config=cfg,
                                        progress=self.progress)
        return {"checkpoint": str(path), **self._trained(run, "decoder", epochs, patches, cfg.batch_size)}

    def _trained(self, run: Path, stage: str, planned: int, patches: int, batch: int) -> dict[str, Any]:
        """What a training stage did: the epochs it ran (of those planned: the time limit may end it early),
        the loop's patches/s (all its time) and the model FLOPs utilisation against the device's datasheet bf16
        peak (:mod:`sssphase_core.learning.flops`)."""
        from sssphase_core.learning.flops import datasheet_peak, training_flops_per_patch
        from sssphase_core.learning.runlog import METRICS, read_rows

        rows = read_rows(run / METRICS)
        out: dict[str, Any] = {"epochs": int(rows[-1]["epoch"]) if rows else 0, "planned_epochs": planned,
                               "patches": patches, "batch": batch}
        if not rows or not rows[-1].get("wall_s"):
            return out
        rate = int(rows[-1]["step"]) * batch / float(rows[-1]["wall_s"])
        flops = training_flops_per_patch(self.cfg.model, stage)
        peak = datasheet_peak(self.environment()["device"])
        return {**out, "patches_s": round(rate, 1), "gflop_per_patch": round(flops / 1e9, 2),
                "mfu": None if peak is None else round(flops * rate / peak, 4)}

    def footprints(self) -> dict[str, Any]:
        """Table 1: the unseen objects' footprints against the simulator's exact ones (the demo's step), and
        whether LPIPS could be computed."""
        from sssphase_core.learning import lpips

        return {**super().footprints(), "lpips": lpips.available()[1] or "computed"}

    def knn(self) -> dict[str, Any]:
        """Table 2: kNN accuracy per object (view-level leave-one-out) of both encoders."""
        from sssphase_core.learning.evaluation import knn_of_views
        from sssphase_core.learning.training import load_encoder

        views = self.train_views(footprints=False)
        objects = list(self.cfg.train_objects)
        k = min(20, sum(len(v.pixels) for v in views) // 4 or 1)
        out: dict[str, Any] = {"k": k}
        for augment in self.cfg.augments:
            run = self.results.get(f"pretrain_{augment}", {})
            if run.get("status") != "done":
                out[augment] = {"status": "not available", "reason": f"pretrain_{augment} is {run.get('status', 'missing')}"}
                continue
            res = knn_of_views(load_encoder(run["checkpoint"]), views, objects, ks=(k,), device=self.device)[k]
            out[augment] = {"overall": res["overall"], "per_class": res["per_class"]}
        if not any("overall" in v for v in out.values() if isinstance(v, dict)):
            raise NotAvailable("no pretrained encoder to evaluate")
        return out

    def relight(self) -> dict[str, Any]:
        """The demo's relight step within the budget: relights the budget left out make it "partial", so that a
        rerun (with a budget of its own) does them and keeps the others."""
        out = super().relight()
        left = [key for key, why in out["skipped"].items() if why.startswith(BUDGET_SPENT)]
        if left:
            out["status"] = "partial"
            out["reason"] = f"{', '.join(left)} left to the budget: a rerun relights them"
        return out

    def _relight_progress(self, units: dict[str, list[dict[str, Any]]], skipped: dict[str, str]) -> None:
        """The relights finished so far go into the report at once (a run stopped from outside keeps them) and
        time the next ones (:meth:`relight_estimate_s`)."""
        self._relit = dict(units)
        self.results["relight"] = {"status": "running", "rows": [r for rows in units.values() for r in rows],
                                   "skipped": dict(skipped),
                                   "seconds": sum(float(rows[0].get("unit_seconds", 0.0)) for rows in units.values() if rows)}
        self.write_report()

    def relight_estimate_s(self, backend: str, pixels: int) -> float:
        """Seconds a relight of a view with ``pixels`` lit pixels will take with ``backend``: per lit pixel, as
        long as the slowest relight with it so far; before any, :data:`RELIGHT_OVER_FOOTPRINTS` (of the device's kind)
        times the seconds per footprint of its model(s) in the footprints step (a blend runs both); else the longest relight so far.
        At least :data:`RELIGHT_MIN_S`."""
        def unit_s(rows: list[dict[str, Any]]) -> float:  # the relight's, the scoring's and the figures' seconds
            return float(rows[0].get("unit_seconds") or sum(float(r["seconds"]) for r in rows))

        same = [unit_s(rows) / max(1, int(rows[0]["lit_pixels"])) for key, rows in self._relit.items()
                if key.rsplit("/", 1)[-1] == backend and rows]
        per_footprint = self.results.get("footprints", {}).get("seconds_per_pixel") or {}
        models = BLENDS.get(backend, (backend,))
        if same:
            guess = max(same) * pixels
        elif all(m in per_footprint for m in models):
            guess = RELIGHT_OVER_FOOTPRINTS[self._device_kind()] * sum(float(per_footprint[m]) for m in models) * pixels
        else:
            guess = max((unit_s(rows) for rows in self._relit.values() if rows), default=0.0)
        return max(RELIGHT_MIN_S, guess)

    def _may_relight(self, backend: str, pixels: int) -> str | None:
        """A relight starts only if its estimate (:meth:`relight_estimate_s`) fits in what is left of the budget."""
        need = self.relight_estimate_s(backend, pixels)
        if self.left_s() <= need:
            return (f"{BUDGET_SPENT} ({max(self.left_s(), 0):.0f} s left, a relight with {backend} of "
                    f"{pixels:,} pixels would take about {need:.0f} s)")
        return None

    # --- report ------------------------------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        path = self.write_report()
        return {"path": str(path)}

    def write_report(self) -> Path:
        """``report.md`` and ``report.json`` from the steps finished so far."""
        from sssphase_core.reporting.repro_report import repro_markdown

        self.report_dir.mkdir(parents=True, exist_ok=True)
        info = self.environment()
        data = {"config": asdict(self.cfg), "device": self.device, "budget_s": self.budget_s,
                "spent_s": round(self.spent_s(), 1), "environment": info, "steps": self.results,
                "paper": {"table1": PAPER_TABLE1, "table2": PAPER_TABLE2, "scale": PAPER_SCALE}}
        write_text(self.report_dir / "report.json", json.dumps(data, indent=1, default=str))
        path = self.report_dir / "report.md"
        write_text(path, repro_markdown(data))
        return path

    def environment(self) -> dict[str, Any]:
        import os
        import platform

        import torch

        from sssphase_core.compute import compute_device

        dev = compute_device(self.device)
        name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or "CPU"
        return {"device": f"{name} ({dev})", "torch": torch.__version__, "cpu_cores": os.cpu_count()}

    def run(self) -> Path:
        for name in STEPS:
            if name == "report":
                self.fresh_report()  # it reflects every step, newly finished ones included
            self.step(name, getattr(self, name))
        self.write_report()  # with the report step's own record
        return self.report_dir / "report.md"


MAX_BUDGET_S = 30 * 86400.0  # a month


def check_repro_options(out: Path | str, preset: str, device: str, budget_s: float) -> None:
    """Refuse, in one line before any work, an unknown preset or device, a budget that is no positive number
    of seconds, or an ``out`` that cannot hold the run."""
    if preset not in PRESETS:
        raise InputError(f"unknown repro preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if not (math.isfinite(budget_s) and 0 < budget_s <= MAX_BUDGET_S):  # (1e308 overflowed a timer after the report)
        raise InputError(f"--budget must be a number of seconds in (0, {MAX_BUDGET_S:g}], got {budget_s:g}")
    from sssphase_core.compute import check_device
    from sssphase_core.store.session import check_output_folder

    check_device(device)
    check_output_folder(out)


def run_repro(out: Path | str, capture: Capture, *, preset: str = "paper", device: str = "auto", budget_s: float = 480.0,
              fresh: bool = False, log: Callable[[str], None] = print,
              progress: Callable[[str, int, int, str], None] | None = None, **overrides: Any) -> Path:
    """Run (or resume) ``sss repro paper`` into ``out``; returns the report's path. ``overrides``: fields of the
    preset's :class:`ReproConfig` (objects, views, sizes)."""
    check_repro_options(out, preset, device, budget_s)
    config = replace(PRESETS[preset], **overrides)
    repro = PaperRepro(Path(out), config, capture, device=device, budget_s=budget_s, fresh=fresh, log=log, progress=progress)
    repro.report_dir = Path(out)
    path = repro.run()
    log(f"repro finished in {repro.spent_s():.1f} s of a {budget_s:.0f} s budget")
    repro.raise_unless_done(("train_sessions", "test_sessions"), path)  # later steps may be left to the budget
    return path
