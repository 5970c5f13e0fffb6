"""Task and material files (docs/formats.md) -> validated, typed values in SI units.

Units are converted here and nowhere else, by the schema engine (cell.task.schema): every problem is
one TaskError naming the file, the dotted key path, what was found and what was expected. The
schemas below read like the file format; then the mesh is loaded and the feature snapped to it.
"""

from __future__ import annotations

import copy
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import ArrayLike

from cell.core import geometry
from cell.task import plausible
from cell.task.board import DICTIONARIES, Board
from cell.task.collision import COLLISION, collision_config
from cell.task.device_config import SECTIONS as DEVICES, devices_config, hand_eye
from cell.core.errors import TaskError
from cell.core.frames import Frames
from cell.core.inputs import checked_file
from cell.physics.material import PARAMETERS, TERMS, Material, Unresolved
from cell.physics import sensor as sensor_model
from cell.physics.radiometry import camera_constant_from_datasheet
from cell.task.schema import (NON_NEGATIVE, POSITIVE, Anything, Band, Choice, Flag, Integer, Invalid, Number, Pair,
                         Section, Sections, Spec, Table, Text, ToSI, Vector, parse, read_yaml, show)
from cell.task.types import (DEFECT_KINDS, LIGHT_TYPES, MOUNTS, Calibration, CameraModel, CellConfig, Channel,
                       Defect, Feature, Goniometer, Lamp, LampRig, Lens, Light, LoopSettings, Part, Requirements, Sample,
                       SimConfig, Sensor, Task, Truth, Viewpoint)

EFFECTS = ("shadows", "cone_falloff", "vignetting", "defocus", "noise", "black_level", "quantization", "defects",
           "collisions")
SURFACE_TOLERANCE_M = 1e-3       # feature center at most this far from the mesh surface
MAX_SAMPLES = 4096
MAX_SENSOR_SIDE_PX = 65_536
MAX_SENSOR_PIXELS = 160_000_000  # the largest machine-vision sensors (151 Mpx): a frame fits in memory
MIN_F_NUMBER = 0.5               # the physical limit of a lens in air (numerical aperture 1)
DATASHEET_AGREEMENT = 0.01       # camera_constant against the EMVA 1288 keys' c: relative


class Effects(Spec):
    """The simulator's effects: names from EFFECTS, each at most once."""

    expected = "a list of effect names"
    default = ()

    def convert(self, raw: Any, to_si: ToSI) -> tuple[str, ...]:
        if not isinstance(raw, list):
            raise Invalid(raw, self.expected)
        for i, name in enumerate(raw):
            if name == "interreflection":
                raise Invalid(name, "a simulated effect (interreflection is not modelled)", i)
            if name not in EFFECTS:
                raise Invalid(name, "one of " + ", ".join(EFFECTS), i)
            if name in raw[:i]:
                raise Invalid(name, "each effect at most once", i)
        return tuple(raw)


class ChannelScales(Spec):
    """`sim.truth.channel_power_scale`: {channel: the true power over the model's}, each channel a
    controller channel (an integer >= 1), each scale a number >= 0 (0: a dead channel)."""

    expected = "a mapping of channel numbers to scales >= 0, e.g. {1: 0.8, 3: 0}"
    default: dict[int, float] = {}

    def convert(self, raw: Any, to_si: ToSI) -> dict[int, float]:
        if not isinstance(raw, dict):
            raise Invalid(raw, self.expected)
        for channel, scale in raw.items():
            if isinstance(channel, bool) or not isinstance(channel, int) or channel < 1:
                raise Invalid(channel, "a channel number (an integer >= 1)")
            if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0 <= scale < float("inf"):
                raise Invalid(scale, f"a scale >= 0 for channel {channel}")
        return {channel: float(scale) for channel, scale in raw.items()}


class DefectAngles(Spec):
    """`sim.truth.defect_orientation_deg`: {a scratch's name: its orientation in the world}, each
    an angle within [-360, 360] deg (which scratch each name is, _truth checks)."""

    expected = "a mapping of scratch names to angles within [-360, 360] deg, e.g. {fine: 30}"
    default: dict[str, float] = {}

    def convert(self, raw: Any, to_si: ToSI) -> dict[str, float]:
        if not isinstance(raw, dict):
            raise Invalid(raw, self.expected)
        out = {}
        for name, angle in raw.items():
            if not isinstance(name, str) or not name.strip():
                raise Invalid(name, "a defect's name")
            if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not abs(to_si(angle)) <= DEG(360):
                raise Invalid(angle, f"an angle within [-360, 360] deg for '{name}'")
            out[name] = float(to_si(angle))
        return out


class SensorSection(Section):
    """`camera.sensor`: its keys in the task, or the name of a camera file holding them (relative
    to the task file; `cell calibrate camera-constant` writes one), checked alike; "file" is the
    camera file's path, or None."""

    expected = "a mapping of keys, or the name of a camera file holding them"

    def read(self, file: str | PathLike[str], path: str, raw: Any, to_si: ToSI) -> dict[str, Any]:
        if not isinstance(raw, str):
            return super().read(file, path, raw, to_si) | {"file": None}
        camera_file = _relative_file(Path(file), path, raw, "yaml")
        return parse(camera_file, "", _read_mapping(camera_file), self.fields) | {"file": camera_file}


DEG = np.radians

