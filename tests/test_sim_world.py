"""The simulated camera's world (sim.world, sim.cell): with no effects and a neutral truth the
image shows the planner's predicted gray; each effect, switched on alone, does what its physics
says; the truth changes the image as declared; a seed fixes every random choice."""
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.stats import norm

from cell.core import geometry
from cell.core.errors import DeviceFault
from cell.task.loader import load_task
from cell.physics.material import Material
from cell.physics import depth_of_field as dof, radiometry
from cell.planning.one_shot import plan
from cell.physics.projection import pixel_rays, project
from cell.devices.rig import lamp_aim
from cell.planning.scene import build_scene
from cell.task.types import Defect, SimConfig, Truth
from sim import world
from sim.cell import make_sim_devices
from sim.world import Renderer

TASKS = Path(__file__).resolve().parent.parent / "tasks"
ALL_EFFECTS = ("shadows", "cone_falloff", "vignetting", "defocus", "noise", "black_level",
               "quantization")
SCALE = 0.25                   # test grid: 258 x 194 pixels of 18.6 um, 0.37 mm on the plate
OVERHEAD = np.array([0.025, 0.0, 0.2])        # lamp 0.2 m above the plate, aimed straight down
EXPOSURE = (8e-4, 4.0)         # shutter [s], f-number: plate gray ~100 under that lamp
WIDE = 60.0                    # cone angle [deg] of a lamp that lights the whole view
WIDE_EXPOSURE = (0.12, 4.0)    # plate gray ~100 under a wide lamp 0.4-0.5 m away
DOWN = np.array([0.0, 0.0, -1.0])


def with_sim(task, effects=(), seed=1, **truth):
    return replace(task, sim=SimConfig(seed, tuple(effects), Truth(**truth)))


def box(size, center):
    return trimesh.creation.box(size, trimesh.transformations.translation_matrix(center))


@pytest.fixture(scope="module")
def hinge():
    return load_task(TASKS / "hinge.yaml")


@pytest.fixture(scope="module")
def plans(hinge):
    """The task files (effects as given) and their plans; a plan does not depend on sim."""
    return {name: (task, plan(task)) for name, task in
            (("hinge", hinge), ("conrod", load_task(TASKS / "conrod.yaml")), ("ring", load_task(TASKS / "ring.yaml")))}


@pytest.fixture(scope="module")
def plate(hinge):
    return plate_world(hinge)


def plate_world(hinge):
    """A diffuse (rho 0.3) 160 mm plate, top face z = 0, filling the view (96 x 72 mm) of the
    hinge's camera 0.5 m straight above x = 15 mm, with an 8 mm cube standing on it at x = -15 mm."""
    mesh = trimesh.util.concatenate([box((0.16, 0.16, 0.002), (0.0, 0.0, -0.001)),
                                     box((0.008, 0.008, 0.008), (-0.015, 0.0, 0.004))])
    ones = np.ones(2)
    diffuse = Material("diffuse", "test", phase_rad=np.array([0.0, np.pi]), rho=0.3 * ones,
                       sigma1=0 * ones, m1=ones, sigma2=0 * ones, m2=2 * ones)
    task = replace(hinge, part=replace(hinge.part, mesh=mesh, material=diffuse),
                   features=(replace(hinge.feature, center_m=np.array([0.015, 0.0, 0.0]),
                                    normal=np.array([0.0, 0.0, 1.0]), radius_m=0.005, samples=8),),
                   camera=replace(hinge.camera, view_direction=np.array([0.0, 0.0, 1.0])))
    return task, build_scene(task)


def shoot(plate, effects=(), lamp=OVERHEAD, aim=DOWN, cone_deg=12.0, exposure=EXPOSURE,
          focus_m=None, seed=1, profile=None, **truth):
    """Image of the plate world at the test grid, and its renderer."""
    task, scene = plate
    task = with_sim(replace(task, lamp=replace(task.lamp, cone_angle_rad=np.radians(cone_deg), profile=profile)),
                    effects, seed, **truth)
    renderer = Renderer(task, scene, scale=SCALE)
    return renderer(scene.T_cell_cam, lamp, aim, *exposure, focus_m), renderer


def pixel(renderer, scene, point):
    """(row, column) of the pixel nearest to a cell-frame point."""
    uv, _ = project(renderer.K, scene.T_cell_cam, np.atleast_2d(point))
    u, v = np.rint(uv[0]).astype(int)
    return v, u


