"""Write the example part meshes (millimetres, part frame): hinge.yaml's, conrod.yaml's,
bracket.yaml's and ring.yaml's, and for the tests' tasks (tests/tasks/) the curved parts (a sphere
cap, a cylinder, a filleted block) and conrod_beam.yaml's fixture (a beam, cell frame).

Regenerate with `python tasks/make_parts.py`. Solids are concatenated, not booleaned: the
planner only casts rays at them, so overlapping closed shells are fine and no CSG library
is needed. The shapes are plausible stand-ins for the paper's parts, not their CAD. The curved
surfaces are tessellated finely (facets under 1 mm, about 1.3 deg apart) so that a 5-8 mm patch is
smooth, yet each file stays under 1 MB.
"""
from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent / "parts"


def box(size, center):
    return trimesh.creation.box(extents=size, transform=trimesh.transformations.translation_matrix(center))


def cylinder(radius, height, center, axis="z", sections=64):
    T = trimesh.transformations.translation_matrix(center)
    if axis == "y":
        T = T @ trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    return trimesh.creation.cylinder(radius=radius, height=height, sections=sections, transform=T)


def hinge():
    """A hinge leaf 60 x 40 x 4 mm (top face z = 4), its knuckle along y at x = -34 mm,
    and two screw heads standing 2 mm proud of the leaf."""
    parts = [
        box((60.0, 40.0, 4.0), (0.0, 0.0, 2.0)),
        cylinder(6.0, 40.0, (-34.0, 0.0, 6.0), axis="y"),
        cylinder(4.0, 2.0, (18.0, 12.0, 5.0)),
        cylinder(4.0, 2.0, (18.0, -12.0, 5.0)),
    ]
    return trimesh.util.concatenate(parts)


def conrod():
    """A connecting rod: shank 90 x 14 x 8 mm (top face z = 8), big-end boss r 25 x 16 mm at
    x = -70 mm, small-end boss r 14 x 14 mm at x = +58 mm."""
    parts = [
        box((90.0, 14.0, 8.0), (0.0, 0.0, 4.0)),
        cylinder(25.0, 16.0, (-70.0, 0.0, 8.0)),
        cylinder(14.0, 14.0, (58.0, 0.0, 7.0)),
    ]
    return trimesh.util.concatenate(parts)


def _ring_angles(radius, step):
    """Azimuths of a ring of the given radius with points at most `step` apart (one on the axis)."""
    n = 1 if radius <= 1e-9 else max(3, int(np.ceil(2.0 * np.pi * radius / step)))
    return 2.0 * np.pi * np.arange(n) / n


def _zip(a, b, angles_a, angles_b):
    """Triangles between two rings of vertex indices a, b (azimuths ascending from 0): a fan to a
    ring of one point (the axis), otherwise always advancing the ring whose next point comes first."""
    if len(a) == 1:
        return [(a[0], b[k], b[(k + 1) % len(b)]) for k in range(len(b))]
    if len(b) == 1:
        return [(a[k], b[0], a[(k + 1) % len(a)]) for k in range(len(a))]
    ext_a, ext_b = np.append(angles_a, 2 * np.pi), np.append(angles_b, 2 * np.pi)
    faces, i, j = [], 0, 0
    while i < len(a) or j < len(b):
        if j == len(b) or (i < len(a) and ext_a[i + 1] <= ext_b[j + 1]):
            faces.append((a[i], b[j % len(b)], a[(i + 1) % len(a)]))
            i += 1
        else:
            faces.append((a[i % len(a)], b[j], b[(j + 1) % len(b)]))
            j += 1
    return faces


def revolve(profile, step):
    """Closed solid of revolution about z of a profile [(r, z), ...] that starts and ends on the
    axis (r = 0): one ring of vertices per profile point, at most `step` apart around it."""
    vertices, rings, faces = [], [], []
    for r, z in profile:
        angles = _ring_angles(r, step)
        rings.append((np.arange(len(angles)) + len(vertices), angles))
        vertices.extend((r * np.cos(a), r * np.sin(a), z) for a in angles)
    for (a, angles_a), (b, angles_b) in zip(rings[:-1], rings[1:]):
        faces.extend(_zip(a, b, angles_a, angles_b))
    return _outward(trimesh.Trimesh(np.array(vertices), np.array(faces)))


def extrude(outline, length, step):
    """Closed prism of a convex outline [(x, z), ...] (counter-clockwise seen from -y) along y,
    centred on y = 0, in slices at most `step` long; the ends are fans from the outline's centroid."""
    outline = np.asarray(outline, dtype=float)
    n = len(outline)
    ys = np.linspace(-0.5 * length, 0.5 * length, max(1, int(np.ceil(length / step))) + 1)
    vertices = [(x, y, z) for y in ys for x, z in outline]
    c = outline.mean(axis=0)
    vertices += [(c[0], ys[0], c[1]), (c[0], ys[-1], c[1])]
    first, last = len(vertices) - 2, len(vertices) - 1
    faces = []
    for s in range(len(ys) - 1):
        for k in range(n):
            a, b = s * n + k, s * n + (k + 1) % n
            faces += [(a, b, b + n), (a, b + n, a + n)]
    top = (len(ys) - 1) * n
    faces += [(first, (k + 1) % n, k) for k in range(n)]
    faces += [(last, top + k, top + (k + 1) % n) for k in range(n)]
    return _outward(trimesh.Trimesh(np.array(vertices), np.array(faces)))