DEFECT = {
    "name": Text(),
    "kind": Choice(*DEFECT_KINDS),
    "min_cnr": Number(**POSITIVE),
    "width_m": Number(**POSITIVE, default=None),
    "depth_m": Number(**POSITIVE, default=None),
    "orientation_deg": Pair(lambda v: DEG(-360) <= v <= DEG(360), "angles within [-360, 360] deg", default=None),
    "radius_m": Number(**POSITIVE, default=None),
    "material": Text(default=None),
    "position_m": Vector(default=None),
}
FEATURE = {
    "center_m": Vector(),
    "radius_m": Number(**POSITIVE),
    "samples": Integer(1, MAX_SAMPLES),
    "defects": Sections(DEFECT),
}
REQUIREMENTS = {
    "gray_band": Band(),
    "reflection": Choice("diffuse", "lobe", "spike", "any"),
    "region_margin_deg": Number(**NON_NEGATIVE),
    "lamp_tolerance_deg": Number(**NON_NEGATIVE),
    "depth_of_field_m": Number(**NON_NEGATIVE, default=0.0),
    "resolution_m": Number(**POSITIVE, default=None),
    "view_angle_deg": Number(lambda v: 0 < v <= DEG(90), "an angle in (0, 90] deg", default=None),
    "drive_tolerance": Number(lambda v: 0 <= v < 1, "a fraction in [0, 1)", default=0.0),
    "light_tolerance_deg": Number(**NON_NEGATIVE, default=0.0),
}
PROFILE = {
    "off_axis_deg": Table(lambda v: 0 <= v <= np.pi, "an angle within [0, 180] deg",
                          default=None, per="off-axis angle"),
    "relative": Table(lambda v: 0 <= v <= 1, "a number in [0, 1]", default=None,
                      per="off-axis angle"),
}
RIG = {
    "pivot_m": Vector(),
    "pan_range_deg": Pair(lambda v: DEG(-360) <= v <= DEG(360), "angles within [-360, 360] deg"),
    "tilt_range_deg": Pair(lambda v: DEG(-90) <= v <= DEG(90), "angles within [-90, 90] deg"),
    "radius_range_m": Pair(lambda v: v > 0, "positive lengths"),
    "radius_axis": Choice("manual", "servo"),
}
CHANNEL = {
    "channel": Integer(1, 255, default=None),        # the controller's numbering (Gardasoft's: from 1)
    "drive_range": Pair(lambda v: 0 <= v <= 1, "drive levels within [0, 1]", default=(0.0, 1.0)),
    "switched": Flag(default=False),
}
LIGHT = {
    "name": Text(),
    "type": Choice(*LIGHT_TYPES),
    "mount": Choice(*MOUNTS),
    "power_w": Number(**POSITIVE),
    **CHANNEL,
    "profile": Section(PROFILE, required=False),
    "cone_angle_deg": Number(lambda v: 0 < v < DEG(180), "an angle in (0, 180) deg", default=None),
    "position_m": Vector(default=None),
    "aim_m": Vector(default=None),
    "offset_m": Number(lambda v: True, "a length", default=None),
    "along": Vector(direction=True, default=None),
    "radius_m": Number(**POSITIVE, default=None),
    "tilt_deg": Number(lambda v: 0 <= v < DEG(90), "an angle within [0, 90) deg", default=None),
    "length_m": Number(**POSITIVE, default=None),
    "size_m": Pair(lambda v: v > 0, "positive lengths [width, height]", default=None, ascending=False),
    "hole_radius_m": Number(**POSITIVE, default=None),
    "housing_depth_m": Number(**POSITIVE, default=None),
    "aperture_radius_m": Number(**POSITIVE, default=None),
    "outer_radius_m": Number(**POSITIVE, default=None),
    "rig": Section(plausible.copied(RIG), required=False, defaults=False),
}


def _overriding(fields):
    """The same keys, each optional: absent (None), the task's top-level value is taken."""
    specs = {key: copy.copy(spec) for key, spec in fields.items()}
    for spec in specs.values():
        spec.default = None
    return specs


TASK = {
    "name": Text(),
    "part": Section({
        "mesh": Text(),
        "mesh_unit": Choice("m", "mm"),
        "position_m": Vector(),
        "rpy_deg": Vector(),
        "material": Text(),
    }),
    "feature": Section(FEATURE, required=False, defaults=False),        # one feature, or
    "features": Sections({"name": Text(), **plausible.copied(FEATURE),  # several
                          "requirements": Section(_overriding(REQUIREMENTS), required=False)}),
    "requirements": Section(REQUIREMENTS),                              # every feature's defaults
    "camera": Section({
        "distance_m": Number(**POSITIVE),
        "view_direction": Vector(direction=True),
        "sensor": SensorSection({
            "width_px": Integer(1, MAX_SENSOR_SIDE_PX),
            "height_px": Integer(1, MAX_SENSOR_SIDE_PX),
            "pixel_pitch_m": Number(**POSITIVE),
            "bit_depth": Integer(1, 16),
            "camera_constant": Number(**POSITIVE, default=None),
            "camera_constant_stderr": Number(**NON_NEGATIVE, default=None),
            "quantum_efficiency": Number(lambda v: 0 < v <= 1, "a number in (0, 1]", default=None),
            "wavelength_m": Number(lambda v: 0.2e-6 <= v <= 2e-6, "a wavelength of light within "
                                   "[0.2, 2] um", default=None),
            "system_gain_dn_per_e": Number(**POSITIVE, default=None),
            "dark_noise_e": Number(**NON_NEGATIVE, default=None),
            "saturation_capacity_e": Number(**POSITIVE, default=None),
            "source": Text(default=None),
            "black_level": Number(**NON_NEGATIVE, default=None),
        }),
        "lens": Section({
            "focal_length_m": Number(**POSITIVE),
            "f_number_range": Pair(lambda v: v >= MIN_F_NUMBER,
                                   f"f-numbers of at least {MIN_F_NUMBER:g} (no lens in air is faster)"),
            "circle_of_confusion_m": Number(**POSITIVE),
        }),
        "shutter_range_s": Pair(lambda v: v > 0, "positive times"),
        "viewpoint": Choice("fixed", "planned", default="fixed"),
        "standoff_range_m": Pair(lambda v: v > 0, "positive lengths", default=None),
        "standoff_steps": Integer(1, 16, default=3),
        "view_step_deg": Number(lambda v: DEG(1) <= v <= DEG(45), "an angle within [1, 45] deg",
                                default=float(DEG(15))),
        "views_per_feature": Integer(1, 32, default=3),
    }),
    "lamp": Section({
        "power_w": Number(**POSITIVE),
        "cone_angle_deg": Number(lambda v: 0 < v < DEG(180), "an angle in (0, 180) deg"),
        "profile": Section(PROFILE, required=False),
        "rig": Section(RIG),
        **CHANNEL,
    }, required=False, defaults=False),
    "lights": Sections(LIGHT),
    "cell": Section({
        "backend": Choice("sim", "hw", default="sim"),
        **DEVICES,                                       # arm, pan_tilt, camera: cell.task.device_config
        "collision": COLLISION,                          # cell.task.collision
    }, required=False),
    "sim": Section({
        "seed": Integer(0, 2**32 - 1, default=1),
        "effects": Effects(),
        "truth": Section({
            "albedo_scale": Number(**POSITIVE, default=1.0),
            "camera_constant_scale": Number(**POSITIVE, default=1.0),
            "lamp_direction_error_deg": Number(lambda v: 0 <= v <= DEG(90), "an angle within [0, 90] deg",
                                               default=0.0),
            "material": Text(default=None),
            "part_offset_m": Vector(default=(0.0, 0.0, 0.0)),
            "part_rpy_deg": Vector(default=(0.0, 0.0, 0.0)),
            "camera_offset_m": Vector(default=(0.0, 0.0, 0.0)),
            "camera_rpy_deg": Vector(default=(0.0, 0.0, 0.0)),
            "lamp_radius_error_m": Number(lambda v: True, "a number", default=0.0),
            "channel_power_scale": ChannelScales(),
            "defect_orientation_deg": DefectAngles(),
        }, required=False),
    }, required=False),
    "calibration": Section({
        "sample": Section({
            "material": Text(default=None),
            "radius_m": Number(**POSITIVE, default=0.025),
            "thickness_m": Number(**POSITIVE, default=0.002),
            "normal": Vector(direction=True, default=(0.0, 0.0, 1.0)),
        }, required=False),
        "goniometer": Section({
            "phase_deg": Table(lambda v: 0 < v < np.pi, "an angle within (0, 180) deg",
                               default=(np.radians(20.0), np.radians(40.0), np.radians(60.0))),
            "step_deg": Number(lambda v: 0 < v <= DEG(30), "an angle within (0, 30] deg", default=np.radians(2.0)),
            "max_angle_deg": Number(lambda v: 0 < v < DEG(90), "an angle within (0, 90) deg",
                                    default=np.radians(80.0)),
            "lamp_radius_m": Number(**POSITIVE, default=None),
        }, required=False),
        "board": Section({
            "squares_x": Integer(3, 100, default=9),
            "squares_y": Integer(3, 100, default=7),
            "square_size_m": Number(**POSITIVE, default=0.008),
            "marker_size_m": Number(**POSITIVE, default=0.006),
            "dictionary": Choice(*DICTIONARIES, default="DICT_5X5_100"),
            "position_m": Vector(default=(0.0, 0.08, 0.0)),
            "rpy_deg": Vector(default=(np.pi, 0.0, 0.0)),
        }, required=False),
    }, required=False),
    "loop": Section({
        "albedo_scale_range": Pair(lambda v: v > 0, "positive scales", default=(0.1, 10.0)),
        "registration_limit_m": Number(lambda v: v > 0, "a positive distance", default=None),
    }, required=False),
    "limits": plausible.Limits(),                        # wider plausible ranges (cell.task.plausible)
}
plausible.attach(TASK)