def plate_points(renderer, scene):
    """Where each pixel's ray meets the plane z = 0 (H, W, 3)."""
    T = scene.T_cell_cam
    rays = pixel_rays(renderer.K, T, renderer.shape[1], renderer.shape[0])
    return (T[:3, 3] - T[2, 3] / rays[:, 2:] * rays).reshape(*renderer.shape, 3)


# --- (a) no effects, neutral truth: the planner's prediction -------------------------------------

def planned_drives(shot):
    """{channel: drive} of a shot's lights on the lighting controller."""
    return {light.channel: light.drive for light in shot.lights if light.channel is not None}


@pytest.mark.parametrize("name", ["hinge", "conrod", "ring"])
def test_without_effects_the_image_shows_the_planned_gray_at_every_sample(plans, name):
    """The ring task: the spot and both rings at the plan's drives (the bright-field ring off),
    each ring as the planner's emitter points."""
    task, p = plans[name]
    task, scene = with_sim(task), p.scene
    renderer = Renderer(task, scene)
    aim = lamp_aim(task.lamp.rig.pivot_m, p.shot.lamp_position)
    image = renderer(scene.T_cell_cam, p.shot.lamp_position, aim, p.shot.exposure.shutter_s, p.shot.exposure.f_number,
                     drives=planned_drives(p.shot))
    assert image.shape == (776, 1032) and image.dtype == np.float64
    uv, _ = project(renderer.K, scene.T_cell_cam, scene.points)
    u, v = np.rint(uv).astype(int).T
    assert abs(image[v, u].mean() - p.shot.gray.mean()) < 1.0
    np.testing.assert_allclose(image[v, u], p.shot.gray, atol=1.0)


def test_the_simulated_cell_driven_to_the_plan_captures_the_predicted_gray(plans):
    task, p = plans["hinge"]
    devices = make_sim_devices(task, p.scene)
    devices.arm.move_camera(p.scene.T_cell_cam)
    devices.lamp.move(*p.shot.joints)
    devices.camera.set_exposure(p.shot.exposure.shutter_s)
    devices.camera.set_aperture(p.shot.exposure.f_number)
    devices.camera.set_focus(p.shot.exposure.focus_m)
    image = devices.camera.capture()            # hinge.yaml: shadows, cone_falloff, quantization
    assert image.dtype == np.uint8 and image.shape == (776, 1032)
    uv, _ = project(devices.camera.render.K, devices.arm.camera_pose(), p.scene.points)
    u, v = np.rint(uv).astype(int).T
    np.testing.assert_allclose(image[v, u], p.shot.gray, atol=1.0)  # rounding, servo ticks of 0.09 deg


@pytest.mark.parametrize("faults, act, message", [
    ({"arm_fail_on_move": 1}, lambda d: d.arm.move_camera(d.arm.camera_pose()), "protective stop"),
    ({"lamp_fail_on_move": 1, "servo_bits": 0x20}, lambda d: d.lamp.move(0.0, 0.8, 0.3),
     r"servo 2: Hardware Error Status 0x20 \(overload\)"),
    ({"camera_fail_on_capture": 1}, lambda d: d.camera.capture(), "timed out"),
])
def test_the_simulated_cell_injects_faults(hinge, plate, faults, act, message):
    devices = make_sim_devices(hinge, plate[1], faults=faults)
    with pytest.raises(DeviceFault, match=message):
        act(devices)


# --- (b) each effect alone -------------------------------------------------------------------

def test_shadows_darken_the_plate_behind_the_cube_and_nothing_else(plate):
    lamp = np.array([-0.015 - 0.3, 0.0, 0.3])        # 45 deg above the plate, from -x
    aim = geometry.unit([-0.015, 0.0, 0.0] - lamp)
    lit, renderer = shoot(plate, (), lamp, aim, WIDE, WIDE_EXPOSURE)
    shadowed, _ = shoot(plate, ("shadows",), lamp, aim, WIDE, WIDE_EXPOSURE)
    scene = plate[1]
    assert np.all(shadowed <= lit)
    behind, beside = (pixel(renderer, scene, [-0.007, y, 0.0]) for y in (0.0, 0.01))
    assert shadowed[behind] == 0.0 < lit[behind] and shadowed[beside] == lit[beside] > 0.0
    # the cube (8 mm, light at 45 deg) shades 8 x 8 mm of plate; a pixel sees p z / f of it
    footprint_mm = 1e3 * renderer.pixel_pitch_m * 0.5 / 0.025
    assert np.sum(shadowed < lit) == pytest.approx(64.0 / footprint_mm**2, rel=0.05)


