"""Every command quoted on the README's first screen (what comes before its contents) holds as
written (issue 29, item 8), checked cheaply: each `&&`-joined step's program exists and takes the
options given (its own `--help`, or for `cell` its own parser), the files and extras it names
exist, and a task it names loads. Running them whole (a fresh install, the suite) is
tests/test_readme_commands.py's (`pytest -m slow`) and CI's."""
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from cell.cli import build_parser
from cell.task.loader import load_task

ROOT = Path(__file__).resolve().parents[1]


def first_screen_commands():
    """The README's indented command lines before its contents, each split into its `&&` steps."""
    text = (ROOT / "README.md").read_text()
    screen = text[:text.index("## Contents")]
    lines = re.findall(r"^    (\S.*)$", screen, re.M)
    return [[shlex.split(step) for step in line.split(" && ")] for line in lines]


def options(argv):
    """The options of a step (`-e`, `--flag`, `-q`), their values left out."""
    return [a.split("=")[0] for a in argv if a.startswith("-") and a != "-m"]


def help_text(*program):
    done = subprocess.run([*program, "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, (program, done.stderr)
    return done.stdout


def test_the_first_screen_quotes_the_two_commands_a_new_user_runs():
    commands = first_screen_commands()
    assert len(commands) == 2
    assert [step[0] for step in commands[0]] == ["python3", ".", "pip", "cell"]
    assert [step[0] for step in commands[1]] == ["python3", ".", "pip", "pytest"]


@pytest.mark.parametrize("line", range(2))
def test_each_step_of_a_first_screen_command_names_what_exists(line):
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    venv = None
    for step in first_screen_commands()[line]:
        program, args = step[0], step[1:]
        if program == "python3":
            assert args[:2] == ["-m", "venv"] and len(args) == 3, step
            help_text(sys.executable, "-m", "venv")
            venv = args[2]
        elif program == ".":
            assert venv is not None and args == [f"{venv}/bin/activate"], step   # the script venv makes
        elif program == "pip":
            assert args[0] == "install", step
            said = help_text(sys.executable, "-m", "pip", "install")
            for option in options(args[1:]):
                assert re.search(rf"(^|[\s,]){re.escape(option)}[\s,<]", said, re.M), (option, step)
            target = args[-1]
            path, _, extra = target.partition("[")
            assert (ROOT / path / "pyproject.toml").is_file(), step
            for name in filter(None, extra.rstrip("]").split(",")):
                assert name in extras, (name, sorted(extras))
        elif program == "pytest":
            said = help_text(sys.executable, "-m", "pytest")
            for option in options(args):
                assert re.search(rf"(^|[\s,]){re.escape(option)}[\s,]", said, re.M), (option, step)
        elif program == "cell":
            parsed = build_parser().parse_args(args)          # an unknown option or command exits 2
            task = getattr(parsed, "task", None)
            assert task is not None and load_task(ROOT / task).name, step
        else:
            pytest.fail(f"the README's first screen runs {program!r}, which this test does not know: teach it")
