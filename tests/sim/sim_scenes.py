"""Small custom simulator scenes for tests (a module with a unique name, imported by the sim tests)."""

from __future__ import annotations

import numpy as np

from sssphase_core.sim import SimObject, SimScene, rig_preset, with_transport
from sssphase_core.sim import geometry as g
from sssphase_core.sim.materials import Material
from sssphase_core.sim.objects import uniform


def custom_object(sdf, material: Material, radius: float = 50.0, name: str = "test") -> SimObject:
    return SimObject(name, "test", "made for a test", radius, sdf, uniform(material))


def slab_scene(material: Material, tilt_deg: float = 0.0, transport: str = "burley", anisotropy: float = 0.0) -> SimScene:
    """A flat square slab facing the camera (optionally turned about y), filling most of the view."""
    obj = custom_object(lambda p: g.round_box(p, (0, 0, 0), (40, 40, 3), 1.0), material, radius=57.0)
    obj = SimObject(obj.name, obj.split, obj.description, obj.radius, obj.natural_sdf, obj.natural_shade,
                    tuple(tuple(row) for row in g.rotation_y(np.deg2rad(tilt_deg))))
    return SimScene(obj, rig=with_transport(rig_preset("cpu"), transport, anisotropy))


def centre_pixel(scene: SimScene) -> tuple[int, int]:
    """The lit pixel nearest the image centre."""
    ys, xs = np.nonzero(scene.lit)
    h, w = scene.shape
    i = np.argmin((ys - h / 2) ** 2 + (xs - w / 2) ** 2)
    return int(ys[i]), int(xs[i])
