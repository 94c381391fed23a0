"""Projector response calibration: a grey ramp captured through the daemon, fitted per colour.

The projector turns a pattern value v in [0, 1] into light ``black + (1 - black) * v**gamma``. A
camera pixel sees ``I(v) = a * (black + (1 - black) * r(v)) + ambient`` with an unknown reflectance
``a``; with the ramp's own v = 0 and v = 1 frames,

    r(v) = (I(v) - I(0)) / (I(1) - I(0))          (albedo and ambient cancel)

per pixel and colour. ``r`` is averaged over well-exposed pixels, then ``gamma`` is fitted by least
squares on log r = gamma log v (v in [0.1, 1], where r is above the noise). The black level relative
to white is ``(I(0) - ambient) / (I(1) - ambient)``; the ambient light cannot be told apart from the
projector's black with a projector alone, so ``black`` is an upper bound (exact in a dark room).
The tabulated curve r(v) is kept with the fit so a response that is not a power law shows up as a
large ``rms``.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sssphase_core.capture.plan import BLACK_LIMIT, GAMMA_RANGE
from sssphase_core.errors import DataError, InputError
from sssphase_core.store.files import atomic_path

RAMP_LEVELS = tuple(float(v) for v in np.round(np.linspace(0.0, 1.0, 17), 4))
FIT_RANGE = (0.1, 1.0)  # values whose response is fitted (below, r is at the noise floor)


@dataclass(frozen=True)
class ProjectorResponse:
    """A fitted response: per-colour gamma and black, their means (used for patterns and relighting),
    the tabulated curve ``levels -> response`` (3 colours) and the fit's RMS residual in r."""

    gamma: float
    black: float
    gamma_rgb: tuple[float, float, float]
    black_rgb: tuple[float, float, float]
    levels: tuple[float, ...]
    response_rgb: tuple[tuple[float, ...], ...]
    rms: float
    pixels: int

    def to_table(self) -> dict[str, Any]:
        """The rig file's ``[projector]`` table."""
        def rounded(v: Any) -> Any:
            if isinstance(v, float):
                return round(v, 5)
            return [rounded(x) for x in v] if isinstance(v, list | tuple) else v

        return {k: rounded(v) for k, v in asdict(self).items()}


def ramp_frames(width: int, height: int, levels: tuple[float, ...] = RAMP_LEVELS) -> list[dict[str, Any]]:
    """The daemon's frame specs of a grey ramp (uniform ``level`` frames, first 0, last 1)."""
    if levels[0] != 0.0 or levels[-1] != 1.0 or len(levels) < 4 or list(levels) != sorted(set(levels)):
        raise DataError("a calibration ramp needs >= 4 increasing levels from 0 to 1")
    return [{"name": f"cal/level/{v:.4f}", "key": f"cal/level/{v:.4f}", "kind": "level", "exposure": 1.0,
             "params": {"width": width, "height": height, "value": v}} for v in levels]


def ramp_response(images: np.ndarray, *, saturation: float = 0.98,
                  min_signal: float = 0.05) -> tuple[np.ndarray, np.ndarray, int]:
    """From ramp images (L, H, W, 3): the median normalised response r (L, 3), the black level relative
    to white per colour (3,), and the number of pixels used.

    Pixels used: the white frame is above ``min_signal`` over black and below ``saturation`` in every
    colour (clipped pixels would flatten the top of the curve).
    """
    imgs = np.asarray(images, np.float64)
    lo, hi = imgs[0], imgs[-1]
    good = ((hi - lo) > min_signal).all(axis=-1) & (hi < saturation).all(axis=-1) & np.isfinite(imgs).all(axis=(0, -1))
    n = int(good.sum())
    if n < 50:
        raise DataError(f"only {n} camera pixels see the projector's white well exposed (need 50): aim the projector "
                        "at a matte target that fills the view, and check the exposure")
    r = (imgs[:, good] - lo[good]) / (hi[good] - lo[good])  # (L, N, 3)
    black = np.clip(np.median(lo[good] / hi[good], axis=0), 0.0, None)
    if (np.round(black, 5) >= BLACK_LIMIT).any():  # (as the rig file rounds it) a projector's black is ~0.01 of white
        raise DataError(f"the ramp's black frame reads {black.max():.2f} of its white frame (a projector's black is a "
                        "few hundredths): the camera does not see the projector's ramp, or ambient light outweighs it; "
                        "aim the projector at a matte target in the camera's view and darken the room (nothing written)")
    return np.median(r, axis=1), black, n