MATERIAL = {
    "name": Text(),
    "source": Text(),
    "phase_deg": Table(lambda v: 0 <= v <= np.pi, "an angle within [0, 180] deg"),
    "rho": Table(**POSITIVE),
    "sigma1": Table(**NON_NEGATIVE),
    "m1": Table(**POSITIVE),
    "sigma2": Table(**NON_NEGATIVE),
    "m2": Table(**POSITIVE),
    # written by the fitter; an unidentifiable parameter may have an infinite standard error
    **{f"{p}_stderr": Table(**NON_NEGATIVE, default=None, finite=False) for p in PARAMETERS},
    "rms_residual": Table(**NON_NEGATIVE, default=None),
    "unidentifiable": Anything(),
    "unresolved": Section({                  # written by cell measure-brdf
        "terms": Section({term: Table(lambda v: True, "a phase angle [deg] of the table's phase_deg", default=None,
                                      per="phase angle whose term is unresolved")
                          for term in TERMS}),
        "step_deg": Number(lambda v: v > 0, "a positive angle"),
        "resolvable_m_max": Number(**POSITIVE),
    }, required=False, defaults=False),
}


def _read_mapping(path):
    """A YAML file that must hold a mapping of keys (not empty, not a list)."""
    data = read_yaml(path)
    if data is None:
        raise TaskError(path, "", "an empty file", "a mapping of keys")
    return data


def load_material(path: str | PathLike[str]) -> Material:
    """A material file -> Material (phase in radians, parameters as arrays)."""
    path = Path(path)
    v = parse(path, "", _read_mapping(path), MATERIAL)
    phase = v["phase_rad"]
    for key, column in v.items():
        if isinstance(column, np.ndarray) and len(column) != len(phase):
            raise TaskError(path, key, f"{len(column)} values", f"{len(phase)}, one per phase_deg entry")
    if np.any(np.diff(phase) <= 0):
        found = show(np.round(np.degrees(phase), 6))
        raise TaskError(path, "phase_deg", found, "strictly ascending phase angles")
    for i, (m1, m2) in enumerate(zip(v["m1"], v["m2"])):
        if not m2 > m1:
            raise TaskError(path, f"m2[{i}]", show(m2), f"a spike exponent m2 > m1 = {m1:g}")
    table = ("name", "source", "phase_rad", "unresolved", *PARAMETERS)
    extra = {k: x for k, x in v.items() if k not in table and x is not None}
    return Material(v["name"], v["source"], phase, **{p: v[p] for p in PARAMETERS}, extra=extra,
                    unresolved=_unresolved(path, v["unresolved"], phase))


def _unresolved(path, section, phase):
    """The `unresolved` section -> Unresolved (phases in radians), or None; each term's phase
    angles must be rows of the table (they mark those rows' fitted terms as unknown)."""
    if section is None:
        return None
    terms = {term: phases for term, phases in section["terms"].items() if phases is not None}
    if not terms:
        raise TaskError(path, "unresolved.terms", "no term", "lobe: [phase angles] and/or spike: [phase angles]")
    table_deg = np.degrees(phase)
    for term, phases in terms.items():
        for i, p in enumerate(phases):
            if not np.isclose(table_deg, p, rtol=0, atol=1e-6).any():
                raise TaskError(path, f"unresolved.terms.{term}[{i}]", f"{p:g}",
                                "one of the table's phase_deg [" + ", ".join(f"{a:.6g}" for a in table_deg) + "]")
    return Unresolved({t: tuple(phase[np.argmin(abs(table_deg[:, None] - np.asarray(ps)), axis=0)].tolist())
                       for t, ps in terms.items()}, section["step_rad"], section["resolvable_m_max"])


def _relative_file(file, key, name, kind):
    """A file named relative to the task file: a regular file under its kind's size limit."""
    return checked_file(file.parent / name, kind, file, key, relative_to="the task file")


def _load_mesh(file, part, key="part.mesh"):
    """The part's mesh (or the fixture's: `key`) in metres; missing, unreadable, empty or
    non-finite meshes are errors."""
    name = part["mesh"]
    path = _relative_file(file, key, name, "mesh")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception:  # trimesh raises many kinds of errors on garbage
        mesh = None
    if not isinstance(mesh, trimesh.Trimesh):
        raise TaskError(file, key, f"'{name}', which trimesh cannot read", "a mesh file (STL, OBJ, PLY, ...)")
    if len(mesh.faces) == 0:
        raise TaskError(file, key, f"'{name}' with 0 triangles", "a mesh with triangles")
    if not np.isfinite(mesh.vertices).all():
        raise TaskError(file, key, f"'{name}' with NaN or infinite vertices", "finite coordinates")
    mesh.process()
    mesh.update_faces(mesh.nondegenerate_faces())       # zero-area triangles have no normal
    if len(mesh.faces) == 0:
        raise TaskError(file, key, f"'{name}' whose triangles all have zero area", "a mesh with a surface")
    if mesh.is_watertight and mesh.volume < 0:          # a closed shell wound inside out
        raise TaskError(file, key, f"'{name}' whose triangles face inward (a closed mesh of negative volume)",
                        "outward-facing triangles (reverse the mesh's winding)")
    if part["mesh_unit"] == "mm":
        mesh.apply_scale(1e-3)
    plausible.check_mesh(file, key, part["mesh_unit"], mesh.extents, name)
    return path, mesh


