"""cell.html, the cell in 3D (cell.report.cell_view): written beside cell.png by `cell plan` (and so
by every run, through the same write_plan), self-contained (plotly.js inside, no script fetched
from the network), every body of the collision scene named at every shot, and it renders in
Debian's headless Chromium with no error on the page's console."""
import re
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import pytest

from cell import cli
from cell.collision.scene import ARM_LINKS
from cell.planning.whole_part import plan_features
from cell.report.cell_view import write_cell_view
from cell.task.loader import load_task

ROOT = Path(__file__).resolve().parent.parent
MAX_BYTES = 8_000_000          # plotly.js is ~4.7 MB; the part, thinned, and the shots a few hundred kB


@pytest.fixture(scope="module")
def planned():
    """The hinge's, the bracket's and the ring's (two ring lights besides the spot) tasks with their
    plans, made once: the bracket's takes seconds."""
    out = {}
    for name in ("hinge", "bracket", "ring"):
        task = load_task(ROOT / "tasks" / f"{name}.yaml")
        out[name] = task, plan_features(task)
    return out


def expected_names(task, plan):
    """Every body, feature and light the view must name: the part (and fixture), each feature,
    each fixed light's housing (its collision body: a ring's drawn once), and at each shot the arm's links, the
    camera body, its frustum, the lamp's body and cone, the pan-tilt's links (the tilt servo; its
    arm where cell.collision.rig_reach_m declares the rig's reach) and the task's other lights;
    the route when there are several shots."""
    names = {"part", *(f"feature {f.name}" for f in task.features)}
    names |= {light.name for light in task.lights if light.mount == "fixed"}
    if task.cell.collision.fixture is not None:
        names.add("fixture")
    for k, shot in enumerate(plan.shots):
        names |= {f"shot {k} {body}" for body in ("camera_body", "frustum", "lamp_body", "lamp cone", "tilt_servo")}
        if task.cell.collision.rig_reach_m is not None:
            names.add(f"shot {k} rig_arm")
        names |= {f"shot {k} {link}" for link, _ in ARM_LINKS}
        names |= {f"shot {k} light {light.name}" for light in task.lights}
    return names


def test_cell_plan_of_the_hinge_writes_cell_html_beside_cell_png(tmp_path):
    out = tmp_path / "out"
    assert cli.main(["plan", str(ROOT / "tasks" / "hinge.yaml"), "--out", str(out)]) == 0
    assert (out / "cell.png").exists()
    html = (out / "cell.html").read_text()
    assert html.startswith("<!doctype html>") and "plotly.js" in html


@pytest.mark.parametrize("name", ["hinge", "bracket", "ring"])
def test_the_view_names_every_body_at_every_shot_and_loads_nothing_from_the_network(planned, name, tmp_path):
    task, plan = planned[name]
    view = write_cell_view(tmp_path / "cell.html", plan, task)
    html = view.path.read_text()
    missing = expected_names(task, plan) - set(view.names)
    assert not missing, f"not drawn: {sorted(missing)}"
    for trace in view.names:
        assert f'"name":"{trace}"' in html.replace("\\u0027", "'")
    assert not re.search(r"<script[^>]*\bsrc\s*=\s*[\"']?(https?:)?//", html), "a script fetched from the network"
    assert not re.search(r"<link[^>]*\bhref\s*=\s*[\"']?(https?:)?//", html)
    assert view.path.stat().st_size < MAX_BYTES
    if len(plan.shots) > 1:
        assert any(n.startswith("route (") for n in view.names)
    for k, shot in enumerate(plan.shots):      # a light off at a shot is drawn dim, one on bright
        for setting in shot.lights[1:]:
            trace = html.index(f'"name":"shot {k} light {setting.name}"')
            start = html.rindex('{"hovertemplate"', 0, trace)
            assert ('"#ffe14d"' if setting.drive > 0 else '"#8c8c8c"') in html[start:trace]


def test_a_declared_rig_reach_draws_the_pan_tilt_s_arm_at_every_shot(planned, tmp_path):
    """The hinge's plan drawn for its task with cell.collision.rig_reach_m: the servo stands at
    the reach and the rig's arm joins it to the lamp, named at every shot in the lamp's colour."""
    task, plan = planned["hinge"]
    long = replace(task, cell=replace(task.cell, collision=replace(task.cell.collision, rig_reach_m=0.69)))
    view = write_cell_view(tmp_path / "cell.html", plan, long)
    assert not expected_names(long, plan) - set(view.names)
    html = view.path.read_text()
    for k in range(len(plan.shots)):
        trace = html.index(f'"name":"shot {k} rig_arm"')
        assert '"#ffcc33"' in html[html.rindex('{"hovertemplate"', 0, trace):trace]


