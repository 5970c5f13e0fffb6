"""Every picture a person reads: the plan's maps (paper Fig. 4-6: BRDF on the visibility map,
segmented region map, cost map, each with the camera direction (square) and the lamp (dot)
marked), the cell of a plan (part, features, each shot's camera and lamp, the rig's sphere), the
closed loop's convergence and its captures with the measured feature drawn, the
calibration fit and the benchmark's error vs time.

Drawn through matplotlib's object API (a Figure per picture, saved by its own canvas): no global
figure state and no backend to select, so drawing is safe in worker processes, and a figure is
freed with its last reference; threads draw one picture at a time (_DRAWING).
"""
from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ParamSpec, Protocol, TypeVar

import cv2
import numpy as np
import trimesh
from matplotlib.colors import ListedColormap, to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from mpl_toolkits.mplot3d import proj3d
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from cell.physics.sensor import levels, saturation_level
from cell.core import geometry
from cell.planning import regions


from cell.physics import projection

from cell.devices import rig
from cell.physics import brdf

if TYPE_CHECKING:
    from cell.physics.material import Material
    from cell.planning.plan import Plan
    from cell.planning.scene import Scene
    from cell.task.types import Task

PathLike = str | os.PathLike[str]


# What the pictures read of the results of the stages above this one (cell.run, cell.calibration),
# which cell.report may not import: each named for the class it stands for.
class CameraConstantFit(Protocol):
    """cell.calibration.reference_part.Fit: G = b + c P t."""
    @property
    def camera_constant(self) -> float: ...
    @property
    def black_level(self) -> float: ...


class LaserFit(Protocol):
    """cell.calibration.camera_constant.LaserFit: S = offset + c P t."""
    @property
    def offset(self) -> float: ...
    @property
    def camera_constant(self) -> float: ...
    @property
    def camera_constant_stderr(self) -> float: ...
    @property
    def r_squared(self) -> float: ...


class LaserFrame(Protocol):
    """cell.calibration.camera_constant.Frame: a frame of the laser's sweep."""
    @property
    def shutter_s(self) -> float: ...
    @property
    def spot_sum(self) -> float | None: ...
    @property
    def saturated(self) -> bool: ...
    @property
    def too_dark(self) -> bool: ...
    @property
    def usable(self) -> bool: ...


class GoniometerReading(Protocol):
    """cell.calibration.goniometer.Reading: R at one pose."""
    @property
    def phase_deg(self) -> float: ...
    @property
    def beta_deg(self) -> float: ...
    @property
    def reflectance(self) -> float: ...


class MeasuredRegion(Protocol):
    """cell.run.measurement.Measurement: the feature's pixels in a capture."""
    @property
    def saturated(self) -> np.ndarray: ...
    @property
    def region(self) -> np.ndarray | None: ...
    @property
    def row(self) -> np.ndarray: ...
    @property
    def col(self) -> np.ndarray: ...


# Fixed margins fit these figure sizes and labels: tight_layout would cost a layout pass each.
MARGINS = {"left": 0.08, "right": 0.98, "bottom": 0.12, "top": 0.93}
PNG = {"compress_level": 1}     # zlib: lossless like the default, at a fraction of its time

# Each picture has its own Figure, but matplotlib's text layout (mathtext parser, font cache) is
# shared and not thread-safe: two threads laying out log-axis tick labels at once raise a
# ParseException. One picture at a time, then.
_DRAWING = threading.RLock()      # reentrant: a picture may draw another


P = ParamSpec("P")
Drawn = TypeVar("Drawn")      # what a picture function returns


def _one_at_a_time(write: Callable[P, Drawn]) -> Callable[P, Drawn]:
    @functools.wraps(write)
    def locked(*args: P.args, **kwargs: P.kwargs) -> Drawn:
        with _DRAWING:
            return write(*args, **kwargs)
    return locked


def _feature_angles(plan, scene, position):
    az, el = geometry.angles_from_direction((position - scene.center) @ scene.frame)
    return np.degrees(az), np.degrees(el)


def _mark_camera(ax, cam):
    """The camera's square where it is seen from the feature, whole at the map's edge (a camera
    near the normal has an azimuth of +-180 or any other: the corner), and named beside it, the
    label and its arrow inside the map."""
    az, el = (float(np.ravel(x)[0]) for x in cam)
    ax.plot(az, el, marker="s", ms=11, mfc="none", mec="white", mew=2, ls="none", label="camera", clip_on=False,
            zorder=5)
    ax.annotate(f"camera (elevation {el:.0f} deg)", xy=(az, el), xytext=(40 if az < 0 else -40, -28 if el > 0 else 28),
                textcoords="offset points", ha="left" if az < 0 else "right", va="center", fontsize=8,
                bbox={"boxstyle": "round", "fc": "white", "alpha": 0.8},
                arrowprops={"arrowstyle": "->", "color": "black", "lw": 1.2}, zorder=6)


def _mark(ax, plan, scene):
    lamp = _feature_angles(plan, scene, plan.shot.lamp_position)
    _mark_camera(ax, _feature_angles(plan, scene, plan.shot.camera_position))
    ax.plot(*lamp, marker="o", ms=8, mfc="white", mec="black", ls="none", label="lamp")
    ax.legend(loc="lower right", fontsize=8, framealpha=0.6)


