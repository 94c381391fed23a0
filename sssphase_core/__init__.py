"""sssphase core library: patterns, PSP decoding, camera raw processing, the simulated rig.

Pure library code: no hardware access and no networking. Modules that need torch import it
lazily, so numpy-only parts (patterns, the simulator) load without it.
"""

from sssphase_core.errors import SssError

__all__ = ["SssError"]
__version__ = "0.1.0"