def fit_response(levels: tuple[float, ...], images: np.ndarray) -> ProjectorResponse:
    """Fit gamma and black per colour from ramp images (L, H, W, 3) taken at ``levels``."""
    v = np.asarray(levels, np.float64)
    r, blacks, n = ramp_response(images)
    use = (v >= FIT_RANGE[0]) & (v <= FIT_RANGE[1])
    gammas, rms = [], 0.0
    for c in range(3):
        ok = use & (r[:, c] > 1e-4)
        if ok.sum() < 3:
            raise DataError("the ramp's response is at the noise floor: raise the exposure")
        x, y = np.log(v[ok]), np.log(r[ok, c])
        g = float((x * y).sum() / (x * x).sum())  # through the origin: r(1) = 1
        if not GAMMA_RANGE[0] <= g <= GAMMA_RANGE[1]:  # (a rig file with it would be refused by `sss capture`)
            raise DataError(f"the fitted gamma {g:.2f} ({'RGB'[c]}) is outside [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}]: "
                            "the camera does not follow the projector's ramp; check that it sees the projector's light "
                            "and nothing else changes between frames (nothing written)")
        gammas.append(g)
        rms = max(rms, float(np.sqrt(np.mean((v[use] ** g - r[use, c]) ** 2))))
    return ProjectorResponse(
        gamma=float(np.mean(gammas)), black=float(np.mean(blacks)),
        gamma_rgb=tuple(float(g) for g in gammas), black_rgb=tuple(float(b) for b in blacks),  # type: ignore[arg-type]
        levels=tuple(float(x) for x in v), response_rgb=tuple(tuple(float(x) for x in r[:, c]) for c in range(3)),
        rms=rms, pixels=n)


def phase_harmonic(gamma_true: float, gamma_assumed: float, n_shifts: int = 4, samples: int = 720) -> float:
    """Peak phase error (radians) of ``n_shifts``-step PSP when patterns pre-distorted for
    ``gamma_assumed`` are shown by a projector with ``gamma_true`` (analytic check of the fit's use)."""
    t = np.linspace(0, 2 * math.pi, samples, endpoint=False)
    shifts = 2 * math.pi * np.arange(n_shifts) / n_shifts
    frames = np.clip(0.5 + 0.5 * np.cos(t[:, None] + shifts[None]), 0, 1) ** (gamma_true / gamma_assumed)
    phi = np.arctan2(-(frames * np.sin(shifts)).sum(1), (frames * np.cos(shifts)).sum(1))
    err = np.angle(np.exp(1j * (phi - t)))
    return float(np.abs(err - np.angle(np.mean(np.exp(1j * err)))).max())


def capture_ramp(client: Any, rig: Any, levels: tuple[float, ...] = RAMP_LEVELS, *,
                 sim_options: dict[str, Any] | None = None) -> np.ndarray:
    """Capture the grey ramp through the daemon with ``rig`` (a :class:`RigSpec`) -> images (L, H, W, 3)."""
    from sssphase_core.capture import develop_frame

    options = {**(sim_options or {}), **rig.options} if rig.is_sim else dict(rig.options)
    opened = client.call("open_rig", camera=rig.camera, projector=rig.projector, turntable=None, options=options)
    try:
        frames = ramp_frames(*opened["projector_size"], levels)
        images = [develop_frame(f.data, rig, 1.0, f.header.get("meta", {}).get("bayer"), f.header.get("meta"))
                  for f in client.capture(opened["rig"], frames)]
    finally:
        try:
            client.call("close_rig", timeout_s=2.0, rig=opened["rig"])
        except Exception:  # the daemon may be gone (the caller hears of it from the capture)
            pass
    if len(images) != len(levels):
        raise DataError(f"the ramp capture returned {len(images)} of {len(levels)} frames")
    return np.stack(images)