def _axes(ax, title):
    ax.set_xlabel("azimuth [deg] (feature frame)")
    ax.set_ylabel("elevation [deg] (+90 = feature normal)")
    ax.set_title(title, fontsize=10)


@_one_at_a_time
def write_plan_pictures(plan: Plan, task: Task, scene: Scene, out_dir: PathLike) -> list[Path]:
    """Write visibility_brdf.png, regions.png and cost.png into out_dir; return their paths."""
    out_dir = Path(out_dir)
    m = plan.maps
    if m is None:
        raise ValueError("a multi-feature plan has no maps of its own: its features' plans have theirs")
    extent = (float(np.degrees(m.grid.azimuth[0])), float(np.degrees(m.grid.azimuth[-1])),
              float(np.degrees(m.grid.elevation[0])), float(np.degrees(m.grid.elevation[-1])))
    paths = []

    fig = Figure(figsize=(9, 4.8))
    ax = fig.subplots()
    # R at the feature centre for a lamp in each direction (the paper's 'BRDF mapped on the visibility map')
    brdf_map = regions.reflectance_map(m.grid, scene.frame, scene.normal,
                                       geometry.unit(scene.camera_position - scene.center), task.part.material)
    shown = np.ma.masked_where(~m.visible | (brdf_map <= 0), np.log10(np.maximum(brdf_map, 1e-12)))
    ax.set_facecolor("0.25")
    im = ax.imshow(shown, origin="lower", extent=extent, aspect="auto", cmap="inferno")
    fig.colorbar(im, ax=ax, label="log10 R (occluded: dark gray)")
    _mark(ax, plan, scene)
    _axes(ax, f"{plan.task_name}: BRDF mapped on the visibility map")
    paths.append(out_dir / "visibility_brdf.png")

    shown_defects = task.feature.defects if len(m.defect_cnr) else ()
    fig2 = Figure(figsize=(9 * (1 + len(shown_defects)), 4.8))
    ax, *defect_axes = np.atleast_1d(fig2.subplots(1, 1 + len(shown_defects)))
    seg = np.where(m.visible, m.dominant, brdf.OCCLUDED).astype(float)
    cmap = ListedColormap(["black", "tab:blue", "tab:orange", "tab:red"])
    ax.imshow(seg, origin="lower", extent=extent, aspect="auto", cmap=cmap, vmin=-1.5, vmax=2.5,
              interpolation="nearest")
    ax.contour(np.degrees(m.grid.azimuth), np.degrees(m.grid.elevation), m.wanted.astype(float),
               levels=[0.5], colors="white", linewidths=1)
    for color, name in zip(["black", "tab:blue", "tab:orange", "tab:red"], ["occluded", *brdf.TERM_NAMES]):
        ax.plot([], [], "s", color=color, label=name)
    _mark(ax, plan, scene)
    _axes(ax, "segmented region map (white line: wanted region)")
    for axd, defect, signed in zip(defect_axes, shown_defects, m.defect_cnr):
        _defect_map(fig2, axd, defect, signed, extent, np.degrees(m.grid.azimuth), np.degrees(m.grid.elevation))
        _mark(axd, plan, scene)
    paths.append(out_dir / "regions.png")

    fig3 = Figure(figsize=(13, 4.8))
    ax1, ax2 = fig3.subplots(1, 2)
    margin = max(task.requirements.region_margin_rad, 1e-6)
    cost = (m.distance.full() / margin + 1.0) / np.log(10.0)    # log10 of exp(d / margin + 1)
    im = ax1.imshow(cost, origin="lower", extent=extent, aspect="auto", cmap="viridis", vmin=-3, vmax=3)
    fig3.colorbar(im, ax=ax1, label="log10 region cost (<= 0: met)")
    _mark(ax1, plan, scene)
    _axes(ax1, "region cost exp(d / margin + 1)")
    pan, tilt, obj = np.degrees(m.candidate_pan), np.degrees(m.candidate_tilt), m.candidate_objective
    keys = np.round(np.column_stack([pan, tilt]), 6)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    best = np.full(len(uniq), np.inf)
    np.minimum.at(best, inv.ravel(), obj)
    sc = ax2.scatter(uniq[:, 0], uniq[:, 1], c=np.clip(best, -2, 10), cmap="magma_r", s=28, marker="s")
    fig3.colorbar(sc, ax=ax2, label="objective ln sum f_i (eq. 22), best over radius")
    jp, jt, _ = plan.shot.joints
    ax2.plot(np.degrees(jp), np.degrees(jt), "o", mfc="white", mec="black", ms=9, label="lamp")
    ax2.set_xlabel("rig pan [deg]")
    ax2.set_ylabel("rig tilt [deg]")
    ax2.set_title("overall cost over the rig's candidates", fontsize=10)
    ax2.legend(loc="lower right", fontsize=8)
    paths.append(out_dir / "cost.png")

    fig.subplots_adjust(**MARGINS)
    beside = {"left": 0.05, "right": 0.99, "top": 0.88, "wspace": 0.15}     # the defects' panels, two-line titles
    fig2.subplots_adjust(**({**MARGINS, **beside} if shown_defects else MARGINS))
    fig3.subplots_adjust(**{**MARGINS, "left": 0.06, "wspace": 0.11})
    for f, p in zip((fig, fig2, fig3), paths):
        f.savefig(p, dpi=90, pil_kwargs=PNG)
    return paths


