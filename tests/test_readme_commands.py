"""Every command of the README's commands table, run on the examples as a new user runs them (no
--out, the calibrations' defaults) in a copy of the checkout's tasks under git: afterwards `git
status` is clean, so no command writes into the examples' folder (issue 29, item 4), and no line
they print holds what a person should not have to read (issue 29's done-when: a raw objective
value, "1e+30", a library's source path, OpenCV's "[ WARN"). Minutes of work: marked slow
(`pytest -m slow`)."""
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_plain_output import RAW

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def table_commands():
    """The `cell X` (or `cell calibrate X`) of each row of the README's commands table."""
    text = (ROOT / "README.md").read_text()
    table = text[text.index("## Commands"):text.index("## Output folders")]
    return {" ".join(m.group(1).split()[:3 if m.group(1).startswith("cell calibrate") else 2])
            for m in re.finditer(r"^\| `(cell [^`]*)`", table, re.M)}


# what no printed line may hold: test_plain_output's planner's internal words ("max f_i"), library
# warnings, tracebacks and source paths, and a raw objective value ("binding depth_of_field = 1"), the
# planner's 1e+30, a huge number ("= 1.014e+304", a gray of 430 digits) or a library's folder. A number
# in exponent form itself is fine here: the camera constant is one (c = 1.5e+16 1/(W s)).
NOT_FOR_PEOPLE = [(pattern, why) for pattern, why in RAW if why in (
    "the planner's internal words", "a library's warning or a traceback", "a source path")] + [
    (re.compile(r"binding \w+ = \S|\b1e\+30\b|e\+\d{3}|\d{25,}|site-packages/"),
     "a raw objective value, 1e+30, a huge number or a library's folder")]


def git(clone, *args):
    return subprocess.run(["git", *args], cwd=clone, capture_output=True, text=True, check=True).stdout


def test_every_readme_command_leaves_the_examples_folder_as_it_was(tmp_path):
    clone = tmp_path / "checkout"
    shutil.copytree(ROOT / "tasks", clone / "tasks", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / ".gitignore", clone / ".gitignore")
    git(clone, "init", "-q")
    git(clone, "add", "-A")
    git(clone, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "the examples")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def cell(*args, codes=(0,)):
        done = subprocess.run([sys.executable, "-m", "cell", *args], cwd=clone, env=env, capture_output=True,
                              text=True, timeout=900)
        assert done.returncode in codes, (args, done.stdout[-2000:], done.stderr[-2000:])
        printed.extend((" ".join(args[:2]), line) for line in (done.stdout + done.stderr).splitlines())
        return done

    printed = []
    hinge = "tasks/hinge.yaml"
    ran = []
    for args in (["check", hinge], ["plan", hinge], ["run", hinge], ["bench", "--quick"],
                 ["calibrate", "camera-constant", hinge, "--laser-power-w", "2e-10"],
                 ["calibrate", "camera-constant", hinge, "--laser-power-w", "2e-10"],   # again: its own folder
                 ["calibrate", "reference-part", hinge], ["measure-brdf", hinge],
                 ["calibrate", "hand-eye", hinge]):
        done = cell(*args)
        ran.append("cell " + " ".join(args[:2 if args[0] == "calibrate" else 1]))
        if args[:2] == ["calibrate", "camera-constant"]:
            line = next(x for x in done.stdout.splitlines() if "camera.yaml: to use it" in x)
            assert re.search(r"wrote runs/hinge-calibration-[\d-]+/camera\.yaml: to use it, write camera: "
                             r"\{sensor: \.\./runs/hinge-calibration-[\d-]+/camera\.yaml, \.\.\.\} in tasks/hinge.yaml",
                             line), line
    csv = sorted(clone.glob("runs/hinge-brdf-*/goniometer.csv"))[0]
    cell("fit-brdf", str(csv.relative_to(clone)), "--out", str(csv.parent.relative_to(clone) / "fit.yaml"))
    ran.append("cell fit-brdf")
    cell("hw-check", hinge, codes=(2,))                # the examples name no real device: bad input, nothing written
    ran.append("cell hw-check")
    assert set(ran) == table_commands()
    assert len(printed) > 50
    said = [(command, line, why) for command, line in printed for pattern, why in NOT_FOR_PEOPLE
            if pattern.search(line)]
    assert not said, said[:10]
    assert git(clone, "status", "--porcelain", "--ignored=no") == ""
    assert len(list(clone.glob("runs/hinge-calibration-*/camera.yaml"))) == 2
    assert len(list(clone.glob("runs/hinge-calibration-*/hand-eye.yaml"))) == 1