def _outward(mesh):
    """The mesh with its triangles wound so that the normals point out (positive volume)."""
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def _arc(center, radius, start, stop, step):
    """Points (r, z) or (x, z) on a circular arc from angle `start` to `stop` [rad], at most `step` apart."""
    n = max(1, int(np.ceil(radius * abs(stop - start) / step)))
    a = np.linspace(start, stop, n + 1)
    return np.column_stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)])


def sphere_cap():
    """A dome: the part of a sphere r 30 mm (centre at z = -5 mm) above z = 5 mm, apex z = 25 mm,
    sunk into a base 80 x 80 x 10 mm (top face z = 10 mm), so 15 mm of it stands proud."""
    step = 0.7
    arc = _arc((0.0, -5.0), 30.0, np.pi / 2, np.arcsin(10.0 / 30.0), step)
    r_cut = arc[-1, 0]
    floor = [(r_cut * k / 4, 5.0) for k in (3, 2, 1, 0)]
    dome = revolve([tuple(p) for p in arc] + floor, step)
    return trimesh.util.concatenate([box((80.0, 80.0, 10.0), (0.0, 0.0, 5.0)), dome])


def lying_cylinder():
    """A shaft r 20 x 80 mm lying along x, its axis at z = 22 mm, sunk 3 mm into a plate
    100 x 60 x 5 mm (top face z = 5 mm); the top of the shaft is z = 42 mm."""
    step = 0.4
    ends = [(20.0 * k / 4, z) for z in (-40.0, 40.0) for k in (0, 1, 2, 3)]
    side = [(20.0, z) for z in np.linspace(-40.0, 40.0, 9)]
    profile = ends[:4] + side + ends[4:][::-1]
    shaft = revolve(profile, step)
    shaft.apply_transform(trimesh.transformations.translation_matrix((0.0, 0.0, 22.0))
                          @ trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return trimesh.util.concatenate([box((100.0, 60.0, 5.0), (0.0, 0.0, 2.5)), shaft])


def filleted_block():
    """A block 60 (x) x 40 (y) x 30 (z) mm on z = 0 whose edge between the top face (z = 30) and the
    +x face (x = 30) is rounded with a fillet r 10 mm, its axis along y through x = z = 20 mm."""
    fillet = _arc((20.0, 20.0), 10.0, 0.0, np.pi / 2, 0.2)
    outline = [(-30.0, 0.0), (30.0, 0.0)] + [tuple(p) for p in fillet] + [(-30.0, 30.0)]
    return extrude(outline, 40.0, 4.0)


def bracket(length=40.0):
    """A cast angle bracket standing on z = 0, its faces at five angles (the outward normal in the
    xz plane; part frame, mm, y in [-length / 2, length / 2] throughout, 40 mm for bracket.yaml):
      base plate x in [-20, 25], z in [0, 6]: its top face z = 6 (+z) from the chamfer to x = 25;
      upright web x in [-25, -15], z in [0, 40]: inner face x = -15 (+x) above the chamfer, outer
        face x = -25 (-x) below the bevel;
      a 45 deg bevel on the web's outer top edge, from (-25, 32) to (-17, 40): normal (-1, 0, 1);
      a 45 deg chamfer filling the inner corner, on x + z = 3 from (-3, 6) to (-15, 18): (1, 0, 1).
    The chamfer's prism reaches into the plate and the web, so that no face of it lies on theirs."""
    web = extrude([(-25.0, 0.0), (-15.0, 0.0), (-15.0, 40.0), (-17.0, 40.0), (-25.0, 32.0)], length, length)
    chamfer = extrude([(-16.0, 5.0), (-2.0, 5.0), (-16.0, 19.0)], length, length)
    return trimesh.util.concatenate([box((45.0, length, 6.0), (2.5, 0.0, 3.0)), web, chamfer])


def plate():
    """A milled plate 80 (x) x 60 (y) x 8 mm on z = 0, its top face z = 8 (ring.yaml's)."""
    return box((80.0, 60.0, 8.0), (0.0, 0.0, 4.0))


def beam():
    """conrod_beam.yaml's fixture (cell frame, mm): a beam 10 mm thick (x in [-11, -1]) and 80 mm
    wide (y in [-40, 40]) hanging over the connecting rod between its two bosses, from z = 250 to
    400 mm: clear of the camera above either boss, across the straight line between them."""
    return box((10.0, 80.0, 150.0), (-6.0, 0.0, 325.0))


PARTS = {"hinge": hinge, "beam": beam, "plate": plate, "conrod": conrod, "bracket": bracket, "sphere_cap": sphere_cap, "lying_cylinder": lying_cylinder,
         "filleted_block": filleted_block}


def main():
    HERE.mkdir(exist_ok=True)
    for name, make in PARTS.items():
        path = HERE / f"{name}.stl"
        make().export(path)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