def test_cone_falloff_softens_the_edge_as_a_blurred_cone(plate):
    hard, renderer = shoot(plate)
    soft, _ = shoot(plate, ("cone_falloff",))
    points = plate_points(renderer, plate[1])
    theta = np.degrees(np.arccos(geometry.unit(points - OVERHEAD) @ DOWN))
    on_plate = (points[..., 0] > 0.0) & (hard > 0.0)                 # clear of the cube
    ratio = soft[on_plate] / hard[on_plate]
    # hard cone of half angle 6 deg convolved with a Gaussian of 1 deg in angle
    np.testing.assert_allclose(ratio, norm.sf((theta[on_plate] - 6.0) / 1.0), rtol=1e-4)
    assert ratio[theta[on_plate] < 2.0].min() > 0.9999                # eq. (11) in the core
    assert ratio[theta[on_plate] > 5.9].max() < 0.55                  # half at the nominal edge
    spill = (points[..., 0] > 0.0) & (theta > 6.5) & (theta < 7.0)
    assert np.all(hard[spill] == 0.0) and np.all(soft[spill] > 0.0)


# a soft-edged profile for the 12 deg cone [off_axis_rad, relative]: half at the nominal edge
SOFT_EDGE = np.column_stack([np.radians([0.0, 2.0, 4.0, 5.0, 6.0, 7.0, 8.0]),
                             [1.0, 0.99, 0.93, 0.80, 0.50, 0.15, 0.0]])
# its axis intensity over the hard 12 deg cone's: the same power spread over its solid angle
SOFT_AXIS = (radiometry.profile_solid_angle(radiometry.hard_cone_profile(np.radians(12.0)))
             / radiometry.profile_solid_angle(SOFT_EDGE))


def test_without_cone_falloff_the_world_has_the_tasks_lamp_profile(plate):
    hard, renderer = shoot(plate)
    model, _ = shoot(plate, profile=SOFT_EDGE)
    points = plate_points(renderer, plate[1])
    theta = np.arccos(geometry.unit(points - OVERHEAD) @ DOWN)
    inside = (points[..., 0] > 0.0) & (hard > 0.0)
    # the kernel's hit points are float32 distances along the ray: theta to ~1e-6 relative
    np.testing.assert_allclose(model[inside], hard[inside] * SOFT_AXIS * np.interp(theta[inside], *SOFT_EDGE.T),
                               rtol=1e-5)
    spill = (points[..., 0] > 0.0) & (theta > np.radians(6.2)) & (theta < np.radians(7.8))
    assert spill.sum() > 100 and np.all(hard[spill] == 0.0) and np.all(model[spill] > 0.0)
    assert np.all(model[theta > SOFT_EDGE[-1, 0]] == 0.0)


def test_cone_falloff_with_a_profile_blurs_the_tasks_profile(plate):
    """The world's lamp then differs from the model's: the task's profile blurred in angle by the
    same 1 deg Gaussian (across the axis, f(|theta + x|)), checked by quadrature."""
    hard, renderer = shoot(plate)
    soft, _ = shoot(plate, ("cone_falloff",), profile=SOFT_EDGE)
    points = plate_points(renderer, plate[1])
    theta = np.arccos(geometry.unit(points - OVERHEAD) @ DOWN)
    inside = (points[..., 0] > 0.0) & (hard > 0.0)
    x = np.linspace(-8.0, 8.0, 8001)                                  # in units of s = 1 deg
    weights = norm.pdf(x) * (x[1] - x[0])
    blurred = [np.sum(weights * np.interp(np.abs(t + np.radians(x)), *SOFT_EDGE.T, right=0.0))
               for t in theta[inside][::50]]
    np.testing.assert_allclose(soft[inside][::50] / hard[inside][::50], SOFT_AXIS * np.array(blurred),
                               rtol=1e-5, atol=1e-7)
    beyond = (points[..., 0] > 0.0) & (theta > np.radians(8.2)) & (theta < np.radians(9.0))
    assert beyond.sum() > 100 and np.all(soft[beyond] > 0.0)         # spills past the profile's end


def test_blurring_the_hard_cones_profile_is_the_erfc_edge():
    theta = np.radians(np.linspace(0.0, 12.0, 241))
    gamma = np.radians(12.0)
    np.testing.assert_allclose(world.cone_falloff(theta, gamma, radiometry.hard_cone_profile(gamma)),
                               world.cone_falloff(theta, gamma), rtol=0, atol=1e-8)


