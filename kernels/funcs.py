"""@wp.func building blocks: the paper's formulas, one function each, in float64.

They mirror the NumPy reference in cell.physics (brdf.py, radiometry.py) and
cell.physics.material.Material.at, and serve both the planner's bulk kernels (gray.py,
visibility.py) and the simulator's renderer (render.py), so the two cannot drift apart.

Radiometry is float64 throughout: c**m with m ~ 1e4 in float32 carries a relative error of
about m * eps32 ~ 1e-3, too much for a 1e-5 agreement with the reference. Only ray casting is
float32, because wp.Mesh stores float32 vertices.
Directions point away from the surface point: n normal, s to the lamp, v to the camera.
What depends on the point alone (v, cos te, the shadow ray's origin) or on the lamp alone (its
unit aim, its axis intensity) is computed once by the callers, not per evaluation.
"""

import warp as wp

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

# exp(x) is 0 in float64 below this (e^-746 < half the smallest subnormal): no need to call it
EXP_ZERO_BELOW = wp.constant(wp.float64(-746.0))


@wp.func
def power_of(log_base: wp.float64, exponent: wp.float64) -> wp.float64:
    """b**m = exp(m ln b) from ln b (one log serves the lobe and the spike); exactly 0 where
    exp underflows. ln b <= 0 and m up to ~1e5 (c^m in float32 would be off by ~m eps32)."""
    x = exponent * log_base
    if x < EXP_ZERO_BELOW:
        return wp.float64(0.0)
    return wp.exp(x)


@wp.func
def _interp_column(table: wp.array2d(dtype=wp.float64), j: int, column: int, slopes: int,
                   x: wp.float64) -> wp.float64:
    """numpy.interp's formula slope * (x - x_j) + y_j on the bracket [j, j + 1] of one table
    column, its slope (y_j+1 - y_j) / (x_j+1 - x_j) precomputed in column `column + slopes`
    (kernels._arrays: the same division, done once)."""
    return table[j, column + slopes] * (x - table[j, 0]) + table[j, column]


@wp.func
def material_at(table: wp.array2d(dtype=wp.float64), phase_rad: wp.float64) -> BrdfParameters:
    """Material table (K, 11) [phase_rad, rho, sigma1, m1, sigma2, m2, their 5 slopes]
    (kernels._arrays.table2d) at a phase angle: linear in phase, clamped at the ends
    (numpy.interp, as cell.physics.material.Material.at)."""
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
    p.rho = _interp_column(table, j, 1, 5, phase_rad)
    p.sigma1 = _interp_column(table, j, 2, 5, phase_rad)
    p.m1 = _interp_column(table, j, 3, 5, phase_rad)
    p.sigma2 = _interp_column(table, j, 4, 5, phase_rad)
    p.m2 = _interp_column(table, j, 5, 5, phase_rad)
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
    if c <= wp.float64(0.0):
        return wp.vec3d(cos_i, wp.float64(0.0), wp.float64(0.0))
    log_c = wp.log(wp.min(c, wp.float64(1.0)))
    return wp.vec3d(cos_i, p.sigma1 * power_of(log_c, p.m1), p.sigma2 * power_of(log_c, p.m2))


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
    """cos alpha = <s, v>, clamped to [-1, 1]."""
    return wp.clamp(wp.dot(s, v), wp.float64(-1.0), wp.float64(1.0))


@wp.func
def phase_angle(s: wp.vec3d, v: wp.vec3d) -> wp.float64:
    """alpha = atan2(|s x v|, <s, v>), accurate at every angle: acos(<s, v>) is not near 0, where a
    rounding of <s, v> to 1 - 1e-16 reads alpha = 1.5e-8 rad (the camera beside the lamp)."""
    return wp.atan2(wp.length(wp.cross(s, v)), wp.dot(s, v))


# --- Radiometry, eq. (10), (11), (17) -----------------------------------------------------

@wp.func
def off_axis_angle(lamp_axis: wp.vec3d, to_lamp: wp.vec3d) -> wp.float64:
    """Angle [rad] between the lamp's unit aim a and the ray from the lamp to the point, -s for
    the unit s toward the lamp: 2 asin(|a + s| / 2), the chord's angle, which needs no clamp and
    is accurate near 0 where acos(<a, -s>) is not (and costs less there)."""
    return wp.float64(2.0) * wp.asin(wp.min(wp.float64(0.5) * wp.length(lamp_axis + to_lamp), wp.float64(1.0)))


