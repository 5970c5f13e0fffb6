"""Pictures a person reads (paper Fig. 4-6): BRDF on the visibility map, segmented region map,
cost map, each with the camera direction (square) and the lamp (dot) marked.

`picture_data` takes what the pictures show out of a plan (plain arrays); `draw_plan_pictures`
draws them with matplotlib alone (no pyplot). `cell plan` starts a `PictureWorker` before it
plans: a forked process that imports matplotlib meanwhile (on the other core) and, once the plan
is sent to it, draws the same figures in two processes at once.
"""
import importlib
import os
import pickle
import select
import signal
import sys
import time
import warnings
from pathlib import Path

import numpy as np

PICTURES = ("visibility_brdf.png", "regions.png", "cost.png")
DPI = 90
PNG = {"compress_level": 1}      # zlib level: lossless like the default 6, a fraction of its time

# Fixed margins: what tight_layout finds for these figure sizes, fonts and labels (so the
# pictures of tasks/hinge.yaml are pixel for pixel those of tight_layout), without its layout
# pass over every figure. Only the colour bars' tick labels depend on the data; the right
# margin keeps tight_layout's pad (0.15 in) beyond the colour bar's label for them.
_MARGINS = {"left": 0.0829048514660494, "right": 0.9833333333333332,
            "bottom": 0.12188178168402777, "top": 0.9284722222222224}
_MARGINS_WIDE = {"left": 0.057395666399572665, "right": 0.9884615384615385,
                 "bottom": 0.12188178168402777, "top": 0.9284722222222224,
                 "wspace": 0.10984346160332005}


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def picture_data(plan, task, scene):
    """Everything the three pictures show, as plain (picklable) arrays and numbers."""
    from cell import geometry
    from cell.physics import brdf

    def feature_angles(position):
        az, el = geometry.angles_from_direction((position - scene.center) @ scene.frame)
        return float(np.degrees(az)), float(np.degrees(el))

    m = plan.maps
    return {
        "task_name": plan.task_name,
        "azimuth_deg": np.degrees(m.grid.azimuth),
        "elevation_deg": np.degrees(m.grid.elevation),
        "visible": m.visible,
        "reflectance": m.reflectance,
        "segments": np.where(m.visible, m.dominant, brdf.OCCLUDED).astype(float),
        "segment_names": ("occluded", *brdf.TERM_NAMES),
        "wanted": m.wanted,
        "distance": m.distance,
        "region_margin_rad": task.requirements.region_margin_rad,
        "candidate_pan": m.candidate_pan,
        "candidate_tilt": m.candidate_tilt,
        "candidate_objective": m.candidate_objective,
        "joints": tuple(float(x) for x in plan.joints),
        "camera_angles_deg": feature_angles(plan.camera_position),
        "lamp_angles_deg": feature_angles(plan.lamp_position),
    }


def _mark(ax, d):
    ax.plot(*d["camera_angles_deg"], marker="s", ms=11, mfc="none", mec="white", mew=2, ls="none",
            label="camera")
    ax.plot(*d["lamp_angles_deg"], marker="o", ms=8, mfc="white", mec="black", ls="none", label="lamp")
    ax.legend(loc="lower right", fontsize=8, framealpha=0.6)


def _axes(ax, title):
    ax.set_xlabel("azimuth [deg] (feature frame)")
    ax.set_ylabel("elevation [deg] (+90 = feature normal)")
    ax.set_title(title, fontsize=10)


def _visibility_brdf(d, extent):
    fig = _figure((9, 4.8))
    ax = fig.subplots()
    R = d["reflectance"]
    shown = np.ma.masked_where(~d["visible"] | (R <= 0), np.log10(np.maximum(R, 1e-12)))
    ax.set_facecolor("0.25")
    im = ax.imshow(shown, origin="lower", extent=extent, aspect="auto", cmap="inferno")
    fig.colorbar(im, ax=ax, label="log10 R (occluded: dark gray)")
    _mark(ax, d)
    _axes(ax, f"{d['task_name']}: BRDF mapped on the visibility map")
    fig.subplots_adjust(**_MARGINS)
    return fig