def rig_file_with_response(text: str, response: ProjectorResponse) -> str:
    """A rig file's text with its ``[projector]`` table replaced by ``response``: everything else, comments
    included, kept as it was where a line edit can do it; where it cannot (a quoted ``["projector"]`` header,
    dotted ``projector.gamma`` keys) the whole file is written again from its parsed tables, without comments,
    rather than left with two projector tables or without a table it had."""
    import re
    import tomllib

    import tomli_w

    note = "# projector response fitted by `sss calibrate projector` (gamma, black: used for patterns and relighting)"
    header = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\-\"' ]+?)\s*\]\]?\s*(#.*)?$")  # [table] or [[array]]
    out, skipping = [], False
    for line in text.splitlines():
        match = header.match(line)
        if match:
            skipping = match.group(1) == "[" and match.group(2) == "projector"
        if not skipping and line.strip() != note:
            out.append(line)
    while out and not out[-1].strip():
        out.pop()
    table = {"projector": response.to_table()}
    edited = "\n".join(out) + ("\n\n" if out else "") + note + "\n" + tomli_w.dumps(table)
    wanted = {**{k: v for k, v in tomllib.loads(text).items() if k != "projector"}, **table}
    try:
        if tomllib.loads(edited) == wanted:
            return edited
    except tomllib.TOMLDecodeError:
        pass
    return note + "\n" + tomli_w.dumps(wanted)


def correspondence_error(session: Any, view: int = 0) -> float:
    """Median distance (projector px) between a sim session's decoded and exact correspondences."""
    xp, yp = np.asarray(session.load(view, "corr/xp")), np.asarray(session.load(view, "corr/yp"))
    mask = np.asarray(session.load(view, "corr/mask")).astype(bool)
    gt = np.asarray(session.load(view, "gt/proj_xy"))
    ok = mask & np.isfinite(gt[..., 0])
    if not ok.any():
        raise DataError("no decoded pixel with an exact correspondence")
    return float(np.median(np.hypot(xp[ok] - gt[ok, 0], yp[ok] - gt[ok, 1])))


@dataclass
class CalibrationRequest:
    """`sss calibrate projector`: the rig file to calibrate (``rig``; None: the sim rig) and the rig file to write
    (``out``; default: ``rig`` itself, else ``rig.toml``), checked on construction: ``spec`` and ``target``
    are what they resolve to. ``check`` (sim rigs only) compares the correspondence error with 2.2 and with the
    fitted curve against the simulator's exact map."""

    rig: Path | None = None
    out: Path | None = None
    levels: int = 17
    object_name: str = "soap"
    check: bool = False

    def __post_init__(self) -> None:
        from sssphase_core.capture.plan import RigSpec

        self.spec = RigSpec.from_toml(self.rig) if self.rig else RigSpec()
        self.target = self.out or self.rig or Path("rig.toml")
        if self.target.is_symlink():  # the file the link names is calibrated (the link was replaced by a copy)
            self.target = self.target.resolve()
        target = self.target
        if target.is_dir():
            raise InputError(f"--out {target} is a folder: give the rig file to write (e.g. {target / 'rig.toml'})")
        blocking = next((p for p in target.parents if p.exists() and not p.is_dir()), None)
        if blocking is not None:  # said only after the whole capture and fit: "File exists"
            raise InputError(f"--out {target}: {blocking} is a file, not a folder")
        if target.exists() and (self.rig is None or target.resolve() != self.rig.resolve()):
            try:  # rewriting another file (a script, an image) would destroy it
                other = RigSpec.from_toml(target)
            except InputError:
                raise InputError(f"--out {target} exists and is not a rig file: choose a new file, or the rig file "
                                 "itself") from None
            if (other.camera, other.projector) != (self.spec.camera, self.spec.projector):  # its gamma is not ours
                raise InputError(f"{target} is the rig file of other devices (camera {other.camera}, projector "
                                 f"{other.projector}) than the ones calibrated ({self.spec.camera}, "
                                 f"{self.spec.projector}): pass --rig {target} to calibrate that rig, or another --out")
        if self.check and not self.spec.is_sim:
            raise InputError("--check needs the simulator's exact correspondences: it works on sim rigs only")

    @property
    def ramp(self) -> tuple[float, ...]:
        return tuple(float(v) for v in np.round(np.linspace(0, 1, self.levels), 4))


