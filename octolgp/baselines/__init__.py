"""Baselines of Kim & Kim Table II: the occupancy grid, one global GP, a mixture of GPs."""