def _defect_map(fig, ax, defect, signed, extent, azimuth_deg, elevation_deg):
    """A defect's panel of regions.png: its signed CNR per lamp direction (Maps.defect_cnr; red:
    brighter than the surface, as dark-field light shows it; blue: darker, as bright-field light
    does; the colour's depth the worst CNR over its orientations, up to 3 min_cnr), its min_cnr
    outlined (black), hidden directions dark gray."""
    ax.set_facecolor("0.25")
    top = 3.0 * defect.min_cnr
    im = ax.imshow(np.ma.masked_invalid(signed), origin="lower", extent=extent, aspect="auto", cmap="RdBu_r",
                   vmin=-top, vmax=top, interpolation="nearest")
    fig.colorbar(im, ax=ax, label="CNR: + the defect brighter than the surface, - darker")
    if np.nanmax(np.abs(signed), initial=0.0) >= defect.min_cnr:
        ax.contour(azimuth_deg, elevation_deg, np.nan_to_num(np.abs(signed)), levels=[defect.min_cnr],
                   colors="black", linewidths=1)
    _axes(ax, f"{defect.kind} '{defect.name}' where it lies: its CNR per lamp direction\n(the shot's distance "
              f"and exposure; worst over orientations; black line: min_cnr {defect.min_cnr:g})")


LIGHT_COLORS = ("white", "tab:cyan", "tab:green", "tab:pink", "tab:olive", "tab:purple", "tab:brown", "tab:gray")


@_one_at_a_time
def write_lights(path: PathLike, plan: Plan, task: Task) -> None:
    """lights.png of a one-feature plan with several lights: left, where each light is as seen
    from the feature centre (its emitter points on the feature frame's map of dominant terms,
    filled where the light is on); right, what each adds to the feature at its planned drive and
    the shot's exposure (mean gray, the bar; darkest to brightest sample, the line), with its
    channel and drive, and the band."""
    from cell.planning.lights import START_POINTS, emitters
    m, scene, shot = plan.maps, plan.planned_scene, plan.shot
    if m is None:
        raise ValueError("a multi-feature plan has no maps of its own: its features' plans have theirs")
    fig = Figure(figsize=(13, 4.8))
    ax1, ax2 = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.4, 1.0]})
    extent = (float(np.degrees(m.grid.azimuth[0])), float(np.degrees(m.grid.azimuth[-1])),
              float(np.degrees(m.grid.elevation[0])), float(np.degrees(m.grid.elevation[-1])))
    seg = np.where(m.visible, m.dominant, brdf.OCCLUDED).astype(float)
    ax1.imshow(seg, origin="lower", extent=extent, aspect="auto", vmin=-1.5, vmax=2.5, interpolation="nearest",
               cmap=ListedColormap(["black", "tab:blue", "tab:orange", "tab:red"]), alpha=0.55)
    by_name = {light.name: light for light in task.lights}
    for k, setting in enumerate(shot.lights):
        light = by_name.get(setting.name)
        points = (setting.position_m[None] if light is None else
                  emitters(light, shot.T_cell_cam, START_POINTS[light.type]).position)
        az, el = _feature_angles(plan, scene, points)
        color = LIGHT_COLORS[k % len(LIGHT_COLORS)]
        ax1.plot(az, el, "o", ms=7 if light is None else 4, mec="black", mew=0.6, ls="none",
                 mfc=color if setting.drive > 0 else "none", label=setting.name)
    _mark_camera(ax1, _feature_angles(plan, scene, shot.camera_position))
    ax1.legend(loc="lower right", fontsize=8, framealpha=0.6)
    _axes(ax1, "where each light is, seen from the feature (filled: on); dominant terms as regions.png")
    names = [f"{s.name}\n(ch {'-' if s.channel is None else s.channel}, drive {s.drive:.0%})" for s in shot.lights]
    means = np.array([s.gray.mean() for s in shot.lights])
    lows = means - np.array([s.gray.min() for s in shot.lights])
    highs = np.array([s.gray.max() for s in shot.lights]) - means
    y = np.arange(len(names))
    ax2.barh(y, means, color=[LIGHT_COLORS[k % len(LIGHT_COLORS)] for k in y], edgecolor="black")
    ax2.errorbar(means, y, xerr=[lows, highs], fmt="none", ecolor="black", capsize=3)
    low, high = task.requirements.gray_band
    for x in (low, high):
        ax2.axvline(x, color="0.4", ls="--", lw=1)
    ax2.set_yticks(y, names, fontsize=8)
    ax2.invert_yaxis()
    ax2.set_xlabel(f"gray added to the feature (dashed: the band {low:g}-{high:g})")
    e = shot.exposure
    ax2.set_title(f"what each channel adds at {1e3 * e.shutter_s:.3g} ms, f/{e.f_number:.1f}", fontsize=10)
    fig.subplots_adjust(**{**MARGINS, "left": 0.05, "right": 0.99, "wspace": 0.42})
    fig.savefig(path, dpi=90, pil_kwargs=PNG)


