"""Geometry of the map: OctoMap keys, ray traversal, box clipping, rotations."""
