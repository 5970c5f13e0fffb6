"""cell.html: the cell of a plan in 3D, to turn and zoom in a browser. Every body of the collision
scene (cell.collision.scene) at every shot: the part and the fixture, the UR5e's links as their
capsules, the camera body with its frustum to the focus distance, the lamp's body with its cone
(the lit half angle, to the rig's pivot) and the pan-tilt's links holding it (the tilt servo's
box, its arm's capsule where the rig's reach is declared), the task's other lights as their emitter points (bright:
on, dim: off) and each fixed light's housing, the body it collides with and blocks light and view with
(cell.planning.occluders), each feature's patch and normal; each shot's clearance (and the two bodies that set
it) in its legend entry and hover text; the camera's paths of the plan's collision-checked moves
(Plan.moves, cell.run.moves: from the home pose through the shots, straight between a move's
via points, as moveL takes them), or where a plan has none, straight segments between consecutive
shots' cameras in the route's order (a run's) or the plan's, which are NOT collision-checked paths.

Drawn with plotly, its JavaScript embedded in the file (include_plotlyjs=True): the page opens
offline, with no network at view time. The part's mesh is thinned for the file's size
(pictures.display_mesh), so the file stays about plotly.js's 5 MB.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import plotly.graph_objects as go

from cell.collision.bodies import Body, Box, Capsule, Mesh
from cell.collision.scene import LAMP_BODIES, CollisionScene, reaching_joints
from cell.core import geometry
from cell.physics import projection
from cell.planning import occluders
from cell.report.pictures import FEATURE_COLORS, display_mesh

if TYPE_CHECKING:
    from cell.planning.plan import Plan, Shot
    from cell.task.types import Task

PathLike = str | os.PathLike[str]

MAX_PART_FACES = 20_000      # the part's mesh thinned beyond this: ~1 MB of JSON, beside plotly.js's ~5 MB
SHOT_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#bcbd22", "#17becf",
               "#e377c2", "#ff7f0e", "#7f7f7f")     # matplotlib's tab10, as cell.png's shots
ROLES = {"camera_body": "camera body", "lamp_body": "lamp body", "rig_arm": "the pan-tilt's arm holding the lamp",
         "tilt_servo": "the pan-tilt's tilt servo"}     # a moving body's words in its hover text (else an arm link)
BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


@dataclass(frozen=True)
class CellView:
    """cell.html's path and the names of its traces (one per body, feature, frustum, cone, light
    and the route), in drawing order."""

    path: Path
    names: tuple[str, ...]


def box_mesh(box: Box) -> tuple[np.ndarray, np.ndarray]:
    """(8, 3) corners (cell frame) and (12, 3) triangles of a Box."""
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    return geometry.apply(box.T_cell_box, signs * box.half_m), BOX_FACES


def capsule_mesh(capsule: Capsule, sides: int = 16, rings: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A Capsule as triangles: a tube of `sides` about a-b closed by two hemispheres of `rings`
    latitude bands each (one closed surface, its poles on the axis)."""
    a, b, r = capsule.a, capsule.b, capsule.radius_m
    axis = b - a
    frame = geometry.frame_from_normal(axis if np.linalg.norm(axis) > 1e-12 else np.array([0.0, 0.0, 1.0]))
    u, v, w = frame[:, 0], frame[:, 1], frame[:, 2]
    phi = 2.0 * np.pi * np.arange(sides) / sides
    around = np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v
    # latitude from the pole below a (-90 deg) to the pole above b (+90 deg), the equators twice
    lat = np.concatenate([np.linspace(-0.5 * np.pi, 0.0, rings + 1), np.linspace(0.0, 0.5 * np.pi, rings + 1)])
    ends = np.concatenate([np.zeros(rings + 1), np.ones(rings + 1)])
    rows = [(a + e * axis) + r * (np.cos(t) * around + np.sin(t) * w) for t, e in zip(lat, ends)]
    vertices = np.vstack(rows)
    faces = []
    for i in range(len(rows) - 1):
        for j in range(sides):
            p, q = i * sides + j, i * sides + (j + 1) % sides
            faces += [[p, q, q + sides], [p, q + sides, p + sides]]
    return vertices, np.array(faces)