SHOT_COLORS = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:brown", "tab:olive", "tab:cyan",
               "tab:pink", "tab:orange", "tab:gray")
FEATURE_COLORS = ("gold", "magenta", "darkorange", "deepskyblue", "limegreen", "sienna", "teal", "pink")
LIGHT = geometry.unit(np.array([0.4, -0.6, 1.0]))     # the mesh's shading: a light above, in front
VIEW = (30.0, -75.0)            # cell.png's (elevation, azimuth) [deg]: from the front (-y), a little left, above


@dataclass(frozen=True)
class DrawnShot:
    """One shot as cell.png draws it (cell frame [m]): the camera, its image's corners at the
    focus distance, the lamp and its aim point (the rig's pivot), the colour, and where the camera's
    and the lamp's markers of the whole-cell view lie in the PNG ([column, row] px)."""

    camera_m: np.ndarray
    frustum_m: np.ndarray
    lamp_m: np.ndarray
    aim_m: np.ndarray
    color: str
    camera_px: tuple[float, float]
    lamp_px: tuple[float, float]


@dataclass(frozen=True)
class CellPicture:
    """cell.png's path, its shots as drawn and its features (name, colour, covering shot or None)."""

    path: Path
    shots: tuple[DrawnShot, ...]
    features: tuple[tuple[str, str, int | None], ...]