@wp.func
def relative_intensity(profile: wp.array2d(dtype=wp.float64), off_axis_rad: wp.float64) -> wp.float64:
    """Lamp profile (M, 3) [off_axis_rad ascending from 0, relative, slope]
    (kernels._arrays.profile2d) at an off-axis angle:
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
    return _interp_column(profile, j, 1, 1, theta)


@wp.func
def cone_irradiance(intensity_w_sr: wp.float64, distance_m: wp.float64, off_axis_rad: wp.float64,
                    profile: wp.array2d(dtype=wp.float64)) -> wp.float64:
    """Phi = I(theta)/I(0) I(0) / d^2 [W/m^2], I(0) by kernels.emission.axis_intensity (the
    lamp's power over the solid angle its profile fills; eq. 11's for the ideal cone, whose
    profile is 1 up to gamma/2 and 0 beyond)."""
    relative = relative_intensity(profile, off_axis_rad)
    if relative <= wp.float64(0.0):
        return wp.float64(0.0)
    return relative * intensity_w_sr / (distance_m * distance_m)


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


SECTORS = wp.constant(16)        # azimuth sectors of a point's free cones (kernels.cone)
SECTORS_PER_QUADRANT = wp.constant(wp.float64(SECTORS / 4))


@wp.func
def tangent_u(normal: wp.vec3d) -> wp.vec3d:
    """A unit vector in the tangent plane (n x x, or n x y for a normal near x): with w = n x u
    it measures a direction's azimuth about the normal."""
    e = wp.vec3d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0))
    if wp.abs(normal[0]) > wp.float64(0.9):
        e = wp.vec3d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0))
    return wp.normalize(wp.cross(normal, e))


@wp.func
def diamond_angle(x: wp.float64, y: wp.float64) -> wp.float64:
    """A stand-in for atan2(y, x) in [0, 4), increasing with it, with no transcendental
    (y / (|x| + |y|) per quadrant); (0, 0) gives 0."""
    r = wp.abs(x) + wp.abs(y)
    if r == wp.float64(0.0):
        return wp.float64(0.0)
    if y >= wp.float64(0.0):
        if x >= wp.float64(0.0):
            return y / r
        return wp.float64(1.0) - x / r
    if x < wp.float64(0.0):
        return wp.float64(2.0) - y / r
    return wp.float64(3.0) + x / r


@wp.func
def sector_of(diamond: wp.float64) -> wp.int32:
    """The azimuth sector 0..SECTORS-1 of a diamond angle."""
    k = wp.int32(wp.floor(diamond * SECTORS_PER_QUADRANT))
    return wp.min(k, SECTORS - 1)


@wp.struct
class Surface:
    """A surface point as the shading sees it, all of it the point's own (computed once per
    point, whatever the lamp): where it is, its unit normal, the unit direction v and cos te to
    the camera, the shadow ray's origin point + offset * normal, the cosine of its free cone
    (kernels.cone: a ray to the lamp with <n, s> above it meets no triangle; NO_CONE when
    unknown), and its row in the table of its sectors' free cones (-1: none), with the tangent
    axes u, n x u that give a direction's sector."""

    point: wp.vec3d
    normal: wp.vec3d
    view: wp.vec3d
    cos_e: wp.float64
    ray_origin: wp.vec3d
    free_cos: wp.float64
    sector_row: wp.int32
    u: wp.vec3d
    w: wp.vec3d


@wp.func
def surface(point: wp.vec3d, normal: wp.vec3d, camera: wp.vec3d, offset_m: wp.float64,
            free_cos: wp.float64, sector_row: wp.int32) -> Surface:
    """The Surface of a point with unit normal seen from the camera."""
    out = Surface()
    out.point = point
    out.normal = normal
    out.view = wp.normalize(camera - point)
    out.cos_e = wp.dot(normal, out.view)
    out.ray_origin = point + offset_m * normal
    out.free_cos = free_cos
    out.sector_row = sector_row
    out.u = tangent_u(normal)
    out.w = wp.cross(normal, out.u)
    return out


@wp.func
def needs_ray(free_cos: wp.float64, sector_cos: wp.array2d(dtype=wp.float64), sector_row: wp.int32,
              u: wp.vec3d, w: wp.vec3d, s: wp.vec3d, cos_i: wp.float64) -> wp.bool:
    """Whether the unit direction s (<n, s> = cos_i) leaves a point's free cones (kernels.cone),
    so that only a ray can tell whether it is blocked: outside the narrowest cone (free_cos),
    then outside its azimuth sector's (row sector_row of sector_cos; none if -1)."""
    if cos_i > free_cos:
        return False
    if sector_row < 0:
        return True
    return cos_i <= sector_cos[sector_row, sector_of(diamond_angle(wp.dot(s, u), wp.dot(s, w)))]


