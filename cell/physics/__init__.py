"""The paper's physics as readable NumPy, one equation family per module: the BRDF and its
table over the phase angle (`brdf`, `material`) and its fit to goniometer data (`brdf_fit`),
radiometry and the sensor (`radiometry`, `sensor`), depth of field, the pinhole camera
(`projection`), the requirement costs (`costs`); `reference` holds the kernels' NumPy versions
built from them.

Layer 2: imports `cell.core` and the result types of `kernels`."""