def closest_surface_point(mesh: trimesh.Trimesh, point: ArrayLike) -> tuple[np.ndarray, np.ndarray, float]:
    """(closest point on the mesh, that face's unit normal, distance) for one point.
    Brute force over all faces: trimesh's `mesh.nearest` needs rtree, which we do not depend on."""
    point = np.asarray(point, dtype=float)
    points = np.broadcast_to(point, (len(mesh.faces), 3))
    closest = trimesh.triangles.closest_point(mesh.triangles, points)
    distances = np.linalg.norm(closest - point, axis=1)
    i = int(np.argmin(distances))
    return closest[i], mesh.face_normals[i], float(distances[i])


def _feature(file, mesh, f, key, name, requirements):
    """The feature with its center snapped to the surface and the outward normal there."""
    center, normal, distance = closest_surface_point(mesh, f["center_m"])
    if distance > SURFACE_TOLERANCE_M:
        found = f"{show(f['center_m'])} m, {distance * 1e3:.1f} mm from the surface"
        raise TaskError(file, f"{key}.center_m", found,
                        "a point within 1 mm of the part's surface (part frame)")
    return Feature(name, center, normal, f["radius_m"], f["samples"], Requirements(**requirements), key,
                   _defects(file, key, f["defects"] or [], center, f["radius_m"]))


# each defect kind's keys (SI names) beside name, kind, min_cnr and position_m: all required, and
# a key of another kind is a mistake in the file (a `width_m` on a dent does nothing)
DEFECT_KEYS: dict[str, tuple[str, ...]] = {
    "scratch": ("width_m", "depth_m"),
    "dent": ("radius_m", "depth_m"),
    "coating": ("material", "radius_m"),
}
DEFECT_OPTIONAL = {"scratch": ("orientation_rad",)}


def _defects(file, key, entries, center, radius):
    """A feature's `defects` entries -> Defects: names unique on the feature, each kind's keys and
    only those, a dent no deeper than its radius (a spherical cap is at most a hemisphere), a
    coating's material file loaded and checked like `part.material`, a position within the
    feature's radius of its centre."""
    _unique_names(file, [(f"{key}.defects[{i}]", d["name"]) for i, d in enumerate(entries)], "the feature's defects")
    out = []
    for i, d in enumerate(entries):
        at = f"{key}.defects[{i}]"
        kind = d["kind"]
        for k in ("width_m", "depth_m", "orientation_rad", "radius_m", "material"):
            name = "orientation_deg" if k == "orientation_rad" else k
            if k in DEFECT_KEYS[kind] and d[k] is None:
                raise TaskError(file, f"{at}.{name}", "nothing", f"a value (required for a {kind})")
            if k not in DEFECT_KEYS[kind] + DEFECT_OPTIONAL.get(kind, ()) and d[k] is not None:
                owners = [t for t, ks in DEFECT_KEYS.items() if k in ks + DEFECT_OPTIONAL.get(t, ())]
                raise TaskError(file, f"{at}.{name}", show(d[k]),
                                f"no value: it is a key of a {' and a '.join(owners)}, not of a {kind}")
        if kind == "dent" and not d["depth_m"] <= d["radius_m"]:
            raise TaskError(file, f"{at}.depth_m", show(d["depth_m"]),
                            f"at most the dent's radius_m {d['radius_m']:g} m (a spherical dimple is at most a "
                            f"hemisphere)")
        material = None if d["material"] is None else load_material(
            _relative_file(Path(file), f"{at}.material", d["material"], "yaml"))
        position = d["position_m"]
        if position is not None and not np.linalg.norm(position - center) <= radius + SURFACE_TOLERANCE_M:
            raise TaskError(file, f"{at}.position_m", f"{show(position)} m, "
                            f"{1e3 * np.linalg.norm(position - center):.1f} mm from the feature's centre",
                            f"a point of the feature's patch, within its radius_m {radius:g} m of its centre "
                            f"(part frame)")
        orientation = (0.0, float(np.pi)) if d["orientation_rad"] is None else d["orientation_rad"]
        out.append(Defect(d["name"], kind, d["min_cnr"], d["width_m"], d["depth_m"], orientation, d["radius_m"],
                          material, None if position is None else tuple(map(float, position)), at))
    return tuple(out)


def _unique_names(file, keyed: list[tuple[str, str]], among: str) -> None:
    """Each (entry's key, its name) a name no earlier entry has, else one TaskError naming both."""
    seen: dict[str, str] = {}
    for key, name in keyed:
        if name in seen:
            raise TaskError(file, f"{key}.name", f"'{name}', also the name of {seen[name]}", f"a name unique among {among}")
        seen[name] = key


def _feature_entries(file, v):
    """[(key, name, feature values, requirement values)] from `feature:` (named `feature`) or
    `features:`, each feature's requirements the task's with its own keys replacing them (SI)."""
    if v["feature"] is not None and v["features"] is not None:
        raise TaskError(file, "feature, features", "both", "one of them: feature (one) or features (a list)")
    if v["feature"] is not None:
        return [("feature", "feature", v["feature"], v["requirements"])]
    if v["features"] is None:
        raise TaskError(file, "features", "nothing",
                        "a non-empty list of mappings of keys, or one feature as `feature` (required key)")
    _unique_names(file, [(f"features[{i}]", f["name"]) for i, f in enumerate(v["features"])], "the features")
    entries = []
    for i, f in enumerate(v["features"]):
        key = f"features[{i}]"
        own = f["requirements"]
        entries.append((key, f["name"], f, {k: v["requirements"][k] if own[k] is None else own[k] for k in own}))
    return entries


def any_band(sensor: dict[str, Any]) -> tuple[float, float]:
    """The band `gray_band: any` stands for, the sensor's range: low = b + 3 K sigma_d, three
    times the dark noise (EMVA 1288: K the system gain [gray/e-], sigma_d the dark noise [e-],
    cell.physics.sensor's defaults where the camera gives none) above the black level b (0 while
    unknown), so the good surface is not black; high = 2^bit_depth - 2, one level below the
    saturation level 2^bit_depth - 1 (a pixel reading that may be brighter), so it is not saturated."""
    bits = sensor["bit_depth"]
    noise = sensor_model.system_gain(bits, sensor["system_gain_dn_per_e"]) * sensor_model.dark_noise(sensor["dark_noise_e"])
    black = sensor["black_level"] or 0.0
    return float(black + 3.0 * noise), float(sensor_model.saturation_level(bits) - 1)


def _resolve_any(file, entries, written, sensor):
    """The entries with each `gray_band: any` replaced by any_band (Requirements.gray_any set);
    `any` on a feature without `defects` asks nothing of it: refused, naming the key it was written at."""
    out = []
    for key, name, f, req in entries:
        any_band_here = req["gray_band"] == "any"
        if any_band_here and not f["defects"]:
            own = key != "feature" and written(f) == "any"
            raise TaskError(file, f"{key}.requirements.gray_band" if own else "requirements.gray_band", "any",
                            f"an ascending pair of gray levels: `any` (only contrast matters) needs the feature's "
                            f"`defects` ({key} declares none)")
        out.append((key, name, f, req | {"gray_band": any_band(sensor) if any_band_here else req["gray_band"],
                                         "gray_any": any_band_here}))
    return out


