"""Measuring what the model needs with the cell itself: the camera constant by a laser
(`camera_constant`) or a reference part (`reference_part`), the material as a goniometer
(`goniometer`), the focal length and hand-eye transform (`hand_eye`).

Layer 9: imports the layers below (the run's acquisition and measurement)."""
