"""Gaussian-process numerics: kernels, quadrature items, regression, likelihood and LOO, PLSC, learning."""
