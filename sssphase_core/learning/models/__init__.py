"""Networks: PSP patch encoder, SimSiam heads, footprint decoder, and their size presets."""

from sssphase_core.learning.models.decoder import Decoder
from sssphase_core.learning.models.encoder import Encoder
from sssphase_core.learning.models.presets import PRESETS, ModelPreset, get_preset
from sssphase_core.learning.models.simsiam import SimSiam, simsiam_loss

__all__ = ["PRESETS", "Decoder", "Encoder", "ModelPreset", "SimSiam", "get_preset", "simsiam_loss"]
