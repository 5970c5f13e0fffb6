"""What a person opens and a machine reads: the run folder (`recorder`: log.jsonl, plan.json,
result files, the routines' ending), the verdict every result file carries (`result`) and
every picture (`pictures`; `cell_view`, the cell in 3D as cell.html).

Layer 7: imports `cell.core` to `cell.planning`."""