def _check_gray_band(file, key, band, bit_depth):
    if band == "any":
        return
    top = 2**bit_depth - 1
    for i, gray in enumerate(band):
        if not 0 <= gray <= top:
            raise TaskError(file, f"{key}.gray_band[{i}]", show(gray),
                            f"a gray level in [0, {top}] (bit_depth {bit_depth})")


def _sensor(task_file, sensor):
    """The Sensor, its camera constant as given or from the EMVA 1288 keys (c = eta lambda K /
    (h c0)); given both ways, they must agree within DATASHEET_AGREEMENT. Errors name the camera
    file's keys when the sensor came from one."""
    file, key = (sensor["file"], str) if sensor["file"] else (task_file, "camera.sensor.{}".format)
    eta, wavelength, gain = (sensor[k] for k in ("quantum_efficiency", "wavelength_m", "system_gain_dn_per_e"))
    for name, value, needs in (("quantum_efficiency", eta, ("wavelength_m", wavelength)),
                               ("wavelength_m", wavelength, ("quantum_efficiency", eta)),
                               ("quantum_efficiency", eta, ("system_gain_dn_per_e", gain))):
        if value is not None and needs[1] is None:
            raise TaskError(file, key(needs[0]), "nothing", f"a value beside {name} (c = eta lambda K / (h c0) "
                                                            "needs quantum_efficiency, wavelength_m and "
                                                            "system_gain_dn_per_e)")
    c = sensor["camera_constant"]
    if eta is not None:
        datasheet = camera_constant_from_datasheet(eta, wavelength, gain)
        if c is not None and abs(c / datasheet - 1.0) > DATASHEET_AGREEMENT:
            raise TaskError(file, key("camera_constant"),
                            f"{show(c)}, {100 * abs(c / datasheet - 1):.1f} % from the {datasheet:.4g} of "
                            f"quantum_efficiency {eta:g}, wavelength_m {wavelength:g} and system_gain_dn_per_e {gain:g}",
                            f"the two within {100 * DATASHEET_AGREEMENT:g} % (or only one of them)")
        c = datasheet if c is None else c
    elif c is None:
        raise TaskError(file, key("camera_constant"), "nothing",
                        "c in G = c P t [1/(W s)], or quantum_efficiency, wavelength_m and system_gain_dn_per_e "
                        "from an EMVA 1288 datasheet (required key)")
    return Sensor(**(sensor | {"camera_constant": c}))


def _check_black_level(file, band, black_level):
    """A known black level below the band's top: the band must be reachable by light."""
    if band != "any" and black_level is not None and not black_level < band[1]:
        raise TaskError(file, "camera.sensor.black_level", show(black_level),
                        f"a gray level below the band's top {band[1]:g} (requirements.gray_band)")


def _truth(file, truth, rig, features):
    """The simulated world's truth: its material file loaded and checked like the task's, a
    lamp radius error that keeps the lamp beyond the rig's pivot, and orientations of scratches
    the features declare."""
    if not truth["lamp_radius_error_m"] > -rig.radius_range_m[0]:
        raise TaskError(file, "sim.truth.lamp_radius_error_m", show(truth["lamp_radius_error_m"]),
                        f"more than -{rig.radius_range_m[0]:g} m (the true lamp beyond the pivot)")
    scratches = sorted({d.name for f in features for d in f.defects if d.kind == "scratch"})
    for name in truth["defect_orientation_rad"]:
        if name not in scratches:
            raise TaskError(file, f"sim.truth.defect_orientation_deg.{name}", "no scratch of that name",
                            "the name of a scratch in a feature's defects"
                            + (f" ({', '.join(scratches)})" if scratches else " (the task declares none)"))
    name = truth["material"]
    material = None if name is None else load_material(
        _relative_file(file, "sim.truth.material", name, "yaml"))
    vectors = {k: tuple(map(float, v)) for k, v in truth.items() if isinstance(v, np.ndarray)}
    scales = tuple(sorted(truth["channel_power_scale"].items()))
    angles = tuple(sorted(truth["defect_orientation_rad"].items()))
    return Truth(**(truth | vectors | {"material": material, "channel_power_scale": scales,
                                       "defect_orientation_rad": angles}))


def _calibration(file, calibration, material, rig):
    """The calibration routines' set-up: the goniometer's sample (its material file loaded and
    checked like `part.material`, else the part's) and its sampling, whose lamp radius lies in the
    rig's range (default: the middle of it) and whose phase angles fit under twice max_angle."""
    sample, gonio = calibration["sample"], calibration["goniometer"]
    name = sample["material"]
    sample_material = material if name is None else load_material(
        _relative_file(file, "calibration.sample.material", name, "yaml"))
    lo, hi = rig.radius_range_m
    radius = gonio["lamp_radius_m"]
    if radius is None:
        radius = 0.5 * (lo + hi)
    elif not lo <= radius <= hi:
        raise TaskError(file, "calibration.goniometer.lamp_radius_m", show(radius),
                        f"a radius within lamp.rig.radius_range_m [{lo:g}, {hi:g}] m")
    phases = np.asarray(gonio["phase_rad"], float)
    if np.any(np.diff(phases) <= 0):
        raise TaskError(file, "calibration.goniometer.phase_deg", show(np.degrees(phases).tolist()),
                        "ascending phase angles")
    if phases[-1] >= 2 * gonio["max_angle_rad"]:
        raise TaskError(file, "calibration.goniometer.phase_deg", f"{np.degrees(phases[-1]):g} deg",
                        f"phase angles below twice max_angle_deg ({np.degrees(2 * gonio['max_angle_rad']):g} deg): "
                        "lamp and camera each within max_angle_deg of the normal")
    return Calibration(Sample(sample_material, sample["radius_m"], sample["thickness_m"],
                              tuple(map(float, sample["normal"]))),
                       goniometer=Goniometer(tuple(map(float, phases)), gonio["step_rad"], gonio["max_angle_rad"],
                                             lamp_radius_m=radius))


def _board(file, board):
    """The ChArUco board: markers smaller than their squares, and no more of them than the
    dictionary holds."""
    if not board["marker_size_m"] < board["square_size_m"]:
        raise TaskError(file, "calibration.board.marker_size_m", show(board["marker_size_m"]),
                        f"less than square_size_m {board['square_size_m']:g} m (a marker lies inside a square)")
    squares = (board["squares_x"], board["squares_y"])
    made = Board(squares, board["square_size_m"], board["marker_size_m"], board["dictionary"],
                 geometry.from_rpy(board["rpy_rad"], board["position_m"]))
    if made.markers > DICTIONARIES[made.dictionary]:
        raise TaskError(file, "calibration.board.dictionary", made.dictionary,
                        f"a dictionary of at least {made.markers} markers ({squares[0]} x {squares[1]} squares)")
    return made


