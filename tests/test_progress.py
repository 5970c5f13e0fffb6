"""Progress a person can read (issue 29, item 7): off a terminal a stage says a plain line at each
quarter and one at its end, never a control character; on a terminal (a pseudo-terminal here) it
is one bar redrawn in place. `cell measure-brdf` both ways; the kernels' compile said once, and
nothing on a cached load."""
import fcntl
import io
import math
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

from cell.core.progress import Progress

import simcell
from test_goniometer import sim_task

ROOT = Path(__file__).resolve().parent.parent
CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f]")        # anything but a tab or a newline


def test_off_a_terminal_a_stage_of_183_says_its_quarters_and_its_end():
    out = io.StringIO()
    with Progress(out).stage("poses", 183) as stage:
        for _ in stage.each(range(183)):
            pass
    lines = out.getvalue().splitlines()
    # the first step at or past each quarter of 183: ceil(q * 183 / 4)
    quarters = [math.ceil(q * 183 / 4) for q in (1, 2, 3)]
    assert quarters == [46, 92, 138]
    assert lines[:3] == [f"poses: {n} of 183 ({100 * n // 183} %)" for n in quarters]
    assert len(lines) == 4 and re.fullmatch(r"poses: 183 of 183 in \d+\.\d s", lines[3])
    assert not CONTROL.search(out.getvalue())


def test_a_short_stage_says_only_its_end():
    out = io.StringIO()
    with Progress(out).stage("shutter sweep", 8) as stage:
        for _ in stage.each(range(8)):
            pass
    assert re.fullmatch(r"shutter sweep: 8 of 8 in \d+\.\d s\n", out.getvalue())


def test_a_stage_whose_total_grows_and_a_labelled_progress_close_once():
    out = io.StringIO()
    progress = Progress(out).labelled("hinge: ")
    stage = progress.stage("lamp searches", 10)
    stage.advance(3)
    stage.grow(10)
    progress.say("a line that stays")
    stage.advance(17)
    stage.close()
    stage.close()
    lines = out.getvalue().splitlines()
    # 3 of 10 is past its first quarter; the step to 20 of 20 is its end, said once
    assert lines[:2] == ["hinge: lamp searches: 3 of 10 (30 %)", "hinge: a line that stays"]
    assert len(lines) == 3 and re.fullmatch(r"hinge: lamp searches: 20 of 20 in \d+\.\d s", lines[2])


def terminal():
    """A pseudo-terminal (master, slave) 100 columns wide, as a person's terminal window is."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 100, 0, 0))
    return master, slave


def read_all(fd):
    """What a pseudo-terminal's master side reads until the other side closes."""
    chunks = []
    while True:
        ready, _, _ = select.select([fd], [], [], 120)
        if not ready:
            break
        try:
            chunk = os.read(fd, 65536)
        except OSError:                 # the slave side closed (Linux: EIO)
            break
        if not chunk:
            break
        chunks.append(chunk)
    return b"".join(chunks).decode("utf-8", "replace")


def test_on_a_terminal_a_stage_is_one_bar_redrawn_in_place():
    master, slave = terminal()
    with os.fdopen(slave, "w", encoding="utf-8") as tty:
        progress = Progress(tty)
        assert progress.terminal
        with progress.stage("poses", 50) as stage:
            for _ in stage.each(range(50)):
                pass
    shown = read_all(master)
    os.close(master)
    assert "\r" in shown and "poses" in shown and "50/50" in shown and "100%" in shown
    assert shown.count("\n") <= 2                           # one bar, not a line per step


def test_measure_brdf_off_a_terminal_says_a_few_plain_lines(tmp_path, capsys):
    from cell.cli import main
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10})
    assert main(["measure-brdf", str(task), "--out", str(tmp_path / "run")]) == 0
    err = capsys.readouterr().err
    poses = (tmp_path / "run" / "log.jsonl").read_text().count('"step": "pose"')
    assert poses >= 10                                      # each pose is in the log ...
    assert len(err.splitlines()) <= 12, err                 # ... the terminal has a few lines
    assert re.search(r"^poses: \d+ of \d+ in \d+\.\d s$", err, re.M) and not CONTROL.search(err)


