"""Collision checking of the cell: its bodies as geometry and a conservative distance between two
(`bodies`: boxes, capsules, sampled meshes), the scene of a task and the clearance of a pose of
the arm, camera and lamp (`scene`), the moves between two shots checked along their
paths, with via points around a collision (`paths`).

Layer 5: imports `cell.core`, `cell.physics`, `cell.task`, `cell.devices` (not `hw`)."""