def _no_status(text: str) -> contextlib.AbstractContextManager[None]:
    return contextlib.nullcontext()


def calibrate_projector(client: Any, req: CalibrationRequest, *,
                        status: Callable[[str], contextlib.AbstractContextManager[Any]] = _no_status,
                        on_fit: Callable[[ProjectorResponse], None] | None = None,
                        on_check: Callable[[str, float], None] | None = None) -> ProjectorResponse:
    """Capture ``req``'s grey ramp through the daemon ``client``, fit the response (told to ``on_fit``), with
    ``req.check`` capture a view three ways and tell each median correspondence error to ``on_check(label,
    error)``, then write the ``[projector]`` table into ``req.target``. ``status(text)`` wraps each capture."""
    spec = req.spec
    with status(f"capturing a {req.levels}-level grey ramp"):
        images = capture_ramp(client, spec, req.ramp, sim_options={"object": req.object_name, "n_views": 1})
    fitted = fit_response(req.ramp, images)
    if on_fit is not None:
        on_fit(fitted)
    if req.check:
        errors = _check_response(client, req, fitted, status)
        for label, err in errors.items():
            if on_check is not None:
                on_check(label, err)
    write_rig_response(req, fitted)
    return fitted


def _check_response(client: Any, req: CalibrationRequest, fitted: ProjectorResponse,
                    status: Callable[[str], contextlib.AbstractContextManager[Any]]) -> dict[str, float]:
    """The median correspondence error of a sim view captured with patterns for 2.2, for the fitted gamma, and
    on a nominal 2.2 projector."""
    import tempfile

    from sssphase_core.capture.engine import run_capture
    from sssphase_core.capture.plan import CaptureRequest, RigSpec

    spec, errors = req.spec, {}
    with tempfile.TemporaryDirectory(prefix="sss-cal-") as tmp:
        nominal = {k: v for k, v in spec.options.items() if k not in ("projector_gamma", "projector_black")}
        for label, options, gamma in (
                ("patterns for gamma 2.2", spec.options, None),
                (f"patterns for the fitted {fitted.gamma:.3f}", spec.options, fitted.gamma),
                ("nominal: a 2.2 projector with patterns for 2.2", nominal, None)):
            checked = RigSpec(spec.camera, spec.projector, spec.turntable, dict(options), gamma=gamma)
            with status(f"checking: {label}"):
                session = run_capture(client, CaptureRequest(req.object_name, views=1, out=Path(tmp) / str(len(errors))),
                                      checked)
            errors[label] = correspondence_error(session)
    return errors


def write_rig_response(req: CalibrationRequest, fitted: ProjectorResponse) -> Path:
    """Write ``fitted`` as the ``[projector]`` table of ``req.target`` (a new file: a copy of ``req.rig``, or the sim
    rig's devices)."""
    target, spec = req.target, req.spec
    source = target if target.exists() else req.rig  # a new --out: a copy of the whole rig file, calibrated
    text = source.read_text() if source is not None else ""
    if not text and req.rig is None:
        import tomli_w

        text = tomli_w.dumps({"devices": {"camera": spec.camera, "projector": spec.projector},
                              **({"options": spec.options} if spec.options else {})})
    target.parent.mkdir(parents=True, exist_ok=True)
    mode = target.stat().st_mode & 0o7777 if target.exists() else None
    with atomic_path(target) as tmp:
        tmp.write_text(rig_file_with_response(text, fitted))
        if mode is not None:  # a private rig file stays private, from the moment it replaces the old one
            tmp.chmod(mode)
    return target
