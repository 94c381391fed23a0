"""`sss demo`: the whole method end to end on the simulated rig, resumable step by step.

Steps (each writes ``<out>/steps/<name>.json`` when done and is skipped on the next run):

1. ``train_data``   simulate the training objects' PSP captures with exact footprints (npz cache);
2. ``test_sessions`` capture unseen objects into session folders: the full PSP plan (decoded with
   ``sssphase_core.psp.decode``), white, black and reference patterns (checkerboard, stripes),
   plus the simulator's noise-free renders of the references as ground truth;
3. ``pretrain``     SimSiam pretraining of the encoder (torch backend);
4. ``decoder``      fit the footprint decoder on the frozen encoder;
5. ``relight``      relight the unseen objects under the reference patterns with every backend and
   evaluate against the ground truth (GT / relit / difference figures);
6. ``footprints``   footprint metrics of the model backends against the exact footprints (Table 1);
7. ``knn`` and ``pca`` the paper-style kNN table and PCA-RGB maps of the embeddings;
8. ``report``       ``<out>/report/index.html``.

A step whose prerequisites are missing (e.g. the learning code) is recorded as not available
with the reason, and the report says so.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.errors import InputError


@dataclass(frozen=True)
class DemoConfig:
    train_objects: tuple[str, ...]
    train_views: tuple[int, ...]
    test_objects: tuple[str, ...]
    n_views: int = 4
    test_view: int = 1
    pixels_per_view: int = 600
    pretrain_epochs: int = 3
    pretrain_batch: int = 64
    decoder_epochs: int = 3
    decoder_batch: int = 32
    backends: tuple[str, ...] = ("none", "analytic", "torch", "exact")
    analytic_supersample: int = 2
    pca_stride: int = 2
    footprint_pixels: int = 200
    model: str = "lite"
    seed: int = 0


PRESETS = {
    # Under 5 minutes on 2 CPU cores (140 s measured): 4000 training patches, 2 SimSiam epochs,
    # 3 decoder epochs (the reciprocal head's profile generalises better from more patches than from
    # more epochs); the unseen objects are the two smallest at view 1 (crab 2.5k, sand rake 1.4k
    # valid pixels, every one run through the network).
    "lite": DemoConfig(("apple", "pear", "orange", "star", "shovel"), (0, 2), ("crab", "sand_rake"), pixels_per_view=400,
                       pretrain_epochs=2, pretrain_batch=32, decoder_epochs=3),
    "tiny": DemoConfig(("apple", "star"), (0, 2), ("sand_rake",), pixels_per_view=8, pretrain_epochs=1, pretrain_batch=32,
                       decoder_epochs=1, decoder_batch=16, backends=("none", "torch", "exact"), pca_stride=4,
                       footprint_pixels=32),
}

STEPS = ("train_data", "test_sessions", "pretrain", "decoder", "relight", "footprints", "knn", "pca", "report")


class NotAvailable(Exception):
    """A step that cannot run in this build (its reason goes into the report)."""


def _write_patterns(width: int, height: int) -> dict[str, np.ndarray]:
    from sssphase_core.bench.relight_bench import reference_patterns

    return reference_patterns(width, height)


def capture_sim_session(root: Path, obj: str, view: int, n_views: int, seed: int, preset: str = "cpu") -> Path:
    """A session folder for one view of a simulated object (same layout as ``sss capture``)."""
    from sssphase_core.patterns import PlannedFrame, capture_plan
    from sssphase_core.psp import decode
    from sssphase_core.session import Session
    from sssphase_core.sim import SimScene, rig_preset

    cfg = rig_preset(preset)
    scene = SimScene(obj, rig=cfg, view=view, n_views=n_views, seed=seed)
    hp, wp = scene.shape_projector
    plan = capture_plan(wp, hp, references=("white", "black", "checkerboard", "stripes_x"), gamma=cfg.projector.gamma)
    pats = np.stack([f.pattern() for f in plan])
    frames = scene.capture(pats, np.random.default_rng(seed + 7919 * view))
    by_key = dict(zip(plan.keys(), frames, strict=True))
    corr = decode({k: v for k, v in by_key.items() if k.startswith("psp/")}, plan.psp, (wp, hp),
                  saturation=cfg.sensor.saturation(1.0))
    session = Session.create(root, obj, resume=True, n_views=n_views, plan=json.loads(plan.to_json()),
                             rig={"camera": "sim:camera0", "projector": "sim:projector0", "patch": cfg.patch,
                                  "options": {"object": obj, "preset": preset, "seed": seed, "n_views": n_views}})
    w = session.begin_view(view)
    order = [f"psp/{o}/p{float(plan.psp.period):g}/s{n}" for o in ("x", "y") for n in range(plan.psp.n_shifts)]
    w.write("psp", np.stack([by_key[k] for k in order]).astype(np.float32))
    for name in ("xp", "yp", "mask", "reason", "modulation", "offset"):
        w.write(f"corr/{name}", np.asarray(getattr(corr, name)))
    refs = [f for f in plan if f.kind in ("white", "black", "ref")]
    for f in refs:
        w.write(f.key, by_key[f.key].astype(np.float32))
    truth = scene.render(np.stack([PlannedFrame(f.key, f.kind, f.params, 1.0).pattern() for f in refs if f.kind == "ref"]))
    for f, img in zip([f for f in refs if f.kind == "ref"], truth, strict=True):
        w.write(f"gt/render/{f.key.removeprefix('ref/')}", img)
    w.write("gt/proj_xy", scene.proj_xy.astype(np.float32))
    w.write("gt/labels", scene.material.astype(np.int16))
    w.write("gt/mask", scene.mask)
    w.commit({"angle": 360.0 * view / n_views, "coverage": corr.coverage(), "psp_keys": order})
    return session.path


class Demo:
    """Runs the steps in order; ``log`` receives one line per event (the CLI prints them)."""

    def __init__(self, out: Path, config: DemoConfig, *, fresh: bool = False, log: Callable[[str], None] = print):
        self.out, self.cfg, self.fresh, self.log = Path(out), config, fresh, log
        self.steps_dir = self.out / "steps"
        self.steps_dir.mkdir(parents=True, exist_ok=True)
        self.results: dict[str, dict[str, Any]] = {}

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
        except NotAvailable as exc:
            result = {"status": "not available", "reason": str(exc)}
        except (ImportError, AttributeError, TypeError) as exc:  # a part of the project that is not ready
            result = {"status": "not available", "reason": f"{type(exc).__name__}: {exc}",
                      "traceback": traceback.format_exc(limit=3)}
        result["seconds"] = time.perf_counter() - t0
        (self.steps_dir / f"{name}.json").write_text(json.dumps(result, indent=1, default=str))
        self.log(f"[{name}] {result['status']} in {result['seconds']:.1f} s" + (f": {result.get('reason')}" if result["status"] != "done" else ""))
        self.results[name] = result
        return result

    def _need(self, *names: str) -> None:
        for n in names:
            if self.results.get(n, {}).get("status") != "done":
                raise NotAvailable(f"needs step {n!r}, which is {self.results.get(n, {}).get('status', 'missing')}")

    # --- steps -------------------------------------------------------------------------------

    def train_views(self, footprints: bool = True):
        from sssphase_core.data import simulate_views

        c = self.cfg
        return simulate_views(c.train_objects, c.train_views, n_views=c.n_views, pixels_per_view=c.pixels_per_view,
                              footprints=footprints, seed=c.seed, cache_dir=self.out / "cache")

    def train_data(self) -> dict[str, Any]:
        vds = self.train_views()
        return {"views": [f"{v.object}/{v.view}" for v in vds], "patches": int(sum(len(v.pixels) for v in vds))}

    def test_sessions(self) -> dict[str, Any]:
        root = self.out / "sessions"
        paths = [str(capture_sim_session(root, o, self.cfg.test_view, self.cfg.n_views, self.cfg.seed))
                 for o in self.cfg.test_objects]
        return {"sessions": paths}

    def pretrain(self) -> dict[str, Any]:
        self._need("train_data")
        from sssphase_core.backends import get_backend
        from sssphase_core.training import PretrainConfig

        c = self.cfg
        cfg = PretrainConfig(epochs=c.pretrain_epochs, batch_size=c.pretrain_batch, seed=c.seed, preset=c.model,
                             warmup_epochs=min(1.0, c.pretrain_epochs / 2), device="cpu")
        path = get_backend("torch").pretrain(self.train_views(footprints=False), self.out / "runs" / "pretrain", config=cfg)
        return {"checkpoint": str(path)}

    def decoder(self) -> dict[str, Any]:
        self._need("train_data", "pretrain")
        from sssphase_core.backends import get_backend
        from sssphase_core.training import DecoderConfig

        c = self.cfg
        cfg = DecoderConfig(epochs=c.decoder_epochs, batch_size=c.decoder_batch, seed=c.seed, device="cpu")
        path = get_backend("torch").fit(self.train_views(), self.out / "runs" / "decoder",
                                        encoder=self.results["pretrain"]["checkpoint"], config=cfg)
        return {"checkpoint": str(path)}

    def relight(self) -> dict[str, Any]:
        self._need("test_sessions")
        from sssphase_core.relight import load_view
        from sssphase_core.relight_eval import evaluate_view
        from sssphase_core.session import Session

        img_dir = self.out / "report" / "img"
        rows, skipped = [], {}
        ckpt = self.results.get("decoder", {}).get("checkpoint") if self.results.get("decoder", {}).get("status") == "done" else None
        for path in self.results["test_sessions"]["sessions"]:
            rv = load_view(Session.open(path), self.cfg.test_view)
            for b in self.cfg.backends:
                if b == "torch" and ckpt is None:
                    skipped[b] = "no decoder checkpoint (the decoder step is not available)"
                    continue
                try:
                    opts = {"supersample": self.cfg.analytic_supersample} if b == "analytic" else {}
                    rows += evaluate_view(rv, b, img_dir, checkpoint=ckpt, **opts)
                except (ImportError, AttributeError, TypeError) as exc:
                    skipped[b] = f"{type(exc).__name__}: {exc}"
                self.log(f"  relit {rv.object} with {b}")
        for r in rows:
            r["figure"] = str(Path(r["figure"]).relative_to(self.out / "report"))
        return {"rows": rows, "skipped": skipped}

    def footprints(self) -> dict[str, Any]:
        """The paper's Table 1: footprint MSE / PSNR / SSIM on sampled pixels of the unseen objects."""
        self._need("test_sessions")
        from sssphase_core.data import sample_pixels
        from sssphase_core.evaluation import footprint_metrics, summarise
        from sssphase_core.relight import load_view, make_source
        from sssphase_core.session import Session

        ckpt = self.results.get("decoder", {}).get("checkpoint") if self.results.get("decoder", {}).get("status") == "done" else None
        backends = [b for b in self.cfg.backends if b in ("analytic", "torch") and (b != "torch" or ckpt)]
        table: dict[str, dict[str, dict[str, float]]] = {}
        for path in self.results["test_sessions"]["sessions"]:
            rv = load_view(Session.open(path), self.cfg.test_view)
            px = sample_pixels(rv.proj.mask, self.cfg.footprint_pixels, self.cfg.seed)
            gt = rv.scene().footprints(px)
            table[rv.object] = {}
            for b in backends:
                opts = {"supersample": self.cfg.analytic_supersample} if b == "analytic" else {}
                source, _ = make_source(b, rv, checkpoint=ckpt, **opts)
                table[rv.object][b] = summarise(footprint_metrics(np.asarray(source(px), np.float32), gt))
        return {"metrics": table, "backends": backends, "pixels": self.cfg.footprint_pixels}

    def knn(self) -> dict[str, Any]:
        self._need("pretrain")
        from sssphase_core.evaluation import embed_pixels, knn_leave_one_view_out
        from sssphase_core.training import load_encoder

        enc = load_encoder(self.results["pretrain"]["checkpoint"])
        vds = self.train_views(footprints=False)
        names = list(self.cfg.train_objects)
        emb = np.concatenate([embed_pixels(enc, v.psp, v.pixels) for v in vds])
        labels = np.concatenate([np.full(len(v.pixels), names.index(v.object)) for v in vds])
        views = np.concatenate([np.full(len(v.pixels), v.view) for v in vds])
        res = knn_leave_one_view_out(emb, labels, views, k=min(20, len(emb) // 4 or 1), class_names=names)
        res.pop("pred")
        return res

    def pca(self) -> dict[str, Any]:
        self._need("pretrain", "test_sessions")
        from PIL import Image

        from sssphase_core.evaluation import embed_pixels, paint, pca_rgb
        from sssphase_core.session import Session
        from sssphase_core.training import load_encoder

        enc = load_encoder(self.results["pretrain"]["checkpoint"])
        panels, embs, grids = [], [], []
        sessions = [Session.open(p) for p in self.results["test_sessions"]["sessions"]]
        stride = self.cfg.pca_stride
        for s in sessions:
            mask = s.load(self.cfg.test_view, "corr/mask").astype(bool)
            px = np.argwhere(mask)
            px = px[(px[:, 0] % stride == 0) & (px[:, 1] % stride == 0)]
            embs.append(embed_pixels(enc, s.load(self.cfg.test_view, "psp"), px))
            grids.append((px, mask.shape))
        for (px, shape), rgb in zip(grids, pca_rgb(embs), strict=True):
            panels.append(paint((-(-shape[0] // stride), -(-shape[1] // stride)), px // stride, rgb))
        path = self.out / "report" / "img" / "pca_rgb.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray((np.concatenate(panels, axis=1) * 255).round().astype(np.uint8)).resize(
            (sum(p.shape[1] for p in panels) * 2, panels[0].shape[0] * 2), Image.Resampling.NEAREST).save(path)
        return {"figure": "img/pca_rgb.png", "objects": [s.name for s in sessions]}

    def report(self) -> dict[str, Any]:
        from sssphase_core.report import write_report

        path = write_report(self.out / "report", self.results, asdict(self.cfg))
        return {"path": str(path)}

    def run(self) -> Path:
        for name in STEPS:
            if name == "report":
                self.results.pop("report", None)
                self.fresh_report()
            self.step(name, getattr(self, name))
        return self.out / "report" / "index.html"

    def fresh_report(self) -> None:
        """The report is rewritten on every run (it reflects all steps, including newly finished ones)."""
        (self.steps_dir / "report.json").unlink(missing_ok=True)


def run_demo(out: Path | str, *, preset: str = "lite", fresh: bool = False, console: Any = None,
             log: Callable[[str], None] | None = None) -> Path:
    """Run (or resume) the demo into ``out``; returns the report's path."""
    if preset not in PRESETS:
        raise InputError(f"unknown demo preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if log is None:
        log = (lambda m: console.print(m, markup=False, highlight=False)) if console is not None else print
    t0 = time.perf_counter()
    demo = Demo(Path(out), PRESETS[preset], fresh=fresh, log=log)
    path = demo.run()
    log(f"demo finished in {time.perf_counter() - t0:.1f} s")
    return path
