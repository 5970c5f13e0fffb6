"""Warp CPU kernels: BRDF, gray value, visibility and rendering over candidates x points.

Pure arrays in, NumPy out; nothing here knows of task files or devices. Warp starts lazily
(kernels.runtime.ensure_init) on the first call, not on import.

    kernels.mesh.WarpMesh(vertices, faces)                 BVH of a triangle mesh [m]
    kernels.visibility.visibility_maps(...)  -> bool (P, E, A)
    kernels.visibility.visible_from_all(...) -> bool (E, A), every point's maps combined
    kernels.gray.gray_per_exposure(...)      -> GrayResult (value, shadowed, off_axis, dominant)
    kernels.gray.GrayInputs(...)(lamps, aims) the same, its fixed inputs converted once
    kernels.cone.free_cone_cosines(...)      -> the cones about each normal no triangle enters
    kernels.render.render(...)               -> RenderResult (value, hit, depth, normal)
    kernels.proximity.closest_points(...)    -> (point, face, normal) on the surface

Their NumPy references (tests, `cell bench`) are cell.physics.reference, built from the readable
physics in cell; the throughput benchmark is cell.bench.throughput.
"""
