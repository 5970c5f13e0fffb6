"""A material's BRDF parameters as a table over the phase angle (sec. 4.2, Fig. 2),
interpolated linearly and clamped at the table's ends."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

PARAMETERS = ("rho", "sigma1", "m1", "sigma2", "m2")
TERMS = ("lobe", "spike")           # the specular terms: (sigma1, m1) and (sigma2, m2)


@dataclass(frozen=True)
class BrdfParameters:
    """Eq. (6) parameters (arrays or floats): albedo rho, lobe sigma1/m1, spike sigma2/m2."""

    rho: np.ndarray
    sigma1: np.ndarray
    m1: np.ndarray
    sigma2: np.ndarray
    m2: np.ndarray


@dataclass(frozen=True)
class Unresolved:
    """What `cell measure-brdf` could not resolve (the material file's `unresolved`): the phase
    angles [rad] of each term ("lobe", "spike") narrower than its step, the step of the
    half-angle tilt beta [rad] and the largest exponent it resolves, M = ln 2 / (2 step^2)."""

    terms: dict[str, list[float]]
    step_rad: float
    resolvable_m_max: float

    def spike_rows(self, phase_rad: ArrayLike) -> np.ndarray:
        """(n_phase,) 1.0 at the table's rows whose spike is unresolved, else 0.0."""
        spike = np.asarray(self.terms.get("spike", ()), float)
        return np.isclose(np.asarray(phase_rad)[:, None], spike[None, :], rtol=0, atol=1e-9).any(axis=1) * 1.0


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
    extra: dict[str, object] = field(default_factory=dict)# optional fitter output (stderr, rms_residual)
    unresolved: Unresolved | None = None         # what the goniometer could not resolve

    def unresolved_spike(self, phase_rad: ArrayLike) -> np.ndarray:
        """Whether an unresolved spike may shape the parameters at phase angle(s) alpha [rad]:
        a row whose spike is unresolved carries weight in at()'s interpolation there (or is the
        clamped end row)."""
        if self.unresolved is None:
            return np.zeros(np.shape(phase_rad), bool)
        return np.interp(np.asarray(phase_rad, float), self.phase_rad, self.unresolved.spike_rows(self.phase_rad)) > 0

    def at(self, phase_rad: ArrayLike) -> BrdfParameters:
        """Parameters at phase angle(s) alpha [rad], linear in alpha, clamped at the ends."""
        a = np.asarray(phase_rad, dtype=float)
        return BrdfParameters(*(np.interp(a, self.phase_rad, getattr(self, k)) for k in PARAMETERS))

    def table(self) -> np.ndarray:
        """(n_phase, 6) float32-ready array [phase_rad, rho, sigma1, m1, sigma2, m2] for the kernels."""
        return np.column_stack([self.phase_rad] + [getattr(self, k) for k in PARAMETERS])

    def scaled(self, albedo_scale: float) -> Material:
        """The same material with rho multiplied by albedo_scale (sim truth, loop correction)."""
        return replace(self, rho=self.rho * albedo_scale)