def display_mesh(vertices: np.ndarray, faces: np.ndarray, max_faces: int,
                 split: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A mesh for drawing: beyond max_faces merged by vertex clustering (each cell of a grid, sized
    for about max_faces facets over the surface area, becomes its vertices' mean; facets that
    collapse or repeat dropped: a dense curved surface thins, a big flat facet's corners stay
    put), then facets longer than 1 / split of its size split (matplotlib sorts whole polygons by
    depth, so a long one drawn large hides what lies in front of it)."""
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64)
    if len(faces) > max_faces:
        tri = vertices[faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
        size = np.sqrt(2.0 * area / max_faces)                  # two facets per cell of the surface
        key = np.floor((vertices - vertices.min(axis=0)) / size).astype(np.int64)
        _, cluster, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        cluster = cluster.ravel()
        merged = np.zeros((len(count), 3))
        np.add.at(merged, cluster, vertices)
        f = cluster[faces]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        _, first = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
        vertices, faces = merged / count[:, None], f[np.sort(first)]
    if split is None:
        return vertices, faces
    return trimesh.remesh.subdivide_to_size(vertices, faces, np.ptp(vertices, axis=0).max() / split)


def _draw_mesh(ax, vertices, faces, scale, max_faces, split=None):
    v, f = display_mesh(vertices, faces, max_faces, split)
    tri = v[f] * scale
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    lit = np.abs(geometry.unit(normals + 1e-30) @ LIGHT)          # two-sided: merged facets may flip
    shade = (0.35 + 0.6 * lit)[:, None] * np.array([0.78, 0.80, 0.84])
    ax.add_collection3d(Poly3DCollection(tri, facecolors=shade, edgecolors="none", zorder=1))


def _rig_lines(lamp_rig):
    """Polylines of the rig's sphere at both ends of its radius range over its pan and tilt ranges:
    5 circles of latitude and a meridian every 30 deg of pan."""
    pan = np.linspace(*lamp_rig.pan_range_rad, 73)
    tilt = np.linspace(*lamp_rig.tilt_range_rad, 19)
    lines = []
    for r in sorted(set(lamp_rig.radius_range_m)):
        lines += [rig.lamp_position(lamp_rig.pivot_m, pan, t, r) for t in np.linspace(*lamp_rig.tilt_range_rad, 5)]
        lines += [rig.lamp_position(lamp_rig.pivot_m, p, tilt, r)
                  for p in np.arange(lamp_rig.pan_range_rad[0], lamp_rig.pan_range_rad[1] + 1e-9, np.radians(30.0))]
    return lines


def _cube(ax, points, unit):
    """Equal scales on the three axes: a cube around the points."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    middle, half = 0.5 * (lo + hi), 0.5 * (hi - lo).max() * 1.02
    for axis, m in zip("xyz", middle):
        getattr(ax, f"set_{axis}lim")(m - half, m + half)
        getattr(ax, f"set_{axis}label")(f"{axis} [{unit}]", fontsize=8, labelpad=-2)
    ax.set_box_aspect((1, 1, 1))
    ax.tick_params(labelsize=7, pad=0)


def _disk(center, normal, radius, n=36):
    frame = geometry.frame_from_normal(normal)
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return center + radius * (np.cos(a)[:, None] * frame[:, 0] + np.sin(a)[:, None] * frame[:, 1])


def _pixel(ax, point, height_px):
    """[column, row] of a 3D point in the saved PNG (after the draw that laid the axes out)."""
    x, y, _ = proj3d.proj_transform(*point, ax.get_proj())
    column, up = ax.transData.transform((x, y))
    return float(column), float(height_px - up)


def _covered(plan, task):
    """Per shot the names of the features it covers, per feature the shot covering it (or None)."""
    if plan.features:
        return [[c.feature for c in shot.covers] for shot in plan.shots], [f.covered_by for f in plan.features]
    return [[task.feature.name] if plan.feasible else []], [0 if plan.feasible else None]


def _draw_cell(ax, vertices, faces, shots, lamp_rig):
    """The whole cell [m]: part, rig's sphere and pivot, each shot's frustum, camera and lamp."""
    pivot = np.asarray(lamp_rig.pivot_m, float)
    _draw_mesh(ax, vertices, faces, 1.0, 600)
    sphere = _rig_lines(lamp_rig)
    ax.add_collection3d(Line3DCollection(sphere, colors="0.7", linewidths=0.5, zorder=2))
    ax.plot(*pivot, "k+", ms=8, zorder=4)
    for k, (shot, color, corners) in enumerate(shots):
        c, lamp = shot.camera_position, shot.lamp_position
        edges = [np.array([c, q]) for q in corners] + [np.vstack([corners, corners[:1]])]
        ax.add_collection3d(Line3DCollection(edges, colors=color, linewidths=1.0, zorder=3))
        ax.plot(*np.array([lamp, pivot]).T, "--", color=color, lw=0.9, zorder=3)
        ax.plot(*c, "s", color=color, mec="black", mew=0.5, ms=9, zorder=10)
        ax.plot(*lamp, "o", color=color, mec="black", mew=0.5, ms=9, zorder=10)
        ax.text(*c, f"   camera {k}", fontsize=7, color=color, zorder=11)      # spaces: off the marker
        ax.text(*lamp, f"   lamp {k}", fontsize=7, color=color, zorder=11)
    _cube(ax, np.vstack([vertices, *sphere, *(np.vstack([s.camera_position, s.lamp_position, q])
                                              for s, _, q in shots)]), "m")
    ax.set_title("the cell: cameras with their frusta, lamps, the rig's sphere", fontsize=9)


def _draw_part(ax, vertices, faces, features, shots, pivot):
    """The part [mm]: mesh, each feature's patch and normal, each shot's view axis and lamp
    direction as stubs of 0.8 x the part's size."""
    mm, stub = 1e3, 0.8 * np.ptp(vertices, axis=0).max()
    elev, azim = np.radians(VIEW)
    viewer = np.array([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)])
    _draw_mesh(ax, vertices, faces, mm, 1500, split=6)
    for name, center, normal, radius, color in features:
        disk = _disk(center + 2e-4 * normal, normal, radius) * mm
        behind = normal @ viewer < 0.0                        # on a face turned away: seen through the part
        ax.add_collection3d(Poly3DCollection([disk], facecolors=to_rgba(color, 0.4 if behind else 1.0),
                                             edgecolors="black", linewidths=0.6, linestyles="--" if behind else "-",
                                             zorder=5))
        tip = center + 0.3 * stub * normal                    # its normal: read even when seen edge-on
        ax.plot(*np.array([center, tip]).T * mm, "-", color="black", lw=0.8, zorder=6)
        ax.text(*tip * mm, name, fontsize=7, zorder=11)
    ax.plot(*pivot * mm, "k+", ms=8, zorder=6)
    ends = []
    for k, (shot, color, _) in enumerate(shots):
        axis = shot.T_cell_cam[:3, 2]
        focus = shot.camera_position + shot.exposure.focus_m * axis        # on the shot's own feature
        for start, end, style, marker, label in (
                (focus, focus - stub * axis, "-", "s", f" camera {k}"),
                (pivot, pivot + stub * geometry.unit(shot.lamp_position - pivot), "--", "o", f" lamp {k}")):
            ax.plot(*np.array([start, end]).T * mm, style, color=color, lw=1.2, zorder=7)
            ax.plot(*end * mm, marker, color=color, mec="black", mew=0.5, ms=7, zorder=10)
            ax.text(*end * mm, label, fontsize=7, color=color, zorder=11)
            ends.append(end)
    _cube(ax, np.vstack([vertices, *ends]) * mm, "mm")
    ax.set_title("the part: features, each shot's view axis and lamp direction", fontsize=9)


FIXED_LIGHT_COLOR = "goldenrod"