def test_vignetting_is_the_cos4_law_at_the_corner(plate):
    lamp = np.array([0.015, 0.0, 0.5])
    plain, renderer = shoot(plate, (), lamp, DOWN, WIDE, WIDE_EXPOSURE)
    vignetted, _ = shoot(plate, ("vignetting",), lamp, DOWN, WIDE, WIDE_EXPOSURE)
    K = renderer.K
    tan_corner = np.hypot(K[0, 2], K[1, 2]) / K[0, 0]                 # half diagonal / focal length
    ratio = vignetted / plain
    assert ratio[0, 0] / ratio[renderer.shape[0] // 2, renderer.shape[1] // 2] == pytest.approx(
        np.cos(np.arctan(tan_corner))**4, rel=1e-6)


def edge_profile(image, renderer, scene):
    """Gray along the image row through the lamp's axis, right of the axis (the hard cone's edge)."""
    row, column = pixel(renderer, scene, [OVERHEAD[0], 0.0, 0.0])
    return image[row, column:]


def edge_spread(profile, edge, half_width=12):
    """Standard deviation [px] of the line spread (the profile's fall) within half_width of edge."""
    fall = np.clip(-np.diff(profile), 0.0, None)[edge - half_width:edge + half_width + 1]
    x = np.arange(len(fall))
    mean = np.sum(x * fall) / fall.sum()
    return np.sqrt(np.sum((x - mean)**2 * fall) / fall.sum())


def test_defocus_blurs_by_the_circle_of_confusion_and_not_in_focus(plate):
    scene = plate[1]
    sharp, renderer = shoot(plate)
    in_focus, _ = shoot(plate, ("defocus",))                      # focus default: the feature
    near_focus, _ = shoot(plate, ("defocus",), focus_m=0.35)
    profiles = [edge_profile(image, renderer, scene) for image in (sharp, in_focus, near_focus)]
    steps = [np.abs(np.diff(profile)).max() for profile in profiles]
    assert steps[1] > 0.8 * steps[0] and steps[2] < 0.35 * steps[0]
    assert near_focus.sum() == pytest.approx(sharp.sum(), rel=1e-3)   # light is only moved
    # the edge spreads by the Gaussian with the thin-lens disk's second moment, sigma = c / 4
    f, kappa, u, z = 0.025, EXPOSURE[1], 0.35, 0.5
    c_px = f**2 * abs(z - u) / (kappa * (u - f) * z) / renderer.pixel_pitch_m
    edge = int(np.argmax(-np.diff(profiles[0])))
    blur = np.sqrt(edge_spread(profiles[2], edge)**2 - edge_spread(profiles[0], edge)**2)
    assert blur == pytest.approx(c_px / 4.0, rel=0.1)


def test_blur_diameter_is_the_circle_of_confusion_at_the_depth_of_field_limits():
    u, f, kappa, sigma = 0.35, 0.025, 6.2, 5.015e-6
    for z in (dof.near_limit(u, f, kappa, sigma), dof.far_limit(u, f, kappa, sigma)):
        assert dof.blur_diameter(z, u, f, kappa) == pytest.approx(sigma, rel=1e-12)
    assert dof.blur_diameter(u, u, f, kappa) == 0.0
    assert dof.blur_diameter(np.inf, u, f, kappa) == pytest.approx(f**2 / (kappa * (u - f)))


def test_noise_has_the_shot_and_read_variance_and_a_seed_fixes_it(plate):
    clean, _ = shoot(plate)
    noisy, renderer = shoot(plate, ("noise",))
    again, _ = shoot(plate, ("noise",))
    assert np.array_equal(noisy, again)
    assert not np.array_equal(noisy, renderer(plate[1].T_cell_cam, OVERHEAD, DOWN, *EXPOSURE))
    assert not np.array_equal(noisy, shoot(plate, ("noise",), seed=2)[0])
    gain = 255.0 / world.FULL_WELL_E                      # gray per electron
    z = (noisy - clean) / np.sqrt(gain * clean + (gain * world.READ_NOISE_E)**2)
    lit = clean > 50.0
    assert lit.sum() > 5000
    assert abs(z[lit].mean()) < 0.03 and z[lit].std() == pytest.approx(1.0, abs=0.03)
    assert z[clean == 0.0].std() == pytest.approx(1.0, abs=0.03)     # read noise alone


def test_black_level_adds_a_constant(plate):
    plain, _ = shoot(plate)
    offset, _ = shoot(plate, ("black_level",))
    np.testing.assert_allclose(offset - plain, 5.0, atol=1e-12)     # 2 % of 255, rounded


