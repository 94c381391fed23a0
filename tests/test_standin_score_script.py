"""The stand-in scorer's edge profile (benchmarks/standin_score.py edges) measures distance to the patterns' edges, and its
regions (``regions``) the distance to the object's silhouette; every truth is compared in the session's units."""

import numpy as np
from benchmark_script import load_benchmark

script = load_benchmark("standin_score")


def test_edge_distance_is_signed_toward_the_bright_side_whichever_way_the_edge_steps():
    pattern = np.zeros((20, 30), np.float32)
    pattern[:, 10:20] = 1.0  # bright columns 10-19: edges between 9|10 (dark to bright) and 19|20 (bright to dark)
    xp = np.array([[8.0, 9.0, 9.4, 9.6, 10.0, 12.0, 18.0, 19.6, 20.4, 25.0]], np.float32)
    yp = np.full_like(xp, 5.0)
    d = script.edge_distance(pattern, xp, yp, 1, np.ones(xp.shape, bool))
    np.testing.assert_allclose(d[0, :9], [-1.5, -0.5, -0.1, 0.1, 0.5, 2.5, 1.5, -0.1, -0.9], atol=1e-6)  # the nearer edge
    assert np.isnan(d[0, 9])  # 3 px or more from every edge
    stripes = pattern.T.copy()  # the same steps along y
    d_y = script.edge_distance(stripes, yp.T * 0 + xp.T, xp.T * 0 + 5.0, 0, np.ones(xp.T.shape, bool))
    np.testing.assert_allclose(d_y.T, d, equal_nan=True)


def test_silhouette_distance_is_positive_inside_negative_outside_and_grows_away_from_the_edge():
    inside = np.zeros((40, 40), bool)
    inside[10:30, 10:30] = True
    d = script.silhouette_distance(inside)
    assert (d[inside] > 0).all() and (d[~inside] < 0).all()
    assert abs(d[20, 10] - 1.0) < 0.1 and abs(d[20, 9] + 1.0) < 0.1  # the pixels either side of the edge
    assert abs(d[20, 19] - 10.0) < 0.5 and abs(d[20, 0] + 10.0) < 0.5  # 10 px in, 10 px out
    labels = [label for label, lo, hi in script.REGIONS if lo < d[20, 25] <= hi]
    assert labels == ["3-12 px inside"]  # 6 px from the right edge


def test_truth_is_put_in_the_sessions_units_by_the_frame_scale_that_the_import_recorded():
    class Imported:  # what the scorer reads of a session: its manifest's rig
        def __init__(self, rig: dict) -> None:
            self.manifest = {"rig": rig}

    assert script.session_scale(Imported({"frame_scale": 2.75, "imported": True})) == 2.75
    assert script.session_scale(Imported({"imported": True})) == 1.0  # sessions from before it was recorded
