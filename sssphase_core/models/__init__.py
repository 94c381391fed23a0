"""Networks: PSP patch encoder, SimSiam heads, footprint decoder, and their size presets."""

from sssphase_core.models.decoder import Decoder
from sssphase_core.models.encoder import Encoder
from sssphase_core.models.presets import PRESETS, ModelPreset, get_preset
from sssphase_core.models.simsiam import SimSiam, simsiam_loss

__all__ = ["PRESETS", "Decoder", "Encoder", "ModelPreset", "SimSiam", "get_preset", "simsiam_loss"]
