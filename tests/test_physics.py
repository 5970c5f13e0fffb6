"""The physics core against the worked values of the physics notes and stability properties."""
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cell.physics import brdf, costs, depth_of_field as dof, radiometry

PITCH = 4.65e-6
A_PIXEL = PITCH**2
C_CAMERA = 1.5e16
P_LAMP = 0.23043
GAMMA = math.radians(12.0)


def test_rod_irradiance_at_040_m_is_41_84():
    assert radiometry.cone_irradiance(P_LAMP, GAMMA, 0.40) == pytest.approx(41.84, abs=0.005)


def test_hinge_irradiance_at_0258_m_is_100_57():
    assert radiometry.cone_irradiance(P_LAMP, GAMMA, 0.258) == pytest.approx(100.57, abs=0.005)


@pytest.mark.parametrize("distance, f_number, shutter, gray, expected_r", [
    (0.40, 6.2, 11.7e-3, 130.0, 0.252),     # connecting rod
    (0.258, 5.6, 11.6e-3, 120.0, 0.0796),   # hinge
])
def test_corrected_inverse_gives_the_papers_reflectance(distance, f_number, shutter, gray, expected_r):
    phi = radiometry.cone_irradiance(P_LAMP, GAMMA, distance)
    r = radiometry.reflectance_from_gray(gray, C_CAMERA, shutter, f_number, A_PIXEL, phi)
    assert r == pytest.approx(expected_r, rel=2e-3)
    # and forward again: eq. (17) then eq. (10) reproduce the gray value
    p = radiometry.pixel_power(A_PIXEL, phi, r, f_number)
    assert radiometry.gray_value(C_CAMERA, p, shutter) == pytest.approx(gray, rel=1e-12)


def test_gray_is_proportional_to_shutter_over_f_number_squared():
    per_exposure = radiometry.gray_per_exposure(C_CAMERA, A_PIXEL, 100.57, 0.0796)
    assert per_exposure * 11.6e-3 / 5.6**2 == pytest.approx(120.0, rel=2e-3)


def test_albedo_inverse_at_the_mirror_geometry():
    alpha = math.radians(30.0)
    rho, s1, s2 = 0.05, 2.0, 10.0
    # at the mirror geometry <v,r> = 1: R = rho (cos(alpha/2) + s1 + s2)
    r = brdf.reflectance(math.cos(alpha / 2), math.cos(alpha / 2), math.cos(alpha), rho, s1, 5.0, s2, 500.0)
    phi = 60.0
    gray = radiometry.gray_value(C_CAMERA, radiometry.pixel_power(A_PIXEL, phi, r, 4.0), 5e-3)
    est = radiometry.albedo_from_gray(gray, C_CAMERA, 5e-3, 4.0, A_PIXEL, phi, alpha, s1, s2)
    assert est == pytest.approx(rho, rel=1e-12)


def test_irradiance_is_zero_outside_the_cone():
    assert radiometry.cone_irradiance(P_LAMP, GAMMA, 0.3, math.radians(6.01)) == 0.0
    assert radiometry.cone_irradiance(P_LAMP, GAMMA, 0.3, math.radians(5.99)) > 0.0


def _emitted_power(power_w, cone_angle_rad, profile=None, nodes=32):
    """The power through the unit sphere about the lamp, by Gauss-Legendre quadrature of the
    irradiance radiometry.cone_irradiance gives at 1 m (E at 1 m is the intensity in W/sr) over
    2 pi sin(theta) dtheta, on each of the profile's linear segments (where the integrand is
    smooth) and 0 beyond its last angle: independent of the closed form."""
    if profile is None:
        profile = radiometry.hard_cone_profile(cone_angle_rad)
    x, w = np.polynomial.legendre.leggauss(nodes)
    total = 0.0
    for t0, t1 in zip(profile[:-1, 0], profile[1:, 0]):
        theta = 0.5 * (t1 - t0) * x + 0.5 * (t1 + t0)
        e = radiometry.cone_irradiance(power_w, cone_angle_rad, 1.0, theta, profile)
        total += 0.5 * (t1 - t0) * np.sum(w * e * 2.0 * np.pi * np.sin(theta))
    return total


