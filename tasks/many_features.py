"""A generated example with many features (issue 28): the bracket's five faces (bracket.yaml,
make_parts.bracket) repeated along a longer bracket (make_parts.bracket of another length), one segment of five features every
PITCH_MM along y, and its task: bracket.yaml's requirements, camera, lamp and cell with the
features of every segment. `cell bench` writes one into a folder of its own for each size it
times (cell.bench.scaling), so no large mesh is committed.

    python -m lightplan_tasks.many_features OUT [--features 40]    writes OUT/many-40.yaml and .stl
"""
import argparse
import copy
from pathlib import Path

import numpy as np
import yaml

from lightplan_tasks.make_parts import bracket

HERE = Path(__file__).resolve().parent
PITCH_MM = 14.0      # segments along y: the faces' features (radius 4-6 mm) 2 mm apart at least
END_MM = 13.0        # the bracket past the first and last segment's centre (bracket.yaml's 20 mm part: 20 - 7)


def segment_offsets_mm(segments):
    """y of each segment's features [mm], centred on y = 0 (the rig's pivot stays amid them)."""
    return PITCH_MM * (np.arange(segments) - 0.5 * (segments - 1))


def length_mm(segments):
    """The bracket's length along y [mm]: END_MM beyond the first and the last segment's centre."""
    return 2.0 * END_MM + (segments - 1) * PITCH_MM


def task(features, mesh):
    """bracket.yaml with `features` features (its five faces in turn, segment by segment) on the
    part `mesh` (a path), the material by its absolute path (the task is written elsewhere)."""
    doc = yaml.safe_load((HERE / "bracket.yaml").read_text())
    faces = doc["features"]
    segments = -(-features // len(faces))
    doc["name"] = f"Cast iron angle bracket, {features} features"
    doc["part"]["mesh"] = str(mesh)
    doc["part"]["material"] = str(HERE / doc["part"]["material"])
    doc["features"] = []
    for s, y in enumerate(segment_offsets_mm(segments)):
        for face in faces:
            if len(doc["features"]) < features:
                feature = copy.deepcopy(face)
                feature["name"] = f"{face['name']}_{s + 1}"
                feature["center_mm"][1] = float(y)
                doc["features"].append(feature)
    return doc


def write(folder, features):
    """OUT/many-N.stl and OUT/many-N.yaml (N = features); the task's path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh = folder / f"many-{features}.stl"
    bracket(length_mm(-(-features // 5))).export(mesh)
    path = folder / f"many-{features}.yaml"
    path.write_text(yaml.safe_dump(task(features, mesh.name), sort_keys=False, default_flow_style=None))
    return path


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out")
    parser.add_argument("--features", type=int, default=40)
    args = parser.parse_args()
    print(f"wrote {write(args.out, args.features)}")
