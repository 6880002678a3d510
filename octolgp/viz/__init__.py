"""Visualisation and streaming (Rerun)."""