def test_a_lamp_profile_scales_its_energy_conserving_axis_intensity():
    """Phi = I(0) I(theta)/I(0) / d^2 with I(0) = P / (2 pi integral p sin): the profile
    interpolates linearly and ends in 0; its axis is eq. (11)'s 41.84 W/m^2 at 0.40 m scaled by
    the hard cone's solid angle over the profile's; the ideal cone is the table ending at gamma/2."""
    profile = np.column_stack([np.radians([0.0, 4.0, 6.0, 8.0]), [1.0, 0.9, 0.5, 0.0]])
    ratio = 2 * np.pi * (1 - np.cos(GAMMA / 2)) / radiometry.profile_solid_angle(profile)
    phi = radiometry.cone_irradiance(P_LAMP, GAMMA, 0.40, np.radians([0.0, 5.0, 6.0, 7.0, 8.5]), profile)
    np.testing.assert_allclose(phi, 41.84 * ratio * np.array([1.0, 0.7, 0.5, 0.25, 0.0]), rtol=1e-4)
    assert _emitted_power(P_LAMP, GAMMA, profile) == pytest.approx(P_LAMP, rel=1e-12)
    off = np.radians([0.0, 5.99, 6.01])
    np.testing.assert_array_equal(radiometry.cone_irradiance(P_LAMP, GAMMA, 0.3, off),
                                  radiometry.cone_irradiance(P_LAMP, GAMMA, 0.3, off,
                                                             radiometry.hard_cone_profile(GAMMA)))


@pytest.mark.parametrize("gamma_deg", [0.5, 1.0, 12.0, 36.0, 90.0, 179.0])
def test_the_hard_cone_is_eq_11(gamma_deg):
    """Eq. (11)'s 2 pi (1 - cos(gamma/2)), to rounding: the closed form is written as
    4 pi sin^2(gamma/4), the same number without 1 - cos's cancellation for narrow cones."""
    gamma = math.radians(gamma_deg)
    eq_11 = 2.0 * math.pi * (1.0 - math.cos(0.5 * gamma))
    stable = 4.0 * math.pi * math.sin(0.25 * gamma) ** 2
    assert radiometry.profile_solid_angle(radiometry.hard_cone_profile(gamma)) == pytest.approx(stable, rel=1e-15)
    assert stable == pytest.approx(eq_11, rel=1e-10)       # 1 - cos(gamma/2) rounds to ~1e-11 at 0.5 deg
    assert radiometry.axis_intensity(P_LAMP, gamma) == pytest.approx(P_LAMP / stable, rel=1e-15)
    assert radiometry.axis_intensity(P_LAMP, gamma, radiometry.hard_cone_profile(gamma)) == \
        radiometry.axis_intensity(P_LAMP, gamma)


@st.composite
def profiles(draw):
    """A lamp profile table: 2-12 angles strictly ascending from 0 to at most 180 deg, 1 on the
    axis, the rest in [0, 1]."""
    n = draw(st.integers(2, 12))
    steps = draw(st.lists(st.floats(1e-3, 1.0), min_size=n - 1, max_size=n - 1))
    end = draw(st.floats(math.radians(0.2), math.pi))
    angles = np.concatenate([[0.0], np.cumsum(steps)])
    angles *= end / angles[-1]
    angles[-1] = min(angles[-1], math.pi)
    assume(np.all(np.diff(angles) > 0.0))
    relative = [1.0] + draw(st.lists(st.floats(0.0, 1.0), min_size=n - 1, max_size=n - 1))
    return np.column_stack([angles, relative])


@settings(max_examples=200, deadline=None)
@given(profiles(), st.floats(1e-3, 100.0))
def test_a_profiled_lamp_emits_its_power(profile, power_w):
    """Energy conservation: the irradiance integrated over a sphere about the lamp is P, whatever
    the profile (and whatever the cone angle: the profile alone says where the power goes)."""
    assert _emitted_power(power_w, GAMMA, profile) == pytest.approx(power_w, rel=1e-9)


