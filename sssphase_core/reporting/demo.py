"""`sss demo`: the user's path end to end on the simulated rig, resumable step by step.

Everything goes through what a lab runs: the daemon, sessions, training from sessions.

Steps (each writes ``<out>/steps/<name>.json`` when done and is skipped on the next run):

1. ``train_sessions`` capture the training objects through the daemon into ``<out>/sessions/train``:
   PSP, unwrapping set, white, black and dot grids, whose crops become the captured footprints;
2. ``test_sessions``  capture the unseen objects into ``<out>/sessions/test`` with reference patterns
   (checkerboard, stripes); the sim rig also stores its noise-free renders, used for scoring only;
3. ``pretrain``       SimSiam pretraining of the encoder on the training sessions' PSP patches;
4. ``decoder``        the footprint decoder on the frozen encoder, trained on the captured crops;
5. ``relight``        relight the unseen objects under the reference patterns with every backend and
   evaluate against the noise-free renders (GT / relit / difference figures);
6. ``footprints``     footprint metrics of the model backends against the simulator's exact footprints;
7. ``knn`` and ``pca`` the paper-style kNN table and PCA-RGB maps of the embeddings;
8. ``report``         ``<out>/report/index.html``.

The simulator's exact footprints appear only as the ``exact`` row (ground truth no lab has) and in
the footprint metrics. A step whose prerequisites are missing is recorded as not available with the
reason, and the report says so.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import DataError, InputError, SssError
from sssphase_core.store.files import write_text
from sssphase_core.store.session import DamagedArray

#: What a kept relight row must hold to be reused (the report reads these).
ROW_KEYS = frozenset({"object", "view", "pattern", "backend", "psnr", "ssim", "seconds", "lit_pixels", "figure"})
#: The footprints step times its models on the pixels after these (the first call loads a model, warms a device).
WARM_UP_PIXELS = 8


@dataclass(frozen=True)
class DemoConfig:
    train_objects: tuple[str, ...]
    test_objects: tuple[str, ...]
    train_views: int = 2  # turntable views captured per training object (0 and 180 degrees)
    test_view: int = 0  # the one view captured per unseen object
    pixels_per_view: int = 600
    pretrain_epochs: int = 3
    pretrain_batch: int = 64
    decoder_epochs: int = 3
    decoder_batch: int = 32
    references: tuple[str, ...] = ("checkerboard", "stripes_x")
    backends: tuple[str, ...] = ("none", "analytic", "torch", "blend", "exact")  # blend: `sss relight`'s default with a decoder
    analytic_supersample: int = 2
    pca_stride: int = 2
    footprint_pixels: int = 200
    model: str = "lite"
    seed: int = 0
    dot_stride: int = 1  # dot grids every S-th shift: footprint crops for 1/S^2 of the pixels, from 1/S^2 of the frames

    def pretrain_config(self, **changes: Any):  # noqa: ANN201  (PretrainConfig: torch is imported lazily)
        """The demo's pretraining recipe (``PretrainConfig``), with ``changes`` (e.g. another seed)."""
        from sssphase_core.learning.training import PretrainConfig

        return PretrainConfig(**{"epochs": self.pretrain_epochs, "batch_size": self.pretrain_batch, "seed": self.seed,
                                 "preset": self.model, "warmup_epochs": min(1.0, self.pretrain_epochs / 2),
                                 "device": "cpu", **changes})


PRESETS = {
    # Under 5 minutes on 2 CPU cores: 10 footprint views captured through the daemon (~10 s each),
    # 4000 training patches, 2 SimSiam epochs, 3 decoder epochs on the captured crops; the unseen
    # objects are the two smallest (crab, sand rake), every valid pixel run through the network.
    "lite": DemoConfig(("apple", "pear", "orange", "star", "shovel"), ("crab", "sand_rake"), pixels_per_view=400,
                       pretrain_epochs=2, pretrain_batch=32, decoder_epochs=3),
    "tiny": DemoConfig(("apple", "star"), ("sand_rake",), pixels_per_view=8, pretrain_epochs=1, pretrain_batch=32,
                       decoder_epochs=1, decoder_batch=16, backends=("none", "torch", "exact"), pca_stride=4,
                       footprint_pixels=32, dot_stride=4),  # 8 pixels a view need no full dot grid
}

