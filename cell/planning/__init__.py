"""Planning (sec. 2, 5 of the paper): the task's geometry (`scene`), the spherical maps
(`regions`), one shot's problem and the model's prediction over lamp poses (`evaluate`), the
requirement registry (`requirements`), one shot's lamp and camera settings (`one_shot`: global
search, refinement, `certificate`), planned camera viewpoints (`viewpoints`), a part's several
features (`whole_part`: candidate shots, `coverage` of each feature, `set_cover` for the fewest
shots), where independent jobs run (`parallel`), several light channels' drive levels, shutter and
f-number by linear programming (`drives`); what it produces is `plan` (Plan, Shot).

Layer 6: imports `cell.core`, `cell.physics`, `cell.task`, `cell.devices` (not `hw`),
`cell.collision` and `kernels`."""