@pytest.mark.parametrize("name, emits", [("hinge", 1.021), ("conrod", 1.021), ("bracket", 1.021)])
def test_the_examples_profiles_emit_their_power(name, emits):
    """The examples' lamps emit P, and their profiles fill about 1.02 times the solid angle of the
    hard cone of their cone_angle_deg (so their axis is about 2 % dimmer than eq. (11) says)."""
    import yaml
    from pathlib import Path
    lamp = yaml.safe_load((Path(__file__).resolve().parent.parent / "tasks" / f"{name}.yaml").read_text())["lamp"]
    power = lamp["power_w"] if "power_w" in lamp else lamp["power_mw"] * 1e-3
    gamma = math.radians(lamp["cone_angle_deg"])
    profile = np.column_stack([np.radians(lamp["profile"]["off_axis_deg"]), lamp["profile"]["relative"]])
    assert _emitted_power(power, gamma, profile) == pytest.approx(power, rel=1e-9)
    hard = 2.0 * math.pi * (1.0 - math.cos(0.5 * gamma))
    assert radiometry.profile_solid_angle(profile) / hard == pytest.approx(emits, abs=0.002)


def test_a_1_deg_cone_with_the_hinges_profile_would_emit_147_times_its_power():
    """The issue's case: normalised by a 1 deg cone (eq. 11) instead of its profile, the hinge's
    lamp would emit about 147 P; normalised by the profile it emits P."""
    profile = np.column_stack([np.radians([0.0, 1.0, 2.0, 3.0, 4.0, 4.5, 5.0, 5.5, 6.0, 6.5, 7.0, 7.5, 8.0, 9.0]),
                               [1.0, 0.997, 0.99, 0.98, 0.955, 0.92, 0.84, 0.69, 0.50, 0.31, 0.16, 0.07, 0.025, 0.0]])
    one_deg = math.radians(1.0)
    old = radiometry.profile_solid_angle(profile) / (2.0 * math.pi * (1.0 - math.cos(0.5 * one_deg)))
    assert old == pytest.approx(147, abs=0.5)
    assert _emitted_power(P_LAMP, one_deg, profile) == pytest.approx(P_LAMP, rel=1e-12)


def test_depth_of_field_worked_values():
    u, f, sigma = 0.35, 0.025, 5.015e-6
    assert dof.near_limit(u, f, 6.2, sigma) == pytest.approx(0.3444, abs=5e-5)
    assert dof.far_limit(u, f, 6.2, sigma) == pytest.approx(0.3558, abs=5e-5)


@pytest.mark.parametrize("u", [0.1, 0.35, 0.5, 2.0])
@pytest.mark.parametrize("kappa", [1.4, 6.2, 16.0])
def test_german_sign_convention_is_equivalent(u, kappa):
    f, sigma = 0.025, 5.015e-6
    assert -dof.near_limit_german(-u, f, kappa, sigma) == pytest.approx(dof.near_limit(u, f, kappa, sigma), rel=1e-12)
    far = dof.far_limit(u, f, kappa, sigma)
    assert -dof.far_limit_german(-u, f, kappa, sigma) == pytest.approx(far, rel=1e-12)


def test_far_limit_is_infinite_beyond_hyperfocal():
    f, kappa, sigma = 0.025, 8.0, 5.015e-6
    h = dof.hyperfocal_distance(f, kappa, sigma)
    assert np.isinf(dof.far_limit(h * 1.01, f, kappa, sigma))
    assert np.isfinite(dof.far_limit(h * 0.99, f, kappa, sigma))


@pytest.mark.parametrize("depth", [1e-4, 0.0114, 0.021, 0.2])
def test_f_number_for_depth_inverts_depth_of_field(depth):
    u, f, sigma = 0.35, 0.025, 5.015e-6
    kappa = dof.f_number_for_depth(u, f, sigma, depth)
    assert dof.depth_of_field(u, f, kappa, sigma) == pytest.approx(depth, rel=1e-9)


def _f_number_for_depth_exact(u, f, sigma, depth):
    """f_number_for_depth's root x = f^2 (sqrt(u^2 + D^2) - u) / D in 60 digits (decimal), the
    cancelling form evaluated where it cannot cancel."""
    from decimal import Decimal, localcontext
    with localcontext() as ctx:
        ctx.prec = 60
        u_, f_, s_, d_ = (Decimal(v) for v in (u, f, sigma, depth))
        x = f_**2 * ((u_**2 + d_**2).sqrt() - u_) / d_
        return float(x / (s_ * (u_ - f_)))


