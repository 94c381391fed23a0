"""Rig geometry: pinhole camera at the origin looking down +z (x right, y down), a verged pinhole
projector with pose ``X_p = R X_c + t``, a turntable about the camera's y axis, and the presets."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.sim.sensor import THREE_CHIP, SensorConfig

if TYPE_CHECKING:
    from sssphase_core.processing.triangulation import StereoCalibration

Matrix3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class Pinhole:
    """Intrinsics in pixels; pixel (y, x) has its centre at integer coordinates."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def rays(self) -> np.ndarray:
        """Unit ray directions (H, W, 3) through every pixel centre, in this device's frame."""
        ys, xs = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        d = np.stack([(xs - self.cx) / self.fx, (ys - self.cy) / self.fy, np.ones_like(xs)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points in this device's frame -> (N, 2) pixel coordinates (x, y)."""
        z = points[:, 2]
        return np.stack([self.fx * points[:, 0] / z + self.cx, self.fy * points[:, 1] / z + self.cy], axis=1)


@dataclass(frozen=True)
class ProjectorModel(Pinhole):
    """The simulated projector: intrinsics, pose relative to the camera and transfer curve (not a device:
    the device protocol is ``sssphase_plugins.api.Projector``)."""

    rotation: Matrix3 = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gamma: float = 2.2
    black: float = 0.002  # emitted radiance of a 0 pattern value, relative to white

    @property
    def centre(self) -> np.ndarray:
        """Projector centre in camera coordinates, -R^T t."""
        return -np.asarray(self.rotation).T @ np.asarray(self.translation)

    def to_projector(self, points_cam: np.ndarray) -> np.ndarray:
        return points_cam @ np.asarray(self.rotation).T + np.asarray(self.translation)


#: Light-transport models of the simulator: Christensen-Burley normalized diffusion (radially
#: symmetric footprints), the directional dipole (footprints skewed by the incidence direction) and
#: radiative transfer (random-walk profiles, :mod:`sssphase_core.sim.radiative`: no diffusion approximation).
TRANSPORTS = ("burley", "directional_dipole", "radiative")
#: The phase function's mean cosine g of the radiative transport (the range its table covers).
ANISOTROPY_RANGE = (0.0, 0.85)
#: Accepted backdrop distances (mm behind the turntable centre): beyond the catalogue's 55 mm bounding spheres.
BACKDROP_RANGE = (60.0, 1000.0)
#: Accepted spectral skews of the objects' mean free paths (``RigConfig.mfp_skew``).
MFP_SKEW_RANGE = (0.25, 4.0)


@dataclass(frozen=True)
class RigConfig:
    """Everything fixed about the rig. ``sss_scale`` multiplies all scattering distances so that
    footprints fit the ``patch``; ``reference_distance`` is where a white target reads 1.0;
    ``transport`` is one of :data:`TRANSPORTS`; ``anisotropy`` the mean cosine g of the media's
    Henyey-Greenstein phase function (the radiative transport's; the diffusion models have none)."""

    name: str
    camera: Pinhole
    projector: ProjectorModel
    patch: int
    sensor: SensorConfig = field(default_factory=SensorConfig)
    turntable_centre: tuple[float, float, float] = (0.0, 0.0, 400.0)
    reference_distance: float = 400.0
    sss_scale: float = 1.0
    transport: str = "burley"
    anisotropy: float = 0.0
    #: distance (mm) behind the turntable centre of a matte grey wall facing the camera (``backdrop`` material);
    #: None: the objects float in the dark
    backdrop: float | None = None
    #: the objects' red mean free paths times this and their blue ones divided by it (green kept): materials of
    #: another spectral shape than the catalogue's
    mfp_skew: float = 1.0

    def __post_init__(self) -> None:
        if self.transport not in TRANSPORTS:
            raise InputError(f"unknown transport model {self.transport!r}; choose one of {', '.join(TRANSPORTS)}")
        if self.backdrop is not None and not BACKDROP_RANGE[0] <= self.backdrop <= BACKDROP_RANGE[1]:  # NaN fails too
            raise InputError(f"the backdrop must be {BACKDROP_RANGE[0]:g} to {BACKDROP_RANGE[1]:g} mm behind the turntable "
                             f"centre (behind any catalogue object), got {self.backdrop!r}")
        if not MFP_SKEW_RANGE[0] <= self.mfp_skew <= MFP_SKEW_RANGE[1]:  # NaN fails too
            raise InputError(f"mfp_skew must be in [{MFP_SKEW_RANGE[0]:g}, {MFP_SKEW_RANGE[1]:g}], got {self.mfp_skew!r}")
        if not ANISOTROPY_RANGE[0] <= self.anisotropy <= ANISOTROPY_RANGE[1]:  # NaN fails too
            raise InputError(f"anisotropy (the phase function's mean cosine) must be in [{ANISOTROPY_RANGE[0]:g}, "
                             f"{ANISOTROPY_RANGE[1]:g}], got {self.anisotropy!r}")

    def view_angle(self, view: int, n_views: int) -> float:
        """Turntable angle in degrees of view ``view`` out of ``n_views``."""
        if n_views < 1 or not 0 <= view < n_views:
            raise InputError(f"view must be in [0, {n_views}), got {view}")
        return 360.0 * view / n_views

    def to_dict(self) -> dict:
        return asdict(self)


def _look_at(centre: np.ndarray, target: np.ndarray) -> tuple[Matrix3, tuple[float, float, float]]:
    """Pose (R, t) of a device at ``centre`` looking at ``target``, keeping the camera's y down."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    t = -r @ centre
    return tuple(tuple(float(v) for v in row) for row in r), tuple(float(v) for v in t)


def make_rig(
    name: str,
    size: tuple[int, int],
    projector_size: tuple[int, int],
    patch: int,
    *,
    distance: float = 400.0,
    half_height_mm: float = 62.0,
    baseline: float = 150.0,
    sss_scale: float = 1.0,
    sensor: SensorConfig | None = None,
) -> RigConfig:
    """A rig whose camera sees ``+-half_height_mm`` at ``distance`` and whose projector, ``baseline``
    mm to the camera's right and verged on the turntable centre, has about the same pixel pitch there."""
    w, h = size
    f = (h / 2) / half_height_mm * distance
    camera = Pinhole(w, h, f, f, (w - 1) / 2, (h - 1) / 2)
    target = np.array([0.0, 0.0, distance])
    p_centre = np.array([baseline, 0.0, 0.0])
    rot, trans = _look_at(p_centre, target)
    wp, hp = projector_size
    d_proj = float(np.linalg.norm(target - p_centre))
    fp = f * (hp / h) * d_proj / distance
    projector = ProjectorModel(wp, hp, fp, fp, (wp - 1) / 2, (hp - 1) / 2, rotation=rot, translation=trans)
    return RigConfig(
        name=name,
        camera=camera,
        projector=projector,
        patch=patch,
        sensor=sensor or SensorConfig(),
        turntable_centre=(0.0, 0.0, distance),
        reference_distance=d_proj,
        sss_scale=sss_scale,
    )


PRESETS = ("cpu", "paper")
#: Turntable views of one sim session at most (its steps: one view per 0.1 degree).
MAX_VIEWS = 3600


def rig_preset(name: str = "cpu") -> RigConfig:
    """``cpu``: 256x192 camera and projector, K = 32. ``paper``: 1920x1080 both, K = 90.

    Scattering distances are scaled (``sss_scale``) so the widest catalogue footprints (apple,
    marble soap, skin) lose only a few percent of their energy outside the patch.
    """
    if name == "cpu":
        return make_rig("cpu", (256, 192), (256, 192), 32, sss_scale=1.0, sensor=SensorConfig(isp_median=False))
    if name == "paper":
        # 1080p sees the same field as the CPU preset with 5.6x finer pixels; a 90 px patch then spans
        # 11 mm on the object (22 mm at the CPU preset), so distances are halved.
        return make_rig("paper", (1920, 1080), (1920, 1080), 90, sss_scale=0.5)
    raise InputError(f"unknown rig preset {name!r}; choose one of {', '.join(PRESETS)}")


def anisotropy_option(transport: str | None, anisotropy: float | None) -> dict[str, float]:
    """The rig option ``{"anisotropy": g}`` of a ``--anisotropy`` given with light-transport model ``transport``
    ({} when none is given), refused in one line with a model that has no phase function (any but radiative)."""
    if anisotropy is None:
        return {}
    if transport != "radiative":
        raise InputError("--anisotropy is the phase function of the sim rig's radiative transport: give it with "
                         "--transport radiative")
    return {"anisotropy": anisotropy}


def with_transport(rig: RigConfig, transport: str | None, anisotropy: float | None = None) -> RigConfig:
    """``rig`` with light-transport model ``transport`` and phase-function ``anisotropy`` (None keeps the rig's)."""
    if transport is not None:
        rig = replace(rig, transport=str(transport))
    return rig if anisotropy is None else replace(rig, anisotropy=float(anisotropy))


#: Sim rig options that change the camera (``SensorConfig`` fields): name -> (low, high) of the
#: accepted values. ``white_fraction`` is the exposure: the share of the full well a white target fills.
SENSOR_OPTIONS: dict[str, tuple[float, float]] = {"lens_blur": (0.0, 5.0), "read_noise": (0.0, 100.0),
                                                  "white_fraction": (0.02, 1.0)}
DEMOSAIC_METHODS = ("malvar", "opencv")
#: every rig option of the sim device plugin (``sssphase_plugins.sim_plugin``'s docstring says what each does)
#: The sim devices' fault injection (tests): options that change when a capture fails, not what it captures.
FAULT_OPTIONS = frozenset({"fail_at_frame", "disconnect_at_frame", "stall_at_frame", "garbage_at_frame", "grab_delay_s",
                           "frame_timeout_s"})
#: Options that change where the sim computes, not what it captures (``device``: the light transport on a
#: torch device, ``sssphase_core.sim_accel``): a session resumes across them.
COMPUTE_OPTIONS = frozenset({"device"})
SIM_RIG_OPTIONS = frozenset({"object", "preset", "seed", "n_views", "view", "latency_s", "frame_period_s", "realtime",
                             "projector_gamma", "projector_black", "transport", "anisotropy", "backdrop", "mfp_skew", "demosaic", "raw", "fail_at_frame",
                             "disconnect_at_frame", "stall_at_frame", "garbage_at_frame",
                             "grab_delay_s", "frame_timeout_s", "shape", "dtype", *SENSOR_OPTIONS, *COMPUTE_OPTIONS})


def _option(options: Mapping[str, Any], name: str, lo: float, hi: float) -> float | None:
    value = options.get(name)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:  # NaN fails too
        raise InputError(f"sim option {name} must be a number in [{lo:g}, {hi:g}], got {value!r}")
    return float(value)


def with_camera(rig: RigConfig, options: Mapping[str, Any]) -> RigConfig:
    """``rig`` with the camera options among ``options`` (:data:`SENSOR_OPTIONS`, ``demosaic``); others
    keep the preset's."""
    changes: dict[str, Any] = {k: v for k in SENSOR_OPTIONS if (v := _option(options, k, *SENSOR_OPTIONS[k])) is not None}
    if "demosaic" in options:
        if options["demosaic"] not in (*DEMOSAIC_METHODS, THREE_CHIP):
            raise InputError(f"sim option demosaic must be one of {', '.join(DEMOSAIC_METHODS)} (a Bayer camera's) or "
                             f"{THREE_CHIP} (a three-chip camera: every pixel sees R, G and B), got {options['demosaic']!r}")
        changes["demosaic"] = str(options["demosaic"])
    return replace(rig, sensor=replace(rig.sensor, **changes)) if changes else rig


def rig_from_options(options: Mapping[str, Any]) -> RigConfig:
    """The sim rig a session or daemon was given: ``preset`` (default cpu), then the optional
    ``projector_gamma`` / ``projector_black``, ``transport``, ``anisotropy``, ``backdrop`` and camera options
    (:func:`with_camera`) (the sim plugin's options)."""
    rig = rig_preset(str(options.get("preset", "cpu")))
    rig = with_projector_response(rig, _option(options, "projector_gamma", 0.3, 5.0),
                                  _option(options, "projector_black", 0.0, 0.2))
    rig = with_transport(rig, options.get("transport"), _option(options, "anisotropy", *ANISOTROPY_RANGE))
    if (backdrop := _option(options, "backdrop", *BACKDROP_RANGE)) is not None:
        rig = replace(rig, backdrop=backdrop)
    if (skew := _option(options, "mfp_skew", *MFP_SKEW_RANGE)) is not None:
        rig = replace(rig, mfp_skew=skew)
    return with_camera(rig, options)


#: Ranges of :func:`randomised_rig_options`: what differs between labs, projectors and cameras.
RANDOMISED_RANGES: dict[str, tuple[float, float]] = {
    "projector_gamma": (1.8, 2.6),  # the projector's true response; patterns are still made for 2.2
    "projector_black": (0.0, 0.01),
    "lens_blur": (0.0, 1.0),
    "read_noise": (1.0, 12.0),
    "white_fraction": (0.3, 0.85),
    "anisotropy": ANISOTROPY_RANGE,  # the radiative transport's media: isotropic to strongly forward (skin, milk)
}


#: What :func:`randomised_rig_options` can draw: the camera and projector alone, or the light transport too.
RANDOMISED_PARTS = ("camera", "rig")
_TRANSPORT_KEYS = ("transport", "anisotropy")


def randomised_rig_options(seed: int, salt: str = "", what: str = "rig") -> dict[str, Any]:
    """Domain randomisation: sim rig options drawn from :data:`RANDOMISED_RANGES` (uniform), a
    demosaicing method and a light-transport model (``anisotropy`` matters to the radiative one only),
    reproducibly from ``seed`` and ``salt`` (e.g. the object's name: each object gets its own rig). Sessions captured with different draws teach a
    model several rigs and profile families instead of one. ``what="camera"`` keeps the same draw's projector
    response, lens blur, read noise, exposure and demosaicing and leaves the transport out (the rig's own)."""
    import zlib

    if what not in RANDOMISED_PARTS:
        raise ValueError(f"unknown randomisation {what!r} ({' or '.join(RANDOMISED_PARTS)})")
    rng = np.random.default_rng([int(seed), zlib.crc32(salt.encode()), 0x5EED])
    out: dict[str, Any] = {k: round(float(rng.uniform(lo, hi)), 4) for k, (lo, hi) in RANDOMISED_RANGES.items()}
    out["demosaic"] = DEMOSAIC_METHODS[int(rng.integers(len(DEMOSAIC_METHODS)))]
    out["transport"] = TRANSPORTS[int(rng.integers(len(TRANSPORTS)))]
    if what == "camera":
        out = {k: v for k, v in out.items() if k not in _TRANSPORT_KEYS}
    return out


def with_projector_response(rig: RigConfig, gamma: float | None = None, black: float | None = None) -> RigConfig:
    """``rig`` with its projector emitting ``black + (1 - black) * v**gamma`` (None keeps the preset's)."""
    proj = replace(rig.projector, gamma=rig.projector.gamma if gamma is None else float(gamma),
                   black=rig.projector.black if black is None else float(black))
    return replace(rig, projector=proj)


def pixel_pitch_mm(rig: RigConfig) -> float:
    """Camera pixel size on a fronto-parallel surface at the turntable centre (mm)."""
    return rig.turntable_centre[2] / rig.camera.fx


def stereo_calibration(rig: RigConfig) -> StereoCalibration:
    """The rig's exact camera-projector calibration (ideal lenses, mm) and turntable axis: what a lab's stereo and
    turntable calibrations estimate."""
    from sssphase_core.processing.triangulation import StereoCalibration

    def matrix(p: Pinhole) -> np.ndarray:
        return np.array([[p.fx, 0.0, p.cx], [0.0, p.fy, p.cy], [0.0, 0.0, 1.0]])

    # the turntable turns the object by +angle about the camera's y axis through its centre (SimScene)
    return StereoCalibration(matrix(rig.camera), np.zeros(0), matrix(rig.projector), np.zeros(0),
                             np.asarray(rig.projector.rotation, np.float64),
                             np.asarray(rig.projector.translation, np.float64), unit="mm",
                             turntable_axis=np.array([0.0, 1.0, 0.0]),
                             turntable_point=np.asarray(rig.turntable_centre, np.float64))


def session_rig_calibration(rig_record: Mapping[str, Any]) -> StereoCalibration | None:
    """The exact calibration of the rig a session records (its manifest's ``rig``) where that is the simulated one,
    else None."""
    if not str(rig_record.get("camera", "")).startswith("sim:"):
        return None
    return stereo_calibration(rig_from_options(rig_record.get("options", {})))