def cone_mesh(apex: np.ndarray, axis: np.ndarray, half_angle_rad: float, length_m: float,
              sides: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """A light's cone: apex, unit axis, half opening angle, length along the axis; open at the base."""
    frame = geometry.frame_from_normal(axis)
    phi = 2.0 * np.pi * np.arange(sides) / sides
    radius = length_m * np.tan(min(half_angle_rad, np.radians(80.0)))     # a wide profile stays drawable
    rim = apex + length_m * frame[:, 2] + radius * (np.cos(phi)[:, None] * frame[:, 0]
                                                     + np.sin(phi)[:, None] * frame[:, 1])
    faces = [[0, 1 + j, 1 + (j + 1) % sides] for j in range(sides)]
    return np.vstack([apex, rim]), np.array(faces)


def _mesh3d(vertices, faces, name, color, hover, opacity=1.0, group=None, legend=True) -> go.Mesh3d:
    v, f = np.asarray(vertices, float), np.asarray(faces, int)
    return go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2], name=name, color=color,
                     opacity=opacity, flatshading=True, hovertemplate=f"{hover}<extra></extra>",
                     legendgroup=group or name, showlegend=legend)


def _lines(segments: Sequence[np.ndarray], name, color, hover, group=None, width=3, dash="solid",
           legend=True) -> go.Scatter3d:
    """Polylines as one trace, separated by gaps (None)."""
    xyz: list[Any] = [[], [], []]
    for seg in segments:
        for axis in range(3):
            xyz[axis] += [*np.asarray(seg, float)[:, axis].tolist(), None]
    return go.Scatter3d(x=xyz[0], y=xyz[1], z=xyz[2], mode="lines", name=name, line={"color": color, "width": width,
                        "dash": dash}, hovertemplate=f"{hover}<extra></extra>", legendgroup=group or name,
                        showlegend=legend)


def _body(body: Body, name: str, color: str, hover: str, group: str, legend: bool,
          opacity: float = 1.0) -> go.Mesh3d:
    if isinstance(body, Box):
        v, f = box_mesh(body)
    elif isinstance(body, Capsule):
        v, f = capsule_mesh(body)
    else:
        assert isinstance(body, Mesh), f"{body.name}: a light's body is drawn as its housing"
        v, f = display_mesh(body.vertices, body.faces, MAX_PART_FACES)
    return _mesh3d(v, f, name, color, hover, opacity, group, legend)


def _clearance_words(shot: Shot) -> str:
    c = shot.clearance
    if c is None:
        return "clearance not checked"
    return f"clearance {c.distance_m * 1e3:.1f} mm ({c.bodies[0]} to {c.bodies[1]})"


