"""A session view as relighting reads it: correspondences, PSP stack, white image, references and,
for simulated sessions, the scene (:func:`load_view`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from sssphase_core.errors import DataError, InputError
from sssphase_core.store.light import light_problem, projector_light, white_level
from sssphase_core.store.session import coordinates_problem

if TYPE_CHECKING:
    from sssphase_core.relight.engine import Projection


#: :meth:`RelightView.decoded_warning` warns when less than this share of the lit pixels decoded.
DECODED_SHARE_WARN = 0.9  # (99.7-100% on the Mitsuba and demo views; 67-86% where an object or most of one was lost)


@dataclass
class RelightView:
    """What relighting one view of a session needs, plus its references when it has any."""

    object: str
    view: int
    proj: Projection
    psp: np.ndarray  # (8, H, W, 3)
    white: np.ndarray  # (H, W, 3)
    patch: int
    references: dict[str, np.ndarray]  # name -> pattern (Hp, Wp[, 3]) of the ref/<name> captures
    captured: dict[str, np.ndarray]  # name -> reference image (noise-free sim render if stored, else capture)
    sim: dict | None = None  # SimScene arguments of a simulated session
    session: object | None = None
    saturation: float | None = None  # clipping level of the PSP frames (linear units), None: unknown
    white_saturation: float | None = None  # the white capture's (None: it does not clip, e.g. HDR)
    plan: dict = field(default_factory=dict, repr=False)  # the session's capture plan
    camera_isp: dict | None = None  # the camera pipeline that made its captures, when known (view info)
    codes_range: tuple[float, float] | None = None  # (0, top code) in linear units: integer frames' range (imports)
    _camera: dict[str, np.ndarray] = field(default_factory=dict, repr=False, compare=False)
    _model_inputs: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)
    _exit_white: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)
    _noise_model: np.ndarray | None = field(default=None, repr=False, compare=False)

    @cached_property
    def decoded_share(self) -> float:
        """The share of the pixels the projector lights (white less black, colours summed, above a fifth of its 99th
        percentile) that decoded, i.e. that relighting gives light and every score is made on: an object whose
        fringes did not decode (too wide a scattering for the fringes' period, too dim) is black in the relit
        images and left out of the scores, which then hold only what did decode (a background wall)."""
        arrays = self.session.arrays(self.view) if self.session is not None else ()  # type: ignore[attr-defined]
        black = self.session.load(self.view, "black") if "black" in arrays else None  # type: ignore[attr-defined]
        lit = projector_light(self.white, black)[1]
        return float((lit & self.proj.mask).sum() / lit.sum()) if lit.any() else 1.0

    def decoded_warning(self) -> str | None:
        """A line when less than :data:`DECODED_SHARE_WARN` of the lit pixels decoded (:attr:`decoded_share`)."""
        if self.decoded_share >= DECODED_SHARE_WARN:
            return None
        return (f"{self.object} view {self.view}: only {self.decoded_share:.0%} of the pixels the projector lights "
                "decoded; the others stay black in the relit images and out of every score, which is then made on "
                "those pixels only (`sss decode` shows why the rest were dropped: fringes too fine for the scattering, "
                "too dim)")

    @cached_property
    def psp_patterns(self) -> np.ndarray | None:
        """(8, Hp, Wp) projector images of the ``psp`` captures (None if the plan does not say), made
        when first asked: only calibration needs them."""
        return paper_input_patterns(self.plan)

    def through_camera(self, images: np.ndarray) -> np.ndarray:
        """Linear images (..., H, W, 3) as this view's camera records them, noise aside (Bayer sampling and
        its demosaicing, :func:`isp.through_camera`), so that they compare with its captures; unchanged when
        the session does not say how its frames were made (a camera that demosaics itself, imports). Frames of
        integer codes (``codes_range``) hold none of the demosaicing's overshoot below 0 or above the top code: the
        images are clipped to it as the camera's files were (unclipped, an imported crab scored 3.6 dB low)."""
        if not self.camera_isp or self.camera_isp.get("demosaic") == "other":  # (an import's unknown demosaicer)
            return np.asarray(images, np.float32)
        from sssphase_core.processing.isp import through_camera

        seen = through_camera(images, demosaic=str(self.camera_isp.get("demosaic", "malvar")),
                              median=bool(self.camera_isp.get("median", False)),
                              layout=str(self.camera_isp.get("bayer", "RGGB")))
        return seen if self.codes_range is None else np.clip(seen, *self.codes_range)

    @property
    def reference_name(self) -> str:
        """What its references are, for figures: a simulated session's noise-free renders (ground truth), else the
        camera's captures of the patterns."""
        return "reference (GT)" if self.sim is not None else "reference capture"

    def camera_image(self, name: str) -> np.ndarray:
        """The camera's noise-free image of reference ``name`` (simulated sessions; evaluation only): its
        render through the sensor's Bayer sampling and demosaicing, without noise. Made once for every
        reference of the view when first asked."""
        if not self._camera:
            names = sorted(self.captured)
            images = self.scene().sense_noise_free(np.stack([self.captured[n] for n in names]))
            self._camera.update(zip(names, images, strict=True))
        return self._camera[name]

    def scene(self):
        """The simulator scene of a simulated session (exact footprints, ``exact``: evaluation only)."""
        from sssphase_core.sim import SimScene, rig_from_options

        if self.sim is None:
            raise InputError(f"{self.object}: not a simulated session")
        s = self.sim
        return SimScene(s["object"], rig=rig_from_options(s["options"]), view=self.view, n_views=s["n_views"], seed=s["seed"])


