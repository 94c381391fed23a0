"""What a session's images may hold: linear light in the camera's units (a white surface under the projector's
full white near 1), finite, not huge, at most noise below zero. One rule for `sss import` (the files it reads),
`sss validate` (the arrays a session holds) and every reader that relights or trains from them: a session
another program wrote with checksums that match can still hold numbers no capture makes."""

from __future__ import annotations

import numpy as np

#: A frame may hold at most this share of its values below ``-NEGATIVE_LIMIT x`` the view's white level
#: (Malvar's overshoot at a sharp edge reaches -0.15 x white): beyond, a black level was subtracted twice or a
#: signed format was read wrongly.
NEGATIVE_LIMIT, NEGATIVE_SHARE = 0.25, 1e-3
#: The white level below which the negative test uses this floor instead (a black object's white is noise; its
#: frames' noise may go below -0.25 x that level without anything being wrong).
LEVEL_FLOOR = 0.02
#: The largest magnitude of light a session's image may hold: beyond it, squares and sums of the fits that read
#: the images overflow float32 (the view calibration's least squares failed to converge on a white of 1e38).
MAX_LIGHT = 1e6
#: The arrays of a view that hold light (by name or prefix): the PSP frames, white, black and reference captures.
LIGHT_ARRAYS = ("psp", "white", "black", "ref/", "gt/render/")  # (gt/render/: a simulated session's clean references)


def white_level(white: np.ndarray) -> float:
    """(H, W, 3) white capture -> its level: the 99.9th percentile of its finite values (0 when none is)."""
    w = np.asarray(white, np.float32)
    finite = w[np.isfinite(w)]
    return float(np.percentile(finite, 99.9)) if finite.size else 0.0


def far_below_zero(image: np.ndarray, level: float) -> float:
    """The share of ``image``'s values below ``-NEGATIVE_LIMIT x level`` when it exceeds :data:`NEGATIVE_SHARE`
    (a black level subtracted twice, a signed format read wrongly), else 0: noise around zero passes."""
    x = np.asarray(image)
    share = np.count_nonzero(x < -NEGATIVE_LIMIT * level) / max(x.size, 1)
    return float(share) if share > NEGATIVE_SHARE else 0.0


def light_problem(name: str, image: np.ndarray, level: float | None = None) -> str | None:
    """What is wrong with an image of light named ``name`` (one clause to follow its name), or None: NaN or
    infinite values, magnitudes beyond :data:`MAX_LIGHT`, or, given the view's white ``level``
    (:func:`white_level`), more than :data:`NEGATIVE_SHARE` of its values below ``-NEGATIVE_LIMIT x`` that level."""
    x = np.asarray(image)
    if x.dtype.kind not in "fiub":  # complex light was relit from its real part without a word
        return f"{name} holds {x.dtype} values; images are real numbers of light"
    bad = int(np.count_nonzero(~np.isfinite(x)))
    if bad:
        return f"{name} holds {bad} NaN or infinite values; images must be finite"
    top = float(np.abs(x).max(initial=0.0))
    if top > MAX_LIGHT:
        return (f"{name} holds values up to {top:.3g}: images are linear light in the camera's units (a white surface "
                f"under full white near 1), at most {MAX_LIGHT:.0g}")
    if level is not None:
        far = far_below_zero(x, max(level, LEVEL_FLOOR))
        if far:
            return (f"{name}: {100 * far:.3g}% of its values are below -{NEGATIVE_LIMIT:g} x the white level "
                    f"(down to {float(x.min()):.3g}, white {level:.3g}): frames must be linear light, at most noise "
                    "below zero")
    return None


def projector_light(white: np.ndarray, black: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(light, lit)``: the projector's light in a view (white less black, colours summed, float64; the white alone
    without a black) and where it is above a fifth of its 99th percentile, both (H, W)."""
    w = np.asarray(white, np.float64)
    light = (w - (0.0 if black is None else np.asarray(black, np.float64))).reshape(*w.shape[:2], -1).sum(-1)
    return light, light > 0.2 * float(np.percentile(light, 99))


def holds_light(array_name: str) -> bool:
    """Whether a view's array of that name holds light (:data:`LIGHT_ARRAYS`)."""
    return any(array_name == a or (a.endswith("/") and array_name.startswith(a)) for a in LIGHT_ARRAYS)