def _draw_fixed_lights(ax, task: Task) -> list[str]:
    """The task's fixed lights on the cell's view: each one's housing as it blocks light and view
    (cell.planning.occluders, translucent), its emitter points (cell.planning.lights, its starting
    count) and a line from its centre along its axis (0.3 of its distance to the rig's pivot); the
    names drawn. A flange light moves with the camera (drawn in lights.png)."""
    from cell.planning.lights import START_POINTS, emitters, pose
    from cell.planning.occluders import housing
    drawn = []
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    for light in task.lights:
        if light.mount != "fixed":
            continue
        h = housing(light)
        ax.add_collection3d(Poly3DCollection(h.vertices[h.faces], facecolors=to_rgba("0.55", 0.35),
                                             edgecolors="none", zorder=2))
        points = emitters(light, np.eye(4), START_POINTS[light.type]).position
        centre, axis, _ = pose(light, np.eye(4))
        tip = centre + 0.3 * np.linalg.norm(pivot - centre) * axis
        ax.plot(*points.T, "*", color=FIXED_LIGHT_COLOR, mec="black", mew=0.3, ms=8, zorder=9)
        ax.plot(*np.array([centre, tip]).T, "-", color=FIXED_LIGHT_COLOR, lw=2.0, zorder=8)
        ax.text(*centre, f" {light.name}", fontsize=6, zorder=11)
        drawn.append(light.name)
    return drawn


def _legend(fig, shots, names, features, covered, lamp_rig, fixed=()):
    handles = [Line2D([], [], color=color, lw=2, label=f"shot {k}: " + (", ".join(n) or "covers nothing"))
               for k, ((_, color, _), n) in enumerate(zip(shots, names))]
    handles += [Line2D([], [], color="black", marker="s", mfc="white", label="camera (left: its frustum to the focus)"),
                Line2D([], [], color="black", marker="o", mfc="white", ls="--",
                       label="lamp (left: dashed to its aim; right: its direction from the pivot)")]
    handles += [Patch(facecolor=color, edgecolor="black", label=f"{name}: " + ("no shot" if by is None else f"shot {by}"))
                for (name, *_, color), by in zip(features, covered)]
    r0, r1 = lamp_rig.radius_range_m
    handles += [Line2D([], [], color="0.7", lw=0.8, label=f"rig's sphere, radius {r0:.2f} and {r1:.2f} m"),
                Line2D([], [], color="black", marker="+", ls="none", label="rig's pivot (every lamp's aim)")]
    if fixed:
        handles.append(Line2D([], [], color=FIXED_LIGHT_COLOR, marker="*", mec="black", mew=0.3,
                              label=f"fixed lights ({', '.join(fixed)}): emitter points, axis, housing (grey)"))
    fig.legend(handles=handles, loc="lower center", ncol=3, fontsize=7, frameon=False)


@_one_at_a_time
def write_cell(path: PathLike, plan: Plan, task: Task) -> CellPicture:
    """cell.png: the cell of a plan in two views. Left, the whole cell [m]: the part, each shot's
    camera (square) with its frustum to the focus distance (the image's corners there: the pinhole's
    W p d / f by H p d / f), its lamp (dot) with a dashed line to the aim point (the rig's pivot),
    and the rig's sphere at both ends of its radius range; right, the part [mm]: its mesh shaded,
    each feature's patch in its colour (pale and dashed on a face turned away), each shot's optical
    axis toward its camera and the line from the pivot toward its lamp. Returns a CellPicture."""
    T = task.frames.T_cell_part
    vertices, faces = geometry.apply(T, task.part.mesh.vertices), np.asarray(task.part.mesh.faces)
    sensor, lamp_rig = task.camera.sensor, task.lamp.rig
    K = projection.intrinsics(sensor, task.camera.lens)
    names, covered = _covered(plan, task)
    features = [(f.name, geometry.apply(T, f.center_m), geometry.unit(geometry.rotate(T, f.normal)), f.radius_m,
                 FEATURE_COLORS[j % len(FEATURE_COLORS)]) for j, f in enumerate(task.features)]
    shots = [(shot, SHOT_COLORS[k % len(SHOT_COLORS)],
              projection.frustum_corners(K, shot.T_cell_cam, sensor.width_px, sensor.height_px,
                                         shot.exposure.focus_m)) for k, shot in enumerate(plan.shots)]
    fig = Figure(figsize=(13, 6.4), dpi=90)
    whole = fig.add_subplot(1, 2, 1, projection="3d", computed_zorder=False)    # drawn in zorder: markers on top
    near = fig.add_subplot(1, 2, 2, projection="3d", computed_zorder=False)
    _draw_cell(whole, vertices, faces, shots, lamp_rig)
    _draw_part(near, vertices, faces, features, shots, np.asarray(lamp_rig.pivot_m, float))
    fixed = _draw_fixed_lights(whole, task)
    for ax in (whole, near):
        ax.view_init(*VIEW)
    verdict = "feasible" if plan.feasible else f"not feasible ({plan.binding})"
    fig.suptitle(f"{plan.task_name}: {len(shots)} shot{'s' * (len(shots) != 1)}, {verdict}", fontsize=10)
    _legend(fig, shots, names, features, covered, lamp_rig, fixed)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.17, top=0.93, wspace=0.0)
    fig.savefig(path, dpi=90, pil_kwargs=PNG)
    height = fig.get_figheight() * fig.dpi
    drawn = tuple(DrawnShot(shot.camera_position.copy(), corners, shot.lamp_position.copy(),
                            np.asarray(lamp_rig.pivot_m, float), color, _pixel(whole, shot.camera_position, height),
                            _pixel(whole, shot.lamp_position, height)) for shot, color, corners in shots)
    return CellPicture(Path(path), drawn, tuple((name, color, by) for (name, *_, color), by in zip(features, covered)))


