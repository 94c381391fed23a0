"""One view of one object on the simulated rig: exact geometry, correspondences, rendering, capture."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sssphase_core.errors import InputError
from sssphase_core.processing.projector import sample_projector
from sssphase_core.sim import geometry as g
from sssphase_core.sim.materials import MATERIALS, burley_scale
from sssphase_core.sim.objects import MaterialSample, SimObject, get_object, uniform
from sssphase_core.sim.rig import RigConfig, rig_preset
from sssphase_core.sim.sensor import develop, expose
from sssphase_core.sim.transport import (
    DirectionalMaps,
    DirectionalTransport,
    RadiativeTransport,
    SurfaceMaps,
    Transport,
)

#: |cos| between the view ray and the normal is clamped here, bounding cell areas at grazing angles.
COS_VIEW_MIN = 0.1
SHADOW_OFFSET = 0.05  # mm, start of shadow rays off the surface


#: Patterns lighting less than this share of the projector (dot grids) are looked up only where they reach.
SPARSE_SHARE = 0.05


def _sample_sparse(light: np.ndarray, xy: np.ndarray, on: np.ndarray | None = None) -> np.ndarray:
    """``sample_projector(light, x, y)`` (P, Hp, Wp, C) at (N, 2) points -> (N, P, C), for sparse light (a dot
    grid lights ~1/3000 of a 1080p projector) computed only at the points whose four bilinear taps meet a lit
    projector pixel: the same values, without a lookup at every lit camera pixel per frame. ``on``: the
    (Hp, Wp) projector pixels any pattern lights, when known."""
    on = (light > 0).any(axis=(0, 3)) if on is None else on
    if on.mean() >= SPARSE_SHARE:
        return sample_projector(light, xy[:, 0], xy[:, 1])
    padded = np.zeros((on.shape[0] + 2, on.shape[1] + 2), bool)  # taps outside the projector read 0
    padded[1:-1, 1:-1] = on
    finite = np.isfinite(xy).all(axis=1)  # (NaN: no projector light; it reads 0)
    safe = np.where(finite[:, None], xy, -2.0)
    x0 = np.clip(np.floor(safe[:, 0]).astype(np.int64) + 1, 0, on.shape[1])
    y0 = np.clip(np.floor(safe[:, 1]).astype(np.int64) + 1, 0, on.shape[0])
    reach = finite & (padded[y0, x0] | padded[y0, x0 + 1] | padded[y0 + 1, x0] | padded[y0 + 1, x0 + 1])
    out = np.zeros((len(xy), light.shape[0], light.shape[3]), np.float32)
    sel = np.flatnonzero(reach)
    out[sel] = sample_projector(light, xy[sel, 0], xy[sel, 1])
    return out


class SimScene:
    """Object ``obj`` (a :class:`SimObject` or catalogue name) on the turntable at view ``view`` of
    ``n_views`` (angle 360 * view / n_views about the camera's y axis through the turntable centre).

    Attributes (all (H, W, ...) camera maps): ``mask`` (a surface: the object, or the rig's ``backdrop`` where
    it has one), ``object_mask`` (the object); ``points`` and ``normals`` (camera space,
    NaN off the surface); ``area`` (mm^2 per pixel); ``irradiance`` E_p; ``lit`` (receives projector
    light); ``proj_xy`` exact projector (x, y), NaN where the pixel gets no projector light
    (off the surface, outside the projector image, back-facing or in shadow); ``material`` (int16
    index into ``sssphase_core.sim.MATERIAL_NAMES``, -1 off the surface), ``albedo``, ``mfp`` (scaled, mm);
    ``light_dir`` (direction the projector light travels), ``cos_in`` and ``cos_view`` (incidence and
    viewing cosines). ``rig.transport`` picks the light-transport model (``burley``,
    ``directional_dipole`` or ``radiative``, the last with the rig's phase-function ``anisotropy``);
    ``transport_factory(maps, patch)`` builds the Burley one elsewhere than numpy, and its ``radiative`` attribute
    the radiative one (``sssphase_core.sim_accel.transport_factory``: on a GPU; same footprints and images).
    """

    def __init__(self, obj: SimObject | str, rig: RigConfig | None = None, view: int = 0, n_views: int = 4, seed: int = 0,
                 transport_factory: Callable[[SurfaceMaps, int], Transport] | None = None):
        self.obj = get_object(obj) if isinstance(obj, str) else obj
        self.rig = rig or rig_preset("cpu")
        self.view, self.n_views, self.seed = view, n_views, seed
        self.angle = self.rig.view_angle(view, n_views)
        self._trace()
        maps = SurfaceMaps(self.mask, self.points, self.area, self.irradiance, self.albedo, self.rate, self.rho_s)
        if self.rig.transport == DirectionalTransport.name:
            directional = DirectionalMaps(self.normals, self.light_dir, self.cos_in, self.cos_view, self.mfp)
            self.transport: Transport = DirectionalTransport(maps, self.rig.patch, directional)
        elif self.rig.transport == RadiativeTransport.name:  # on the factory's device where it offers one
            make = getattr(transport_factory, "radiative", RadiativeTransport)
            self.transport = make(maps, self.rig.patch, self.mfp, self.rig.anisotropy)
        else:
            self.transport = (transport_factory or Transport)(maps, self.rig.patch)
        self._unit_white: np.ndarray | None = None

    # --- geometry ------------------------------------------------------------------------------

    def _trace(self) -> None:
        cam, proj, rig = self.rig.camera, self.rig.projector, self.rig
        h, w = cam.height, cam.width
        turn = self.obj.orientation(self.angle, self.view)  # object -> camera: the turntable's, or a hand-held target's
        centre = np.asarray(rig.turntable_centre, np.float64)
        rays = cam.rays().reshape(-1, 3)
        origin = -centre @ turn  # camera centre in object space (R^T (0 - C))
        dirs = rays @ turn
        origins = np.broadcast_to(origin, dirs.shape)
        t0, t1, meets = g.ray_sphere(origins, dirs, self.obj.radius)
        sel = np.flatnonzero(meets)
        t, hit = g.sphere_trace(self.obj.sdf, origins[sel], dirs[sel], t0[sel], t1[sel])
        sel, t = sel[hit], t[hit]
        p_obj = origin + t[:, None] * dirs[sel]
        n_obj = g.sdf_normals(self.obj.sdf, p_obj)
        p_cam = p_obj @ turn.T + centre
        n_cam = n_obj @ turn.T
        on_object = np.ones(len(sel), bool)
        if rig.backdrop is not None:  # the rays that miss the object meet the wall z = centre z + backdrop
            wall = np.setdiff1d(np.arange(len(rays)), sel)  # (every pinhole ray runs along +z)
            pw = rays[wall] * ((centre[2] + rig.backdrop) / rays[wall, 2])[:, None]
            sel = np.concatenate([sel, wall])
            p_cam = np.concatenate([p_cam, pw])
            n_cam = np.concatenate([n_cam, np.broadcast_to([0.0, 0.0, -1.0], pw.shape)])
            p_obj = np.concatenate([p_obj, (pw - centre) @ turn])
            n_obj = np.concatenate([n_obj, np.broadcast_to([0.0, 0.0, -1.0], pw.shape) @ turn])
            on_object = np.concatenate([on_object, np.zeros(len(wall), bool)])

        cos_view = np.maximum(np.abs(np.einsum("ij,ij->i", n_cam, rays[sel])), COS_VIEW_MIN)
        area = p_cam[:, 2] ** 2 * rays[sel, 2] / (cam.fx * cam.fy * cos_view)

        xy_p = proj.project(proj.to_projector(p_cam))
        in_frame = (
            (proj.to_projector(p_cam)[:, 2] > 0)
            & (xy_p[:, 0] >= -0.5) & (xy_p[:, 0] <= proj.width - 0.5)
            & (xy_p[:, 1] >= -0.5) & (xy_p[:, 1] <= proj.height - 0.5)
        )
        to_light = proj.centre - p_cam
        dist = np.linalg.norm(to_light, axis=1)
        to_light /= dist[:, None]
        cos_in = np.einsum("ij,ij->i", n_cam, to_light)
        lit = in_frame & (cos_in > 0)
        lit[lit] &= ~self._shadowed(p_obj[lit], n_obj[lit], to_light[lit] @ turn)
        e = np.where(lit, cos_in * (rig.reference_distance / dist) ** 2, 0.0)

        mat = self._shade(p_obj, on_object)
        skew = np.array([rig.mfp_skew, 1.0, 1.0 / rig.mfp_skew])
        mfp = mat.mfp * rig.sss_scale * np.where(on_object[:, None], skew, 1.0)
        rate = burley_scale(mat.albedo) / mfp

        def to_map(values: np.ndarray, fill: float) -> np.ndarray:
            out = np.full((h * w,) + values.shape[1:], fill, values.dtype)
            out[sel] = values
            return out.reshape((h, w) + values.shape[1:])

        nan = np.nan
        self.mask = to_map(np.ones(len(sel), bool), False)
        self.object_mask = to_map(on_object, False)
        self.points = to_map(p_cam.astype(np.float32), nan)
        self.normals = to_map(n_cam.astype(np.float32), nan)
        self.area = to_map(area.astype(np.float32), nan)
        self.irradiance = to_map(e.astype(np.float32), 0.0)
        self.lit = to_map(lit, False)
        self.proj_xy = to_map(np.where(lit[:, None], xy_p, nan).astype(np.float32), nan)
        self.material = to_map(mat.label, -1)
        self.albedo = to_map(mat.albedo.astype(np.float32), nan)
        self.mfp = to_map(mfp.astype(np.float32), nan)
        self.rate = to_map(rate.astype(np.float32), nan)
        self.rho_s = to_map(mat.rho_s.astype(np.float32), nan)
        self.light_dir = to_map((-to_light).astype(np.float32), nan)  # the direction projector light travels
        self.cos_in = to_map(np.clip(cos_in, 0.0, 1.0).astype(np.float32), 0.0)
        self.cos_view = to_map(cos_view.astype(np.float32), nan)

    def _shadowed(self, p_obj: np.ndarray, n_obj: np.ndarray, light_obj: np.ndarray) -> np.ndarray:
        """Shadow rays toward the projector (object space), sphere-traced through the object's bounding sphere
        (from the surface for the object's own points, from where they enter it for the backdrop's)."""
        origins = p_obj + SHADOW_OFFSET * n_obj
        t0, t1, meets = g.ray_sphere(origins, light_obj, self.obj.radius)
        t0 = np.maximum(t0, SHADOW_OFFSET)
        return g.sphere_trace(self.obj.sdf, origins, light_obj, np.where(meets, t0, np.inf), t1)[1]

    def _shade(self, p_obj: np.ndarray, on_object: np.ndarray) -> MaterialSample:
        """Materials of the (N, 3) object-space surface points: the object's where ``on_object`` (N,), the
        backdrop's elsewhere."""
        if on_object.all():
            return self.obj.shade(p_obj)
        parts = ((on_object, self.obj.shade(p_obj[on_object])), (~on_object, uniform(MATERIALS["backdrop"])(p_obj[~on_object])))
        fields = {}
        for name in ("albedo", "mfp", "rho_s", "label"):
            like = getattr(parts[0][1], name)
            fields[name] = np.empty((len(p_obj),) + like.shape[1:], like.dtype)
            for where, sample in parts:
                fields[name][where] = getattr(sample, name)
        return MaterialSample(**fields)

    # --- light transport -----------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape

    def _check_patterns(self, patterns: np.ndarray) -> np.ndarray:
        pats = np.asarray(patterns, np.float32)
        proj = self.rig.projector
        if pats.ndim in (2, 3) and pats.shape[:2] == (proj.height, proj.width):
            pats = pats[None]
        if pats.ndim not in (3, 4) or pats.shape[1:3] != (proj.height, proj.width) or (pats.ndim == 4 and pats.shape[3] != 3):
            raise InputError(
                f"patterns must be (P, {proj.height}, {proj.width}) or (P, {proj.height}, {proj.width}, 3), got {pats.shape}"
            )
        if not np.isfinite(pats).all():
            raise InputError("patterns contain NaN or inf")
        return pats

    def emitted(self, patterns: np.ndarray, pixels: np.ndarray | None = None) -> np.ndarray:
        """Projector light above black, ``(1 - black) * L**gamma``, looked up bilinearly at the lit
        pixels' correspondences (0 outside the projector image) -> (N, P, 3) for flat ``pixels``."""
        pats = self._check_patterns(patterns)
        proj = self.rig.projector
        idx = self.transport.lit_index if pixels is None else pixels
        light = np.clip(pats, 0, 1)
        if light.ndim == 3:
            light = light[..., None]  # mono patterns stay one channel until the lookup
        lit = light > 0
        on = lit.any(axis=(0, 3))  # projector pixels any pattern lights
        scale, gamma = np.float32(1 - proj.black), np.float32(proj.gamma)
        if on.mean() < SPARSE_SHARE:  # dot grids: the response only where light is (same values)
            light[lit] = scale * light[lit] ** gamma
        else:
            light = scale * light**gamma
        xy = self.proj_xy.reshape(-1, 2)[idx]
        out = _sample_sparse(light, xy, on)
        return np.broadcast_to(out, out.shape[:2] + (3,))

    def _unit_light(self) -> np.ndarray:
        """Unit emitted light over the whole projector image, looked up at the lit pixels (N, 1, 3)."""
        return self.emitted(np.ones((1,) + self.shape_projector, np.float32)) / (1 - self.rig.projector.black)

    def unit_white(self) -> np.ndarray:
        """Image (H, W, 3) under unit emitted light everywhere: the black level's image is black times it."""
        if self._unit_white is None:
            self._unit_white = self._splat(self._unit_light())[0]
        return self._unit_white

    def _splat(self, light: np.ndarray, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        lit = np.flatnonzero((light > 0).any(axis=(1, 2)))
        return self.transport.splat(self.transport.lit_index[lit], np.ascontiguousarray(light[lit]), progress)

    def render(self, patterns: np.ndarray, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
        """Noise-free images (P, H, W, 3) float32 in linear camera units under projector patterns.

        Cost is proportional to the pixels lit by some pattern; the projector black level adds
        ``black * unit_white()``, computed once per scene (with the first render).
        """
        light = self.emitted(patterns)
        if self._unit_white is None:  # share the pass: one extra all-ones pattern
            images = self._splat(np.concatenate([light, self._unit_light()], axis=1), progress)
            self._unit_white, images = images[-1], images[:-1]
        else:
            images = self._splat(light, progress)
        images += np.float32(self.rig.projector.black) * self._unit_white  # in place: 5 -> 1.7 ms per 1080p frame
        return images

    @property
    def shape_projector(self) -> tuple[int, int]:
        return self.rig.projector.height, self.rig.projector.width

    def footprints(self, pixels: np.ndarray) -> np.ndarray:
        """Exact footprints (N, K, K, 3) of camera pixels (N, 2) int (y, x), centred at K // 2."""
        pix = np.asarray(pixels, np.int64).reshape(-1, 2)
        h, w = self.shape
        if ((pix < 0) | (pix >= (h, w))).any():
            raise InputError(f"pixels must lie inside the {w}x{h} image")
        return self.transport.footprints(pix[:, 0] * w + pix[:, 1])

    def capture(
        self,
        patterns: np.ndarray,
        rng: np.random.Generator | None = None,
        exposure: float = 1.0,
        raw: bool = False,
        progress: Callable[[int, int], None] | None = None,
    ) -> np.ndarray:
        """Noisy sensor frames: raw uint16 Bayer (P, H, W), or developed RGB float32 (P, H, W, 3) in
        linear camera units (same scale as :meth:`render`). Without ``rng``, a generator seeded with
        the scene's ``seed`` is used (the same noise on every call)."""
        if not exposure > 0:
            raise InputError(f"exposure must be positive, got {exposure}")
        rng = rng if rng is not None else np.random.default_rng(self.seed)
        return self.sense(self.render(patterns, progress), rng, exposure, raw)

    def sense_noise_free(self, images: np.ndarray, exposure: float = 1.0) -> np.ndarray:
        """Noise-free images (P, H, W, 3) through the camera without its noise: Bayer sampling (none for a
        three-chip camera), clipping and the ISP (demosaicing), what the camera would record on average.
        Evaluation only."""
        from sssphase_core.sim.sensor import expose_noise_free

        sensor = self.rig.sensor
        frames = expose_noise_free(images, sensor, exposure)
        scale = sensor.dn_per_unit(exposure)
        return develop(frames, sensor, scale)

    def sense(self, images: np.ndarray, rng: np.random.Generator, exposure: float = 1.0, raw: bool = False) -> np.ndarray:
        """Noise-free images (P, H, W, 3) through the sensor: raw Bayer frames, or developed by the ISP."""

        sensor = self.rig.sensor
        frames = expose(images, sensor, rng, exposure)
        if raw:
            return frames
        return develop(frames, sensor, sensor.dn_per_unit(exposure))