def chromium():
    """Debian's Chromium (package chromium), or chromium-headless-shell, or None."""
    return next((shutil.which(b) for b in ("chromium", "chromium-headless-shell") if shutil.which(b)), None)


# First in <head>: every console.error, uncaught error and unhandled rejection of the page kept, and
# written into the page once it has drawn, where --dump-dom reads it.
PROBE = """<script>
window.__errors = [];
const __error = console.error.bind(console);
console.error = (...a) => { window.__errors.push("console.error: " + a.join(" ")); __error(...a); };
window.addEventListener("error", e => window.__errors.push("error: " + e.message));
window.addEventListener("unhandledrejection", e => window.__errors.push("rejection: " + e.reason));
window.addEventListener("load", () => setTimeout(() => {
  const pre = document.createElement("pre"); pre.id = "probe";
  pre.textContent = JSON.stringify(window.__errors); document.body.appendChild(pre); }, 3000));
</script>"""


@pytest.mark.long             # 25-40 s a page; where Chromium is absent it skips anyway
@pytest.mark.parametrize("name", ["hinge", "bracket"])
def test_cell_html_renders_in_headless_chromium_with_no_console_error(planned, name, tmp_path):
    binary = chromium()
    if binary is None:
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium): cell.html's rendering unchecked")
    task, plan = planned[name]
    view = write_cell_view(tmp_path / "cell.html", plan, task)
    probed = tmp_path / "probed.html"
    probed.write_text(view.path.read_text().replace("<head>", "<head>" + PROBE, 1))
    run = subprocess.run(
        [binary, "--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=15000", "--window-size=1400,900",
         "--dump-dom", probed.as_uri()], capture_output=True, text=True, timeout=180)
    dom = run.stdout
    found = re.search(r'<pre id="probe">(.*?)</pre>', dom, re.S)
    assert found, f"the page never finished loading:\n{run.stderr[-2000:]}"
    assert found.group(1) == "[]", f"console errors: {found.group(1)}"
    assert 'class="gl-container"' in dom and "<canvas" in dom, "plotly drew no 3D scene"
    assert "<p>WebGL is not supported" not in dom
    shown = set(re.findall(r'class="legendtext"[^>]*data-unformatted="([^"]*)"', dom))
    assert {"part", *(f"feature {f.name}" for f in task.features)} <= {s.replace("&#39;", "'") for s in shown}


def test_a_runs_route_is_drawn_in_its_order_and_said_not_to_be_a_checked_path(planned, tmp_path):
    task, plan = planned["bracket"]
    view = write_cell_view(tmp_path / "cell.html", plan, task, order=(2, 0, 1))
    route = [n for n in view.names if n.startswith("route (")]
    assert route == ["route (the route's order; straight, not collision-checked)"]
    html = view.path.read_text()
    assert all(f"stop {n + 1}: shot {k}" in html for n, k in enumerate((2, 0, 1)))


def test_a_plans_checked_moves_are_drawn_through_their_via_points_instead_of_straight_lines(planned, tmp_path):
    """Moves as cell.run.moves gives them (here two of the bracket's shots, the second through
    two via points above them): each drawn through its corners, named with its clearance."""
    import base64
    import json
    from dataclasses import replace

    import numpy as np

    from cell.collision.paths import HOME, Move
    from cell.collision.scene import Clearance
    task, plan = planned["bracket"]
    a, b = (plan.shots[k].T_cell_cam for k in (0, 1))
    up = [T.copy() for T in (a, b)]
    for T in up:
        T[2, 3] += 0.1
    moves = (Move(HOME, 0, Clearance(0.05, ("camera_body", "wrist_1"), 0.01), (), 3, (np.zeros(3), a[:3, 3])),
             Move(0, 1, Clearance(0.02, ("fixture", "camera_body"), 0.01), tuple(up), 9,
                  tuple(T[:3, 3] for T in (a, *up, b))))
    view = write_cell_view(tmp_path / "cell.html", replace(plan, moves=moves), task)
    paths = [n for n in view.names if n.startswith("path ")]
    assert paths == ["path home to shot 0: collision-checked, clearance 50.0 mm (camera_body and wrist_1), "
                     "0 via points",
                     "path shot 0 to shot 1: collision-checked, clearance 20.0 mm (fixture and camera_body), "
                     "2 via points"]
    assert not any(n.startswith("route (") for n in view.names)          # no straight stand-in
    html = view.path.read_text()          # plotly stores the trace's x as base64 float64
    drawn = re.search(r'"name":"path shot 0 to shot 1[^"]*","x":\{"dtype":"f8","bdata":"([^"]*)"', html)
    x = np.frombuffer(base64.b64decode(json.loads(f'"{drawn.group(1)}"')), float)
    assert np.allclose(x, [a[0, 3], up[0][0, 3], up[1][0, 3], b[0, 3]])
