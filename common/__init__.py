"""Leaf helpers shared by ``frontends/``, ``mapping/`` and ``slam/``: rigid transforms and packed
voxel keys. This package imports nothing of the project, so every other package may import it."""
