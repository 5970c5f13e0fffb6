"""@wp.func building blocks: the paper's formulas, one function each, in float64.

They mirror the NumPy reference in cell.physics (brdf.py, radiometry.py) and
cell.material.Material.at, and serve both the planner's bulk kernels (gray.py,
visibility.py) and the simulator's renderer (render.py), so the two cannot drift apart.

Radiometry is float64 throughout: c**m with m ~ 1e4 in float32 carries a relative error of
about m * eps32 ~ 1e-3, too much for a 1e-5 agreement with the reference. Only ray casting is
float32, because wp.Mesh stores float32 vertices.
Directions point away from the surface point: n normal, s to the lamp, v to the camera.
"""
import math

import warp as wp

TWO_PI = wp.constant(wp.float64(2.0 * math.pi))   # wp.pi is float32

# Directions within this cosine of a point's tangent plane count as below it: a ray along
# the tangent plane grazes the part's own surface, and the sign of a ~1e-17 dot product
# would otherwise decide visibility by rounding. NumPy reference: cell.physics.reference.
TANGENT_EPS = wp.constant(wp.float64(1.0e-9))

OCCLUDED = wp.constant(-1)       # dominant term where R is clamped to 0 (cell.physics.brdf)
DIFFUSE = wp.constant(0)
LOBE = wp.constant(1)
SPIKE = wp.constant(2)


@wp.struct
class BrdfParameters:
    """Eq. (6) parameters at one phase angle: albedo rho, lobe sigma1/m1, spike sigma2/m2."""

    rho: wp.float64
    sigma1: wp.float64
    m1: wp.float64
    sigma2: wp.float64
    m2: wp.float64


@wp.struct
class Shading:
    """What one lamp does at one surface point (see shade_point)."""

    value: wp.float64            # gray per exposure c A Phi R / 8
    shadowed: wp.bool            # lamp behind the tangent plane, or the ray to it blocked
    off_axis: wp.float64         # angle lamp axis -> (lamp -> point) [rad]
    dominant: wp.int32           # DIFFUSE, LOBE, SPIKE, or OCCLUDED where R is clamped to 0


# --- BRDF, eq. (6)-(7) ---------------------------------------------------------------

@wp.func
def log1p(x: wp.float64) -> wp.float64:
    """log(1 + x), accurate for small x (Goldberg: log(u) x / (u - 1), u = 1 + x)."""
    u = wp.float64(1.0) + x
    if u == wp.float64(1.0):
        return x
    return wp.log(u) * (x / (u - wp.float64(1.0)))


@wp.func
def stable_power(base: wp.float64, exponent: wp.float64) -> wp.float64:
    """base**exponent = exp(m log1p(b - 1)) for b in (0, 1], m up to ~1e5; 0 where base <= 0."""
    b = wp.min(base, wp.float64(1.0))
    if b <= wp.float64(0.0):
        return wp.float64(0.0)
    return wp.exp(exponent * log1p(b - wp.float64(1.0)))


@wp.func
def _interp_column(table: wp.array2d(dtype=wp.float64), j: int, column: int, x: wp.float64) -> wp.float64:
    """numpy.interp's formula on the bracket [j, j + 1] of one table column."""
    slope = (table[j + 1, column] - table[j, column]) / (table[j + 1, 0] - table[j, 0])
    return slope * (x - table[j, 0]) + table[j, column]


@wp.func
def material_at(table: wp.array2d(dtype=wp.float64), phase_rad: wp.float64) -> BrdfParameters:
    """Material table (K, 6) [phase_rad, rho, sigma1, m1, sigma2, m2] at a phase angle:
    linear in phase, clamped at the ends (numpy.interp, as cell.material.Material.at)."""
    k = table.shape[0]
    p = BrdfParameters()
    row = int(-1)
    if phase_rad < table[0, 0]:
        row = 0
    elif phase_rad >= table[k - 1, 0]:
        row = k - 1
    if row >= 0:
        p.rho = table[row, 1]
        p.sigma1 = table[row, 2]
        p.m1 = table[row, 3]
        p.sigma2 = table[row, 4]
        p.m2 = table[row, 5]
        return p
    j = int(0)
    while table[j + 1, 0] <= phase_rad:     # table[j, 0] <= phase < table[j + 1, 0]
        j += 1
    p.rho = _interp_column(table, j, 1, phase_rad)
    p.sigma1 = _interp_column(table, j, 2, phase_rad)
    p.m1 = _interp_column(table, j, 3, phase_rad)
    p.sigma2 = _interp_column(table, j, 4, phase_rad)
    p.m2 = _interp_column(table, j, 5, phase_rad)
    return p