@pytest.mark.parametrize("depth", [1e-9, 1e-12, 1e-6, 0.021])
def test_f_number_for_depth_matches_high_precision_for_tiny_depths(depth):
    # the old hypot(u, D) - u gave 0 at D = 1e-9 m, where kappa is 2.6e-7
    u, f, sigma = 0.35, 0.025, 5.015e-6
    kappa = dof.f_number_for_depth(u, f, sigma, depth)
    assert kappa == pytest.approx(_f_number_for_depth_exact(u, f, sigma, depth), rel=1e-14)
    assert kappa > 0.0


def test_f_number_for_depth_at_a_nanometre_is_its_series():
    # x = f^2 D / (2 u) (1 - D^2 / (4 u^2) + ...): at D = 1e-9 m the first term is exact to 1e-17
    u, f, sigma, depth = 0.35, 0.025, 5.015e-6, 1e-9
    series = f**2 * depth / (2 * u) / (sigma * (u - f))
    assert f**2 * (math.hypot(u, depth) - u) / depth / (sigma * (u - f)) == 0.0   # the old form's
    assert dof.f_number_for_depth(u, f, sigma, depth) == pytest.approx(series, rel=1e-15)


@settings(max_examples=300, deadline=None)
@given(u=st.floats(0.05, 5.0), f=st.floats(0.004, 0.04), sigma=st.floats(1e-6, 2e-5),
       depth=st.floats(1e-3, 2.0))
def test_f_number_for_depth_agrees_with_the_cancelling_form_where_it_is_well_conditioned(u, f, sigma, depth):
    # D >= 1e-3 m and u <= 5 m: hypot(u, D) - u loses at most log10(2 u^2 / D^2) < 8 of 16 digits
    old = f**2 * (math.hypot(u, depth) - u) / depth / (sigma * (u - f))
    assert dof.f_number_for_depth(u, f, sigma, depth) == pytest.approx(old, rel=1e-7)


def test_paper_rod_f_number_gives_its_depth():
    # f/6.2 at 0.35 m spans 0.3444..0.3558 m: asking for that span returns ~6.2
    kappa = dof.f_number_for_depth(0.35, 0.025, 5.015e-6, 0.3558 - 0.3444)
    assert kappa == pytest.approx(6.2, abs=0.05)


def test_cost_functions_are_one_at_their_limits():
    assert costs.value(costs.ln_f_max(10.0, 10.0)) == pytest.approx(1.0)
    assert costs.value(costs.ln_f_min(10.0, 10.0)) == pytest.approx(1.0)
    assert costs.value(costs.ln_f_max(9.0, 10.0)) < 1.0 < costs.value(costs.ln_f_max(11.0, 10.0))
    assert costs.value(costs.ln_f_min(11.0, 10.0)) < 1.0 < costs.value(costs.ln_f_min(9.0, 10.0))
    assert costs.value(costs.ln_count_cost(0)) < 1.0 < costs.value(costs.ln_count_cost(1))


def test_a_miss_far_beyond_the_cap_is_still_ranked_and_reported_finite():
    far, farther = costs.ln_f_max(1e5, 1.0), costs.ln_f_max(1e6, 1.0)
    assert costs.log_sum_exp([far, 0.0]) < costs.log_sum_exp([farther, 0.0])
    assert np.isfinite(costs.value(farther)) and costs.value(farther) == costs.value(far)


def test_feasibility_uses_the_max_not_lse_minus_ln_n():
    # three requirements at 0.9, 0.9 and 1.05: lse - ln 3 < 1 would wrongly accept (eq. 25 erratum)
    reqs = [costs.RequirementValue("a", 0.9), costs.RequirementValue("gray_max", 1.05), costs.RequirementValue("c", 0.9)]
    v = costs.verdict(reqs)
    assert math.log(sum(r.value for r in reqs)) - math.log(3) < 1.0
    assert not v.feasible and v.binding == "gray_max" and v.miss == pytest.approx(0.05)