def _shot_traces(k: int, shot: Shot, plan: Plan, task: Task, scene: CollisionScene, covers: list[str]) -> list[Any]:
    """The traces of shot k: arm links, camera body, frustum, lamp body and cone, other lights."""
    from cell.planning.lights import START_POINTS, emitters
    color, group = SHOT_COLORS[k % len(SHOT_COLORS)], f"shot {k}"
    title = f"shot {k}: " + (", ".join(covers) or "covers nothing") + f"; {_clearance_words(shot)}"
    joints = reaching_joints(task.frames, shot.T_cell_cam, shot.arm_joints)
    title += "" if joints is not None else "; the arm does not reach it"
    bodies = scene.bodies(shot.T_cell_cam, joints, shot.lamp_position)[len(scene.fixed):]
    traces: list[Any] = []
    for body in bodies:
        role = ROLES.get(body.name, f"arm {body.name}")
        traces.append(_body(body, f"shot {k} {body.name}", "#ffcc33" if body.name in LAMP_BODIES else color,
                            f"shot {k}: {role}<br>{title}", group, legend=not traces,
                            opacity=0.55 if isinstance(body, Capsule) else 0.9))
    traces[0].legendgrouptitle = {"text": title}     # the group's legend: the shot, its features, clearance
    sensor = task.camera.sensor
    K = projection.intrinsics(sensor, task.camera.lens)
    corners = projection.frustum_corners(K, shot.T_cell_cam, sensor.width_px, sensor.height_px,
                                         shot.exposure.focus_m)
    c = shot.camera_position
    traces.append(_lines([np.array([c, q]) for q in corners] + [np.vstack([corners, corners[:1]])],
                         f"shot {k} frustum", color,
                         f"shot {k}: camera frustum to the focus {shot.exposure.focus_m * 1e3:.0f} mm<br>"
                         f"{1e3 * shot.exposure.shutter_s:.3g} ms, f/{shot.exposure.f_number:.1f}", group,
                         legend=False))
    traces.append(go.Scatter3d(x=[c[0]], y=[c[1]], z=[c[2]], mode="markers+text", text=[f"camera {k}"],
                               marker={"size": 4, "color": color, "symbol": "square"}, name=f"shot {k} camera",
                               hovertemplate=f"{title}<extra></extra>", legendgroup=group, showlegend=False))
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    aim = pivot - shot.lamp_position
    v, f = cone_mesh(shot.lamp_position, geometry.unit(aim), task.lamp.lit_half_angle_rad, float(np.linalg.norm(aim)))
    spot = shot.lights[0].drive if shot.lights else 1.0
    traces.append(_mesh3d(v, f, f"shot {k} lamp cone", "#ffcc33", f"shot {k}: {task.lamp.name}'s cone, "
                          f"{np.degrees(task.lamp.lit_half_angle_rad):.1f} deg half angle, drive {spot:.0%}",
                          0.18 if spot > 0 else 0.05, group, legend=False))
    by_name = {light.name: light for light in task.lights}
    for setting in shot.lights:
        light = by_name.get(setting.name)
        if light is None:              # the pan-tilt's spot: its body and cone above
            continue
        points = emitters(light, shot.T_cell_cam, START_POINTS[light.type]).position
        on = setting.drive > 0
        traces.append(go.Scatter3d(
            x=points[:, 0], y=points[:, 1], z=points[:, 2], mode="markers", name=f"shot {k} light {setting.name}",
            marker={"size": 3 if on else 2, "color": "#ffe14d" if on else "#8c8c8c", "opacity": 1.0 if on else 0.35,
                    "line": {"color": color, "width": 1}},
            hovertemplate=f"shot {k}: {setting.name} ({setting.type}, {setting.mount}), channel "
                          f"{'-' if setting.channel is None else setting.channel}, drive {setting.drive:.0%}"
                          f"{'' if on else ' (off)'}<extra></extra>", legendgroup=group, showlegend=False))
    return traces