@wp.func
def mirror_cosine(cos_i: wp.float64, cos_e: wp.float64, cos_alpha: wp.float64) -> wp.float64:
    """<v,r> = 2 cos te cos ti - cos alpha (eq. 7)."""
    return wp.float64(2.0) * cos_e * cos_i - cos_alpha


@wp.func
def brdf_terms(cos_i: wp.float64, cos_e: wp.float64, cos_alpha: wp.float64,
               p: BrdfParameters) -> wp.vec3d:
    """(cos ti, s1 c^m1, s2 c^m2) of eq. (6); all 0 if the lamp or camera is behind
    (cos ti <= 0 or cos te <= 0), lobe and spike 0 if c = <v,r> <= 0."""
    if cos_i <= wp.float64(0.0) or cos_e <= wp.float64(0.0):
        return wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    c = mirror_cosine(cos_i, cos_e, cos_alpha)
    return wp.vec3d(cos_i, p.sigma1 * stable_power(c, p.m1), p.sigma2 * stable_power(c, p.m2))


@wp.func
def dominant_term(terms: wp.vec3d, cos_i: wp.float64, cos_e: wp.float64) -> wp.int32:
    """Sec. 5.2: index of the largest term (first on ties, as numpy.argmax); OCCLUDED if behind."""
    if cos_i <= wp.float64(0.0) or cos_e <= wp.float64(0.0):
        return OCCLUDED
    best = DIFFUSE
    if terms[1] > terms[best]:
        best = LOBE
    if terms[2] > terms[best]:
        best = SPIKE
    return best


@wp.func
def phase_cosine(s: wp.vec3d, v: wp.vec3d) -> wp.float64:
    """cos alpha = <s, v>, clamped to [-1, 1] so acos is defined."""
    return wp.clamp(wp.dot(s, v), wp.float64(-1.0), wp.float64(1.0))


@wp.func
def brdf_reflectance(n: wp.vec3d, s: wp.vec3d, v: wp.vec3d,
                     table: wp.array2d(dtype=wp.float64)) -> wp.float64:
    """R of eq. (7) for unit vectors, material at the phase angle alpha = angle(s, v)."""
    cos_alpha = phase_cosine(s, v)
    p = material_at(table, wp.acos(cos_alpha))
    t = brdf_terms(wp.dot(n, s), wp.dot(n, v), cos_alpha, p)
    return p.rho * (t[0] + t[1] + t[2])


@wp.func
def brdf_dominant(n: wp.vec3d, s: wp.vec3d, v: wp.vec3d,
                  table: wp.array2d(dtype=wp.float64)) -> wp.int32:
    """dominant_term for unit vectors (DIFFUSE, LOBE, SPIKE or OCCLUDED)."""
    cos_alpha = phase_cosine(s, v)
    p = material_at(table, wp.acos(cos_alpha))
    cos_i = wp.dot(n, s)
    cos_e = wp.dot(n, v)
    return dominant_term(brdf_terms(cos_i, cos_e, cos_alpha, p), cos_i, cos_e)


# --- Radiometry, eq. (10), (11), (17) -----------------------------------------------------

@wp.func
def off_axis_angle(lamp_axis: wp.vec3d, lamp_to_point: wp.vec3d) -> wp.float64:
    """Angle [rad] between the lamp's aim and the ray from the lamp to the point."""
    c = wp.dot(wp.normalize(lamp_axis), wp.normalize(lamp_to_point))
    return wp.acos(wp.clamp(c, wp.float64(-1.0), wp.float64(1.0)))


@wp.func
def relative_intensity(profile: wp.array2d(dtype=wp.float64), off_axis_rad: wp.float64) -> wp.float64:
    """Lamp profile (M, 2) [off_axis_rad ascending from 0, relative] at an off-axis angle:
    I(theta) / I(0), linear between the angles, 0 beyond the last (numpy.interp(..., right=0),
    as cell.physics.radiometry.relative_intensity)."""
    theta = wp.abs(off_axis_rad)
    m = profile.shape[0]
    if theta > profile[m - 1, 0]:
        return wp.float64(0.0)
    if theta <= profile[0, 0]:
        return profile[0, 1]
    if theta == profile[m - 1, 0]:
        return profile[m - 1, 1]
    j = int(0)
    while profile[j + 1, 0] <= theta:       # profile[j, 0] <= theta < profile[j + 1, 0]
        j += 1
    return _interp_column(profile, j, 1, theta)


