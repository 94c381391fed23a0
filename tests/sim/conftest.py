"""Simulator fixtures: a catalogue scene and the CPU rig (custom test scenes are in sim_scenes.py)."""

from __future__ import annotations

import pytest

from sssphase_core.sim import SimScene, rig_preset


@pytest.fixture(scope="session")
def apple() -> SimScene:
    return SimScene("apple", rig=rig_preset("cpu"), view=0, n_views=4)


@pytest.fixture(scope="session")
def slab_rig():
    return rig_preset("cpu")
