"""Run checkpoints: atomic writes, safe reads (plain tensors, ``weights_only``), a run folder's best or
last checkpoint, and the encoder and decoder they hold."""

from __future__ import annotations

import errno
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import torch
from torch import nn

from sssphase_core.errors import DataError, SssError
from sssphase_core.learning.models import Decoder, Encoder, ModelPreset, get_preset
from sssphase_core.learning.runlog import (  # noqa: F401  (the run folder's layout)
    BEST,
    CHECKPOINT,
    check_checkpoint_file,
    check_same_version,
    resolve_checkpoint,
)
from sssphase_core.store.files import atomic_path

M = TypeVar("M", bound=nn.Module)


def save_checkpoint(path: Path, payload: dict) -> None:
    """Atomic ``torch.save`` (write to a temporary file, then rename): a disk that fills keeps the previous
    checkpoint and raises :class:`DataError` naming the file (torch says "unexpected pos 768 vs 662")."""
    import shutil

    existed = Path(path).exists()
    try:
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)
    except (OSError, RuntimeError) as exc:
        import resource

        free = shutil.disk_usage(Path(path).parent).free
        limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
        again = "resume" if existed else "run it again"
        if free < (1 << 20):
            why, fix = f"the disk is full ({free:,} bytes free)", f"free some space and {again}"
        elif limit != resource.RLIM_INFINITY or getattr(exc, "errno", None) == errno.EFBIG:  # (torch: "unexpected pos")
            limit_text = f"{limit:,} bytes" if limit != resource.RLIM_INFINITY else "a file system's limit"
            why, fix = f"it outgrew the largest file this process may write ({limit_text}: ulimit -f)", \
                f"raise the limit and {again}"
        else:
            why, fix = f"{str(exc).splitlines()[0][:160]} ({free:,} bytes free)", f"{again} once it can be written"
        kept = "the previous checkpoint is kept" if existed else "no checkpoint was written"
        raise DataError(f"could not write the checkpoint {path}: {why}; {kept}: {fix}") from None


def load_checkpoint(path: Path | str, *, mmap: bool = False) -> dict:
    """Load with ``weights_only=True``: tensors, dicts, lists and numbers only, never arbitrary objects.
    A run folder loads its best checkpoint (:func:`resolve_checkpoint`). Anything that is not a
    sssphase checkpoint (pickled objects, an empty or truncated file, another program's tensors) is
    refused with a :class:`DataError` that says what it is."""
    import pickle

    path = check_checkpoint_file(path)
    check_same_version(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)  # mmap: tensors read when touched
    except pickle.UnpicklingError:
        raise DataError(f"{path} is not a sssphase checkpoint: it holds pickled Python objects, which are never "
                        "loaded (only tensors, numbers and dicts)") from None
    except Exception as exc:
        lines = [line.strip().rstrip(".") for line in str(exc).strip().splitlines() if line.strip()]
        # torch's first line is only "Error(s) in loading state_dict for Decoder:": the keys follow it
        reason = "; ".join(lines[1:3] if len(lines) > 1 else lines)[:300] or type(exc).__name__
        cut = isinstance(exc, OSError) and exc.errno == errno.EINVAL  # torch seeking past a cut file's end
        if cut or "PytorchStreamReader" in reason or "miniz" in reason or "zip archive" in reason:  # a cut file
            reason = "the file is damaged or truncated (its zip archive cannot be read)"
        elif "inline_container" in reason or "not in a subdirectory" in reason:  # a zip, but not torch's layout
            reason = "it is a zip archive, but not one torch saved (no checkpoint inside)"
        raise DataError(f"cannot read checkpoint {path}: {reason}") from None
    missing = [k for k in ("kind", "preset", "encoder") if not isinstance(ckpt, dict) or k not in ckpt]
    if missing or ckpt.get("kind") not in ("pretrain", "decoder"):
        what = type(ckpt).__name__ if not isinstance(ckpt, dict) else f"a dict without {', '.join(missing) or 'a known kind'}"
        raise DataError(f"{path} is not a sssphase checkpoint ({what}); use a run folder or .pt written by "
                        "`sss train pretrain` or `sss train decoder`")
    return ckpt


def _built(make: Callable[[], M], state: object, path: Path | str, what: str) -> M:
    """``make()`` with ``state`` loaded. The module is first built on the meta device (no memory) and ``state``'s
    names and shapes are checked against it, so a checkpoint whose preset asks for a huge model but holds no
    such weights is refused before any memory is taken (it asked for 38 GB); weights that do not fit, or that are
    not all finite (NaN or infinite: every prediction would be NaN, silently zeroed downstream), are refused
    naming the file."""
    with torch.device("meta"):
        expected = {name: tuple(t.shape) for name, t in make().state_dict().items()}
    held = ({name: tuple(t.shape) for name, t in state.items() if isinstance(t, torch.Tensor)}
            if isinstance(state, dict) else {})
    missing = [n for n in expected if n not in held]
    wrong = [n for n in expected if n in held and held[n] != expected[n]]
    if missing or wrong:  # (names beyond the preset's are left to load_state_dict: older checkpoints' are dropped)
        why = ("it holds no weights" if not held else
               f"{wrong[0]} is {'x'.join(map(str, held[wrong[0]]))}, the preset's {'x'.join(map(str, expected[wrong[0]]))}"
               if wrong else f"{len(missing)} missing, first {missing[0]}")
        raise DataError(f"{path}: the {what} weights do not fit the checkpoint's preset ({why}): the checkpoint is "
                        "damaged or not a sssphase one; take another one or train again")
    module = make()
    _load_weights(module, state, path, what)
    return module


