"""The pictures: drawn from several threads at once they come out as if drawn one after the other;
convergence.png shows a refit's probe shots and where it took effect."""
from concurrent.futures import ThreadPoolExecutor

from cell.pictures import write_bench

ROWS = [{"task": "t", "name": n, "time_s": t, "gray_error_max": e, "default": n == "default", "pareto": True}
        for n, t, e in [("coarse", 0.1, 1.8), ("default", 0.3, 0.5), ("fine", 1.5, 0.2)]]


def test_bench_plots_drawn_in_threads_equal_one_drawn_alone(tmp_path):
    """Log axes lay out their tick labels with matplotlib's shared mathtext parser."""
    write_bench(tmp_path / "alone.png", ROWS)
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda k: write_bench(tmp_path / f"{k}.png", ROWS), range(8)))
    alone = (tmp_path / "alone.png").read_bytes()
    assert all((tmp_path / f"{k}.png").read_bytes() == alone for k in range(8))


def test_convergence_shows_each_refits_probe_shots_and_where_it_took_effect(tmp_path, monkeypatch):
    """Capture 1 disagreed and was refitted from it and two probes: two probe bars (grey, their
    raw min-max, a triangle at the mean) between captures 1 and 2, and the refit's dashed line."""
    from matplotlib.figure import Figure
    from cell.pictures import write_convergence
    drawn = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: drawn.append(fig))
    gray = lambda lo, hi: {"min": lo, "max": hi, "mean": (lo + hi) / 2}
    iterations = [{"iteration": k, "measured_gray": gray(*g), "predicted_gray": gray(104, 120), "in_band": k == 2,
                   "shutter_s": 5e-3, "f_number": 5.5, "correction": {"action": a} if a else None}
                  for k, g, a in ((1, (138, 178), "refit"), (2, (104, 119), None))]
    shots = [{"measured_gray": gray(*g)} for g in ((138, 178), (112, 154), (162, 197))]
    write_convergence(tmp_path / "c.png", iterations, (100, 125), [{"iteration": 1, "shots": shots,
                                                                    "captures": ["a", "b", "c"]}])
    (ax,) = drawn[0].axes
    probes = [line for line in ax.lines if line.get_marker() == "v" and len(line.get_xdata())]
    assert [tuple(p.get_ydata()) for p in probes] == [(133.0,), (179.5,)]
    assert all(1 < p.get_xdata()[0] < 2 for p in probes)
    bars = [line for line in ax.lines if tuple(line.get_ydata()) in ((112, 154), (162, 197))]
    assert len(bars) == 2
    assert any(line.get_linestyle() == "--" and tuple(line.get_xdata()) == (1.9, 1.9) for line in ax.lines)
    assert any("refit (3 captures)" in t.get_text() for t in ax.texts)