@wp.func
def lamp_shadowed(mesh_id: wp.uint64, shadows: wp.int32, at: Surface, sector_cos: wp.array2d(dtype=wp.float64),
                  s: wp.vec3d, d: wp.float64, cos_i: wp.float64) -> wp.bool:
    """Whether a lamp at distance d in the unit direction s (<n, s> = cos_i) from a Surface is
    shadowed there: attached shadow (cos_i <= 0) or, with `shadows`, a triangle on the ray from
    the point's ray origin toward it (none cast inside its free cones, where none can hit)."""
    shadowed = cos_i <= wp.float64(0.0)
    if not shadowed and shadows != 0:
        if needs_ray(at.free_cos, sector_cos, at.sector_row, at.u, at.w, s, cos_i):
            shadowed = ray_blocked(mesh_id, at.ray_origin, s, d)
    return shadowed


@wp.func
def shadowed_from(mesh_id: wp.uint64, shadows: wp.int32, at: Surface, sector_cos: wp.array2d(dtype=wp.float64),
                  lamp: wp.vec3d) -> wp.bool:
    """shade_point's shadow flag of a lamp at `lamp` alone, its arithmetic (no BRDF, no
    irradiance): what a lamp at the camera tells of a point, whether the camera sees it."""
    to_lamp = lamp - at.point
    s = wp.normalize(to_lamp)
    return lamp_shadowed(mesh_id, shadows, at, sector_cos, s, wp.length(to_lamp), wp.dot(at.normal, s))


@wp.func
def shade_point(mesh_id: wp.uint64, shadows: wp.int32, cone: wp.int32, at: Surface,
                sector_cos: wp.array2d(dtype=wp.float64), lamp: wp.vec3d, lamp_axis: wp.vec3d,
                intensity_w_sr: wp.float64, profile: wp.array2d(dtype=wp.float64),
                table: wp.array2d(dtype=wp.float64), camera_constant: wp.float64,
                pixel_area_m2: wp.float64) -> Shading:
    """One lamp (unit aim lamp_axis, axis intensity I(0) by kernels.emission.axis_intensity) at one Surface
    (its sectors' free cones in sector_cos) seen from the camera: gray per exposure
    c A Phi R / 8, Phi by the lamp's profile (cone_irradiance).

    Shadowed = attached shadow (<n,s> <= 0) or, with `shadows` and a mesh, the ray from
    point + offset * normal toward the lamp hits the mesh before the lamp (any hit within the
    distance; none is cast inside the point's free cones, where none can hit); its value is 0.
    A lamp at the point has direction 0 (wp.normalize, as geometry.direction): shadowed; a camera
    at it (view 0, cos te 0) sees nothing, R = 0. Without `cone` the irradiance is the axis's
    everywhere. The dominant term is
    the BRDF's alone (cast shadows do not change it). A lamp behind the tangent plane
    (cos ti <= 0) gives 0 and OCCLUDED whatever the BRDF: its phase angle (an atan2) and the
    material there are found only for a lamp in front."""
    out = Shading()
    to_lamp = lamp - at.point
    d = wp.length(to_lamp)
    s = wp.normalize(to_lamp)          # 0 for a lamp at the point: cos_i 0, shadowed (not 0/0)
    out.off_axis = off_axis_angle(lamp_axis, s)
    cos_i = wp.dot(at.normal, s)
    out.dominant = OCCLUDED
    p = BrdfParameters()
    t = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if cos_i > wp.float64(0.0):         # behind the lamp (attached shadow): 0 and OCCLUDED whatever the BRDF
        p = material_at(table, phase_angle(s, at.view))
        t = brdf_terms(cos_i, at.cos_e, phase_cosine(s, at.view), p)
        out.dominant = dominant_term(t, cos_i, at.cos_e)
    shadowed = lamp_shadowed(mesh_id, shadows, at, sector_cos, s, d, cos_i)
    out.shadowed = shadowed
    out.value = wp.float64(0.0)
    if not shadowed:
        off_axis = out.off_axis
        if cone == 0:
            off_axis = wp.float64(0.0)
        irradiance = cone_irradiance(intensity_w_sr, d, off_axis, profile)
        out.value = gray_per_exposure(camera_constant, pixel_area_m2, irradiance,
                                      p.rho * (t[0] + t[1] + t[2]))
    return out
