"""Does a view's fringe modulation follow its white-consistent gain, as an exit texture's would?

    python benchmarks/exit_texture_slope.py SESSION [SESSION ...]

For view 0 of each session: the analytic model (uncalibrated) relit under the view's 8 PSP patterns and full white;
the gain's departure ``g - 1`` (the nine-capture white over the model's relit white, as
:func:`~sssphase_core.relight.calibration.exit_gain` forms it before shrinking) and the ratio of the captured
fringes' modulation to the model's, ``a - 1``, on the decoded pixels where the model's white is above the floor and
its fringes are modulated. Prints, per colour, the least-squares slope of ``a - 1`` on ``g - 1`` (the 1st-99th
percentiles of ``g - 1``) and their correlation. A texture where light leaves the surface multiplies the fringes as
it does the white (slope 1); light whose error comes from far entry points would not (slope 0).
"""

from __future__ import annotations

import sys

import numpy as np

from sssphase_core.relight.backends import make_sources
from sssphase_core.relight.calibration import WHITE_FLOOR, exit_white, model_inputs
from sssphase_core.relight.engine import relight
from sssphase_core.relight.pipeline import full_white
from sssphase_core.relight.views import load_view
from sssphase_core.store.session import Session


def modulation(psp: np.ndarray) -> np.ndarray:
    """(8, H, W, 3) PSP frames (4 shifts of x, then of y) -> (H, W, 3) the mean of the two orientations' amplitudes."""
    return 0.25 * (np.hypot(psp[0] - psp[2], psp[1] - psp[3]) + np.hypot(psp[4] - psp[6], psp[5] - psp[7]))


def main(paths: list[str]) -> None:
    for path in paths:
        rv = load_view(Session.open(path), 0)
        (analytic, k), = make_sources("analytic", rv)
        relit = relight(analytic, rv.proj, [*rv.psp_patterns, full_white(*rv.proj.projector_size)], k, white=rv.white)
        psp, lost = model_inputs(rv)
        captured, model = modulation(np.asarray(psp, np.float32)), modulation(relit[:8])
        gain = exit_white(rv) / np.maximum(relit[8], 1e-6)
        ok = rv.proj.mask[..., None] & (relit[8] > WHITE_FLOOR) & (model > 0.02 * relit[8]) & ~lost[..., None]
        cells = []
        for c in range(3):
            x, y = gain[..., c][ok[..., c]] - 1, captured[..., c][ok[..., c]] / model[..., c][ok[..., c]] - 1
            lo, hi = np.percentile(x, [1, 99])
            x, y = x[(x > lo) & (x < hi)], y[(x > lo) & (x < hi)]
            slope = float(((x - x.mean()) * (y - y.mean())).sum() / ((x - x.mean()) ** 2).sum())
            cells.append(f"{slope:.2f} (correlation {np.corrcoef(x, y)[0, 1]:.2f}, sd of g - 1 {x.std():.3f})")
        print(f"{rv.object}: slope of the fringe modulation's ratio on the gain's departure, R / G / B: " + "; ".join(cells))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(sys.argv[1:])
