"""`cell bench`: what accuracy costs in time (`suite`: the planner's resolution sweep),
the kernels' throughput against NumPy and trimesh (`throughput`), planning time against features
and workers (`multi_feature`), the lights' contribution kernel per type and planning time against
the number of channels (`lights`).

Layer 10: imports the layers below."""