def test_quantization_gives_integers_clipped_at_the_bit_depth(plate):
    exposure = (3 * EXPOSURE[0], EXPOSURE[1])            # bright enough to saturate the centre
    plain, _ = shoot(plate, exposure=exposure)
    quantized, _ = shoot(plate, ("quantization",), exposure=exposure)
    assert quantized.dtype == np.uint8
    np.testing.assert_array_equal(quantized, np.clip(np.rint(plain), 0, 255))
    assert np.sum(quantized == 255) == np.sum(plain >= 254.5) > 100
    assert quantized.min() == 0


# --- several lights: linear in every channel's drive --------------------------------------------

def ring_shots(plans, effects, **truth):
    """shoot(drives) -> the ring task's image at the plan's poses and exposure at the test grid with
    these channel drives; and the plan."""
    task, p = plans["ring"]
    renderer = Renderer(with_sim(task, effects, **truth), p.scene, scale=SCALE)
    aim = lamp_aim(task.lamp.rig.pivot_m, p.shot.lamp_position)
    e = p.shot.exposure
    return lambda drives: renderer(p.scene.T_cell_cam, p.shot.lamp_position, aim, e.shutter_s, e.f_number,
                                   drives=drives), p


def test_a_capture_at_the_planned_drives_is_the_sum_of_the_basis_captures_within_the_noise(plans):
    """G = b + sum_k w_k G_k (the linearity the drive program relies on, cell.planning.drives):
    with noise, black level and quantization, the capture with every channel at its planned drive
    less the dark frame (every channel off) equals the sum of the basis captures (one channel at its
    planned drive, the others off), each less the dark frame, to the noise: the residual
    F - sum_k B_k + (K - 1) D over its standard deviation from the sensor model (EMVA 1288's
    K mu_e + (K sigma_d)^2 + 1/12 per frame) has mean 0 and spread 1."""
    shoot_at, p = ring_shots(plans, ("shadows", "noise", "black_level", "quantization"))
    drives = planned_drives(p.shot)
    assert len(drives) == 3 and sum(d > 0 for d in drives.values()) >= 2
    off = dict.fromkeys(drives, 0.0)
    full, dark = shoot_at(drives).astype(float), shoot_at(off).astype(float)
    basis = [shoot_at(off | {channel: drive}).astype(float) for channel, drive in drives.items()]
    clean = ring_shots(plans, ())[0]
    sensor = world.SensorModel.of(plans["ring"][0].camera.sensor)
    gain, read = sensor.gain_dn_per_e, sensor.dark_noise_e

    def variance(signal):
        return gain * signal + (gain * read) ** 2 + 1.0 / 12.0

    signals = [clean(off | {channel: drive}) for channel, drive in drives.items()]
    k = len(basis)
    expected = variance(sum(signals)) + sum(variance(s) for s in signals) + (k - 1) ** 2 * variance(0.0)
    residual = full - sum(basis) + (k - 1) * dark
    lit = (sum(signals) > 20.0) & (full < 250.0)
    assert lit.sum() > 10_000
    z = residual[lit] / np.sqrt(expected[lit])
    assert abs(z.mean()) < 0.05 and z.std() == pytest.approx(1.0, abs=0.05)
    np.testing.assert_allclose((full - dark)[lit].mean(), sum(b - dark for b in basis)[lit].mean(), rtol=2e-3)


def test_a_dead_channel_lights_nothing_and_a_weak_one_its_share(plans):
    """sim.truth.channel_power_scale: the dark-field ring's channel at 0 (dead) leaves the spot's
    light alone; at 0.5 its share of the image halves."""
    task, p = plans["ring"]
    ring = next(light.channel for light in p.shot.lights if light.name == "dark_field_ring")
    drives = planned_drives(p.shot)
    shoot_at = ring_shots(plans, ())[0]
    alone = shoot_at(drives | {ring: 0.0})
    model = shoot_at(drives)
    dead = ring_shots(plans, (), channel_power_scale=((ring, 0.0),))[0](drives)
    weak = ring_shots(plans, (), channel_power_scale=((ring, 0.5),))[0](drives)
    np.testing.assert_allclose(dead, alone, rtol=1e-12, atol=0)
    np.testing.assert_allclose(weak - alone, 0.5 * (model - alone), rtol=1e-9, atol=1e-12)
    assert (model - alone).max() > 50.0


# --- (c) truth ---------------------------------------------------------------------------------

@pytest.mark.parametrize("truth", [{"albedo_scale": 1.4}, {"camera_constant_scale": 1.4}])
def test_the_truth_scales_the_gray(plate, truth):
    model, _ = shoot(plate)
    true, _ = shoot(plate, **truth)
    lit = model > 0.0
    assert np.array_equal(true > 0.0, lit)
    np.testing.assert_allclose(true[lit] / model[lit], 1.4, rtol=1e-12)