def _load_weights(module: nn.Module, state: object, path: Path | str, what: str) -> None:
    """Load ``state`` into ``module``; weights that do not fit, or that are not all finite (NaN or infinite:
    every prediction would be NaN, silently zeroed downstream), are refused naming the file."""
    try:
        module.load_state_dict(state)  # type: ignore[arg-type]
    except (RuntimeError, TypeError, AttributeError) as exc:
        lines = [line.strip().rstrip(".") for line in str(exc).strip().splitlines() if line.strip()]
        # torch's first line is only "Error(s) in loading state_dict for Decoder:": the keys follow it
        reason = "; ".join(lines[1:3] if len(lines) > 1 else lines)[:300] or type(exc).__name__
        raise DataError(f"{path}: the {what} weights do not fit the checkpoint's preset ({reason})") from None
    bad = {name: int((~torch.isfinite(t)).sum()) for name, t in module.state_dict().items() if t.is_floating_point()}
    bad = {name: n for name, n in bad.items() if n}
    if bad:
        raise DataError(f"{resolve_checkpoint(path)}: the {what} weights are not all finite ({sum(bad.values())} NaN or "
                        f"infinite values, first in {next(iter(bad))}); the checkpoint cannot be used: take an earlier "
                        "one or train again")


def load_encoder(path: Path | str) -> Encoder:
    """The frozen encoder (eval mode) of a pretraining or decoder checkpoint."""
    ckpt = load_checkpoint(path)
    preset = _preset_of(ckpt, path)
    enc = _built(lambda: Encoder(preset), ckpt["encoder"], path, "encoder")
    return enc.eval().requires_grad_(False)


def _preset_of(ckpt: dict, path: Path | str) -> ModelPreset:
    try:
        return get_preset(ckpt["preset"])
    except (SssError, KeyError, TypeError, ValueError) as exc:
        raise DataError(f"{path}: its model preset cannot be read ({exc})") from None


def checkpoint_preset(path: Path | str) -> ModelPreset:
    """The model preset a checkpoint was trained at (its tensors are mapped, not read)."""
    return _preset_of(load_checkpoint(path, mmap=True), path)


def trained_views(path: Path | str) -> dict[str, list[int]]:
    """``{object: views}`` a decoder checkpoint's footprints were fitted on (its tensors are mapped, not read);
    ``{}`` for one written before this was recorded, or one whose record is not that shape."""
    record = load_checkpoint(path, mmap=True).get("trained_on")
    if not isinstance(record, dict):
        return {}
    return {str(o): [int(v) for v in views] for o, views in record.items()
            if isinstance(o, str) and isinstance(views, list) and all(type(v) is int for v in views)}


def decoder_patch(encoder_ckpt: Path | str | None, preset: str | ModelPreset) -> int:
    """The footprint size K a decoder trains at: its frozen encoder's, or ``preset``'s end to end (no encoder)."""
    return get_preset(preset).patch if encoder_ckpt is None else load_encoder(encoder_ckpt).preset.patch


def load_decoder(path: Path | str) -> tuple[Encoder, Decoder]:
    """(encoder, decoder) of a decoder checkpoint, both in eval mode."""
    return decoder_modules(load_checkpoint(path), path)


def decoder_modules(ckpt: dict, path: Path | str) -> tuple[Encoder, Decoder]:
    """(encoder, decoder) of an already loaded decoder checkpoint ``ckpt`` (read from ``path``), in eval mode."""
    if "decoder" not in ckpt:
        raise DataError(f"{path} is a pretraining checkpoint; train a decoder with `sss train decoder`")
    preset = _preset_of(ckpt, path)
    if ckpt.get("config") is not None and not isinstance(ckpt.get("config"), dict):
        raise DataError(f"{path}: its config is a {type(ckpt['config']).__name__}, not a table: the checkpoint is damaged")
    cfg = ckpt.get("config") or {}  # old checkpoints: the direct head
    classes, head = cfg.get("aux_classes", 0), cfg.get("head", "direct")
    if isinstance(classes, bool) or not isinstance(classes, int) or not 0 <= classes <= 1 << 16 or not isinstance(head, str):
        raise DataError(f"{path}: its config cannot be read (aux_classes {classes!r}, head {head!r}): the checkpoint is "
                        "damaged; take another one or train again")
    enc = _built(lambda: Encoder(preset), ckpt["encoder"], path, "encoder")
    dec = _built(lambda: Decoder(preset, n_classes=classes, head=head), ckpt["decoder"], path, "decoder")
    # decoders trained before the capture model (their config has no capture_model) read the fringe
    # modulation over an odd 5 x 5 window: run them as trained
    dec.even_window = "capture_model" in cfg
    return enc.eval().requires_grad_(False), dec.eval()
