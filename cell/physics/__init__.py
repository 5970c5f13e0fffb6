"""Readable NumPy reference of the paper's physics, one equation family per module; `reference`
holds the kernels' NumPy versions built from them."""
