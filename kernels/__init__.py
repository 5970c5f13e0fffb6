"""Warp CPU kernels: BRDF, gray value, visibility and rendering over candidates x points.

Pure arrays in, NumPy out; nothing here knows of task files or devices. Warp starts lazily
(kernels.runtime.ensure_init) on the first call, not on import.

    kernels.mesh.WarpMesh(vertices, faces)                 BVH of a triangle mesh [m]
    kernels.visibility.visibility_maps(...)  -> bool (P, E, A)
    kernels.gray.gray_per_exposure(...)      -> GrayResult (value, shadowed, off_axis, dominant)
    kernels.render.render(...)               -> RenderResult (value, hit, depth, normal)
    kernels.proximity.closest_points(...)    -> (point, face, normal) on the surface
    kernels.reference                        NumPy versions of the above (tests, benchmark)
    kernels.bench.benchmark_gray(...)        evaluations/s, Warp vs NumPy
"""