def test_dominant_term_regions():
    # camera on the normal: near the mirror the spike wins, a bit off the lobe, far off the diffuse term
    s1, m1, s2, m2 = 4.0, 6.0, 30.0, 400.0
    def term(alpha_deg):
        a = math.radians(alpha_deg)
        return int(brdf.dominant_term(math.cos(a), 1.0, math.cos(a), s1, m1, s2, m2))
    assert term(2.0) == brdf.SPIKE
    assert term(28.9) == brdf.LOBE
    assert term(70.0) == brdf.DIFFUSE
    assert int(brdf.dominant_term(-0.1, 1.0, 0.0, s1, m1, s2, m2)) == brdf.OCCLUDED


def test_vector_forms_are_the_forms_with_numpys_sums_bit_for_bit():
    """phase_angle, reflectance_vectors and dominant_term_vectors (geometry.row_sum's sums) equal
    the forms with np.linalg.norm and np.sum, for lamps all over the sphere and a fixed camera."""
    from cell.core import geometry
    from cell.task.loader import load_material
    material = load_material(Path(__file__).resolve().parent.parent / "tasks/materials/milled_aluminium.yaml")
    rng = np.random.default_rng(11)
    s = geometry.unit(rng.normal(size=(20000, 3)))
    n, v = geometry.unit(np.array([0.1, -0.2, 1.0])), geometry.unit(np.array([0.3, 0.1, 1.0]))
    alpha = np.arctan2(np.linalg.norm(np.cross(s, v), axis=-1), np.sum(s * v, axis=-1))
    assert np.array_equal(brdf.phase_angle(s, v), alpha)
    p = material.at(alpha)
    cos_i, cos_e, cos_alpha = np.sum(n * s, axis=-1), np.sum(n * v, axis=-1), np.clip(np.sum(s * v, axis=-1), -1.0, 1.0)
    assert np.array_equal(brdf.reflectance_vectors(n, s, v, material),
                          brdf.reflectance(cos_i, cos_e, cos_alpha, p.rho, p.sigma1, p.m1, p.sigma2, p.m2))
    terms = brdf.dominant_term(cos_i, cos_e, cos_alpha, p.sigma1, p.m1, p.sigma2, p.m2)
    assert np.array_equal(brdf.dominant_term_vectors(n, s, v, material), terms)
    assert {brdf.DIFFUSE, brdf.LOBE, brdf.SPIKE, brdf.OCCLUDED} <= set(terms.tolist())
    # row by row (the certificate's samples against their own camera directions), and one pair alone
    views = geometry.unit(rng.normal(size=(20000, 3)))
    alphas = np.arctan2(np.linalg.norm(np.cross(s, views), axis=-1), np.sum(s * views, axis=-1))
    assert np.array_equal(brdf.phase_angle(s, views), alphas)
    assert np.array_equal(brdf.phase_angle(s[:, None], views[None, :3]),
                          np.arctan2(np.linalg.norm(np.cross(s[:, None], views[None, :3]), axis=-1),
                                     np.sum(s[:, None] * views[None, :3], axis=-1)))
    assert brdf.phase_angle(s[7], v) == alpha[7] and np.ndim(brdf.phase_angle(s[7], v)) == 0


