"""`cell bench`: what accuracy costs in time (`suite`: the planner's resolution sweep),
the kernels' throughput against NumPy and trimesh (`throughput`), planning time against features
and workers (`multi_feature`).

Layer 10: imports the layers below."""
