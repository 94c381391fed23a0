"""Point clouds and range-image meshes as binary PLY files (trimesh writes them), coloured by a capture, written
atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sssphase_core.store.files import atomic_path

#: Neighbouring pixels are joined into triangles only where their points lie within this many of the view's median
#: neighbour spacings of each other: a depth step (an occluding edge, the object in front of a wall) is no surface.
MESH_EDGE_SPACINGS = 4.0


def _colours(linear: np.ndarray | None, n: int) -> np.ndarray:
    """(N, 3) linear light -> 8-bit sRGB at an exposure that puts its 99.5th percentile at white; None: grey."""
    from sssphase_core.processing.colour import display_scale, srgb

    if linear is None:
        return np.full((n, 3), 200, np.uint8)
    linear = np.nan_to_num(np.asarray(linear, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    scale = display_scale(linear) if len(linear) else 1.0
    return np.round(255 * srgb(linear / scale)).astype(np.uint8)


def write_point_cloud(path: Path | str, points: np.ndarray, colour: np.ndarray | None = None) -> int:
    """Write the finite points of ``points`` (H, W, 3) as a binary little-endian PLY (x y z float32, in the points'
    unit), each coloured by ``colour`` (H, W, 3) linear light (sRGB-encoded at an exposure that puts the points'
    99.5th percentile at white; None: grey). Returns how many points it holds."""
    import trimesh

    keep = np.isfinite(points).all(-1)
    xyz = points[keep].astype(np.float32)
    cloud = trimesh.PointCloud(xyz, colors=_colours(None if colour is None else np.asarray(colour)[keep], len(xyz)))
    with atomic_path(path, ".ply") as tmp:
        cloud.export(tmp, file_type="ply")
    return len(xyz)


def range_mesh_faces(points: np.ndarray) -> np.ndarray:
    """The triangles (F, 3) of an organised cloud (H, W, 3; NaN where none) as a range image meshes it: each square of
    four neighbouring pixels split into two along its anti-diagonal, a triangle kept where its three points exist and
    its edges are within :data:`MESH_EDGE_SPACINGS` median neighbour spacings; indices into the finite points in row
    order, wound so that the normals face the camera (image x right, y down, depth along +z)."""
    p = np.asarray(points, np.float64)
    valid = np.isfinite(p).all(-1)
    index = np.full(valid.shape, -1, np.int64)
    index[valid] = np.arange(int(valid.sum()))
    with np.errstate(invalid="ignore"):
        across = np.linalg.norm(p[:, 1:] - p[:, :-1], axis=-1)  # (H, W-1)
        down = np.linalg.norm(p[1:] - p[:-1], axis=-1)  # (H-1, W)
        diagonal = np.linalg.norm(p[1:, :-1] - p[:-1, 1:], axis=-1)  # (H-1, W-1): (y, x+1) to (y+1, x)
        steps = np.concatenate([across[np.isfinite(across)], down[np.isfinite(down)]])
        if not steps.size:
            return np.zeros((0, 3), np.int64)
        limit = MESH_EDGE_SPACINGS * float(np.median(steps))
        a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
        short_bc = diagonal < limit
        first = (a >= 0) & (b >= 0) & (c >= 0) & (across[:-1] < limit) & (down[:, :-1] < limit) & short_bc
        second = (b >= 0) & (c >= 0) & (d >= 0) & (across[1:] < limit) & (down[:, 1:] < limit) & short_bc
    return np.concatenate([np.stack([a[first], c[first], b[first]], -1), np.stack([b[second], c[second], d[second]], -1)])


def write_range_mesh(path: Path | str, points: np.ndarray, colour: np.ndarray | None = None) -> tuple[int, int]:
    """Write an organised cloud (H, W, 3) as a binary PLY mesh: its finite points (coloured as
    :func:`write_point_cloud` colours them) and the triangles :func:`range_mesh_faces` joins them by. Returns how many
    points and triangles it holds."""
    return write_range_meshes(path, [(points, colour)])


def write_range_meshes(path: Path | str, parts: list[tuple[np.ndarray, np.ndarray | None]]) -> tuple[int, int]:
    """Several organised clouds (each (H, W, 3) with its colour, in one frame: a turntable's views turned into one)
    as one PLY mesh, each meshed on its own pixel grid (:func:`range_mesh_faces`); the colours share one exposure.
    Returns how many points and triangles it holds."""
    import trimesh

    xyz, faces, linear, grey, offset = [], [], [], False, 0
    for points, colour in parts:
        keep = np.isfinite(points).all(-1)
        xyz.append(points[keep].astype(np.float32))
        faces.append(range_mesh_faces(points) + offset)
        linear.append(np.zeros((int(keep.sum()), 3), np.float32) if colour is None else np.asarray(colour, np.float32)[keep])
        grey |= colour is None
        offset += int(keep.sum())
    vertices, triangles = np.concatenate(xyz), np.concatenate(faces)
    mesh = trimesh.Trimesh(vertices, triangles, vertex_colors=_colours(None if grey else np.concatenate(linear),
                                                                        len(vertices)), process=False)
    with atomic_path(path, ".ply") as tmp:
        mesh.export(tmp, file_type="ply")
    return len(vertices), len(triangles)
