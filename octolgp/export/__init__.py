"""Exports: OctoMap .bt/.ot files, point clouds and images."""
