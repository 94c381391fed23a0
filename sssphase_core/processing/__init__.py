"""Processing: what turns camera frames into measurements, knowing nothing of devices or models.

Projector patterns and the capture plan (:mod:`.patterns`), phase-shift decoding into camera ->
projector correspondences (:mod:`.psp`), footprint extraction from dot grids (:mod:`.footprints`),
camera raw processing (:mod:`.isp`), the projector's light (:mod:`.projector`) and display colour
(:mod:`.colour`). Imports nothing from the later stages (store, acquisition, learning, relighting).
"""