def _regions(d, extent):
    from matplotlib.colors import ListedColormap
    fig = _figure((9, 4.8))
    ax = fig.subplots()
    colors = ["black", "tab:blue", "tab:orange", "tab:red"]
    ax.imshow(d["segments"], origin="lower", extent=extent, aspect="auto", cmap=ListedColormap(colors),
              vmin=-1.5, vmax=2.5, interpolation="nearest")
    ax.contour(d["azimuth_deg"], d["elevation_deg"], d["wanted"].astype(float),
               levels=[0.5], colors="white", linewidths=1)
    for color, name in zip(colors, d["segment_names"]):
        ax.plot([], [], "s", color=color, label=name)
    _mark(ax, d)
    _axes(ax, "segmented region map (white line: wanted region)")
    fig.subplots_adjust(**_MARGINS)
    return fig


def _cost(d, extent):
    fig = _figure((13, 4.8))
    ax1, ax2 = fig.subplots(1, 2)
    margin = max(d["region_margin_rad"], 1e-6)
    cost = (d["distance"] / margin + 1.0) / np.log(10.0)    # log10 of exp(d / margin + 1)
    im = ax1.imshow(cost, origin="lower", extent=extent, aspect="auto", cmap="viridis", vmin=-3, vmax=3)
    fig.colorbar(im, ax=ax1, label="log10 region cost (<= 0: met)")
    _mark(ax1, d)
    _axes(ax1, "region cost exp(d / margin + 1)")
    pan, tilt = np.degrees(d["candidate_pan"]), np.degrees(d["candidate_tilt"])
    keys = np.round(np.column_stack([pan, tilt]), 6)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    best = np.full(len(uniq), np.inf)
    np.minimum.at(best, inv.ravel(), d["candidate_objective"])
    sc = ax2.scatter(uniq[:, 0], uniq[:, 1], c=np.clip(best, -2, 10), cmap="magma_r", s=28, marker="s")
    fig.colorbar(sc, ax=ax2, label="objective lse(ln f_i), best over radius (<= 0 needed)")
    jp, jt, _ = d["joints"]
    ax2.plot(np.degrees(jp), np.degrees(jt), "o", mfc="white", mec="black", ms=9, label="lamp")
    ax2.set_xlabel("rig pan [deg]")
    ax2.set_ylabel("rig tilt [deg]")
    ax2.set_title("overall cost over the rig's candidates", fontsize=10)
    ax2.legend(loc="lower right", fontsize=8)
    fig.subplots_adjust(**_MARGINS_WIDE)
    return fig


def draw_plan_pictures(data, out_dir, names=PICTURES):
    """Draw the pictures of `picture_data` (those of PICTURES in `names`) into out_dir; return
    their paths."""
    out_dir = Path(out_dir)
    az, el = data["azimuth_deg"], data["elevation_deg"]
    extent = [az[0], az[-1], el[0], el[-1]]
    paths = []
    for name, draw in zip(PICTURES, (_visibility_brdf, _regions, _cost)):
        if name not in names:
            continue
        path = out_dir / name
        draw(data, extent).savefig(path, dpi=DPI, pil_kwargs=PNG)
        paths.append(path)
    return paths


def write_plan_pictures(plan, task, scene, out_dir, worker=None):
    """Write visibility_brdf.png, regions.png and cost.png into out_dir; return their paths.
    With a started PictureWorker the worker draws them; if it cannot, this process does."""
    data = picture_data(plan, task, scene)
    if worker is not None and worker.draw(data, out_dir):
        return [Path(out_dir) / name for name in PICTURES]
    return draw_plan_pictures(data, out_dir)