@wp.func
def cone_irradiance(power_w: wp.float64, cone_angle_rad: wp.float64, distance_m: wp.float64,
                    off_axis_rad: wp.float64, profile: wp.array2d(dtype=wp.float64)) -> wp.float64:
    """Eq. (11) scaled by the lamp's profile: Phi = I(theta)/I(0) P_L / (2 pi (1 - cos(gamma/2)) d^2)
    [W/m^2], normalized by the cone angle gamma as eq. (11); the ideal cone's profile is 1 up to
    gamma/2 and 0 beyond."""
    relative = relative_intensity(profile, off_axis_rad)
    if relative <= wp.float64(0.0):
        return wp.float64(0.0)
    solid_angle = TWO_PI * (wp.float64(1.0) - wp.cos(wp.float64(0.5) * cone_angle_rad))
    return relative * power_w / (solid_angle * distance_m * distance_m)


@wp.func
def gray_per_exposure(camera_constant: wp.float64, pixel_area_m2: wp.float64,
                      irradiance: wp.float64, reflectance: wp.float64) -> wp.float64:
    """G / (t / kappa^2) = c A_pixel Phi R / 8 (eq. 10 with eq. 17): gray ~ t / kappa^2."""
    return camera_constant * pixel_area_m2 * irradiance * reflectance / wp.float64(8.0)


# --- Rays -------------------------------------------------------------------------------

@wp.func
def direction_from_angles(azimuth: wp.float64, elevation: wp.float64) -> wp.vec3d:
    """(cos el cos az, cos el sin az, sin el): elevation is latitude (physics notes)."""
    ce = wp.cos(elevation)
    return wp.vec3d(ce * wp.cos(azimuth), ce * wp.sin(azimuth), wp.sin(elevation))


@wp.func
def ray_blocked(mesh_id: wp.uint64, origin: wp.vec3d, direction: wp.vec3d,
                max_dist: wp.float64) -> wp.bool:
    """Any triangle within max_dist along the unit direction (float32 BVH query)."""
    return wp.mesh_query_ray_anyhit(mesh_id, wp.vec3(origin), wp.vec3(direction), wp.float32(max_dist))


@wp.func
def shade_point(mesh_id: wp.uint64, shadows: wp.int32, cone: wp.int32, offset_m: wp.float64,
                point: wp.vec3d, normal: wp.vec3d, camera: wp.vec3d,
                lamp: wp.vec3d, lamp_axis: wp.vec3d, power_w: wp.float64,
                cone_angle_rad: wp.float64, profile: wp.array2d(dtype=wp.float64),
                table: wp.array2d(dtype=wp.float64),
                camera_constant: wp.float64, pixel_area_m2: wp.float64) -> Shading:
    """One lamp at one point seen from the camera: gray per exposure c A Phi R / 8, Phi by the
    lamp's profile (cone_irradiance).

    Shadowed = attached shadow (<n,s> <= 0) or, with `shadows` and a mesh, the ray from
    point + offset * normal toward the lamp hits the mesh before the lamp; its value is 0.
    Without `cone` the irradiance is the axis's everywhere. The dominant term is
    the BRDF's alone (cast shadows do not change it)."""
    out = Shading()
    to_lamp = lamp - point
    d = wp.length(to_lamp)
    s = to_lamp / d
    v = wp.normalize(camera - point)
    out.off_axis = off_axis_angle(lamp_axis, -s)
    cos_i = wp.dot(normal, s)
    cos_e = wp.dot(normal, v)
    cos_alpha = phase_cosine(s, v)
    p = material_at(table, wp.acos(cos_alpha))
    t = brdf_terms(cos_i, cos_e, cos_alpha, p)
    reflectance = p.rho * (t[0] + t[1] + t[2])
    out.dominant = dominant_term(t, cos_i, cos_e)
    shadowed = cos_i <= wp.float64(0.0)
    if not shadowed and shadows != 0:
        shadowed = ray_blocked(mesh_id, point + offset_m * normal, s, d)
    out.shadowed = shadowed
    off_axis = out.off_axis
    if cone == 0:
        off_axis = wp.float64(0.0)
    irradiance = cone_irradiance(power_w, cone_angle_rad, d, off_axis, profile)
    out.value = wp.float64(0.0)
    if not shadowed:
        out.value = gray_per_exposure(camera_constant, pixel_area_m2, irradiance, reflectance)
    return out