def _loop(file, loop):
    low, high = loop["albedo_scale_range"]
    if not low <= 1.0 <= high:
        raise TaskError(file, "loop.albedo_scale_range", show([low, high]),
                        "a range of albedo scales holding 1 (the model itself)")
    return LoopSettings(**loop)


def _check_camera(file, cam):
    """A sensor whose frame fits in memory and a camera beyond its lens's focal length."""
    sensor = cam["sensor"]
    pixels = sensor["width_px"] * sensor["height_px"]
    if pixels > MAX_SENSOR_PIXELS:
        raise TaskError(file, "camera.sensor", f"{sensor['width_px']} x {sensor['height_px']} px",
                        f"at most {MAX_SENSOR_PIXELS / 1e6:g} Mpx (a frame must fit in memory)")
    focal = cam["lens"]["focal_length_m"]
    if not cam["distance_m"] > focal:
        raise TaskError(file, "camera.distance_m", show(cam["distance_m"]),
                        f"more than the focal length {focal:g} m (a lens focuses only beyond it)")
    standoff = cam["standoff_range_m"]
    if cam["viewpoint"] == "planned" and standoff is None:
        raise TaskError(file, "camera.standoff_range_m", "nothing",
                        "an ascending pair of positive lengths (required with camera.viewpoint: planned)")
    if standoff is not None and not standoff[0] > focal:
        raise TaskError(file, "camera.standoff_range_m[0]", show(standoff[0]),
                        f"more than the focal length {focal:g} m (a lens focuses only beyond it)")


def _viewpoint(cam):
    return Viewpoint(cam["viewpoint"], cam["standoff_range_m"], cam["standoff_steps"], cam["view_step_rad"],
                     cam["views_per_feature"])


def _check_outside(file, mesh, T_cell_part, points, lights=frozenset()):
    """Each {key: cell-frame point} lies outside the part (winding number below 1/2) or on its
    surface (within SURFACE_TOLERANCE_M): a lamp pivot or a camera inside the part is a mistake.
    A fixed light's centre (its key in `lights`) must lie off the surface too: a light at a
    surface point has no direction to it there (0/0), and one on the part lights nothing around it."""
    T_part_cell = np.linalg.inv(T_cell_part)
    for (key, whose), point in points.items():
        local = geometry.apply(T_part_cell, point)
        distance = closest_surface_point(mesh, local)[2]
        if geometry.winding_number(mesh.vertices, mesh.faces, local) > 0.5 and distance > SURFACE_TOLERANCE_M:
            raise TaskError(file, key, f"{show(np.round(point, 6))} m, inside the part{whose}",
                            "a point outside the part (cell frame)")
        if key in lights and distance <= SURFACE_TOLERANCE_M:
            raise TaskError(file, key, f"{show(np.round(point, 6))} m, {distance * 1e3:.3g} mm from the part's "
                            f"surface{whose}", f"a light off the part, more than {SURFACE_TOLERANCE_M * 1e3:g} mm "
                            "from its surface (cell frame)")


def _lamp_profile(file, profile, key="lamp.profile"):
    """A light's angular profile (M, 2) [off_axis_rad, relative] at `key`, or None (the type's
    default: eq. (11)'s ideal cone for a spot): both columns or neither, of equal length, at least
    two angles strictly ascending from 0, and relative 1 on the axis (the light's power is spread
    over it: radiometry.axis_intensity)."""
    angles, relative = profile["off_axis_rad"], profile["relative"]
    if angles is None and relative is None:
        return None
    for column_key, column in (("off_axis_deg", angles), ("relative", relative)):
        if column is None:
            raise TaskError(file, f"{key}.{column_key}", "nothing",
                            "a list with one value per off-axis angle (required in a profile)")
    if len(angles) < 2:
        raise TaskError(file, f"{key}.off_axis_deg", show(np.degrees(angles)),
                        "at least two off-axis angles, from 0")
    if len(relative) != len(angles):
        raise TaskError(file, f"{key}.relative", f"{len(relative)} values",
                        f"{len(angles)}, one per off_axis_deg entry")
    if angles[0] != 0.0 or np.any(np.diff(angles) <= 0):
        raise TaskError(file, f"{key}.off_axis_deg", show(np.round(np.degrees(angles), 6)),
                        "strictly ascending off-axis angles from 0")
    if relative[0] != 1.0:
        raise TaskError(file, f"{key}.relative[0]", show(relative[0]),
                        "1 (the profile is relative to the axis)")
    return np.column_stack([angles, relative])


# how far the cone angle's half may lie from the profile's half-intensity angle: datasheets round
# an LED optic's beam angle (FWHM) to a degree or two, and a cone off by more is a different lamp
CONE_HALF_TOLERANCE_RAD = np.radians(1.0)
CONE_HALF_TOLERANCE_REL = 0.1


def half_intensity_angle(profile: np.ndarray) -> float:
    """The outermost off-axis angle [rad] where a profile (M, 2) falls through half its axis
    intensity: linear between its angles; a last value still above half falls to 0 at the last
    angle (a hard edge), so that angle."""
    angles, relative = profile[:, 0], profile[:, 1]
    j = int(np.flatnonzero(relative >= 0.5)[-1])
    if j == len(angles) - 1:
        return float(angles[j])
    t = (relative[j] - 0.5) / (relative[j] - relative[j + 1])
    return float(angles[j] + t * (angles[j + 1] - angles[j]))


def _check_cone_angle(file, cone_angle_rad, profile, key="lamp"):
    """The profile, if its half-intensity angle (half_intensity_angle: the beam angle's half, as
    LED datasheets give it) is the cone's half angle within max(1 deg, 10 % of it). The lamp's
    intensity follows from its profile alone (energy conserved: radiometry.axis_intensity), so a
    cone angle that says otherwise is a contradiction in the file, not a lamp: a 1 deg cone with a
    profile lighting to 9 deg would be planned as the profile lights."""
    if profile is None:
        return None
    half, found = 0.5 * cone_angle_rad, half_intensity_angle(profile)
    if abs(found - half) > max(CONE_HALF_TOLERANCE_RAD, CONE_HALF_TOLERANCE_REL * half):
        raise TaskError(file, f"{key}.cone_angle_deg", f"{np.degrees(cone_angle_rad):g} deg",
                        f"{2 * np.degrees(found):.3g} deg, twice the angle where {key}.profile falls to half "
                        f"its axis intensity ({np.degrees(found):.3g} deg; within 1 deg or 10 % of the half angle)")
    return profile


# each type's shape keys (SI names): required ones, and those it may have; a key of another type is
# a mistake in the file (a `tilt_deg` on a bar light does nothing)
SHAPES: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "spot": ((), ("cone_angle_rad",)),
    "ring": (("radius_m",), ("tilt_rad", "aperture_radius_m", "outer_radius_m")),
    "bar": (("length_m",), ("along",)),
    "area": ((), ("size_m", "radius_m", "along")),
    "dome": (("radius_m",), ("hole_radius_m",)),
    "coaxial": ((), ("size_m", "radius_m", "along")),
}
# a fixed light's housing (the shadow geometry, cell.planning.occluders; the collision body): fixed only
HOUSING_KEYS = ("housing_depth_m", "aperture_radius_m", "outer_radius_m")
MOUNT_KEYS = {"fixed": ("position_m", "aim_m", *HOUSING_KEYS), "flange": ("offset_m",), "pan_tilt": ("rig",)}
SHAPE_KEYS = sorted({k for need, may in SHAPES.values() for k in need + may})
FILE_KEY = {"cone_angle_rad": "cone_angle_deg", "tilt_rad": "tilt_deg"}


