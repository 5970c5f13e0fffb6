"""The fixed lights' housings as shadow geometry: triangle meshes the planner's, the certificate's
and the simulated camera's rays meet as they meet the part, so a housing blocks the camera's view,
the spot's beam and every light's emitter rays (kernels.gray, kernels.render, kernels.visibility
cast against the part and these together: Scene.shadow_mesh).

Each light's housing is its collision body (cell.collision.scene.light_body), by its type
(Light.housing gives the sizes, docs/formats.md):
  ring            an annulus about the axis, from aperture_radius_m (the hole the camera looks
                  through) to outer_radius_m;
  bar, area, spot a box, the emitting extent plus a rim;
  dome            a spherical shell outside its emitting hemisphere, open at the camera's hole (a
                  cylinder of hole_radius_m about the axis) and at its rim.
Each lies wholly behind its emitting surface (a plane; a dome's sphere), from EMITTER_PROUD_M to
housing_depth_m behind it: a ray leaving an emitter point to its front never meets its own
housing, and no ray ends on a face (float32 rounding would decide it). Circles are polygons
with their corners on the circle and at most CHORD_M from it (the hole that much smaller).
A flange light moves with the camera and is not a housing here (as the camera body is not).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import trimesh

from cell.collision.bodies import Annulus, Box, Shell
from cell.collision.scene import light_body
from cell.core import geometry

if TYPE_CHECKING:
    from cell.task.types import Light, Task

EMITTER_PROUD_M = 5e-4      # the emitting surface stands this far in front of its housing (the LEDs' lenses)
CHORD_M = 1e-4              # a circle's polygon lies within this of it
MIN_SECTIONS = 16


@dataclass(frozen=True)
class Housing:
    """One fixed light's housing: its name (the light's) and a closed triangle mesh, cell frame."""

    name: str
    vertices: np.ndarray        # (V, 3) [m]
    faces: np.ndarray           # (F, 3)

    def __post_init__(self) -> None:
        self.vertices.flags.writeable = False
        self.faces.flags.writeable = False


def housings(task: Task) -> tuple[Housing, ...]:
    """Each fixed light's Housing, in the order of task.lights."""
    return tuple(housing(light) for light in task.lights if light.mount == "fixed")


def housing(light: Light) -> Housing:
    """A fixed light's Housing: its collision body (cell.collision.scene.light_body) set back
    EMITTER_PROUD_M from its emitting surface, a box as trimesh's, a ring's annulus and a dome's
    shell revolved from their cross-sections about the light's axis."""
    body = light_body(light, EMITTER_PROUD_M)
    if isinstance(body, Box):
        mesh = trimesh.creation.box(extents=2.0 * body.half_m, transform=body.T_cell_box)
        return Housing(light.name, np.ascontiguousarray(mesh.vertices, float), np.ascontiguousarray(mesh.faces, np.int64))
    profile = _annulus_profile(body) if isinstance(body, Annulus) else _shell_profile(body)
    mesh = trimesh.creation.revolve(profile, sections=sections(body.outer_m))      # about z, the light's axis
    return Housing(light.name, np.ascontiguousarray(geometry.apply(body.T_cell_body, mesh.vertices), float),
                   np.ascontiguousarray(mesh.faces, np.int64))


def sections(radius_m: float, chord_m: float = CHORD_M) -> int:
    """Corners of a polygon on a circle of radius_m whose edges lie within chord_m of it:
    the sagitta r (1 - cos(pi / n)) <= chord_m."""
    if radius_m <= chord_m:
        return MIN_SECTIONS
    return max(MIN_SECTIONS, int(np.ceil(np.pi / np.arccos(1.0 - chord_m / radius_m))))


def _annulus_profile(ring: Annulus) -> np.ndarray:
    """A ring housing's closed cross-section [radius, z], counter-clockwise (trimesh.creation.revolve's
    outward faces), in the light's frame (z along its axis, the LEDs at z = 0)."""
    (back, front), inner, outer = ring.z_m, ring.inner_m, ring.outer_m
    return np.array([[inner, back], [outer, back], [outer, front], [inner, front], [inner, back]])


def _shell_profile(dome: Shell) -> np.ndarray:
    """A dome housing's closed cross-section [radius, z], counter-clockwise, in the light's frame
    (z along its axis, its pole at 0, its sphere's centre at z = dome.centre_m): the two arcs
    from the hole's cylinder (none: from the pole) down to the rim, the plane through the centre."""
    steps = max(4, sections(dome.outer_m) // 4)                     # a quarter circle's corners

    def arc(r):
        polar = np.linspace(dome.polar_start(r), 0.5 * np.pi, steps + 1)
        return np.column_stack([r * np.sin(polar), dome.centre_m - r * np.cos(polar)])
    outer_arc = arc(dome.outer_m)
    return np.vstack([outer_arc, arc(dome.inner_m)[::-1], outer_arc[:1]])


def blockers(found: tuple[Housing, ...], origins: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(H, N) whether the segment from each origin (N, 3) to its target (N, 3, or one (3,))
    crosses housing h (Moller-Trumbore on every triangle, NumPy): which light stands in a ray's
    way, to name it (the kernels say only that something does)."""
    origins = np.asarray(origins, float).reshape(-1, 3)
    d = np.broadcast_to(np.asarray(targets, float), origins.shape) - origins
    out = np.zeros((len(found), len(origins)), bool)
    for k, h in enumerate(found):
        a, b, c = (h.vertices[h.faces[:, i]] for i in range(3))            # (F, 3) each
        e1, e2 = b - a, c - a
        p = np.cross(d[:, None], e2[None])                                   # (N, F, 3)
        det = np.einsum("nfj,fj->nf", p, e1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):     # det 0: parallel, no hit
            inv = 1.0 / det
            s = origins[:, None] - a[None]
            u = np.einsum("nfj,nfj->nf", s, p) * inv
            q = np.cross(s, e1[None])
            v = np.einsum("nj,nfj->nf", d, q) * inv
            t = np.einsum("fj,nfj->nf", e2, q) * inv
            hit = (det != 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < 1)
        out[k] = hit.any(axis=1)
    return out


def named(found: tuple[Housing, ...], blocked: np.ndarray) -> str:
    """'the light bar_left (12 samples)', 'the lights bar_left (12 samples), ring (3 samples)': the
    housings that block some of the rays `blocked` (H, N), with how many, most first ('' none)."""
    counts = blocked.sum(axis=1)
    order = [k for k in np.argsort(-counts, kind="stable") if counts[k]]
    names = ", ".join(f"{found[k].name} ({int(counts[k])} sample{'s' * int(counts[k] != 1)})" for k in order)
    return f"the light{'s' * int(len(order) > 1)} {names}" if order else ""
