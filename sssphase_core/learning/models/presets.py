"""Model size presets: ``paper`` (the authors' sizes) and ``lite`` (trains in minutes on 2 CPU cores).

Both presets build the same code; a preset is plain data (ints, floats, tuples) so that it can be
stored inside every checkpoint and loaded with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from sssphase_core.errors import InputError


@dataclass(frozen=True)
class ModelPreset:
    """Sizes of the encoder, SimSiam heads and decoder.

    ``patch`` is the footprint/PSP patch size K; the network works on ``padded`` = K rounded up to a
    multiple of 16 (paper: 90 -> 96) so that four halvings are exact.
    """

    name: str
    patch: int
    in_channels: int
    stem: int
    stages: tuple[int, int, int]
    bottleneck: int
    dropout: float
    proj_hidden: int
    proj_dim: int
    pred_hidden: int
    decoder: tuple[int, int, int, int]
    attention: int
    #: the encoder divides each patch by its mean level (:func:`~sssphase_core.learning.models.encoder.patch_level`)
    #: so that its features do not change with the light's level; False in checkpoints made before it existed
    scale_invariant: bool = False

    def __post_init__(self) -> None:
        """Refuse sizes no network can have (a checkpoint's preset edited or damaged: a negative width was an
        internal error, a patch of 10^6 asked for 12 TB) before any tensor is made."""
        from sssphase_core.processing.footprints import PATCH_RANGE

        def whole(name: str, value: object, low: int, high: int) -> None:
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise InputError(f"{name} must be a whole number from {low} to {high}, got {value!r}")

        if not isinstance(self.name, str):
            raise InputError(f"name must be a string, got {self.name!r}")
        whole("patch", self.patch, *PATCH_RANGE)
        whole("in_channels", self.in_channels, 1, 256)
        for name in ("stem", "bottleneck", "proj_hidden", "proj_dim", "pred_hidden", "attention"):
            whole(name, getattr(self, name), 1, MAX_WIDTH)
        for name, count in (("stages", 3), ("decoder", 4)):
            widths = getattr(self, name)
            if not isinstance(widths, tuple) or len(widths) != count:
                raise InputError(f"{name} must be {count} channel widths, got {widths!r}")
            for w in widths:
                whole(f"each of {name}", w, 1, MAX_WIDTH)
        if not isinstance(self.scale_invariant, bool):
            raise InputError(f"scale_invariant must be true or false, got {self.scale_invariant!r}")
        if isinstance(self.dropout, bool) or not isinstance(self.dropout, int | float) or not 0 <= self.dropout < 1:
            raise InputError(f"dropout must be a number in [0, 1), got {self.dropout!r}")

    @property
    def padded(self) -> int:
        return -(-self.patch // 16) * 16

    @property
    def embed_dim(self) -> int:
        return self.bottleneck

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict) -> ModelPreset:
        optional = {"scale_invariant"}  # added later: absent in older checkpoints, whose encoders read raw levels
        missing = [f.name for f in fields(cls) if f.name not in data and f.name not in optional]
        if missing:
            raise InputError(f"it lacks {', '.join(missing)}")
        kw = {f.name: data[f.name] for f in fields(cls) if f.name in data}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()})


#: The widest layer a preset may ask for (the paper's widest is 2,048).
MAX_WIDTH = 16384

PRESETS: dict[str, ModelPreset] = {
    "paper": ModelPreset(
        name="paper", patch=90, in_channels=24, stem=128, stages=(256, 384, 512), bottleneck=1024,
        dropout=0.2, proj_hidden=2048, proj_dim=2048, pred_hidden=512,
        decoder=(512, 384, 256, 128), attention=64, scale_invariant=True,
    ),
    "lite": ModelPreset(
        name="lite", patch=32, in_channels=24, stem=16, stages=(32, 48, 64), bottleneck=128,
        dropout=0.2, proj_hidden=256, proj_dim=256, pred_hidden=64,
        decoder=(64, 48, 32, 16), attention=8, scale_invariant=True,
    ),
}


def get_preset(preset: str | ModelPreset | dict) -> ModelPreset:
    """A preset by name (``paper``/``lite``), or rebuilt from a checkpoint's dict."""
    if isinstance(preset, ModelPreset):
        return preset
    if isinstance(preset, dict):
        return ModelPreset.from_dict(preset)
    if preset not in PRESETS:
        raise InputError(f"unknown model preset {preset!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[preset]