def _channel(file, key, entry, required):
    """The Channel of a light's `channel`, `drive_range` and `switched` keys; a light without a
    channel is on its own supply, always at full drive, and has no drive levels to give."""
    if entry["channel"] is None:
        if required:
            raise TaskError(file, f"{key}.channel", "nothing",
                            "the light's channel on the lighting controller (an integer, required key)")
        if entry["drive_range"] != (0.0, 1.0) or entry["switched"]:
            raise TaskError(file, f"{key}.drive_range" if entry["drive_range"] != (0.0, 1.0) else f"{key}.switched",
                            "a drive setting", f"a `{key}.channel` first (a light on no channel is always on)")
        return Channel(None, (1.0, 1.0), False)
    if not entry["drive_range"][1] > 0:
        raise TaskError(file, f"{key}.drive_range", show(list(entry["drive_range"])),
                        "a range reaching above 0 (a channel that can never light is no light)")
    return Channel(entry["channel"], entry["drive_range"], entry["switched"])


def _light(file, key, entry):
    """A `lights` entry (not on the pan-tilt) -> Light: its type's shape keys only, its mount's
    pose keys only, an axis from position_m to aim_m (fixed) or the camera's optical axis
    (flange), `along` perpendicular to it."""
    kind, mount = entry["type"], entry["mount"]
    need, may = SHAPES[kind]
    for k in SHAPE_KEYS:
        name = FILE_KEY.get(k, k)
        if k in need and entry[k] is None:
            raise TaskError(file, f"{key}.{name}", "nothing", f"a value (required for a {kind} light)")
        if k not in need + may and entry[k] is not None:
            owners = [t for t, (n, m) in SHAPES.items() if k in n + m]
            raise TaskError(file, f"{key}.{name}", show(entry[k]),
                            f"no value: it is a key of {' and '.join(owners)} lights, not of a {kind} light")
    if kind in ("area", "coaxial") and (entry["size_m"] is None) == (entry["radius_m"] is None):
        raise TaskError(file, f"{key}.size_m", "both or neither of size_m and radius_m",
                        f"one of them: a rectangle [width, height] or a disk's radius (a {kind} light)")
    if kind == "dome" and entry["hole_radius_m"] is not None and not entry["hole_radius_m"] < entry["radius_m"]:
        raise TaskError(file, f"{key}.hole_radius_m", show(entry["hole_radius_m"]),
                        f"less than the dome's radius_m {entry['radius_m']:g} m")
    if kind == "ring":
        for k, side, what in (("aperture_radius_m", -1, "less than"), ("outer_radius_m", 1, "more than")):
            if entry[k] is not None and not side * (entry[k] - entry["radius_m"]) > 0:
                raise TaskError(file, f"{key}.{k}", show(entry[k]), f"{what} the ring's radius_m {entry['radius_m']:g} m "
                                "(its LEDs' circle lies on the housing, between its hole and its outer edge)")
    if kind == "coaxial" and mount != "flange":
        raise TaskError(file, f"{key}.mount", mount, "flange (a coaxial light shines along the camera's axis)")
    for m, keys in MOUNT_KEYS.items():
        for k in keys:
            if m != mount and entry[k] is not None:
                raise TaskError(file, f"{key}.{k}", show(entry[k]) if k != "rig" else "a rig",
                                f"no value: it is a key of {m} lights (this one's mount is {mount})")
    if mount == "fixed":
        for k in ("position_m", "aim_m"):
            if entry[k] is None:
                raise TaskError(file, f"{key}.{k}", "nothing", "a 3-vector [x, y, z] (required for a fixed light)")
        position, axis = entry["position_m"], entry["aim_m"] - entry["position_m"]
        if not np.linalg.norm(axis) > 1e-6:
            raise TaskError(file, f"{key}.aim_m", show(entry["aim_m"]),
                            "a point on the light's axis away from its position_m")
        axis = geometry.unit(axis)
    else:                                           # flange: the camera frame, z its optical axis
        offset = 0.0 if entry["offset_m"] is None else entry["offset_m"]
        position, axis = np.array([0.0, 0.0, offset]), np.array([0.0, 0.0, 1.0])
    along = geometry.frame_from_normal(axis)[:, 0] if entry["along"] is None else entry["along"]
    along = along - (along @ axis) * axis
    if not np.linalg.norm(along) > 1e-6:
        raise TaskError(file, f"{key}.along", show(entry["along"]),
                        "a direction not along the light's axis (its length or width lies across the axis)")
    profile = _lamp_profile(file, entry["profile"], f"{key}.profile")
    if kind == "spot":
        if entry["cone_angle_rad"] is None and profile is None:
            raise TaskError(file, f"{key}.cone_angle_deg", "nothing",
                            "a spot's cone angle, or its profile (one is required)")
        if entry["cone_angle_rad"] is not None:
            profile = _check_cone_angle(file, entry["cone_angle_rad"], profile, key)
    return Light(entry["name"], kind, mount, entry["power_w"], _channel(file, key, entry, required=True),
                 position, axis, geometry.unit(along), profile, entry["cone_angle_rad"], entry["radius_m"],
                 entry["tilt_rad"] or 0.0, entry["length_m"], entry["size_m"], entry["hole_radius_m"], key,
                 **{k: entry[k] for k in HOUSING_KEYS})


