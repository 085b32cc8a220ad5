"""Procedural worlds, trajectories and sensors for `mcl3d simulate`."""
