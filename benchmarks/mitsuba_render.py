"""Frames of translucent objects rendered by Mitsuba 3, an independent volumetric path tracer, in the
geometry of the ``cpu`` rig (`sss rigs`): the lab's workflow on physics we did not write (issue 42).

Mitsuba is not a dependency of sssphase; install it beside it, by hand (the ``mitsuba`` extra pins it):

    pip install -c constraints.txt -e ".[mitsuba]"   # mitsuba 3.5.2: its LLVM variant runs on Debian's LLVM 15
    export DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1   # else the slower scalar variant

    python benchmarks/mitsuba_render.py OUT NAME --shape SHAPE --medium MEDIUM [--scale S] [--g G] \
        [--train | --test] [--spp N] [--seed N] [--groups G]
    sss import OUT/NAME --object NAME --projector 256x192 --out SESSIONS
    python benchmarks/mitsuba_render.py OUT NAME --converged [--spp N] [--groups 8]   # after --test

The scene: the rig's pinhole camera at the origin looking along +z, its projector (Mitsuba's ``projector``
emitter, a textured point light) 150 mm to the right and verged on the turntable centre 400 mm away, one
object of a homogeneous medium there (Jensen et al. 2001's measured coefficients, in mm^-1, times
``--scale``; a Henyey-Greenstein phase function of mean cosine ``--g`` with the scattering coefficient
sigma_s'/(1-g), so the reduced coefficients stay the measured ones) behind an index-matched boundary,
and a diffuse grey wall behind it. Transport is Mitsuba's ``volpath`` (unbounded depth, Russian
roulette), so footprints come from random walks, with single scattering, the diffusion tail, the
forward lean of oblique light and the object's finite thickness and curvature -- nothing of sssphase's
profiles. Extinction is grey (the channels' mean): colour lives in the absorption, because with per-colour
extinction Mitsuba's RGB mode samples each free flight for one colour and weights the others by ratios that
multiply over the hundreds of bounces of a high-albedo walk.

``--train`` renders the capture plan with dot grids (spacing 20, 400 frames, a `sss train` object);
``--test`` the PSP, white and reference patterns (checkerboard, stripes_x, stripes_y) of an unseen one.
All frames of a view share the sampler's seed (common random numbers): every frame is then exactly the
same linear map of its pattern, as a real scene is, and the Monte-Carlo error is a fixed pattern of the
scene rather than noise that changes between frames. The camera adds its own noise per frame (Poisson
shot noise of 6000 photons per unit, Gaussian read noise 7e-4; no colour filter array). Beside the
folder: the noise-free references (``NAME_clean_ref__PATTERN.exr``, for `benchmarks/standin_score.py`),
the exact projector coordinates of every camera pixel's surface point with its incidence angle
(``NAME_geometry.npz``: xp, yp, theta, mask) and what was rendered (``NAME.json``).

The ``clean`` references share the frames' random numbers, so they hold the same fixed Monte-Carlo pattern as
the captures, fireflies included (one pixel of a 32-spp apple is 19x the white level): a model that copies the
captures' pattern is scored as if it were physics. ``--converged`` (after ``--test`` of the same OUT and NAME:
the object, medium and exposure come from its ``NAME.json``) renders the reference patterns alone, without
camera noise, ``--groups`` times at ``--spp`` samples (by default 4 x the ``--test`` render's samples in all) with
random numbers of their own, and keeps each pixel's
mean of the groups without its highest and lowest (a trimmed mean: a firefly falls in one group). It writes
``NAME_converged_ref__PATTERN.exr``, the truth to score against (`standin_score.py --truth converged`), and the
trimmed means of its two halves of groups (``NAME_converged_half{0,1}_ref__PATTERN.exr``: their difference is the
reference's own noise).

``--groups G`` (G >= 3) with ``--train`` or ``--test`` renders every frame G times, each with random numbers of its
own (the same G seeds for every frame), and keeps their trimmed mean: captures, and clean references, without the
fixed pattern's fireflies, at G times the cost.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from sssphase_core.sim.materials import JENSEN_2001

#: the measured media: Jensen et al. 2001's reduced scattering sigma_s' and absorption sigma_a (mm^-1), RGB
MEDIA = JENSEN_2001
SHAPES = ("sphere", "ellipsoid", "box", "blob")
CENTRE = (0.0, 0.0, 400.0)
WALL_Z = 480.0
SHOT_PHOTONS, READ_NOISE, BLACK = 6000.0, 7e-4, 0.002
REFERENCES = ("checkerboard", "stripes_x", "stripes_y")


def medium_coefficients(name: str, scale: float, g: float) -> tuple[float, list[float]]:
    """Grey extinction sigma_t (mm^-1, the channels' mean of sigma_s'/(1-g) + sigma_a, times ``scale``) and the
    per-channel single-scattering albedo that keeps each channel's measured absorption: sigma_a = sigma_t (1 - albedo)
    (sigma_t at least 1.02 x the largest absorption, which only ketchup's blue needs)."""
    s_red, s_abs = (np.asarray(v) * scale for v in MEDIA[name])
    sigma_t = float(max(np.mean(s_red / (1 - g) + s_abs), 1.02 * s_abs.max()))
    return sigma_t, [float(v) for v in 1 - s_abs / sigma_t]


def set_variant():  # noqa: ANN201
    import mitsuba as mi

    for v in ("llvm_ad_rgb", "scalar_rgb"):
        try:
            mi.set_variant(v)
            return mi
        except (ImportError, AttributeError, RuntimeError):
            continue
    raise SystemExit("mitsuba has neither llvm_ad_rgb nor scalar_rgb")


def sphere_obj(path: Path, radii: tuple[float, float, float], lumps: int, seed: int) -> None:
    """A closed UV sphere with semi-axes ``radii`` and ``lumps`` low-order harmonic bumps, as a Wavefront OBJ."""
    rng = np.random.default_rng(seed)
    nt, nphi = 48, 96
    theta = np.linspace(0, np.pi, nt + 1)
    phi = np.linspace(0, 2 * np.pi, nphi, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    r = np.ones_like(t)
    for _ in range(lumps):
        a, m, n, ph = rng.uniform(0.04, 0.09), rng.integers(1, 4), rng.integers(1, 4), rng.uniform(0, 2 * np.pi)
        r += a * np.sin(m * t) * np.cos(n * p + ph)
    xyz = np.stack([r * np.sin(t) * np.cos(p) * radii[0], r * np.cos(t) * radii[1], r * np.sin(t) * np.sin(p) * radii[2]], -1)
    verts = [xyz[0, 0]] + [xyz[i, j] for i in range(1, nt) for j in range(nphi)] + [xyz[nt, 0]]
    idx = lambda i, j: 2 + (i - 1) * nphi + (j % nphi)  # noqa: E731  (1-based OBJ indices)
    faces = [(1, idx(1, j + 1), idx(1, j)) for j in range(nphi)]
    for i in range(1, nt - 1):
        for j in range(nphi):
            faces += [(idx(i, j), idx(i, j + 1), idx(i + 1, j + 1)), (idx(i, j), idx(i + 1, j + 1), idx(i + 1, j))]
    last = len(verts)
    faces += [(idx(nt - 1, j), idx(nt - 1, j + 1), last) for j in range(nphi)]
    lines = [f"v {v[0]:.5f} {v[1]:.5f} {v[2]:.5f}" for v in verts] + [f"f {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def object_dict(mi, shape: str, medium: dict, out: Path, name: str, seed: int, shrink: float = 0.0,  # noqa: ANN001
                exterior: dict | None = None) -> dict:
    """The object's boundary (null BSDF) holding ``medium``; ``shrink`` mm less in every semi-axis (a coated
    object's core, whose ``exterior`` is the coat's medium)."""
    T = mi.ScalarTransform4f
    at = T().translate(list(CENTRE))
    base = {"bsdf": {"type": "null"}, "interior": medium} | ({"exterior": exterior} if exterior else {})
    if shape == "sphere":
        return {"type": "sphere", "to_world": at.scale(42.0 - shrink), **base}
    if shape == "box":
        return {"type": "cube", "to_world": at.rotate([0, 1, 0], 35).rotate([1, 0, 0], 25).scale(30.0 - shrink), **base}
    mesh = out / f"{name}_{shape}{'_core' if shrink else ''}.obj"
    if shape == "ellipsoid":
        sphere_obj(mesh, (58.0 - shrink, 36.0 - shrink, 40.0 - shrink), 0, seed)
        return {"type": "obj", "filename": str(mesh), "to_world": at.rotate([0, 0, 1], 25), **base}
    sphere_obj(mesh, (45.0 - shrink, 45.0 - shrink, 45.0 - shrink), 4, seed)
    return {"type": "obj", "filename": str(mesh), "to_world": at, **base}


def medium_dict(name: str, scale: float, g: float) -> dict:
    """Mitsuba's homogeneous medium of Jensen et al.'s ``name`` times ``scale``, Henyey-Greenstein ``g``."""
    sigma_t, albedo = medium_coefficients(name, scale, g)
    return {"type": "homogeneous", "sigma_t": sigma_t, "scale": 1.0, "albedo": {"type": "rgb", "value": albedo},
            "phase": {"type": "hg", "g": g} if g else {"type": "isotropic"}}


def build_scene(mi, args: argparse.Namespace, rig, out: Path):  # noqa: ANN001, ANN201
    T = mi.ScalarTransform4f
    cam, proj = rig.camera, rig.projector
    fov_cam = float(np.degrees(2 * np.arctan(cam.height / 2 / cam.fy)))
    fov_proj = float(np.degrees(2 * np.arctan(proj.width / 2 / proj.fx)))
    medium = medium_dict(args.medium, args.scale, args.g)
    if args.coat:  # a layered object: the coat's medium fills the shape, the core (--medium) a copy --coat-mm smaller
        shell = medium_dict(args.coat, args.coat_scale, 0.0)
        objects = {"object": object_dict(mi, args.shape, shell, out, args.name, args.seed),
                   "core": object_dict(mi, args.shape, medium, out, args.name, args.seed, args.coat_mm, shell)}
    else:
        objects = {"object": object_dict(mi, args.shape, medium, out, args.name, args.seed)}
    blank = np.zeros((proj.height, proj.width, 3), np.float32)
    d_proj = float(np.linalg.norm(np.asarray(CENTRE) - proj.centre))
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": -1},
        "sensor": {"type": "perspective", "fov": fov_cam, "fov_axis": "y",
                   "to_world": T().look_at(origin=[0, 0, 0], target=list(CENTRE), up=[0, -1, 0]),
                   "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": args.spp}},
        "projector": {"type": "projector", "fov": fov_proj, "scale": d_proj**2,
                      "irradiance": {"type": "bitmap", "bitmap": mi.Bitmap(blank), "raw": True,
                                     "filter_type": "nearest"},
                      "to_world": T().look_at(origin=[float(v) for v in proj.centre], target=list(CENTRE), up=[0, -1, 0])},
        "wall": {"type": "rectangle", "to_world": T().translate([0, 0, WALL_Z]).rotate([0, 1, 0], 180).scale(260),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.35, 0.35, 0.33]}}},
        **objects,
    })
    return scene, {"sigma_t_per_mm": medium["sigma_t"], "albedo": medium["albedo"]["value"], "fov_camera_deg": fov_cam, "fov_projector_deg": fov_proj}


