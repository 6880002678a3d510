"""Simulated scenes with exact ground truth: the paper's 2D scene, 3D rooms and lidar missions."""
