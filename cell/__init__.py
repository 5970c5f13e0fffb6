"""Illumination and sensor planning for visual inspection cells, and the closed loop that drives them."""