@_one_at_a_time
def write_convergence(path: PathLike, iterations: Sequence[dict[str, Any]], band: tuple[float, float],
                      refits: Iterable[dict[str, Any]] = ()) -> None:
    """The closed loop at a glance: per capture the measured gray range (bar) and mean (dot) over
    the feature's pixels, the model's prediction (open diamonds: min, max), the gray band shaded,
    the correction taken written under each capture; each refit's probe shots (their raw gray
    range, grey bars between capture k and k + 1) and a dashed line where the refit took effect."""
    fig = Figure(figsize=(7, 4.2))
    ax = fig.subplots()
    low, high = band
    ax.axhspan(low, high, color="tab:green", alpha=0.15, label=f"band {low:g}-{high:g}")
    for it in iterations:
        k, g, p = it["iteration"], it["measured_gray"], it["predicted_gray"]
        color = "tab:green" if it["in_band"] else "tab:red"
        ax.plot([k, k], [g["min"], g["max"]], color=color, lw=4, alpha=0.6)
        ax.plot(k, g["mean"], "o", color=color)
        ax.plot([k, k], [p["min"], p["max"]], "D", mfc="none", mec="0.3", ms=6)
    for r in refits:
        k, probes = r["iteration"], r["shots"][1:]           # the first is capture k itself
        for j, probe in enumerate(probes, 1):
            x, g = k + j / (len(probes) + 1) * 0.8, probe["measured_gray"]
            ax.plot([x, x], [g["min"], g["max"]], color="0.5", lw=3, alpha=0.6)
            ax.plot(x, g["mean"], "v", color="0.4", ms=5)
        ax.axvline(k + 0.9, color="tab:purple", ls="--", lw=1)
        ax.text(k + 0.9, 0.02, f" refit ({len(r['captures'])} captures)", rotation=90, fontsize=7,
                color="tab:purple", transform=ax.get_xaxis_transform(), va="bottom")
    if refits:
        ax.plot([], [], "v", color="0.4", label="probe shot (lamp tilted): mean, bar: raw min-max")
    ax.plot([], [], "o", color="0.4", label="measured mean, bar: min-max (red: out of band)")
    ax.plot([], [], "D", mfc="none", mec="0.3", ls="none", label="plan's model: min, max")
    ax.set_xticks([it["iteration"] for it in iterations],
                  [f"{it['iteration']}\n{1e3 * it['shutter_s']:.3g} ms, f/{it['f_number']:.1f}\n"
                   f"{(it.get('correction') or {}).get('action', '')}" for it in iterations], fontsize=7)
    ax.set_xlim(0.5, len(iterations) + 0.5)
    top = max(it["measured_gray"]["max"] for it in iterations)
    probes = max((p["measured_gray"]["max"] for r in refits for p in r["shots"]), default=0.0)
    ax.set_ylim(0, max(high * 1.3, top * 1.05, probes * 1.4))     # the legend above the probes
    ax.set_xlabel("capture, exposure, correction")
    ax.set_ylabel("gray over the feature")
    ax.set_title("closed loop: measured against predicted gray", fontsize=10)
    ax.legend(fontsize=7, loc="upper right")
    fig.subplots_adjust(left=0.1, right=0.97, bottom=0.2, top=0.92)
    fig.savefig(path, dpi=90, pil_kwargs=PNG)


@_one_at_a_time
def write_calibration(path: PathLike, exposures: np.ndarray, grays: np.ndarray, fit: CameraConstantFit | None,
                      c_model: float) -> None:
    """cell calibrate's fit: G over the model's P t, the fitted line and the line the task's c
    predicts."""
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    ax.plot(exposures.ravel() * 1e15, grays.ravel(), ".", ms=3, label="measured (per sample and shot)")
    x = np.linspace(0.0, np.nanmax(exposures), 2)
    ax.plot(x * 1e15, c_model * x, "--", label=f"task's c = {c_model:.4g}")
    if fit:
        ax.plot(x * 1e15, fit.black_level + fit.camera_constant * x,
                label=f"fit c = {fit.camera_constant:.4g}, b = {fit.black_level:.2f}")
    ax.set_xlabel("model pixel power x shutter  P t  [fJ]")
    ax.set_ylabel("measured gray G")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


@_one_at_a_time
def write_laser_fit(path: PathLike, frames: Iterable[LaserFrame], fit: LaserFit | None, c_task: float,
                    power_w: float) -> None:
    """cell calibrate camera-constant's fit: the spot's summed gray S over the shutter time, the
    frames fitted, those left out (saturated, too dark), the fitted line and the task's c P t."""
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    summed = [f for f in frames if f.spot_sum is not None]
    for label, style, pick in (("used", "o", lambda f: f.usable), ("saturated, left out", "rx", lambda f: f.saturated),
                               ("too dark, left out", "s", lambda f: f.too_dark and not f.saturated)):
        chosen = [f for f in summed if pick(f)]
        if chosen:
            # every frame of `summed` has its sum: the condition only says so to mypy
            ax.plot([1e3 * f.shutter_s for f in chosen], [f.spot_sum for f in chosen if f.spot_sum is not None],
                    style, mfc="none", label=label)
    t = np.linspace(0.0, max((f.shutter_s for f in summed), default=1e-3), 2)
    ax.plot(1e3 * t, c_task * power_w * t, "--", label=f"the task's c P t, c = {c_task:.5g}")
    if fit:
        ax.plot(1e3 * t, fit.offset + fit.camera_constant * power_w * t,
                label=f"fit c = {fit.camera_constant:.5g} +- {fit.camera_constant_stderr:.2g}, r2 {fit.r_squared:.5f}")
    ax.set_xlabel("shutter time t [ms]")
    ax.set_ylabel("spot's gray above the dark, summed  S")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


