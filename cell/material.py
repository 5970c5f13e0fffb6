"""A material's BRDF parameters as a table over the phase angle (sec. 4.2, Fig. 2),
interpolated linearly and clamped at the table's ends."""
from dataclasses import dataclass, field

import numpy as np

PARAMETERS = ("rho", "sigma1", "m1", "sigma2", "m2")


@dataclass(frozen=True)
class BrdfParameters:
    """Eq. (6) parameters (arrays or floats): albedo rho, lobe sigma1/m1, spike sigma2/m2."""

    rho: np.ndarray
    sigma1: np.ndarray
    m1: np.ndarray
    sigma2: np.ndarray
    m2: np.ndarray


@dataclass(frozen=True)
class Material:
    """BRDF table: phase_rad ascending, one row of each parameter per phase angle."""

    name: str
    source: str
    phase_rad: np.ndarray
    rho: np.ndarray
    sigma1: np.ndarray
    m1: np.ndarray
    sigma2: np.ndarray
    m2: np.ndarray
    extra: dict = field(default_factory=dict)   # optional fitter output (stderr, rms_residual)

    def at(self, phase_rad):
        """Parameters at phase angle(s) alpha [rad], linear in alpha, clamped at the ends."""
        a = np.asarray(phase_rad, dtype=float)
        return BrdfParameters(*(np.interp(a, self.phase_rad, getattr(self, k)) for k in PARAMETERS))

    def table(self):
        """(n_phase, 6) float32-ready array [phase_rad, rho, sigma1, m1, sigma2, m2] for the kernels."""
        return np.column_stack([self.phase_rad] + [getattr(self, k) for k in PARAMETERS])

    def scaled(self, albedo_scale):
        """The same material with rho multiplied by albedo_scale (sim truth, loop correction)."""
        return Material(self.name, self.source, self.phase_rad, self.rho * albedo_scale,
                        self.sigma1, self.m1, self.sigma2, self.m2, self.extra)