def test_a_lamp_aim_error_moves_only_the_cone(plate):
    aimed, renderer = shoot(plate)
    erred, erred_renderer = shoot(plate, lamp_direction_error_rad=np.radians(2.0))
    axis = erred_renderer.lamp_axis(DOWN)
    assert np.degrees(np.arccos(axis @ DOWN)) == pytest.approx(2.0)
    both = (aimed > 0.0) & (erred > 0.0)
    np.testing.assert_allclose(erred[both], aimed[both], rtol=1e-12)
    # the lit disk moves to where the true axis meets the plate
    scene = plate[1]
    hit = OVERHEAD + axis * OVERHEAD[2] / -axis[2]
    shift = np.subtract(pixel(renderer, scene, hit), pixel(renderer, scene, OVERHEAD * [1, 1, 0]))
    centroid = [np.argwhere(image > 0.0).mean(axis=0) for image in (aimed, erred)]
    np.testing.assert_allclose(centroid[1] - centroid[0], shift, atol=1.0)


# --- (d) determinism ---------------------------------------------------------------------------

def test_a_seed_fixes_every_frame_and_every_effect(plate):
    task, scene = plate
    task = with_sim(task, ALL_EFFECTS, seed=7, lamp_direction_error_rad=np.radians(1.0))
    first, second = (Renderer(task, scene, scale=SCALE) for _ in range(2))
    frames = [[r(scene.T_cell_cam, OVERHEAD, DOWN, *EXPOSURE) for _ in range(2)]
              for r in (first, second)]
    assert all(np.array_equal(a, b) for a, b in zip(*frames))
    assert not np.array_equal(*frames[0])                      # fresh noise every capture
    other = Renderer(with_sim(task, ALL_EFFECTS, seed=8, lamp_direction_error_rad=np.radians(1.0)),
                     scene, scale=SCALE)
    assert not np.allclose(other.lamp_axis(DOWN), first.lamp_axis(DOWN))


# --- (e) the truth keys, each on its own -------------------------------------------

F_PX = 0.025 / (4.65e-6 / SCALE)        # focal length over the test grid's pixel pitch [px]
CUBE_TOP = np.array([-0.015, 0.0, 0.008])  # the cube's top face centre, 0.492 m from the camera
OVER_CUBE = CUBE_TOP * [1, 1, 0] + [0.0, 0.0, 0.2]


def lit_centroid(image):
    """(row, col) centroid of the lit pixels."""
    return np.argwhere(image > 0.0).mean(axis=0)


def cube_centroid(image):
    """(row, col) centroid of the cube's top face under a wide lamp 0.2 m above it: 8 mm nearer
    the lamp than the plate, it is (0.2 / 0.192)^2 = 1.085x brighter than any plate point."""
    plate_max = image.max() / (0.2 / 0.192) ** 2
    return np.argwhere(image > 1.04 * plate_max).mean(axis=0)


def test_a_hand_eye_offset_shifts_the_image_by_f_over_pitch_times_offset_over_distance(plate):
    """The camera frame's x is the cell's here (looking straight down, scene.look_at): the true
    camera 2 mm along it sees the lit disk on the plate (0.5 m away) f/p 0.002/0.5 px to the left."""
    aimed, _ = shoot(plate)
    shifted, _ = shoot(plate, camera_offset_m=(0.002, 0.0, 0.0))
    np.testing.assert_allclose(lit_centroid(shifted) - lit_centroid(aimed), [0.0, -F_PX * 0.002 / 0.5], atol=0.1)


def test_a_hand_eye_rotation_turns_the_image_by_f_tan_angle(plate):
    """Turned by +0.25 deg about its x axis, the true camera sees a point of the old axis at
    R^T (0, 0, Z) = (0, Z sin, Z cos): f tan(0.25 deg) px further down the image."""
    aimed, _ = shoot(plate)
    turned, _ = shoot(plate, camera_rpy_rad=(np.radians(0.25), 0.0, 0.0))
    shift = lit_centroid(turned) - lit_centroid(aimed)
    np.testing.assert_allclose(shift, [F_PX * np.tan(np.radians(0.25)), 0.0], atol=0.1)


