"""Write the example part meshes (millimetres, part frame) used by hinge.yaml and conrod.yaml.

Regenerate with `python tasks/make_parts.py`. Solids are concatenated, not booleaned: the
planner only casts rays at them, so overlapping closed shells are fine and no CSG library
is needed. The shapes are plausible stand-ins for the paper's parts, not their CAD.
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


def main():
    HERE.mkdir(exist_ok=True)
    for name, make in (("hinge", hinge), ("conrod", conrod)):
        path = HERE / f"{name}.stl"
        make().export(path)
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