def test_dominant_term_is_numpys_argmax_over_the_stacked_terms():
    """dominant_term's two comparisons pick the term np.argmax picks over the three stacked (the
    first of equal ones, a NaN first), OCCLUDED behind: random angles and parameters, and every
    combination of ties, infinities and NaN among the three terms."""
    import itertools
    from unittest import mock

    def argmax_form(*a):
        terms = np.stack(np.broadcast_arrays(*brdf.brdf_terms(*a)))
        front = (np.asarray(a[0]) > 0.0) & (np.asarray(a[1]) > 0.0)
        return np.where(front, np.argmax(terms, axis=0), brdf.OCCLUDED)

    rng = np.random.default_rng(28)
    n = 100000
    cosines = rng.uniform(-0.2, 1.0, n), rng.uniform(-0.2, 1.0, n), rng.uniform(-1.0, 1.0, n)
    for params in [(rng.uniform(0, 2, n), rng.uniform(1, 1e4, n), rng.uniform(0, 5, n), rng.uniform(1, 1e5, n)),
                   (0.3, 20.0, 1.5, 3000.0)]:
        got, want = brdf.dominant_term(*cosines, *params), argmax_form(*cosines, *params)
        assert got.dtype == want.dtype and np.array_equal(got, want)
        assert set(got.tolist()) == {brdf.OCCLUDED, brdf.DIFFUSE, brdf.LOBE, brdf.SPIKE}
    values = (0.0, 0.5, 1.0, np.inf, np.nan)
    terms = tuple(np.array(list(itertools.product(values, repeat=3))).T)
    with mock.patch.object(brdf, "brdf_terms", lambda *a: terms):
        got = brdf.dominant_term(np.ones(len(terms[0])), 1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert np.array_equal(got, np.argmax(np.stack(terms), axis=0))


def test_stable_powers_are_each_stable_power():
    """The lobe's and the spike's powers of one base with ln b taken once equal each power alone."""
    rng = np.random.default_rng(5)
    base = np.concatenate([rng.uniform(-0.5, 1.5, 1000), [0.0, 1.0, 1.0 - 1e-12, -0.0]])
    m1, m2 = rng.uniform(1, 1e4, base.shape), 3000.0
    b = np.minimum(base, 1.0)
    alone = [np.where(b > 0.0, np.exp(np.asarray(m) * np.log(np.where(b > 0.0, b, 1.0))), 0.0) for m in (m1, m2)]
    together = brdf.stable_powers(base, m1, m2)
    assert all(np.array_equal(x, y) for x, y in zip(together, alone))
    assert np.array_equal(brdf.stable_power(base, m1), alone[0])


def test_stable_power_matches_exact_values():
    c = 1.0 - 1e-6
    assert brdf.stable_power(c, 1e4) == pytest.approx(math.exp(1e4 * math.log1p(-1e-6)), rel=1e-12)
    assert brdf.stable_power(0.5, 3.0) == pytest.approx(0.125, rel=1e-14)
    assert brdf.stable_power(-0.5, 3.0) == 0.0
    assert brdf.stable_power(0.0, 1e5) == 0.0


def test_jacobian_matches_finite_differences():
    args = (math.cos(0.3), math.cos(0.2), math.cos(0.45))
    p = np.array([0.05, 3.0, 7.0, 20.0, 300.0])
    jac = brdf.reflectance_jacobian(*args, *p)
    for k in range(5):
        h = 1e-6 * max(1.0, abs(p[k]))
        up, dn = p.copy(), p.copy()
        up[k] += h
        dn[k] -= h
        fd = (brdf.reflectance(*args, *up) - brdf.reflectance(*args, *dn)) / (2 * h)
        assert jac[k] == pytest.approx(fd, rel=1e-5, abs=1e-12)


unit_cos = st.floats(-1.0, 1.0)
angle = st.floats(0.0, math.pi)


@settings(max_examples=300, deadline=None)
@given(ti=angle, te=angle, az=st.floats(-math.pi, math.pi),
       rho=st.floats(1e-4, 10.0), s1=st.floats(0.0, 100.0), m1=st.floats(1e-3, 1e3),
       s2=st.floats(0.0, 1e3), dm=st.floats(1e-3, 1e5))
def test_reflectance_is_finite_and_non_negative(ti, te, az, rho, s1, m1, s2, dm):
    """Any valid parameters and directions (exponents up to 1e5, grazing, behind): finite R >= 0."""
    n = np.array([0.0, 0.0, 1.0])
    s = np.array([math.sin(ti), 0.0, math.cos(ti)])
    v = np.array([math.sin(te) * math.cos(az), math.sin(te) * math.sin(az), math.cos(te)])
    cos_alpha = float(np.clip(s @ v, -1, 1))
    r = brdf.reflectance(s @ n, v @ n, cos_alpha, rho, s1, m1, s2, m1 + dm)
    jac = brdf.reflectance_jacobian(s @ n, v @ n, cos_alpha, rho, s1, m1, s2, m1 + dm)
    assert np.isfinite(r) and r >= 0.0
    assert np.all(np.isfinite(jac))
    if s @ n <= 0 or v @ n <= 0:
        assert r == 0.0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4), min_size=1, max_size=50))
def test_log_sum_exp_is_finite_and_within_ln_n_of_the_max(xs):
    lse = costs.log_sum_exp(xs)
    assert np.isfinite(lse)
    assert max(xs) - 1e-9 <= lse <= max(xs) + math.log(len(xs)) + 1e-9