def test_a_part_offset_moves_the_part_by_its_projection(plate):
    """The part 3 mm along the cell's x (the camera's x) moves the cube's top f/p 0.003/0.492 px
    right; the lamp stays where it was."""
    kw = dict(lamp=OVER_CUBE, cone_deg=WIDE, exposure=WIDE_EXPOSURE)
    placed, _ = shoot(plate, **kw)
    moved, _ = shoot(plate, part_offset_m=(0.003, 0.0, 0.0), **kw)
    np.testing.assert_allclose(cube_centroid(moved) - cube_centroid(placed), [0.0, F_PX * 0.003 / 0.492],
                               atol=0.3)


def test_a_part_rotation_turns_the_part_about_the_feature_centre(plate):
    """Yawed 90 deg about the feature centre (15, 0, 0) mm, the cube 30 mm to its -x goes 30 mm to
    its -y: its top face images where (15, -30, 8) mm projects."""
    task, scene = plate
    turned_top = np.array([0.015, -0.030, 0.008])
    image, renderer = shoot(plate, lamp=turned_top * [1, 1, 0] + [0.0, 0.0, 0.2], cone_deg=WIDE,
                            exposure=WIDE_EXPOSURE, part_rpy_rad=(0.0, 0.0, np.pi / 2))
    uv, _ = project(renderer.K, scene.T_cell_cam, turned_top[None])
    np.testing.assert_allclose(cube_centroid(image), uv[0, ::-1], atol=0.3)


def test_a_truth_material_with_twice_the_albedo_doubles_the_gray(plate):
    task, _ = plate
    doubled = replace(task.part.material, rho=2.0 * task.part.material.rho)
    model, _ = shoot(plate)
    true, _ = shoot(plate, material=doubled)
    lit = model > 0.0
    np.testing.assert_allclose(true[lit] / model[lit], 2.0, rtol=1e-12)
    assert not true[~lit].any()


def test_a_lamp_radius_error_scales_the_irradiance_at_the_centre_by_the_inverse_square(plate):
    """The lamp 20 mm farther from the pivot along its aim: at the point under it (0.2 m) the
    gray is (0.2 / 0.22)^2 of the model's."""
    scene = plate[1]
    model, renderer = shoot(plate)
    true, _ = shoot(plate, lamp_radius_error_m=0.02)
    below = pixel(renderer, scene, OVERHEAD * [1, 1, 0])
    assert true[below] / model[below] == pytest.approx((0.2 / 0.22) ** 2, rel=1e-4)


def test_the_planner_ignores_the_truth(plans, tmp_path):
    """plan.json (all but its timings) is the same whatever the world's truth."""
    hinge, p = plans["hinge"]
    other = load_task(TASKS / "conrod.yaml").part.material
    truth = Truth(albedo_scale=2.0, camera_constant_scale=0.5, lamp_direction_error_rad=0.05,
                  material=other, part_offset_m=(0.002, 0, 0), part_rpy_rad=(0, 0, 0.1),
                  camera_offset_m=(0, 0.002, 0), camera_rpy_rad=(0.01, 0, 0), lamp_radius_error_m=0.02)
    truthful = plan(replace(hinge, sim=replace(hinge.sim, truth=truth)))
    first, second = (q.to_json() for q in (p, truthful))
    for document in (first, second):
        del document["timing_s"]
    assert first == second


# --- defects (sim.effects: defects) --------------------------------------------------------------

SIDE_LAMP = np.array([0.115, 0.0, 0.1])       # 45 deg above the feature centre (15, 0, 0) mm, from +x
COATED = Material("coat", "test", phase_rad=np.array([0.0, np.pi]), rho=0.6 * np.ones(2), sigma1=np.zeros(2),
                  m1=np.ones(2), sigma2=np.zeros(2), m2=2 * np.ones(2))
PLATE_DEFECTS = {   # each on the plate's feature, 1 mm off its centre (15, 0, 0) mm
    "scratch": Defect("groove", "scratch", 5.0, width_m=1e-3, depth_m=1e-4, position_m=(0.016, 0.0, 0.0)),
    "dent": Defect("ding", "dent", 5.0, depth_m=2e-4, radius_m=2e-3, position_m=(0.016, 0.0, 0.0)),
    "coating": Defect("bare", "coating", 5.0, radius_m=2e-3, material=COATED, position_m=(0.016, 0.0, 0.0)),
}


