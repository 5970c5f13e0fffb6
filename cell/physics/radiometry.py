"""Radiometry of sec. 4: lamp irradiance (eq. 11 generalised to the lamp's angular profile, its
power conserved), pixel
power (eq. 17), gray value (eq. 10) with its camera constant from a sensor datasheet, and the
corrected inverse (erratum eq. 18-19). SI units: W, m, s, rad."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.constants import Planck, speed_of_light

# the one implementation of the lamp's energy normalisation, shared with the kernels (which may
# import nothing of cell/): I(0) = P / (2 pi integral p(theta) sin(theta) dtheta)
from kernels.emission import axis_intensity, hard_cone_profile, profile_solid_angle

__all__ = ["axis_intensity", "hard_cone_profile", "profile_solid_angle", "relative_intensity", "cone_irradiance",
           "pixel_power", "gray_value", "camera_constant_from_datasheet", "reflectance_from_gray"]


def relative_intensity(off_axis_rad: float | np.ndarray, profile: ArrayLike) -> np.ndarray:
    """The lamp's angular profile I(theta) / I(0) at off-axis angle theta [rad]: the table (M, 2)
    [off_axis_rad ascending from 0, relative], linear between its angles and 0 beyond the last."""
    profile = np.asarray(profile, dtype=float)
    return np.interp(np.abs(off_axis_rad), profile[:, 0], profile[:, 1], right=0.0)


def cone_irradiance(power_w: float, cone_angle_rad: float, distance_m: float | np.ndarray,
                    off_axis_rad: float | np.ndarray = 0.0, profile: np.ndarray | None = None) -> np.ndarray:
    """Phi = I(0) I(theta)/I(0) / d^2 [W/m^2], I(0) = axis_intensity: the lamp's power over the
    solid angle its profile fills, so it emits P whatever the profile (eq. 11's
    P_L / (2 pi (1 - cos(gamma/2)) d^2) for the ideal cone). profile (M, 2) as relative_intensity,
    None: the ideal cone of full opening angle gamma (hard_cone_profile)."""
    distance_m = np.asarray(distance_m, dtype=float)
    if profile is None:
        profile = hard_cone_profile(cone_angle_rad)
    relative = relative_intensity(off_axis_rad, profile)
    intensity = axis_intensity(power_w, cone_angle_rad, profile)
    return np.where(relative > 0.0, relative * intensity / distance_m**2, 0.0)


def pixel_power(pixel_area_m2: float, irradiance: float | np.ndarray, reflectance: float | np.ndarray,
                f_number: float | np.ndarray) -> np.ndarray:
    """Eq. (17): P_pixel = A_pixel Phi R / (8 kappa^2) [W]."""
    return pixel_area_m2 * irradiance * reflectance / (8.0 * np.asarray(f_number, dtype=float) ** 2)


def gray_value(camera_constant: float, pixel_power_w: float | np.ndarray, shutter_s: float | np.ndarray,
               bit_depth: int | None = None) -> np.ndarray:
    """Eq. (10): G = c P_pixel t; clipped to [0, 2^bits - 1] when a bit depth is given."""
    gray = camera_constant * np.asarray(pixel_power_w, dtype=float) * shutter_s
    return gray if bit_depth is None else np.clip(gray, 0.0, 2.0**bit_depth - 1.0)


def camera_constant_from_datasheet(quantum_efficiency: float, wavelength_m: float,
                                   system_gain_dn_per_e: float) -> float:
    """c of eq. (10) from EMVA 1288 figures: a watt for a second at wavelength lambda is
    lambda / (h c0) photons, eta of them become electrons, K gray each: c = eta lambda K / (h c0)
    [1/(W s)]. Holds for light of that wavelength (a narrow-band lamp's)."""
    return quantum_efficiency * wavelength_m * system_gain_dn_per_e / (Planck * speed_of_light)


def reflectance_from_gray(gray: float | np.ndarray, camera_constant: float, shutter_s: float, f_number: float,
                          pixel_area_m2: float, irradiance: float | np.ndarray) -> np.ndarray:
    """Corrected eq. (18): R = 8 kappa^2 P_pixel / (A_pixel Phi), P_pixel = G / (c t)."""
    p_pixel = np.asarray(gray, dtype=float) / (camera_constant * shutter_s)
    return 8.0 * f_number**2 * p_pixel / (pixel_area_m2 * irradiance)


def albedo_from_gray(gray: float | np.ndarray, camera_constant: float, shutter_s: float, f_number: float,
                     pixel_area_m2: float, irradiance: float | np.ndarray, phase_angle_rad: float | np.ndarray,
                     sigma1: float | np.ndarray, sigma2: float | np.ndarray) -> np.ndarray:
    """Corrected eq. (19), at the mirror geometry (theta_r = 0, theta_i = alpha/2):
    rho = 8 kappa^2 P_pixel / (A_pixel Phi (cos(alpha/2) + sigma1 + sigma2))."""
    r = reflectance_from_gray(gray, camera_constant, shutter_s, f_number, pixel_area_m2, irradiance)
    return r / (np.cos(0.5 * phase_angle_rad) + sigma1 + sigma2)


def gray_per_exposure(camera_constant: float, pixel_area_m2: float, irradiance: float | np.ndarray,
                      reflectance: float | np.ndarray) -> np.ndarray:
    """G / (t / kappa^2) = c A_pixel Phi R / 8: gray is proportional to t / kappa^2 (sec. 5.4)."""
    return camera_constant * pixel_area_m2 * np.asarray(irradiance) * np.asarray(reflectance) / 8.0