def test_measure_brdf_on_a_terminal_shows_the_poses_bar(tmp_path):
    master, slave = terminal()
    task = sim_task(tmp_path, {"phase_deg": [40], "step_deg": 10})     # one phase angle, 10 deg steps
    done = subprocess.run([sys.executable, "-m", "cell", "measure-brdf", str(task), "--out", str(tmp_path / "run")],
                          stdout=subprocess.PIPE, stderr=slave, env={**os.environ, "PYTHONPATH": str(ROOT)},
                          timeout=300)
    os.close(slave)
    shown = read_all(master)
    os.close(master)
    assert done.returncode == 0, shown
    assert "\r" in shown and re.search(r"poses: +100%\|", shown), shown
    assert "pose 3 of" not in shown                         # the steps are the log's, not lines


COMPILED = r"compiling the lighting kernels \(first use after install, ~7 s\) \.\.\. done in \d+\.\d s"


def test_a_cached_kernel_load_says_nothing():
    """Two processes start Warp and load a kernel module: the first may compile (one line), the
    second finds every kernel in the disk cache and says nothing."""
    code = "import kernels.visibility; from kernels.runtime import ensure_init; ensure_init('kernels.visibility')"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    said = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600).stderr
            for _ in range(2)]
    assert said[0] == "" or re.fullmatch(COMPILED, said[0].strip()), said[0]
    assert said[1] == ""


@pytest.mark.long
def test_the_first_compile_is_said_once_with_its_time_and_a_cached_load_not(tmp_path):
    """In an empty Warp cache (WARP_CACHE_PATH) the first plan compiles the kernels: one line;
    the second plan finds them cached: none."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "WARP_CACHE_PATH": str(tmp_path / "warp")}
    task = simcell.variant(tmp_path, ROOT / "tasks" / "hinge.yaml", {})
    said = []
    for k in range(2):
        done = subprocess.run([sys.executable, "-m", "cell", "plan", str(task), "--out", str(tmp_path / f"p{k}")],
                              capture_output=True, text=True, env=env, timeout=600)
        assert done.returncode == 0, done.stderr
        said.append([line for line in done.stderr.splitlines() if "compiling" in line])
    assert len(said[0]) == 1 and re.fullmatch(COMPILED, said[0][0])
    assert said[1] == []


@pytest.mark.parametrize("terminal", [False, True])
def test_cell_bench_shows_a_stage_per_part_its_rows_lines_said_within(monkeypatch, terminal):
    """suite.run's parts each a stage of the Progress it is given (a step per task; a part with no
    task, none), the rows' own lines said as they come; the work itself stubbed: what is checked
    is what a person sees of it."""
    from types import SimpleNamespace
    from cell.bench import lights, multi_feature, scaling, suite, threads
    said = []

    def part(name, out):
        def work(*args):
            said.append(name)
            args[-1](f"{name} row")                       # the part's `say`
            return out
        return work
    monkeypatch.setattr(suite, "sweep_task", part("sweep", ([], {})))
    monkeypatch.setattr(suite, "kernel_rows", part("kernels", []))
    monkeypatch.setattr(threads, "run", part("threads", []))
    monkeypatch.setattr(multi_feature, "run", part("features", {"features": [], "workers": []}))
    monkeypatch.setattr(lights, "run", part("lights", {"kernels": [], "channels": []}))
    monkeypatch.setattr(scaling, "run", part("scaling", {"scaling": [], "scaling_summary": None}))
    monkeypatch.setattr(multi_feature, "targets", lambda rows, collisions=(): [])
    monkeypatch.setattr(lights, "targets", lambda rows: [])
    monkeypatch.setattr(scaling, "targets", lambda rows, summary: [])
    one = [SimpleNamespace(path=Path(f"{n}.yaml")) for n in ("hinge", "conrod")]
    out = io.StringIO()
    suite.run(one, True, Progress(out, terminal=terminal), [], [SimpleNamespace(path=Path("ring.yaml"))], many=True)
    assert said == ["sweep", "sweep", "kernels", "kernels", "threads", "lights", "scaling"]
    text = out.getvalue()
    stages = ["settings sweep", "kernel rates", "threads", "lights and channels", "many-feature scaling"]
    if terminal:                                                       # a bar each, the rows' lines above them
        assert all(f"{name}:" in text for name in stages) and "multi-feature" not in text
        assert all(f"{name} row" in text for name in said)
    else:
        lines = [line for line in text.splitlines() if " row" not in line]
        assert [re.sub(r" in [\d.]+ s$", "", line) for line in lines] == [
            "settings sweep: 2 of 2", "kernel rates: 2 of 2", "threads: 1 of 1", "lights and channels: 1 of 1",
            "many-feature scaling: 1 of 1"]
        assert text.index("sweep row") < text.index("settings sweep: 2 of 2") < text.index("kernels row")
        assert not CONTROL.search(text)