def expected_normal(kind, p):
    """The surface normal at plate points p (P, 3) on each defect, worked by hand: the groove runs
    along y (the truth's 90 deg), its wall at x < 16 mm turned toward +x by atan(2 h / w), the other
    toward -x; the dimple's normal leans toward its centre by asin(rho / R), R = (a^2 + h^2) / 2h."""
    x, y = p[:, 0] - 0.016, p[:, 1]
    if kind == "scratch":
        beta = np.arctan(2 * 1e-4 / 1e-3)
        return np.column_stack([-np.sign(x) * np.sin(beta), 0 * x, np.full_like(x, np.cos(beta))])
    if kind == "dent":
        rho, R = np.hypot(x, y), (2e-3**2 + 2e-4**2) / (2 * 2e-4)
        t = np.arcsin(rho / R)
        return np.column_stack([-np.sin(t) * x / rho, -np.sin(t) * y / rho, np.cos(t)])
    return np.tile([0.0, 0.0, 1.0], (len(p), 1))


@pytest.mark.parametrize("kind", ["scratch", "dent", "coating"])
def test_a_declared_defect_is_rendered_only_with_the_defects_effect_and_as_its_geometry_says(plate, kind):
    """The Lambertian plate (R = rho cos ti): a pixel on the defect reads the surface's gray times
    (n' s) / (n s) (its normal n' from expected_normal, s toward the lamp) and a coating's times
    0.6 / 0.3; every other pixel, and every pixel without the effect, is the plain plate's."""
    task, scene = plate
    defect = PLATE_DEFECTS[kind]
    with_defect = (replace(task, features=(replace(task.feature, defects=(defect,)),)), scene)
    aim = geometry.unit(scene.center - SIDE_LAMP)
    plain, renderer = shoot(plate, (), SIDE_LAMP, aim, 30.0)
    off, _ = shoot(with_defect, (), SIDE_LAMP, aim, 30.0, defect_orientation_rad=(("groove", np.pi / 2),))
    on, _ = shoot(with_defect, ("defects",), SIDE_LAMP, aim, 30.0, defect_orientation_rad=(("groove", np.pi / 2),))
    assert np.array_equal(off, plain)
    p = plate_points(renderer, scene).reshape(-1, 3)
    x, rho = p[:, 0] - 0.016, np.hypot(p[:, 0] - 0.016, p[:, 1])
    margin = 1e-6                                   # float32 hit distances: skip pixels at an edge
    if kind == "scratch":
        inside = (np.abs(x) < 5e-4 - margin) & (np.hypot(p[:, 0] - 0.015, p[:, 1]) < 0.005 - margin)
        outside = (np.abs(x) > 5e-4 + margin) | (np.hypot(p[:, 0] - 0.015, p[:, 1]) > 0.005 + margin)
    else:
        inside, outside = rho < 2e-3 - margin, rho > 2e-3 + margin
    on, plain = on.reshape(-1), plain.reshape(-1)
    assert inside.sum() > 20 and np.array_equal(on[outside], plain[outside])
    s = geometry.unit(SIDE_LAMP - p[inside])
    ratio = np.einsum("pk,pk->p", expected_normal(kind, p[inside]), s) / s[:, 2] * (2.0 if kind == "coating" else 1.0)
    np.testing.assert_allclose(on[inside], plain[inside] * ratio, rtol=1e-5)
    assert np.ptp(ratio) > 0.05 or kind == "coating"


def test_a_coating_of_twice_the_albedo_doubles_the_gray_under_every_light(plans):
    """The ring task at its plan's drives (the spot and the lit ring's emitter points each
    re-shaded on the defect): a coating of the part's material with rho x 2 (R is linear in rho)
    reads exactly twice the plain capture on its pixels, which cover its disk (pi r^2 over a
    pixel's footprint squared, within 10 %), and nothing else changes."""
    task, p = plans["ring"]
    scene = p.scene
    coat = Defect("double", "coating", 5.0, radius_m=0.004, material=task.part.material.scaled(2.0))
    coated = replace(task, features=(replace(task.feature, defects=(coat,)),))
    aim = lamp_aim(task.lamp.rig.pivot_m, p.shot.lamp_position)
    args = (scene.T_cell_cam, p.shot.lamp_position, aim, p.shot.exposure.shutter_s, p.shot.exposure.f_number)
    plain = Renderer(with_sim(coated), scene)(*args, drives=planned_drives(p.shot))
    on = Renderer(with_sim(coated, ("defects",)), scene)(*args, drives=planned_drives(p.shot))
    changed = on != plain
    np.testing.assert_allclose(on[changed], 2.0 * plain[changed], rtol=1e-9)
    sensor, lens = task.camera.sensor, task.camera.lens
    footprint = sensor.pixel_pitch_m * np.linalg.norm(scene.center - scene.camera_position) / lens.focal_length_m
    assert changed.sum() == pytest.approx(np.pi * 0.004**2 / footprint**2, rel=0.1)
