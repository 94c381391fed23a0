"""The backend names a user may give and the checks that refuse them before any work (no torch is
imported unless a decoder checkpoint is read): :data:`MODEL_FREE`, :data:`BLENDS`, :func:`check_backends`."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sssphase_core.errors import InputError

MODEL_FREE = ("none", "exact", "measured")  # footprint sources that are data, not a model: never calibrated
#: Backends that blend several models by the view calibration (:func:`relight_view` ``also``).
BLENDS: dict[str, tuple[str, ...]] = {"blend": ("torch", "analytic")}


def check_backends(names: Sequence[str], checkpoint: Path | str | None) -> None:
    """Refuse unknown footprint sources, and the decoder's without a readable checkpoint, before any work
    starts (a missing or foreign checkpoint is one line before any progress is shown)."""
    from sssphase_core.learning.backends import available_backends

    known = [*MODEL_FREE, *BLENDS, *available_backends()]
    for name in names:
        if name not in known:
            raise InputError(f"unknown backend {name!r}; available: {', '.join(sorted(set(known)))}")
        needs_checkpoint(name, checkpoint)
    if checkpoint is not None and any(uses_decoder(n) for n in names):
        from sssphase_core.learning.runlog import check_checkpoint_file

        check_checkpoint_file(checkpoint)  # a missing or foreign file is refused without importing torch
        from sssphase_core.learning.training.checkpoints import load_decoder

        load_decoder(checkpoint)  # raises DataError naming what the file is, or weights that are not finite


#: The stretch, along x, y and both (beside the footprints softened), of each model's footprints in the view
#: calibration (``relight_view``'s ``widen``) for backends that run the decoder, unless the user gives one
#: (``--widen``; 1: none). A decoder's footprint widths are a prediction, too narrow on materials wider than its
#: training objects' (the simulator's unseen hand: 1.5 dB below the analytic model's; an independent path tracer's
#: skin: a quarter too narrow), and the calibration of the footprints as they are can only narrow them; the analytic
#: model's widths (one per axis) are fitted to the view's own fringes. Measured in docs/benchmarks/relighting.md.
DECODER_WIDEN = 1.3
#: The largest stretch of a model's footprints in the view calibration (``relight_view``'s ``widen``, ``--widen``).
WIDEN_MAX = 4.0
#: A widened model's members in the view calibration, in their order (:func:`~sssphase_core.relight.engine.member_maps`):
#: its footprints stretched along x, along y and along both, and softened at their own width.
WIDEN_MEMBERS = ("x", "y", "both", "soft")


def widen_for(backend: str, widen: float | None) -> float | None:
    """The stretch of the calibration's members for ``backend``: ``widen`` as given (1: none), or by default
    :data:`DECODER_WIDEN` for backends that run the decoder and none for the others."""
    if widen is None:
        return DECODER_WIDEN if uses_decoder(backend) else None
    return None if widen == 1 else float(widen)


def unused_widen_note(backends: Sequence[str], widen: float | None) -> str | None:
    """The note that ``--widen`` has no effect, where it is given and every one of ``backends`` is data, not a model
    (:data:`MODEL_FREE`: never calibrated, so nothing is stretched); None otherwise."""
    if widen is None or any(b not in MODEL_FREE for b in backends):
        return None
    return (f"note: --widen is not used by --backend {','.join(backends)} (its footprints are data, not a model: "
            "the view calibration that stretches them does not run)")


def uses_decoder(name: str) -> bool:
    """Whether backend ``name`` runs the decoder (``torch``, or a blend with it): it needs a checkpoint."""
    return name == "torch" or "torch" in BLENDS.get(name, ())


def needs_checkpoint(name: str, checkpoint: Path | str | None) -> None:
    """Refuse the decoder, or a blend with it, without a decoder checkpoint."""
    if checkpoint is not None or not uses_decoder(name):
        return
    if name == "torch":
        raise InputError("the torch backend needs --checkpoint (a decoder checkpoint from `sss train decoder`)")
    raise InputError(f"the {name} backend blends the decoder in: it needs --checkpoint (a decoder from `sss train decoder`)")
