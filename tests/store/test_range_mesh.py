"""A view's points as a range-image mesh (`sss geometry --mesh`): neighbouring pixels joined into triangles that
face the camera, none across a depth step or a hole."""

from __future__ import annotations

import numpy as np
import pytest

from sssphase_core.store.pointcloud import MESH_EDGE_SPACINGS, range_mesh_faces, write_range_mesh


def _plane(h: int = 5, w: int = 6, depth: float = 400.0) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w].astype(float)
    return np.stack([x, y, depth + 0 * x], -1)


def test_a_plane_is_two_triangles_a_square_all_facing_the_camera():
    trimesh = pytest.importorskip("trimesh")
    p = _plane()
    faces = range_mesh_faces(p)
    assert faces.shape == (2 * 4 * 5, 3) and len(np.unique(faces)) == 30
    normals = trimesh.Trimesh(p.reshape(-1, 3), faces, process=False).face_normals
    assert np.allclose(normals, [0, 0, -1])  # toward the camera at the origin


def test_no_triangle_spans_a_depth_step_or_a_hole():
    p = _plane()
    p[:, 3:, 2] += 3 * MESH_EDGE_SPACINGS  # the right half far behind: an occluding edge
    assert len(range_mesh_faces(p)) == 2 * 4 * 5 - 2 * 4  # the column of squares across the step is left open
    p[2, 1] = np.nan  # a hole: the six triangles of that pixel go
    faces = range_mesh_faces(p)
    assert len(faces) == 32 - 6 and (faces < np.isfinite(p).all(-1).sum()).all()
    assert len(range_mesh_faces(np.full((4, 4, 3), np.nan))) == 0 and len(range_mesh_faces(np.zeros((1, 1, 3)))) == 0


def test_the_mesh_file_holds_the_points_and_their_triangles(tmp_path):
    trimesh = pytest.importorskip("trimesh")
    p = _plane()
    p[0, 0] = np.inf  # not a point
    colour = np.ones(p.shape, np.float32)
    n_points, n_faces = write_range_mesh(tmp_path / "mesh.ply", p, colour)
    mesh = trimesh.load(tmp_path / "mesh.ply", process=False)
    assert len(mesh.vertices) == n_points == 29 and len(mesh.faces) == n_faces == 40 - 1
    np.testing.assert_allclose(mesh.vertices, p[np.isfinite(p).all(-1)], atol=1e-4)
