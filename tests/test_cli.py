"""Command-line input every command shares: a bad --out is one line and exit 2, before any work."""
from pathlib import Path

import pytest

from cell.cli import main

HINGE = str(Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml")


@pytest.mark.parametrize("command", [["plan", HINGE], ["run", HINGE], ["calibrate", HINGE],
                                     ["bench", "--quick", HINGE]], ids=lambda c: c[0])
def test_an_out_that_is_a_file_is_bad_input_before_any_work(command, tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("not a folder")
    assert main([*command, "--out", str(taken)]) == 2
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and "--out" in err and str(taken) in err and "a folder" in err
    assert out == "" and "maps:" not in err                    # nothing was planned


def test_cell_check_loads_no_kernel_plotting_or_device_library():
    """The CLI imports a command's module only when it runs: checking a task needs no Warp,
    matplotlib, OpenCV or device SDK (a fresh interpreter, so other tests' imports do not count)."""
    import subprocess
    import sys
    heavy = ("warp", "matplotlib", "cv2", "dynamixel_sdk", "rtde_control", "rtde_receive")
    code = (f"import sys; from cell.cli import main; assert main(['check', {HINGE!r}]) == 0; "
            f"print([m for m in {heavy!r} if m in sys.modules])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"