STEPS = ("train_sessions", "test_sessions", "pretrain", "decoder", "relight", "footprints", "knn", "pca", "report")
#: The steps of the user's path: a demo without any of them failed, whatever its report shows
USERS_PATH = ("train_sessions", "test_sessions", "pretrain", "decoder", "relight")
_RIGS_STAMP = {"nominal": "", "camera": ", training cameras randomised", "randomised": ", training rigs randomised"}
#: The rigs the demo's training objects are captured on (the unseen ones: always the nominal rig).
TRAINING_RIGS = tuple(_RIGS_STAMP)
_RIGS_REPORT = {"nominal": "", "camera": "; every training object captured by its own randomised camera and projector "
                "(sim.randomised_rig_options, what=\"camera\")",
                "randomised": "; every training object captured on its own randomised rig (sim.randomised_rig_options)"}


class NotAvailable(Exception):
    """A step that cannot run in this build (its reason goes into the report)."""


class Demo:
    """Runs the steps in order; ``log`` receives one line per event (the CLI prints them)."""

    def __init__(self, out: Path, config: DemoConfig, client: Any, *, fresh: bool = False,
                 log: Callable[[str], None] = print, progress: Callable[[str, int, int, str], None] | None = None,
                 transport: str | None = None, training_rigs: str = "nominal", three_chip: bool = False):
        """``client``: a daemon client (``sssphase_daemon.client``; anything with ``call`` and ``capture``);
        ``progress``: the training loops' step callback (``training.StepProgress``); ``transport``:
        the sim rig's light-transport model (None: burley); ``training_rigs`` (:data:`TRAINING_RIGS`): each
        training object captured on the nominal rig (the default), by its own randomised camera and projector
        (``sim.randomised_rig_options(..., what="camera")``: projector response, lens blur, noise, exposure,
        demosaicing), or on its own randomised rig (the transport model drawn too); the unseen objects always on
        the nominal one (docs/benchmarks/standins.md measures the three); ``three_chip``: every object is
        captured by a three-chip sim camera (nothing demosaiced). All are fixed for a demo folder."""
        self.out, self.cfg, self.client, self.fresh, self.log = Path(out), config, client, fresh, log
        self.progress = progress
        self._psp_read: dict[tuple[str, int], Any] = {}  # the training views' PSP stacks, read once for every step
        self.report_dir = self.out / "report"  # index.html and img/
        self.steps_dir = self.out / "steps"
        self.steps_dir.mkdir(parents=True, exist_ok=True)
        _check_training_rigs(training_rigs)
        self.transport, self.training_rigs, self.three_chip = transport or "burley", training_rigs, three_chip
        physics = (self.transport + _RIGS_STAMP[training_rigs] + (", three-chip camera" if three_chip else ""))
        stamp = self.steps_dir / "transport.txt"
        if stamp.exists() and not fresh and stamp.read_text().strip() != physics:
            raise InputError(f"{self.out} was made with the simulator's {stamp.read_text().strip()!r} physics, this run "
                             f"asks for {physics!r}: use another --out, or --fresh")
        write_text(stamp, physics)
        self.report_rig = (f"Simulated rig (CPU preset), {self.transport.replace('_', ' ')} transport"
                           + _RIGS_REPORT[training_rigs]
                           + ("; a three-chip camera (no colour filter array)" if three_chip else ""))
        self.results: dict[str, dict[str, Any]] = {}
        self.device = "cpu"  # where the models relight and embed (sss repro paper: the GPU)

    def raise_unless_done(self, names: tuple[str, ...], report: Path) -> None:
        """A DataError naming the steps of ``names`` that failed (each one's reason was logged; a step left out by
        the run's budget is not a failure), so that a run whose sessions or models failed does not exit as a success."""
        missing = [n for n in names if self.results.get(n, {}).get("status") != "done"
                   and not self.results.get(n, {}).get("skipped")]
        if missing:
            raise DataError(f"steps {', '.join(missing)} did not run (their reasons are above): {report} lacks what "
                            "they make")

    def _done(self, name: str) -> dict[str, Any] | None:
        path = self.steps_dir / f"{name}.json"
        if self.fresh or not path.exists():
            return None
        result = json.loads(path.read_text())
        return result if result.get("status") == "done" else None

    def step(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        done = self._done(name)
        if done is not None:
            self.log(f"[{name}] already done ({done['seconds']:.1f} s), skipped")
            self.results[name] = {**done, "resumed": True}
            return done
        self.log(f"[{name}] running")
        t0 = time.perf_counter()
        try:
            result = {"status": "done", **fn()}
        except DamagedArray:  # damaged data stops the run in one line (`sss validate` lists it), not reported as lacking
            raise
        except (NotAvailable, SssError) as exc:  # what the step lacks (or a user's data cannot give) is reported
            result = {"status": "not available", "reason": str(exc)}
        except ModuleNotFoundError as exc:  # an optional extra that is not installed; any other error is a bug: raised
            result = {"status": "not available", "reason": f"needs the {exc.name} package, which is not installed"}
        result["seconds"] = time.perf_counter() - t0
        write_text(self.steps_dir / f"{name}.json", json.dumps(result, indent=1, default=str))
        self.log(f"[{name}] {result['status']} in {result['seconds']:.1f} s" + (f": {result.get('reason')}" if result["status"] != "done" else ""))
        self.results[name] = result
        return result

    def _need(self, *names: str) -> None:
        for n in names:
            if self.results.get(n, {}).get("status") != "done":
                raise NotAvailable(f"needs step {n!r}, which is {self.results.get(n, {}).get('status', 'missing')}")

    # --- steps -------------------------------------------------------------------------------

    def _capture(self, obj: str, root: Path, views: int, *, rigs: str = "nominal", **kw: Any) -> str:
        from sssphase_core.capture import CaptureRequest, run_capture

        physics: dict[str, Any] = {"transport": self.transport}
        if rigs != "nominal":
            from sssphase_core.sim import randomised_rig_options

            what = "rig" if rigs == "randomised" else "camera"  # a drawn rig brings its own transport model
            drawn = randomised_rig_options(self.cfg.seed, obj, what=what)
            physics = {"transport": None if what == "rig" else self.transport, "sim_options": drawn}
            self.log(f"  {obj}: randomised {what} " + ", ".join(f"{k} {v}" for k, v in drawn.items()))
        if self.three_chip:
            physics["sim_options"] = {**physics.get("sim_options", {}), "demosaic": "none"}
        req = CaptureRequest(obj, views=views, resume=True, out=root, seed=self.cfg.seed, **physics, **kw)
        session = run_capture(self.client, req)
        self.log(f"  captured {obj}: {len(session.views())} view(s) in {session.path}")
        return str(session.path)

    def train_sessions(self) -> dict[str, Any]:
        root = self.out / "sessions" / "train"
        paths = [self._capture(o, root, self.cfg.train_views, footprints=True, rigs=self.training_rigs,
                               dot_stride=self.cfg.dot_stride) for o in self.cfg.train_objects]
        return {"root": str(root), "sessions": paths}

    def test_sessions(self) -> dict[str, Any]:
        root = self.out / "sessions" / "test"
        paths = [self._capture(o, root, self.cfg.test_view + 1, references=self.cfg.references)
                 for o in self.cfg.test_objects]
        return {"root": str(root), "sessions": paths}

    def train_views(self, footprints: bool = True):
        """The training sessions' views (PSP patches, and captured footprint crops with ``footprints``)."""
        from sssphase_core.learning.data import session_views

        self._need("train_sessions")
        c = self.cfg
        return session_views(self.results["train_sessions"]["root"], c.train_objects, pixels_per_view=c.pixels_per_view,
                             footprints=footprints, seed=c.seed, psp_cache=self._psp_read)

    def pretrain(self) -> dict[str, Any]:
        from sssphase_core.learning.backends import get_backend

        path = get_backend("torch").pretrain(self.train_views(footprints=False), self.out / "runs" / "pretrain",
                                             config=self.cfg.pretrain_config(), progress=self.progress)
        return {"checkpoint": str(path)}

    def decoder(self) -> dict[str, Any]:
        self._need("pretrain")
        from sssphase_core.learning.backends import get_backend
        from sssphase_core.learning.training import DecoderConfig

        c = self.cfg
        cfg = DecoderConfig(epochs=c.decoder_epochs, batch_size=c.decoder_batch, seed=c.seed, device="cpu")
        path = get_backend("torch").fit(self.train_views(), self.out / "runs" / "decoder",
                                        encoder=self.results["pretrain"]["checkpoint"], config=cfg, progress=self.progress)
        return {"checkpoint": str(path)}

    def _decoder_checkpoint(self) -> str | None:
        """The decoder step's checkpoint, when that step is done."""
        d = self.results.get("decoder", {})
        return d.get("checkpoint") if d.get("status") == "done" else None

    def _may_relight(self, backend: str, pixels: int) -> str | None:
        """Why no further relight (of ``pixels`` lit pixels with ``backend``) may start (None: it may); the demo
        has no budget."""
        return None

    # The relights finished so far, one file for the step: a run stopped in the middle of the relight step (a
    # 1080p view takes minutes per backend) keeps them, and the next run relights only the rest.
    RELIT_SO_FAR = "relight_partial.json"

    def _model_identity(self, ckpt: str | None) -> str | None:
        """What a decoder's relights were made with: the footprint caches' tag of its checkpoint (path and
        modification time: a decoder trained again makes them stale)."""
        from sssphase_core.relight.cache import model_tag

        return model_tag(ckpt) if ckpt is not None and Path(ckpt).exists() else None

    def _relit_so_far(self, ckpt: str | None) -> dict[str, list[dict[str, Any]]]:
        """``{"object/backend": rows}`` of the relights an earlier, stopped run finished (none with ``fresh``;
        a decoder backend's only if the decoder is the same)."""
        from sssphase_core.relight.choices import uses_decoder

        path = self.steps_dir / self.RELIT_SO_FAR
        if self.fresh or not path.exists():
            return {}
        try:
            kept = json.loads(path.read_text())
            units = {str(k): list(rows) for k, rows in kept["units"].items()}
            if not all(rows and all(isinstance(r, dict) and ROW_KEYS <= r.keys() for r in rows) for rows in units.values()):
                raise ValueError("rows lack the report's keys")
        except (ValueError, KeyError, TypeError, AttributeError):  # damaged, or of another version: relight again
            self.log(f"  {path} is unreadable: its relights are done again")
            return {}
        same = kept.get("decoder") == self._model_identity(ckpt)
        return {k: rows for k, rows in units.items() if same or not uses_decoder(k.rsplit("/", 1)[-1])}

    def _keep_relit(self, ckpt: str | None, units: dict[str, list[dict[str, Any]]], skipped: dict[str, str]) -> None:
        """Save the relights finished so far (atomically) and show them as the step's progress."""
        write_text(self.steps_dir / self.RELIT_SO_FAR,
                   json.dumps({"decoder": self._model_identity(ckpt), "units": units}, indent=1, default=str))
        self._relight_progress(units, skipped)

    def _relight_progress(self, units: dict[str, list[dict[str, Any]]], skipped: dict[str, str]) -> None:
        """Called with the relights kept so far (``{"object/backend": rows}``) as each one finishes (``sss repro
        paper`` rewrites its report with them and times the next from them)."""

    def relight(self) -> dict[str, Any]:
        """Relight every unseen object under its reference patterns with every backend, scored against the
        references. Each object × backend is kept as it finishes (:attr:`RELIT_SO_FAR`), so that a stopped run
        resumes after the last one."""
        self._need("test_sessions")
        from sssphase_core.relight import load_view
        from sssphase_core.relight.choices import uses_decoder
        from sssphase_core.relight.evaluation import evaluate_view
        from sssphase_core.store.session import Session

        img_dir = self.report_dir / "img"
        skipped: dict[str, str] = {}
        ckpt = self._decoder_checkpoint()
        units = self._relit_so_far(ckpt)
        if units:
            self.log(f"  {len(units)} relight(s) kept from an earlier run: " + ", ".join(units))
            self._relight_progress(units, skipped)
        order: list[str] = []  # the report's: object by object, the backends as configured
        for path in self.results["test_sessions"]["sessions"]:
            session = Session.open(path)
            rv = None  # loaded only if one of its relights is left (a 1080p view takes a while)
            for b in self.cfg.backends:
                key = f"{session.name}/{b}"
                order.append(key)
                if key in units:
                    continue
                if uses_decoder(b) and ckpt is None:
                    skipped[b] = "no decoder checkpoint (the decoder step is not available)"
                    continue
                rv = rv if rv is not None else load_view(session, self.cfg.test_view)
                if (why := self._may_relight(b, int(rv.proj.mask.sum()))) is not None:
                    skipped[key] = why
                    continue
                t0 = time.perf_counter()
                try:
                    opts = {"supersample": self.cfg.analytic_supersample} if b == "analytic" else {}
                    rows = evaluate_view(rv, b, img_dir, checkpoint=ckpt, device=self.device, **opts)
                except DamagedArray:  # damage stops the run in one line (see `step`), never a "skipped" backend
                    raise
                except (NotAvailable, SssError) as exc:  # e.g. no captured transport for `measured`
                    skipped[b] = str(exc)
                    self.log(f"  {rv.object} with {b}: skipped ({exc})")
                    continue
                for r in rows:
                    r["figure"] = str(Path(r["figure"]).relative_to(self.report_dir))
                    r["unit_seconds"] = round(time.perf_counter() - t0, 2)  # its patterns' relight, scoring, figures
                units[key] = rows
                self._keep_relit(ckpt, units, skipped)
                self.log(f"  relit {rv.object} with {b} in {rows[0]['unit_seconds']:.1f} s")
        rows = [r for key in order for r in units.get(key, [])]
        from sssphase_core.relight.evaluation import training_overlap

        seen = training_overlap(ckpt, [(r["object"], r["view"]) for r in rows]) if ckpt is not None else None
        return {"rows": rows, "skipped": skipped, "analytic_supersample": self.cfg.analytic_supersample,
                "training_overlap": seen}

    def footprints(self) -> dict[str, Any]:
        """The paper's Table 1: footprint MSE / PSNR / SSIM on sampled pixels of the unseen objects."""
        self._need("test_sessions")
        from sssphase_core.learning.data import sample_pixels
        from sssphase_core.learning.evaluation import footprint_metrics, summarise
        from sssphase_core.relight import load_view, make_source
        from sssphase_core.relight.engine import footprint_array
        from sssphase_core.store.session import Session

        ckpt = self._decoder_checkpoint()
        backends = [b for b in self.cfg.backends if b in ("analytic", "torch") and (b != "torch" or ckpt)]
        if not backends:  # (it said "done" and the report "the step did not run")
            raise NotAvailable("no footprint model among the backends: the table scores analytic and torch footprints")
        table: dict[str, dict[str, dict[str, float]]] = {}
        rate: dict[str, list[float]] = {}
        inference: dict[str, str] = {}  # the decoder's precision (bf16 where the device computes it natively)
        for path in self.results["test_sessions"]["sessions"]:
            rv = load_view(Session.open(path), self.cfg.test_view)
            if rv.sim is None:
                raise NotAvailable(f"{rv.object} is not a simulated session: footprint metrics need the simulator's "
                                   "exact footprints (relit images are scored against the reference captures above)")
            px = sample_pixels(rv.proj.mask, self.cfg.footprint_pixels, self.cfg.seed)
            gt = rv.scene().footprints(px)
            table[rv.object] = {}
            for b in backends:
                opts = {"supersample": self.cfg.analytic_supersample} if b == "analytic" else {}
                source, _ = make_source(b, rv, checkpoint=ckpt, calibrate=False, device=self.device,
                                        **opts)  # the model's own footprints
                if (precision := getattr(getattr(source, "backend", None), "precision", None)) is not None:
                    inference[b] = precision
                first = footprint_array(source(px[:WARM_UP_PIXELS]))  # (loading, a device's first call)
                t0 = time.perf_counter()
                rest = footprint_array(source(px[WARM_UP_PIXELS:]))  # (on the host: a GPU's work is done)
                rate.setdefault(b, []).append((time.perf_counter() - t0) / max(1, len(px) - WARM_UP_PIXELS))
                table[rv.object][b] = summarise(footprint_metrics(np.concatenate([first, rest]), gt))
        # the slowest object's seconds per footprint after a warm-up: what a relight of a whole view costs
        return {"metrics": table, "backends": backends, "pixels": self.cfg.footprint_pixels,
                "seconds_per_pixel": {b: max(v) for b, v in rate.items()}, "inference": inference}

    def knn(self) -> dict[str, Any]:
        self._need("pretrain")
        if len(self.cfg.train_objects) < 2:
            raise NotAvailable("the kNN table needs training sessions of at least two objects")
        from sssphase_core.learning.evaluation import knn_of_views
        from sssphase_core.learning.training import initial_encoder, load_encoder

        vds = self.train_views(footprints=False)
        k = min(20, sum(len(v.pixels) for v in vds) // 4 or 1)
        checkpoint, objects = self.results["pretrain"]["checkpoint"], list(self.cfg.train_objects)
        result = knn_of_views(load_encoder(checkpoint), vds, objects, ks=(k,))[k]
        # the baseline measured in the same run: the encoder pretraining started from (its random initialisation;
        # unknown for an encoder taken from a decoder run)
        try:
            start = knn_of_views(initial_encoder(checkpoint), vds, objects, ks=(k,))[k]
        except DataError:
            return result
        result["initial"] = {"overall": start["overall"], "per_class": start["per_class"]}
        return result

    def pca(self) -> dict[str, Any]:
        self._need("pretrain", "test_sessions")
        from sssphase_core.learning.evaluation import PCA_TITLE, pca_maps
        from sssphase_core.learning.training import load_encoder
        from sssphase_core.reporting.figures import panels_figure
        from sssphase_core.store.session import Session

        enc = load_encoder(self.results["pretrain"]["checkpoint"])
        sessions = [Session.open(p) for p in self.results["test_sessions"]["sessions"]]
        view = self.cfg.test_view
        maps = pca_maps(enc, [(s.load(view, "psp"), np.argwhere(s.load(view, "corr/mask").astype(bool))) for s in sessions],
                        self.cfg.pca_stride)
        panels_figure(self.report_dir / "img" / "pca_rgb.png", maps, [f"{s.name}, view {view}" for s in sessions],
                      f"{PCA_TITLE} (one pixel in {self.cfg.pca_stride} along x and y)")
        return {"figure": "img/pca_rgb.png", "objects": [s.name for s in sessions]}

    report_title = "sssphase demo report"
    report_rig = "Simulated rig (CPU preset)"
    report_config: dict[str, Any] | None = None  # the report's Configuration table (default: the demo's settings)

    def report(self) -> dict[str, Any]:
        from sssphase_core.reporting.report import write_report

        config = self.report_config if self.report_config is not None else asdict(self.cfg)
        path = write_report(self.report_dir, self.results, config, title=self.report_title, rig=self.report_rig)
        return {"path": str(path)}

    def run(self) -> Path:
        for name in STEPS:
            if name == "report":
                self.results.pop("report", None)
                self.fresh_report()
            self.step(name, getattr(self, name))
        return self.report_dir / "index.html"

    def fresh_report(self) -> None:
        """The report is rewritten on every run (it reflects all steps, including newly finished ones)."""
        (self.steps_dir / "report.json").unlink(missing_ok=True)


def _check_training_rigs(training_rigs: str) -> None:
    if training_rigs not in TRAINING_RIGS:
        raise InputError(f"unknown training rigs {training_rigs!r}; choose one of {', '.join(TRAINING_RIGS)}")


def check_demo_options(out: Path | str, preset: str, transport: str | None, training_rigs: str = "nominal") -> None:
    """Refuse an unknown preset, transport model or training rigs, and an ``out`` that is a file or lies in a session (each step
    had failed there), in one line before a daemon is started for the demo."""
    if preset not in PRESETS:
        raise InputError(f"unknown demo preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if transport is not None:
        from sssphase_core.sim import TRANSPORTS

        if transport not in TRANSPORTS:
            raise InputError(f"unknown transport model {transport!r}; choose one of {', '.join(TRANSPORTS)}")
    _check_training_rigs(training_rigs)
    from sssphase_core.store.session import check_output_folder

    check_output_folder(out)


def run_demo(out: Path | str, client: Any, *, preset: str = "lite", fresh: bool = False,
             log: Callable[[str], None] = print, progress: Callable[[str, int, int, str], None] | None = None,
             transport: str | None = None, training_rigs: str = "nominal", three_chip: bool = False) -> Path:
    """Run (or resume) the demo into ``out`` with a daemon ``client``; returns the report's path.
    ``progress``: the training loops' step callback (``training.StepProgress``); ``transport``: the
    sim rig's light-transport model (:data:`sssphase_core.sim.TRANSPORTS`; None: burley); ``training_rigs``:
    the training captures' rigs (:data:`TRAINING_RIGS`); ``three_chip``: a three-chip sim camera (see :class:`Demo`)."""
    check_demo_options(out, preset, transport, training_rigs)
    t0 = time.perf_counter()
    demo = Demo(Path(out), PRESETS[preset], client, fresh=fresh, log=log, progress=progress, transport=transport,
                training_rigs=training_rigs, three_chip=three_chip)
    path = demo.run()
    log(f"demo finished in {time.perf_counter() - t0:.1f} s")
    demo.raise_unless_done(USERS_PATH, path)
    return path


REPORT_STEPS = ("relight", "footprints", "knn", "pca", "report")


def _report_config(tests: list[Any], train: list[Any], view: int, backends: tuple[str, ...], pretrain: Path | None,
                   decoder: Path | None) -> dict[str, Any]:
    """What ``sss report`` was given, for its Configuration table: the sessions, their references, the backends,
    and each run's checkpoint with the options it was trained with (the demo's own settings are not these)."""
    from sssphase_core.learning.training.checkpoints import load_checkpoint

    config: dict[str, Any] = {"test_objects": [s.name for s in tests], "train_objects": [s.name for s in train],
                              "test_view": view, "backends": list(backends)}
    refs = sorted({f["key"].removeprefix("ref/") for s in tests for f in s.manifest.get("plan", {}).get("frames", [])
                   if f.get("kind") == "ref"})
    config["references"] = refs or ["none"]
    presets = []
    for role, ckpt in (("pretrain", pretrain), ("decoder", decoder)):
        if ckpt is None:
            config[role] = "not given"
            continue
        saved = load_checkpoint(ckpt, mmap=True)
        options = saved.get("config", {}) if isinstance(saved.get("config"), dict) else {}
        presets.append(str((saved.get("preset") or {}).get("name", "?")))
        config[role] = str(ckpt)
        config |= {f"{role}_{k}": options[k] for k in ("epochs", "batch_size", "lr", "head", "augment") if k in options}
    config["model"] = ", ".join(dict.fromkeys(presets)) or "none given"
    return config


#: The file that marks a folder as written by ``sss report`` (which may write there again).
REPORT_MARK = ".sss-report"


def claim_report_folder(out: Path) -> None:
    """Refuse a report folder that holds anything ``sss report`` did not write there (a demo folder's step
    records, a user's own index.html: both were replaced), then mark it as a report's."""
    if out.is_dir() and not (out / REPORT_MARK).is_file():
        held = next(iter(sorted(out.iterdir())), None)
        if held is not None:
            what = ("a demo folder (its step records would be replaced)" if (out / "steps").is_dir() and
                    ((out / "sessions").exists() or (out / "runs").exists()) else f"a folder that holds {held.name}")
            raise InputError(f"--out {out} is {what}, not a folder `sss report` wrote: write the report into a new or "
                             "empty folder (nothing was written)")
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / REPORT_MARK, "written by sss report; it may write here again\n")


def run_report(out: Path | str, test_sessions: list[Any], *, train_sessions: Path | None = None,
               pretrain: Path | None = None, decoder: Path | None = None, view: int = 0,
               backends: tuple[str, ...] = ("none", "analytic", "measured", "torch"),
               log: Callable[[str], None] = print) -> Path:
    """The demo's report for a user's own sessions and runs: relight ``test_sessions`` (their view
    ``view``, against every reference they hold) with ``backends``, footprint metrics (simulated
    sessions only), the kNN table on ``train_sessions`` and PCA maps with the ``pretrain`` encoder.
    Steps without what they need are listed in the report as not available. Returns its path."""
    from sssphase_core.relight.views import has_captured_transport, has_references
    from sssphase_core.store.session import by_object, find_sessions

    tests = list(test_sessions)
    if not tests:
        raise InputError("sss report needs at least one test session (with reference captures)")
    by_object(tests, purpose="the report names its rows and figures by object; report them separately")
    lacking = [f"{s.path} (complete views: {s.views()})" for s in tests if view not in s.views()]
    if lacking:
        raise InputError(f"view {view} is not complete in " + "; ".join(lacking))
    train = find_sessions([train_sessions]) if train_sessions is not None else []
    objects = tuple(s.name for s in train)
    has_measured = all(has_captured_transport(s.arrays(view))
                       for s in tests if view in s.views())
    chosen = tuple(b for b in backends if (b != "torch" or decoder is not None) and (b != "measured" or has_measured))
    why = {"torch": "no --decoder (a run of `sss train decoder`)",
           "measured": "the sessions hold no captured dot-grid crops (capture with --footprints)"}
    left_out = {b: why[b] for b in backends if b not in chosen}
    if not chosen:  # the report said "done" with no relighting at all
        raise InputError(f"no backend of {', '.join(backends)} can run: torch needs --decoder (a run of `sss train "
                         "decoder`), measured needs sessions captured with --footprints")
    for backend, reason in left_out.items():  # (they were left out of the tables without a word)
        log(f"backend {backend} left out: {reason}")
    bare = [s.name for s in tests if not has_references(s.arrays(view))]
    if bare:
        raise InputError(f"view {view} of {', '.join(bare)} has no reference captures to relight against (capture with "
                         "--reference checkerboard ...)")
    claim_report_folder(Path(out))
    config = DemoConfig(objects, tuple(s.name for s in tests), test_view=view, backends=chosen)
    demo = Demo(Path(out), config, client=None, fresh=True, log=log)
    demo.report_dir = Path(out)  # OUT/index.html (step records in OUT/steps)
    demo.report_title = "sssphase report"
    sims = {"simulated" if "gt/proj_xy" in s.arrays(view) else "captured" for s in tests if view in s.views()}
    demo.report_rig = " and ".join(sorted(sims)).capitalize() + " sessions"
    demo.report_config = _report_config(tests, train, view, chosen, pretrain, decoder)
    if left_out:
        demo.report_config["backends_left_out"] = [f"{b}: {reason}" for b, reason in left_out.items()]
    done = {"status": "done", "seconds": 0.0, "given": True}  # (the user's own sessions and runs: not run here)
    if train:
        demo.results["train_sessions"] = {**done, "root": str(Path(train_sessions)), "sessions": [str(s.path) for s in train]}
    demo.results["test_sessions"] = {**done, "sessions": [str(s.path) for s in tests]}
    if pretrain is not None:
        demo.results["pretrain"] = {**done, "checkpoint": str(pretrain)}
    if decoder is not None:
        demo.results["decoder"] = {**done, "checkpoint": str(decoder)}
    for name in REPORT_STEPS:
        demo.step(name, getattr(demo, name))
    report = demo.report_dir / "index.html"
    relit = demo.results["relight"]
    if relit["status"] != "done" or not relit.get("rows"):  # a report of nothing relit is no success (exit 0 before)
        why = relit.get("reason") or "; ".join(f"{k}: {v}" for k, v in relit.get("skipped", {}).items()) or "no rows"
        raise DataError(f"nothing was relit ({why}); {report} says what each step lacked")
    return report
