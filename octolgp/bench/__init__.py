"""Benchmarks that reproduce the paper's results (``octolgp bench``)."""
