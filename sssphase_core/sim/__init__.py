"""Physically based simulated projector-camera rig (numpy only; no torch)."""