class PictureWorker:
    """A forked process that imports matplotlib while this one plans, then draws the pictures of
    the plan sent to `draw` (cost.png in a second fork, beside the other two). Start it before
    planning, as a context manager. `draw` returns False when the worker did not draw them all
    (no fork here, it failed, it timed out): the caller then draws them itself, so a drawing
    error is raised there."""

    TIMEOUT_S = 120.0

    def __init__(self):
        self._pid = self._payload = self._done = None
        if not hasattr(os, "fork"):
            return
        payload_r, payload_w = os.pipe()
        done_r, done_w = os.pipe()
        sys.stdout.flush()
        sys.stderr.flush()
        try:
            with warnings.catch_warnings():
                # Python >= 3.12 warns of fork() beside other threads (here BLAS pools, asleep);
                # the worker uses no BLAS, and draw() has a timeout and a fallback.
                warnings.simplefilter("ignore", DeprecationWarning)
                pid = os.fork()
        except OSError:
            pid = None
        if pid == 0:                                    # the worker: never returns
            code = 1
            try:
                os.close(payload_w)
                os.close(done_r)
                code = _work(payload_r, done_w)
            except BaseException:                       # the caller draws (and reports) instead
                pass
            finally:
                os._exit(code)
        os.close(payload_r)
        os.close(done_w)
        if pid is None:
            os.close(payload_w)
            os.close(done_r)
            return
        self._pid, self._payload, self._done = pid, payload_w, done_r

    def draw(self, data, out_dir):
        """Send one plan's `picture_data`; True once the worker has written all the pictures."""
        if self._pid is None:
            return False
        deadline = time.monotonic() + self.TIMEOUT_S

        def wait(fd, event):
            poll = select.poll()
            poll.register(fd, event)
            if not poll.poll(max(0.0, deadline - time.monotonic()) * 1e3):
                raise TimeoutError("picture worker")

        blob = memoryview(pickle.dumps((data, os.path.abspath(out_dir)), pickle.HIGHEST_PROTOCOL))
        try:
            os.set_blocking(self._payload, False)
            while blob:                                 # read once the worker has matplotlib
                wait(self._payload, select.POLLOUT)
                blob = blob[os.write(self._payload, blob):]
            os.close(self._payload)
            self._payload = None
            wait(self._done, select.POLLIN)
            drawn = os.read(self._done, 1) == b"1"      # b"" if the worker failed
        except OSError:                                 # TimeoutError, BrokenPipeError
            drawn = False
        if drawn:                                       # it is exiting: reap it
            pid, self._pid = self._pid, None
            _reap(pid)
        self.close()
        return drawn

    def close(self):
        """Stop the worker if it still runs (the plan failed, or it timed out) and reap it."""
        for fd in (self._payload, self._done):
            if fd is not None:
                os.close(fd)
        self._payload = self._done = None
        pid, self._pid = self._pid, None
        if pid is not None:
            _reap(pid, kill=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _reap(pid, kill=False):
    try:
        if kill:
            os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):     # reaped already (SIGCHLD ignored)
        pass


def _work(payload_fd, done_fd):
    """The worker: import matplotlib, read the payload, draw cost.png in a forked helper and the
    other two here; exit code 0 and b"1" on done_fd once all three are written."""
    for module in ("matplotlib.figure", "matplotlib.backends.backend_agg", "matplotlib.colors"):
        importlib.import_module(module)                 # now, while the caller plans
    with os.fdopen(payload_fd, "rb") as f:
        blob = f.read()
    if not blob:
        return 0
    data, out_dir = pickle.loads(blob)
    worker = os.getpid()
    helper = os.fork()
    if helper == 0:
        code = 1
        try:
            _die_with_parent()
            if os.getppid() != worker:
                raise ChildProcessError("picture worker gone")
            draw_plan_pictures(data, out_dir, ["cost.png"])
            code = 0
        finally:
            os._exit(code)
    try:
        draw_plan_pictures(data, out_dir, ["visibility_brdf.png", "regions.png"])
    finally:                                            # never leave it writing behind us
        helper_failed = os.waitpid(helper, 0)[1] != 0
    if helper_failed:
        return 1
    os.write(done_fd, b"1")
    return 0


def _die_with_parent():
    """Linux: be killed when the parent process dies (stopped worker: no helper left drawing)."""
    try:
        import ctypes
        ctypes.CDLL(None).prctl(1, signal.SIGKILL)     # PR_SET_PDEATHSIG
    except (OSError, AttributeError):                   # not Linux: the helper ends by itself
        pass
