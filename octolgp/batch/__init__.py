"""Offline batch builds: the paper's OM_LGP, the leaf map, and the baselines of Table II."""
