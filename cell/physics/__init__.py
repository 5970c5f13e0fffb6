"""Readable NumPy reference of the paper's physics, one equation family per module."""