def has_references(arrays) -> bool:
    """Whether a view's arrays (names) hold a reference capture to relight against: a ``ref/<name>`` capture
    or, on simulated sessions, a reference's render (``gt/render/white`` is the white's, not a reference)."""
    return any(a.startswith("ref/") or (a.startswith("gt/render/") and a != "gt/render/white") for a in arrays)


def has_captured_transport(arrays) -> bool:
    """Whether a view's arrays (names) hold the dot-grid crops the ``measured`` backend relights with."""
    return bool({"transport/crops", "footprints/crops"} & set(arrays))


def load_view(session: object, view: int) -> RelightView:
    """Read one complete view of a :class:`sssphase_core.store.session.Session` for relighting."""
    from sssphase_core.processing.patterns import PlannedFrame
    from sssphase_core.relight.engine import Projection

    m = session.manifest  # type: ignore[attr-defined]
    if view not in session.views():  # type: ignore[attr-defined]
        raise InputError(f"session {session.path} has no complete view {view} (has {session.views()})")  # type: ignore[attr-defined]
    plan = m.get("plan", {})
    if "projector" not in plan:
        raise DataError(f"{session.path}: the manifest has no capture plan (plan.projector): the patterns its "  # type: ignore[attr-defined]
                        "frames were captured under are unknown, so it cannot be relit")
    wp, hp = plan["projector"]
    rig = m.get("rig", {})
    opts = rig.get("options", {})
    arrays = session.arrays(view)  # type: ignore[attr-defined]
    load = lambda name: np.asarray(session.load(view, name))  # type: ignore[attr-defined]  # noqa: E731
    white = load("white").astype(np.float32)
    mask = load("corr/mask").astype(bool)
    sim = None
    patch = session_patch(m)
    if str(rig.get("camera", "")).startswith("sim:"):
        sim = {"object": opts.get("object", m.get("object")), "preset": opts.get("preset", "cpu"),
               "n_views": int(opts.get("n_views", m.get("n_views", 4))), "seed": int(opts.get("seed", 0)),
               "options": dict(opts)}
    where = f"view {view} of {session.path}"  # type: ignore[attr-defined]
    xp, yp, psp = (load(name).astype(np.float32) for name in ("corr/xp", "corr/yp", "psp"))
    _check_view_shapes(where, mask, {"corr/xp": xp, "corr/yp": yp}, {"psp": psp, "white": white})
    if not mask.any():  # it relit as black (no warning) and failed only when scored
        raise DataError(f"{where}: no pixel decoded (corr/mask is empty): nothing to relight; check the capture "
                        "(`sss decode` shows why pixels were dropped)")
    if psp.ndim != 4 or len(psp) != 8:
        raise DataError(f"{where}: psp holds {psp.shape[0] if psp.ndim == 4 else 'no'} frames where the paper's "
                        "inputs are 8 (4 shifts x 2 orientations)")
    black = session.projector_black(view, white, mask)  # type: ignore[attr-defined]
    # a camera's pixels integrate the light over their area; our simulator's pinhole samples it at a point
    proj = Projection(xp, yp, mask, (int(wp), int(hp)), float(plan.get("gamma", 2.2)), black, pixel_area=sim is None)
    references, captured = {}, {}
    for f in plan.get("frames", []):
        if f["kind"] == "ref" and f["key"] not in (f"ref/{n}" for n in references):
            name = f["key"].removeprefix("ref/")
            references[name] = PlannedFrame(f["key"], f["kind"], f["params"], 1.0).pattern()
    for name in (a.removeprefix("pattern/") for a in arrays if a.startswith("pattern/")):
        references.setdefault(name, load(f"pattern/{name}").astype(np.float32))  # the user's own pattern files
    stored: dict[str, str] = {}  # reference name -> the array it was read from
    for name in list(references):
        stored[name] = next((a for a in (f"gt/render/{name}", f"ref/{name}") if a in arrays), "")
        if stored[name]:
            captured[name] = load(stored[name]).astype(np.float32)
        else:
            references.pop(name)
    _check_view_shapes(where, mask, {}, {f"reference {n}": c for n, c in captured.items()})
    _check_finite(where, mask, {"corr/xp": xp, "corr/yp": yp},
                  {"psp": psp, "white": white, **{stored[n]: c for n, c in captured.items()}})
    for name, coord, side in (("corr/xp", xp, wp), ("corr/yp", yp, hp)):
        if problem := coordinates_problem(name, coord, mask, side):
            raise DataError(f"{where}: {problem}")
    psp_clip, white_clip = session.clip_levels()  # type: ignore[attr-defined]
    codes = rig.get("frame_codes_range")
    return RelightView(str(m.get("object")), view, proj, psp, white, patch,
                       references, captured, sim, session, psp_clip, white_clip, plan,
                       m.get("views", {}).get(str(view), {}).get("camera_isp"),
                       (float(codes[0]), float(codes[1])) if _codes_range_ok(codes) else None)