def exact_geometry(mi, scene, rig) -> dict[str, np.ndarray]:  # noqa: ANN001
    """Each camera pixel's first surface point -> projector (xp, yp), incidence angle theta (deg), mask."""
    import drjit as dr

    cam, proj = rig.camera, rig.projector
    v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    d = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    n_px = d.shape[0]
    if dr.is_jit_v(mi.Float):
        ray = mi.Ray3f(o=mi.Point3f(0, 0, 0), d=mi.Vector3f(*(mi.Float(d[:, i].astype(np.float32)) for i in range(3))))
        si = scene.ray_intersect(ray)
        p = np.stack([np.asarray(si.p[i]) for i in range(3)], -1)
        n = np.stack([np.asarray(si.n[i]) for i in range(3)], -1)
        valid = np.asarray(si.is_valid())
    else:  # scalar: one ray at a time
        p, n = np.zeros((n_px, 3)), np.zeros((n_px, 3))
        valid = np.zeros(n_px, bool)
        for i in range(n_px):
            si = scene.ray_intersect(mi.Ray3f(o=[0, 0, 0], d=[float(x) for x in d[i]]))
            if si.is_valid():
                valid[i] = True
                p[i], n[i] = np.asarray(si.p), np.asarray(si.n)
    is_obj = valid & (p[:, 2] < WALL_Z - 1)  # the wall is the only other surface
    to_proj = proj.centre[None] - p
    dist = np.linalg.norm(to_proj, axis=1)
    w = to_proj / np.maximum(dist, 1e-9)[:, None]
    cos_in = np.abs(np.sum(n * w, axis=1))
    pc = proj.to_projector(p)
    with np.errstate(divide="ignore", invalid="ignore"):
        xp = proj.fx * pc[:, 0] / pc[:, 2] + proj.cx
        yp = proj.fy * pc[:, 1] / pc[:, 2] + proj.cy
    # lit: nothing between the point and the projector (a shadow ray, offset off the surface)
    if dr.is_jit_v(mi.Float):
        o = p + w * 1e-2
        sray = mi.Ray3f(mi.Ray3f(o=mi.Point3f(*(mi.Float(o[:, i].astype(np.float32)) for i in range(3))),
                                 d=mi.Vector3f(*(mi.Float(w[:, i].astype(np.float32)) for i in range(3)))),
                        mi.Float((dist - 2e-2).astype(np.float32)))
        lit = valid & ~np.asarray(scene.ray_test(sray))
    else:
        lit = np.zeros(n_px, bool)
        for i in np.flatnonzero(valid):
            ray = mi.Ray3f(o=[float(x) for x in p[i] + w[i] * 1e-2], d=[float(x) for x in w[i]])
            lit[i] = not scene.ray_test(mi.Ray3f(ray, float(dist[i] - 2e-2)))
    inside = lit & (xp >= -0.5) & (xp <= proj.width - 0.5) & (yp >= -0.5) & (yp <= proj.height - 0.5)
    shape = (cam.height, cam.width)
    return {"xp": np.where(inside, xp, np.nan).reshape(shape).astype(np.float32),
            "yp": np.where(inside, yp, np.nan).reshape(shape).astype(np.float32),
            "theta": np.degrees(np.arccos(np.clip(cos_in, 0, 1))).reshape(shape).astype(np.float32),
            "mask": (inside & is_obj).reshape(shape), "object": is_obj.reshape(shape)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("name")
    ap.add_argument("--shape", choices=SHAPES, default="sphere")
    ap.add_argument("--medium", choices=sorted(MEDIA), default="skin2")
    ap.add_argument("--scale", type=float, default=1.0, help="multiplies the medium's coefficients (>1: denser)")
    ap.add_argument("--g", type=float, default=0.0, help="Henyey-Greenstein mean cosine")
    ap.add_argument("--coat", choices=sorted(MEDIA), default=None,
                    help="a layered object: this medium (isotropic) in a shell --coat-mm thick around the --medium core")
    ap.add_argument("--coat-scale", type=float, default=1.0, help="multiplies the coat's coefficients")
    ap.add_argument("--coat-mm", type=float, default=0.5, help="the coat's thickness (mm)")
    kind = ap.add_mutually_exclusive_group(required=True)
    kind.add_argument("--train", action="store_true", help="with dot grids (footprints)")
    kind.add_argument("--test", action="store_true", help="with reference patterns")
    kind.add_argument("--converged", action="store_true",
                      help="after --test: its reference patterns with independent random numbers, at --spp")
    ap.add_argument("--spp", type=int, default=None,
                    help="samples per pixel (default 64; --converged: per group, by default enough for "
                         f"{CONVERGED_OVER} x the --test render's samples over the groups)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--groups", type=int, default=None,
                    help="renders per frame, each with its own random numbers, trimmed-mean combined (>= 3; "
                         "--converged: 8 by default; else 1 by default: one render)")
    args = ap.parse_args()
    if args.groups is None:
        args.groups = 8 if args.converged else 1
    if args.spp is None and not args.converged:  # (--converged: from the --test render's record)
        args.spp = 64
    if args.groups < 3 and (args.converged or args.groups != 1):
        raise SystemExit("--groups must be at least 3 (the trimmed mean drops the highest and the lowest)")
    if not -0.95 < args.g < 0.95 or not args.scale > 0:
        raise SystemExit("--g must be in (-0.95, 0.95) and --scale > 0")
    if args.coat and not (args.coat_scale > 0 and 0 < args.coat_mm < 25):
        raise SystemExit("--coat-scale must be > 0 and --coat-mm in (0, 25)")

    from sssphase_core.processing.patterns import capture_plan
    from sssphase_core.sim.rig import rig_preset
    from sssphase_core.store.exr import write_exr

    mi = set_variant()
    rig = rig_preset("cpu")
    if args.converged:
        converged_references(mi, args, rig)
        return
    folder = args.out / args.name
    folder.mkdir(parents=True, exist_ok=False)
    scene, facts = build_scene(mi, args, rig, args.out)
    params = mi.traverse(scene)
    refs = ("white", "black") + (REFERENCES if args.test else ())
    plan = capture_plan(rig.projector.width, rig.projector.height, footprints=args.train, dot_spacing=20,
                        references=refs, gamma=rig.projector.gamma)
    rng = np.random.default_rng(args.seed + 1000)

    seeds = [args.seed] if args.groups == 1 else [args.seed + FRAME_GROUP_SEED + i for i in range(args.groups)]

    def render(pattern: np.ndarray) -> np.ndarray:
        return trimmed(renders_under(mi, scene, params, pattern, rig.projector.gamma, seeds, args.spp))

    t0 = time.time()
    white = render(next(f for f in plan.frames if f.key == "white").pattern())
    geom = exact_geometry(mi, scene, rig)
    gain = 0.8 / float(np.percentile(white[geom["object"]].max(-1), 99.5))  # the camera's exposure
    np.savez_compressed(args.out / f"{args.name}_geometry.npz", **geom)
    for i, f in enumerate(plan.frames):
        img = gain * (white if f.key == "white" else render(f.pattern()))
        noisy = rng.poisson(np.maximum(img, 0) * SHOT_PHOTONS) / SHOT_PHOTONS + rng.normal(0, READ_NOISE, img.shape)
        write_exr(folder / (f.key.replace("/", "__") + ".exr"), noisy.astype(np.float32))
        if f.key.startswith("ref/"):
            write_exr(args.out / f"{args.name}_clean_{f.key.replace('/', '__')}.exr", img.astype(np.float32))
        if i % 25 == 0 or i == len(plan.frames) - 1:
            el = time.time() - t0
            print(f"{args.name}: frame {i + 1}/{len(plan.frames)} ({el:.0f} s, {el / (i + 1):.2f} s/frame)", flush=True)
    facts.update(vars(args) | {"out": str(args.out), "variant": mi.variant(), "frames": len(plan.frames),
                               "seconds": round(time.time() - t0, 1), "gain": gain, "mitsuba": mi.__version__,
                               "llvm": os.environ.get("DRJIT_LIBLLVM_PATH", "")})
    (args.out / f"{args.name}.json").write_text(json.dumps(facts, indent=1) + "\n")


#: the converged references' sampler seeds start this far from the test render's (the object's shape keeps its seed)
INDEPENDENT_SEED = 7919
#: with --groups, the frames' seeds start this far from --seed: apart from the single-render frames' and the
#: converged references'
FRAME_GROUP_SEED = 2 * INDEPENDENT_SEED


def renders_under(mi, scene, params, pattern: np.ndarray, gamma, seeds: list[int], spp: int  # noqa: ANN001
                  ) -> list[np.ndarray]:
    """The scene's camera image with the projector showing ``pattern`` (its emitted light, black level included),
    one (H, W, 3) float32 render of ``spp`` samples per seed in ``seeds``."""
    from sssphase_core.processing.projector import emitted_light

    light = BLACK + (1 - BLACK) * emitted_light(pattern[None], gamma)[0]
    params["projector.irradiance.data"] = mi.TensorXf(np.ascontiguousarray(light, dtype=np.float32))
    params.update()
    return [np.asarray(mi.render(scene, seed=s, spp=spp), dtype=np.float32) for s in seeds]


def trimmed(renders: list[np.ndarray]) -> np.ndarray:
    """Per pixel, the mean of ``renders`` without the highest and the lowest (a plain mean of fewer than 3):
    a firefly falls in one render."""
    from scipy.stats import trim_mean

    stack = np.stack(renders)
    return trim_mean(stack, 1 / len(stack), axis=0) if len(stack) >= 3 else stack.mean(axis=0)


#: --converged renders this many times the --test render's samples per pixel by default (over all its groups)
CONVERGED_OVER = 4


def converged_spp(facts: dict, groups: int, spp: int | None) -> int:
    """Samples per pixel of each of ``groups`` converged renders: ``spp`` as given, else enough for
    :data:`CONVERGED_OVER` x the ``--test`` render's (``facts``: its record; its spp times its groups), at least 64.
    A truth with fewer samples than the captures ranks models by its own noise: said in one line."""
    captured = int(facts.get("spp", 64)) * int(facts.get("groups", 1))
    if spp is None:
        return max(64, -(-CONVERGED_OVER * captured // groups))
    if spp * groups < 2 * captured:
        print(f"note: {groups} x {spp} spp is less than twice the {captured} spp of the captures: the references' own "
              "noise will weigh on every score (the default takes CONVERGED_OVER x)", flush=True)
    return spp


def converged_references(mi, args: argparse.Namespace, rig) -> None:  # noqa: ANN001
    """The reference patterns of the ``--test`` render ``OUT/NAME`` (its object, medium and exposure, from
    ``NAME.json``) without camera noise: per pixel the trimmed mean of ``args.groups`` renders of ``args.spp``
    samples, each seeded apart from the frames and from the others. Prints each pattern's own noise floor: the
    PSNR (data range 1) of the trimmed means of the two halves of the groups against each other."""
    from sssphase_core.processing.patterns import capture_plan
    from sssphase_core.store.exr import write_exr

    record = args.out / f"{args.name}.json"
    if not record.is_file():
        raise SystemExit(f"{record}: no record of a --test render of {args.name} in {args.out}; render it first")
    facts = json.loads(record.read_text())
    if not facts.get("test"):
        raise SystemExit(f"{record}: {args.name} was not rendered with --test (no reference patterns)")
    for key in ("shape", "medium", "scale", "g", "seed", "coat", "coat_scale", "coat_mm"):  # the same object
        setattr(args, key, facts.get(key))
    args.spp = converged_spp(facts, args.groups, args.spp)
    scene, _ = build_scene(mi, args, rig, args.out)
    params = mi.traverse(scene)
    plan = capture_plan(rig.projector.width, rig.projector.height, footprints=False, dot_spacing=20,
                        references=REFERENCES, gamma=rig.projector.gamma)
    t0 = time.time()
    seeds = [facts["seed"] + INDEPENDENT_SEED + i for i in range(args.groups)]
    floors = {}
    for f in (f for f in plan.frames if f.key.startswith("ref/")):
        groups = [facts["gain"] * r for r in renders_under(mi, scene, params, f.pattern(), rig.projector.gamma, seeds,
                                                            args.spp)]
        img = trimmed(groups)
        a, b = (trimmed(g) for g in np.array_split(groups, 2))
        floors[f.key] = round(float(10 * np.log10(1 / np.mean((a - b) ** 2))), 2)
        write_exr(args.out / f"{args.name}_converged_{f.key.replace('/', '__')}.exr", img.astype(np.float32))
        for i, half in enumerate((a, b)):  # their difference measures the converged reference's own noise
            write_exr(args.out / f"{args.name}_converged_half{i}_{f.key.replace('/', '__')}.exr", half.astype(np.float32))
        print(f"{args.name}: {f.key}, {args.groups} x {args.spp} spp ({time.time() - t0:.0f} s); its halves "
              f"agree to {floors[f.key]} dB", flush=True)
    facts["converged"] = {"spp": args.spp, "groups": args.groups, "seeds": seeds, "halves_psnr_db": floors,
                          "seconds": round(time.time() - t0, 1)}
    record.write_text(json.dumps(facts, indent=1) + "\n")


if __name__ == "__main__":
    main()
