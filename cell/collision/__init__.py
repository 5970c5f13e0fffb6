"""Collision checking of the cell: its bodies as geometry and a conservative distance between two
(`bodies`: boxes, capsules, sampled meshes), the scene of a task and the clearance of a pose of
the arm, camera and lamp (`scene`).

Layer 5: imports `cell.core`, `cell.physics`, `cell.task`, `cell.devices` (not `hw`)."""