def _codes_range_ok(codes: object) -> bool:
    """Whether a manifest's ``frame_codes_range`` is a usable (low, high) pair of finite numbers, low < high."""
    return (isinstance(codes, (list, tuple)) and len(codes) == 2
            and all(isinstance(c, (int, float)) and not isinstance(c, bool) and np.isfinite(c) for c in codes)
            and codes[0] < codes[1])


def _check_view_shapes(where: str, mask: np.ndarray, maps: dict[str, np.ndarray], images: dict[str, np.ndarray]) -> None:
    """One clear error when a view's arrays disagree on the camera's size (arrays edited or swapped by
    hand): ``maps`` (H, W) like ``mask``; ``images`` (..., H, W, 3)."""
    h, w = mask.shape
    for name, array in {**maps, **images}.items():
        want = (h, w) if name in maps else (h, w, 3)
        if (array.shape if name in maps else array.shape[-3:]) != want:
            raise DataError(f"{where}: {name} is {'x'.join(map(str, array.shape))} where the decoded mask asks for "
                            f"{'x'.join(map(str, want))} (height x width{' x colour' if len(want) == 3 else ''}): the "
                            "view's arrays do not belong together")


def _check_finite(where: str, mask: np.ndarray, maps: dict[str, np.ndarray], images: dict[str, np.ndarray]) -> None:
    """One clear error for values no capture makes where relighting reads (a session written by another program:
    our writers refuse them): NaN or inf on the decoded ``mask`` in ``maps``; in ``images`` (light, the white
    among them) whatever :func:`~sssphase_core.store.light.light_problem` finds: NaN or inf, huge values, or
    frames far below zero."""
    for name, array in maps.items():
        bad = ~np.isfinite(array[mask])
        if bad.any():
            raise DataError(f"{where}: {name} holds {int(bad.sum())} NaN or infinite values on the decoded pixels")
    level = white_level(images["white"]) if "white" in images else None
    for name, array in images.items():
        problem = light_problem(name, array, level)
        if problem:
            raise DataError(f"{where}: {problem}")


def session_patch(manifest: dict) -> int:
    """The footprint crop size K of a session: its rig's ``patch``, else its sim preset's, else 32."""
    rig = manifest.get("rig", {})
    if rig.get("patch"):
        return int(rig["patch"])
    if str(rig.get("camera", "")).startswith("sim:"):
        from sssphase_core.sim import rig_preset

        return int(rig_preset(rig.get("options", {}).get("preset", "cpu")).patch)
    return 32


def finest_psp_period(plan: dict) -> float | None:
    """The finest PSP period of a capture plan (projector px): the fringes the decoded points come from."""
    periods = [float(f["params"]["period"]) for f in plan.get("frames", []) if f.get("kind") == "psp"]
    return min(periods) if periods else None


def paper_input_patterns(plan: dict) -> np.ndarray | None:
    """(8, Hp, Wp) projector images of a plan's 8 paper inputs (the finest period, x shifts then y shifts),
    the patterns under which a session's ``psp`` stack was captured; None when the plan has no such set."""
    from sssphase_core.processing.patterns import PlannedFrame

    chosen = paper_input_frames(plan)
    if chosen is None:
        return None
    return np.stack([PlannedFrame(f["key"], f["kind"], f["params"], 1.0).pattern() for f in chosen])


def paper_input_frames(plan: dict) -> list[dict] | None:
    """The plan's frames of the 8 paper inputs in the order of a session's ``psp`` stack (the finest period,
    x shifts then y shifts), or None when the plan has no such set. A plan of N != 4 shifts gives the 4-step
    frames its stack was resampled to (keys ending in ``~4``)."""
    # One frame per pattern: an HDR plan lists each pattern once per exposure bracket (same key), merged into one
    # image (without this, HDR sessions silently lost the view calibration: the crab relit 4-6 dB worse).
    frames = list({f["key"]: f for f in plan.get("frames", []) if f.get("kind") == "psp"}.values())
    finest = finest_psp_period(plan)
    if finest is None:
        return None
    chosen = sorted((f for f in frames if float(f["params"]["period"]) == finest),
                    key=lambda f: (f["params"]["orientation"], int(f["params"]["shift"])))
    n = len(chosen) // 2
    if n < 3 or [(f["params"]["orientation"], int(f["params"]["shift"])) for f in chosen] != [(o, k) for o in "xy" for k in range(n)]:
        return None
    if n == 4:
        return chosen
    # an N-step plan: its psp stack holds the 4-step images (psp.four_step), made under these patterns
    return [{**f, "key": f"{f['key']}~4", "params": {**f["params"], "shift": k, "n_shifts": 4}}
            for f in (chosen[0], chosen[n]) for k in range(4)]