def _lamp(file, lamp, entries):
    """The pan-tilt's spot, from `lamp` or from the one `lights` entry with mount: pan_tilt."""
    on_rig = [(i, e) for i, e in enumerate(entries) if e["mount"] == "pan_tilt"]
    if len(on_rig) > 1:
        raise TaskError(file, f"lights[{on_rig[1][0]}].mount", "pan_tilt, also lights[{}]'s".format(on_rig[0][0]),
                        "one light on the pan-tilt (it carries one spot)")
    if on_rig and lamp is not None:
        raise TaskError(file, f"lights[{on_rig[0][0]}].mount", "pan_tilt beside a `lamp` section",
                        "one spot on the pan-tilt: `lamp`, or a `lights` entry with mount: pan_tilt")
    if on_rig:
        i, e = on_rig[0]
        key = f"lights[{i}]"
        if e["type"] != "spot":
            raise TaskError(file, f"{key}.type", e["type"], "spot (the pan-tilt carries a spot)")
        if e["rig"] is None:
            raise TaskError(file, f"{key}.rig", "nothing", "the pan-tilt's rig (required with mount: pan_tilt)")
        for k in ("position_m", "aim_m", "offset_m", "along", "housing_depth_m", *SHAPE_KEYS[1:]):
            if k != "cone_angle_rad" and e.get(k) is not None:
                raise TaskError(file, f"{key}.{FILE_KEY.get(k, k)}", show(e[k]),
                                "no value (the pan-tilt's spot is placed by its rig)")
        if e["cone_angle_rad"] is None:
            raise TaskError(file, f"{key}.cone_angle_deg", "nothing", "the spot's cone angle (required)")
        lamp = {**e, "profile": e["profile"]}
        profile_key, name, channel = f"{key}.profile", e["name"], _channel(file, key, e, required=True)
    elif lamp is not None:
        key, profile_key, name, channel = "lamp", "lamp.profile", "lamp", _channel(file, "lamp", lamp, required=False)
    else:
        raise TaskError(file, "lamp", "nothing", "a spot on the pan-tilt: a `lamp` section, or a `lights` entry "
                                                 "with mount: pan_tilt (required)")
    profile = _check_cone_angle(file, lamp["cone_angle_rad"], _lamp_profile(file, lamp["profile"], profile_key), key)
    return Lamp(lamp["power_w"], lamp["cone_angle_rad"], LampRig(**lamp["rig"]), profile, name, channel, key)


def _lights(file, lamp, entries):
    """(the pan-tilt's Lamp, the other Lights), names and channels unique among them all."""
    spot = _lamp(file, lamp, entries)
    lights = tuple(_light(file, f"lights[{i}]", e) for i, e in enumerate(entries) if e["mount"] != "pan_tilt")
    keys = {spot.name: "lamp" if lamp is not None else "the pan-tilt's light"}
    channels = {} if spot.channel.number is None else {spot.channel.number: keys[spot.name]}
    for light in lights:
        if light.name in keys:
            raise TaskError(file, f"{light.key}.name", f"'{light.name}', also {keys[light.name]}'s",
                            "a name unique among the lights")
        keys[light.name] = light.key
        if light.channel.number in channels:
            raise TaskError(file, f"{light.key}.channel", f"{light.channel.number}, also {channels[light.channel.number]}'s",
                            "a channel used by one light only (each channel drives its own light)")
        channels[light.channel.number] = light.key
    return spot, lights


def _light_centres(lights, cameras):
    """{(key, whose): cell-frame point} of each light's emitting centre, to be checked outside the
    part: a fixed light's own, a flange light's on each camera's optical axis ({(key, whose):
    (camera position, the feature centre it looks at)}) at its offset."""
    out = {}
    for light in lights:
        if light.mount == "fixed":
            out[(f"{light.key}.position_m", "")] = light.position_m
            continue
        for (_, whose), (camera, target) in cameras.items():
            point = camera + light.position_m[2] * geometry.unit(target - camera)
            out[(f"{light.key}.offset_m", f", where the camera{whose} puts it")] = point
    return out


def load_task(path: str | PathLike[str]) -> Task:
    """A task file and everything it references -> Task (SI units, mesh in metres), every
    physical value within its plausible range (cell.task.plausible), as widened by `limits`."""
    path = Path(path)
    data = _read_mapping(path)
    written = data.get("limits") if isinstance(data, dict) else None
    limits = {} if written is None else TASK["limits"].read(path, "limits", written, lambda v: v)
    with plausible.widened(limits):
        return _load_task(path, data)


def _load_task(path: Path, data: Any) -> Task:
    v = parse(path, "", data, TASK)
    part, cam, lamp, cell, sim = v["part"], v["camera"], v["lamp"], v["cell"], v["sim"]
    arm = cell["arm"]
    _check_gray_band(path, "requirements", v["requirements"]["gray_band"], cam["sensor"]["bit_depth"])
    entries = _feature_entries(path, v)
    for key, _, f, _ in entries:
        if key != "feature" and f["requirements"]["gray_band"] is not None:
            _check_gray_band(path, f"{key}.requirements", f["requirements"]["gray_band"], cam["sensor"]["bit_depth"])
    black = cam["sensor"]["black_level"]
    _check_black_level(path, v["requirements"]["gray_band"], black)
    for key, _, f, _ in entries:
        if key != "feature" and f["requirements"]["gray_band"] is not None:
            _check_black_level(path, f["requirements"]["gray_band"], black)
    entries = _resolve_any(path, entries, lambda f: f["requirements"]["gray_band"], cam["sensor"])
    devices = devices_config(path, cell, written=data.get("cell"),
                             bit_depth=cam["sensor"]["bit_depth"])
    _check_camera(path, cam)
    mesh_path, mesh = _load_mesh(path, part)
    material = load_material(_relative_file(path, "part.material", part["material"], "yaml"))
    features = tuple(_feature(path, mesh, f, key, name, req) for key, name, f, req in entries)
    frames = Frames(T_cell_part=geometry.from_rpy(part["rpy_rad"], part["position_m"]),
                    T_cell_base=geometry.from_rpy(arm["base_rpy_rad"], arm["base_position_m"]),
                    T_flange_cam=hand_eye(path, arm, (data.get("cell") or {}).get("arm")))
    spot, lights = _lights(path, lamp, v["lights"] or [])
    aims = {("camera.distance_m", "" if len(features) == 1 else f" of {f.key} ({f.name})"):
            (geometry.apply(frames.T_cell_part, f.center_m + cam["distance_m"] * cam["view_direction"]),
             geometry.apply(frames.T_cell_part, f.center_m)) for f in features}
    cameras = {(key, f", the camera{whose}" if whose else ""): camera for (key, whose), (camera, _) in aims.items()}
    _check_outside(path, mesh, frames.T_cell_part, {(f"{'lamp' if lamp is not None else 'lights'}.rig.pivot_m", ""):
                                                    spot.rig.pivot_m, **cameras,
                                                    **_light_centres(lights, aims if cam["viewpoint"] == "fixed" else {})},
                   lights={f"{light.key}.position_m" for light in lights if light.mount == "fixed"})
    return Task(
        path=path,
        name=v["name"],
        part=Part(mesh_path, mesh, material),
        frames=frames,
        features=features,
        camera=CameraModel(cam["distance_m"], cam["view_direction"], _sensor(path, cam["sensor"]),
                           Lens(**cam["lens"]), cam["shutter_range_s"], _viewpoint(cam)),
        lamp=spot,
        lights=lights,
        cell=CellConfig(cell["backend"], devices, collision_config(
            path, cell["collision"], part["mesh_unit"],
            lambda key, name, unit: _load_mesh(path, {"mesh": name, "mesh_unit": unit}, key)[1],
            spot.rig.radius_range_m[1])),
        sim=SimConfig(sim["seed"], sim["effects"], _truth(path, sim["truth"], spot.rig, features)),
        loop=_loop(path, v["loop"]),
        calibration=_calibration(path, v["calibration"], material, spot.rig),
        board=_board(path, v["calibration"]["board"]),
    )
