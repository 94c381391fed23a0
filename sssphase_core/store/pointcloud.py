"""Point clouds as binary PLY files (trimesh writes them), coloured by a capture, written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sssphase_core.store.files import atomic_path


def write_point_cloud(path: Path | str, points: np.ndarray, colour: np.ndarray | None = None) -> int:
    """Write the finite points of ``points`` (H, W, 3) as a binary little-endian PLY (x y z float32, in the points'
    unit), each coloured by ``colour`` (H, W, 3) linear light (sRGB-encoded at an exposure that puts the points'
    99.5th percentile at white; None: grey). Returns how many points it holds."""
    import trimesh

    from sssphase_core.processing.colour import display_scale, srgb

    keep = np.isfinite(points).all(-1)
    xyz = points[keep].astype(np.float32)
    if colour is None:
        rgb = np.full((len(xyz), 3), 200, np.uint8)
    else:
        linear = np.nan_to_num(np.asarray(colour, np.float32)[keep], nan=0.0, posinf=0.0, neginf=0.0)
        scale = display_scale(linear) if len(linear) else 1.0
        rgb = np.round(255 * srgb(linear / scale)).astype(np.uint8)
    cloud = trimesh.PointCloud(xyz, colors=rgb)
    with atomic_path(path, ".ply") as tmp:
        cloud.export(tmp, file_type="ply")
    return len(xyz)