@_one_at_a_time
def write_goniometer_fit(path: PathLike, readings: Sequence[GoniometerReading], material: Material) -> None:
    """cell measure-brdf's fit: R over the half-angle tilt beta per phase angle, measured (points)
    and the fitted material (lines), on a log scale (the spike over the diffuse)."""
    from cell.physics.brdf import reflectance
    fig = Figure(figsize=(7, 4.5))
    ax = fig.subplots()
    for phase in sorted({r.phase_deg for r in readings}):
        mine = [r for r in readings if r.phase_deg == phase]
        line, = ax.semilogy([r.beta_deg for r in mine], [r.reflectance for r in mine], "o", mfc="none",
                            label=f"phase {phase:g} deg")
        a = np.radians(phase)
        beta = np.radians(np.linspace(min(r.beta_deg for r in mine), max(r.beta_deg for r in mine), 400))
        p = material.at(a)
        ax.semilogy(np.degrees(beta), reflectance(np.cos(beta + a / 2), np.cos(beta - a / 2), np.cos(a), p.rho,
                                                  p.sigma1, p.m1, p.sigma2, p.m2), "-", color=line.get_color())
    ax.set_xlabel("half-angle tilt beta [deg] (ti = |beta + alpha/2|, te = |beta - alpha/2|)")
    ax.set_ylabel("reflectance R")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


@_one_at_a_time
def write_bench(path: PathLike, settings: Sequence[dict[str, Any]]) -> None:
    """cell bench's rows: gray error vs warm time, log-log, a marker set per task, its Pareto
    front as a line and the default setting ringed."""
    floor = 1e-3                    # a zero error still shows on the log axis
    fig = Figure(figsize=(7.5, 5))
    ax = fig.subplots()
    for (label, marker) in zip(dict.fromkeys(r["task"] for r in settings), "osD^v<>"):
        rows = [r for r in settings if r["task"] == label and np.isfinite(r["gray_error_max"])]
        t = np.array([r["time_s"] for r in rows])
        e = np.maximum([r["gray_error_max"] for r in rows], floor)
        dots = ax.plot(t, e, marker, ls="none", label=label)[0]
        front = sorted((ti, ei) for ti, ei, r in zip(t, e, rows) if r["pareto"])
        ax.plot(*zip(*front), "-", color=dots.get_color(), alpha=0.6)
        for ti, ei, r in zip(t, e, rows):
            ax.annotate(r["name"], (ti, ei), fontsize=6, xytext=(3, 3), textcoords="offset points")
            if r["default"]:
                ax.plot(ti, ei, "o", ms=14, mfc="none", mec="red", mew=1.5)
    ax.plot([], [], "o", ms=10, mfc="none", mec="red", label="default setting")
    ax.plot([], [], "k-", alpha=0.6, label="Pareto front")
    ax.axhline(1.0, color="gray", ls=":", label="1 gray level")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("warm plan time [s] (median)")
    ax.set_ylabel("largest error of predicted mean/min/max gray [gray levels]")
    ax.set_title("What accuracy costs in time (vs a fine reference plan)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def annotate_capture(image: np.ndarray, m: MeasuredRegion, bit_depth: int, caption: str,
                     defects: np.ndarray | None = None) -> np.ndarray:
    """8-bit colour copy of a capture (OpenCV): the measured region (measurement.Measurement)
    outlined (green), its saturated pixels red, the samples' pixels blue, the declared defects'
    pixels (defects (H, W), cell.run.defects.on_defects) outlined magenta, a caption."""
    if m.region is None:
        raise ValueError("a joined measurement has no region of its own to draw: annotate each feature's")
    scale = 255.0 / saturation_level(bit_depth)
    view = cv2.cvtColor((levels(image, bit_depth) * scale).astype(np.uint8), cv2.COLOR_GRAY2BGR)
    view[m.saturated] = (0, 0, 255)
    contours, _ = cv2.findContours(m.region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.polylines(view, contours, True, (0, 255, 0), 1)
    for r, c in zip(m.row, m.col):
        cv2.circle(view, (int(c), int(r)), 1, (255, 128, 0), -1)
    if defects is not None and defects.any():
        marks, _ = cv2.findContours(defects.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.polylines(view, marks, True, (255, 0, 255), 1)
    cv2.putText(view, caption, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 255, 255), 1, cv2.LINE_AA)
    return view
