"""Small sessions made of a synthetic view, for the learning tests (fixtures and tests import it)."""

from __future__ import annotations


def synthetic_sessions(root, synthetic, footprints: bool = False, views_of: dict[str, list[int]] | None = None):
    """Sessions 'one' (view 0) and 'three' (views 0, 2, 5) (or ``views_of``: {name: views}) of a synthetic view
    (with footprint crops), under ``root``."""
    import numpy as np

    from sssphase_core.store.session import Session

    v = synthetic[0][0]
    mask = np.zeros(v.psp.shape[1:3], bool)
    mask[v.pixels[:, 0], v.pixels[:, 1]] = True
    for name, views in (views_of or {"one": [0], "three": [0, 2, 5]}).items():
        s = Session.create(root, name)
        for view in views:
            w = s.begin_view(view)
            w.write("psp", v.psp)
            w.write("corr/mask", mask)
            if footprints:
                w.write("footprints/pixels", v.pixels.astype(np.int32))
                w.write("footprints/crops", np.asarray(v.footprints, np.float32))
            w.commit()
    return root
