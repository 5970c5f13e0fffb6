"""Pictures: drawn from several threads at once they come out as if drawn one after the other;
cell.png draws each shot where its numbers put it; convergence.png shows a refit's probe shots and
where it took effect."""
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as plt_image
from matplotlib.colors import to_rgb

from cell.task.loader import load_task
from cell.report.pictures import FEATURE_COLORS, display_mesh, write_bench, write_cell
from cell.planning.one_shot import plan
from cell.report.recorder import write_plan

ROOT = Path(__file__).resolve().parent.parent

ROWS = [{"task": "t", "name": n, "time_s": t, "gray_error_max": e, "default": n == "default", "pareto": True}
        for n, t, e in [("coarse", 0.1, 1.8), ("default", 0.3, 0.5), ("fine", 1.5, 0.2)]]


def test_bench_plots_drawn_in_threads_equal_one_drawn_alone(tmp_path):
    """Log axes lay out their tick labels with matplotlib's shared mathtext parser."""
    write_bench(tmp_path / "alone.png", ROWS)
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda k: write_bench(tmp_path / f"{k}.png", ROWS), range(8)))
    alone = (tmp_path / "alone.png").read_bytes()
    assert all((tmp_path / f"{k}.png").read_bytes() == alone for k in range(8))


"""Pictures: drawn from several threads at once they come out as if drawn one after the other;
cell.png draws each shot where its numbers put it; convergence.png shows a refit's probe shots and
where it took effect."""