def write_cell_view(path: PathLike, plan: Plan, task: Task, order: Sequence[int] | None = None) -> CellView:
    """cell.html of a plan (the module's docstring says what it shows); `order`, the route's order
    of plan.shots indices (a run's), else the plan's own. Returns a CellView."""
    scene = CollisionScene.of(task)
    T = task.frames.T_cell_part
    traces: list[Any] = []
    housings = {h.name: h for h in occluders.housings(task)}
    for body in scene.fixed:
        if isinstance(body, Mesh):          # the part, the fixture (a light's body is its housing, drawn below)
            traces.append(_body(body, body.name, "#c8ccd4" if body.name == "part" else "#9aa0a8", body.name,
                                body.name, legend=True, opacity=1.0 if body.name == "part" else 0.6))
    for h in housings.values():
        traces.append(_mesh3d(h.vertices, h.faces, h.name, "#9aa0a8", f"{h.name}: its housing, a collision body "
                              "that blocks the camera's view and the lights' rays as the part does", 0.6, h.name))
    if plan.features:
        covered = [f.covered_by for f in plan.features]
        covers = [[c.feature for c in shot.covers] for shot in plan.shots]
    else:
        covered = [0 if plan.feasible else None]
        covers = [[task.feature.name] if plan.feasible else []]
    size = float(np.ptp(scene.part.vertices, axis=0).max())
    for j, (feature, by) in enumerate(zip(task.features, covered)):
        center, normal = geometry.apply(T, feature.center_m), geometry.unit(geometry.rotate(T, feature.normal))
        frame = geometry.frame_from_normal(normal)
        a = np.linspace(0.0, 2.0 * np.pi, 33)[:-1]
        rim = center + 5e-4 * normal + feature.radius_m * (np.cos(a)[:, None] * frame[:, 0]
                                                          + np.sin(a)[:, None] * frame[:, 1])
        disk = np.vstack([center + 5e-4 * normal, rim])
        fan = np.array([[0, 1 + i, 1 + (i + 1) % len(a)] for i in range(len(a))])
        name = f"feature {feature.name}"
        where = "no shot" if by is None else f"shot {by}"
        traces.append(_mesh3d(disk, fan, name, FEATURE_COLORS[j % len(FEATURE_COLORS)],
                              f"{name}: radius {feature.radius_m * 1e3:.1f} mm, {where}"))
        traces.append(_lines([np.array([center, center + 0.3 * size * normal])], f"{name} normal", "black",
                             f"{name}'s normal", name, width=4, legend=False))
    for k, shot in enumerate(plan.shots):
        traces += _shot_traces(k, shot, plan, task, scene, covers[k] if k < len(covers) else [])
    pivot = np.asarray(task.lamp.rig.pivot_m, float)
    traces.append(go.Scatter3d(x=[pivot[0]], y=[pivot[1]], z=[pivot[2]], mode="markers", name="rig pivot",
                               marker={"size": 4, "color": "black", "symbol": "cross"},
                               hovertemplate="the rig's pivot: every lamp's aim<extra></extra>"))
    visit = tuple(range(len(plan.shots))) if order is None else tuple(order)
    whose = "the plan's order" if order is None else "the route's order"
    for move in plan.moves:
        corners = np.array(move.corners_m)
        via = f"{len(move.via)} via point{'s' * (len(move.via) != 1)}" + (
            f", {len(move.joint_legs)} leg{'s' * (len(move.joint_legs) != 1)} by moveJ" if move.joint_legs else "")
        start = move.start if isinstance(move.start, str) else f"shot {move.start}"
        text = (f"{start} to shot {move.end}: collision-checked, clearance "
                f"{move.clearance.distance_m * 1e3:.1f} mm ({' and '.join(move.clearance.bodies)}), {via}")
        traces.append(go.Scatter3d(
            x=corners[:, 0], y=corners[:, 1], z=corners[:, 2], mode="lines+markers", name=f"path {text}",
            line={"color": "black", "width": 4}, marker={"size": 3, "color": "black"},
            hovertext=[text] * len(corners), hovertemplate="%{hovertext}<extra></extra>"))
    if len(visit) > 1 and not plan.moves:
        cameras = np.array([plan.shots[k].camera_position for k in visit])
        traces.append(go.Scatter3d(
            x=cameras[:, 0], y=cameras[:, 1], z=cameras[:, 2], mode="lines+markers+text",
            text=[f"{n + 1}." for n in range(len(visit))], textposition="top center",
            name=f"route ({whose}; straight, not collision-checked)",
            line={"color": "black", "width": 3, "dash": "dash"}, marker={"size": 2, "color": "black"},
            hovertext=[f"stop {n + 1}: shot {k}" for n, k in enumerate(visit)],
            hovertemplate="%{hovertext}: straight line between cameras, not a collision-checked path<extra></extra>"))
    verdict = "feasible" if plan.feasible else f"not feasible ({plan.binding})"
    n = len(plan.shots)
    fig = go.Figure(traces)
    fig.update_layout(title=f"{plan.task_name}: {n} shot{'s' * (n != 1)}, {verdict}, padding "
                            f"{scene.padding_m * 1e3:g} mm (cell frame, metres)",
                      scene={"aspectmode": "data", "xaxis_title": "x [m]", "yaxis_title": "y [m]",
                             "zaxis_title": "z [m]"},
                      legend={"groupclick": "togglegroup", "font": {"size": 11}},
                      margin={"l": 0, "r": 0, "t": 40, "b": 0})
    path = Path(path)
    fig.write_html(path, include_plotlyjs=True, full_html=True, auto_open=False,
                   config={"displaylogo": False})
    return CellView(path, tuple(t.name for t in traces))
