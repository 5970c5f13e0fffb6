"""Command-line input every command shares: a bad --out is one line and exit 2, before any work;
a task that fails to load leaves no folder behind; runs never mix in one folder."""
import json
from pathlib import Path

import pytest

from cell.cli import create_folder, main, output_folder

HINGE = str(Path(__file__).resolve().parent.parent / "tasks" / "hinge.yaml")
# the commands that write a folder, each as `cell COMMAND ... TASK`
FOLDER_COMMANDS = [["plan"], ["run"], ["calibrate", "reference-part"],
                   ["calibrate", "camera-constant", "--laser-power-w", "2e-10"], ["bench", "--quick"]]
ids = lambda c: "-".join(c[:2]) if c[0] == "calibrate" else c[0]          # noqa: E731


def one_line_naming_out(capsys):
    """stderr is one line about --out, stdout is empty and nothing was planned."""
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and "--out" in err and "Traceback" not in err
    assert out == "" and "maps:" not in err
    return err


@pytest.mark.parametrize("command", FOLDER_COMMANDS, ids=ids)
def test_an_out_that_is_a_file_is_bad_input_before_any_work(command, tmp_path, capsys):
    taken = tmp_path / "taken"
    taken.write_text("not a folder")
    assert main([*command, HINGE, "--out", str(taken)]) == 2
    err = one_line_naming_out(capsys)
    assert str(taken) in err and "a folder" in err


@pytest.mark.parametrize("command", FOLDER_COMMANDS, ids=ids)
def test_an_out_below_a_file_cannot_be_created_and_is_bad_input_before_any_work(command, tmp_path, capsys):
    (tmp_path / "taken").write_text("not a folder")
    inside = tmp_path / "taken" / "run"
    assert main([*command, HINGE, "--out", str(inside)]) == 2
    err = one_line_naming_out(capsys)
    assert str(inside) in err and "a folder that can be created" in err and "is a file" in err


@pytest.mark.parametrize("command", FOLDER_COMMANDS, ids=ids)
def test_an_empty_out_is_bad_input_not_the_default_folder(command, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main([*command, HINGE, "--out", ""]) == 2
    err = one_line_naming_out(capsys)
    assert err == (f"cell {command[0]}: command line: --out: found '', "
                   "expected a folder path (an empty --out names no folder)\n")
    assert list(tmp_path.iterdir()) == []                      # no runs/ in the current folder


@pytest.mark.parametrize("command", FOLDER_COMMANDS, ids=ids)
def test_an_existing_folder_that_is_not_empty_is_refused_and_left_as_it_was(command, tmp_path, capsys):
    old = tmp_path / "old"
    old.mkdir()
    (old / "log.jsonl").write_text('{"step": "done"}\n')
    assert main([*command, HINGE, "--out", str(old)]) == 2
    err = one_line_naming_out(capsys)
    assert f"found {old}, a folder that exists and is not empty" in err and "pass another --out" in err
    assert [p.name for p in old.iterdir()] == ["log.jsonl"]
    assert (old / "log.jsonl").read_text() == '{"step": "done"}\n'


@pytest.mark.parametrize("command", FOLDER_COMMANDS, ids=ids)
@pytest.mark.parametrize("given", [True, False], ids=["--out", "default"])
def test_a_task_that_fails_to_load_leaves_no_folder(command, given, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: no part, no feature\n")
    tasks = [HINGE, str(bad)] if command[0] == "bench" else [str(bad)]     # bench: the second is bad
    out = ["--out", str(tmp_path / "new")] if given else []
    assert main([*command, *tasks, *out]) == 2
    err = capsys.readouterr().err
    assert err == f"cell {command[0]}: {bad}: part: found nothing, expected a mapping of keys (required section)\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]  # neither new/ nor runs/


def test_a_second_plan_into_the_same_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "plan"
    assert main(["plan", HINGE, "--out", str(out)]) == 0
    first = (out / "plan.json").read_text()
    capsys.readouterr()
    assert main(["plan", HINGE, "--out", str(out)]) == 2
    assert "exists and is not empty" in one_line_naming_out(capsys)
    assert (out / "plan.json").read_text() == first and json.loads(first)["feasible"]


def test_an_existing_empty_folder_is_used_and_a_new_one_created_only_when_asked(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert create_folder(output_folder(str(empty), "x")) == empty
    new = output_folder(str(tmp_path / "a" / "b"), "x")
    assert not (tmp_path / "a").exists()                    # checked, not created
    assert create_folder(new).is_dir()


def test_the_default_folders_are_new_every_time(tmp_path, monkeypatch):
    """Without --out every command writes a folder of its own, runs/<name>-<time>, never an old one."""
    monkeypatch.chdir(tmp_path)
    first = output_folder(None, "hinge-plan")
    assert first.parent == Path("runs") and first.name.startswith("hinge-plan-") and not first.exists()
    (create_folder(first) / "plan.json").write_text("{}")
    second = create_folder(output_folder(None, "hinge-plan"))
    assert second != first and second.parent == Path("runs") and list(second.iterdir()) == []


def test_cell_check_loads_no_plotting_or_device_library():
    """The CLI imports a command's module only when it runs: checking a task needs Warp (the
    feature patch is laid onto the surface as the planner does) but no matplotlib, OpenCV or device
    SDK (a fresh interpreter, so other tests' imports do not count)."""
    import subprocess
    import sys
    heavy = ("matplotlib", "cv2", "dynamixel_sdk", "rtde_control", "rtde_receive", "harvesters", "genicam")
    code = (f"import sys; from cell.cli import main; assert main(['check', {HINGE!r}]) == 0; "
            f"print([m for m in {heavy!r} if m in sys.modules])")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_cell_check_refuses_a_patch_over_the_parts_edge_as_cell_plan_would(tmp_path, capsys):
    """Centred on the hinge leaf's edge (x = 30 mm), half the patch lies beyond it: `cell check`
    lays the patch onto the surface as the planner does, so it is one line and exit 2 here too."""
    from simcell import variant
    task = variant(tmp_path, Path(HINGE), {"feature.center_m": [0.030, 0.0, 0.004]})
    assert main(["check", str(task)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "feature.center_m" in err[0] and "runs over an edge of the part" in err[0]


def test_cell_check_reports_how_far_a_curved_patch_bends(capsys):
    """The sphere cap's feature (tests/tasks, sphere of R = 30 mm): the patch is the surface within
    r = 6 mm (3D distance) of its centre, so its rim lies r^2 / (2 R) = 0.6 mm below the tangent
    plane (chord^2 = 2 R h). The mesh's facets are 0.7 mm wide (tasks/make_parts.py), so the centre
    face's normal may tilt by up to half a facet's angle, 0.35 / 30 rad: r times that more at most."""
    path = Path(__file__).parent / "tasks" / "sphere_paint_wide.yaml"
    assert main(["check", str(path)]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("patch")][0]
    sag_mm = float(line.split("within ")[1].split(" mm")[0])
    r, R = 6.0, 30.0
    assert 0.98 * r**2 / (2 * R) <= sag_mm <= r**2 / (2 * R) + r * 0.35 / R + 0.005, line


def test_version_prints_the_installed_distributions_version(capsys):
    from importlib import metadata
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"cell {metadata.version('lightplan-cell')}"


def test_help_opens_with_a_sentence_for_a_user(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    opening = out.split("\n\n")[1]                     # after the usage line
    assert opening.startswith("Plan where the lamp goes") and "Error" not in opening and "`" not in opening
    assert "exit status: 0 done" in out


# --- the real cell's settings, checked before any work (issue 29, item 2) ---------------------

# each cell-section problem --backend hw refuses: the change to the hinge, the key and what was found
HW_PROBLEMS = [({"cell.backend": "hw"}, "cell.arm.host", "found nothing, expected the robot's address"),
               ({"cell.backend": "hw", "cell.arm.host": "127.0.0.1"}, "cell.pan_tilt.port",
                "found nothing, expected the servos' serial port"),
               ({"cell.backend": "hw", "cell.arm.host": "127.0.0.1", "cell.pan_tilt.port": "/dev/ttyUSB0",
                 "cell.lighting": {"driver": "gardasoft"}}, "cell.lighting.host",
                "found nothing, expected the lighting controller's address")]
HW_COMMANDS = [["run", "--backend", "hw"], ["measure-brdf", "--backend", "hw"],
               ["calibrate", "reference-part", "--backend", "hw"]]


@pytest.mark.parametrize("changes, key, said", HW_PROBLEMS, ids=lambda v: v if isinstance(v, str) and
                         v.startswith("cell.") else None)
def test_cell_check_refuses_what_the_real_cell_would(changes, key, said, tmp_path, capsys):
    from simcell import variant
    task = variant(tmp_path, Path(HINGE), changes)
    assert main(["check", str(task)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == f"cell check: {task}: {key}: {said}" + err.split(said, 1)[1]
    assert err.count("\n") == 1 and "--backend hw" in err


@pytest.mark.parametrize("command", HW_COMMANDS, ids=lambda c: " ".join(c[:2]))
def test_backend_hw_without_the_robots_address_is_refused_before_planning_and_leaves_no_folder(
        command, tmp_path, monkeypatch, capsys):
    from simcell import variant
    from cell.planning import one_shot
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(one_shot, "plan", lambda *a, **k: pytest.fail("planned before the check"))
    task = variant(tmp_path, Path(HINGE), {})                  # backend sim in the task, hw by --backend
    assert main([*command, str(task), "--out", str(tmp_path / "run")]) == 2
    out, err = capsys.readouterr()
    assert err == (f"cell {command[0]}: {task}: cell.arm.host: found nothing, expected the robot's address "
                   f"(required for --backend hw; there is no default)\n"), err
    assert "maps:" not in out + err
    assert sorted(p.name for p in tmp_path.iterdir()) == [task.name]         # neither run/ nor runs/


@pytest.mark.parametrize("changes, key, said", HW_PROBLEMS, ids=lambda v: v if isinstance(v, str) and
                         v.startswith("cell.") else None)
def test_cell_check_backend_hw_refuses_what_cell_run_backend_hw_would_with_no_folder(
        changes, key, said, tmp_path, monkeypatch, capsys):
    """The task's backend sim, hw given on the command line: check and run say the same line."""
    from simcell import variant
    monkeypatch.chdir(tmp_path)
    task = variant(tmp_path, Path(HINGE), {k: v for k, v in changes.items() if k != "cell.backend"})
    assert main(["check", str(task)]) == 0                         # for the simulated cell it is complete
    capsys.readouterr()
    assert main(["check", str(task), "--backend", "hw"]) == 2
    out, checked = capsys.readouterr()
    assert out == "" and checked.startswith(f"cell check: {task}: {key}: {said}") and checked.count("\n") == 1
    assert main(["run", str(task), "--backend", "hw"]) == 2
    assert capsys.readouterr().err == checked.replace("cell check:", "cell run:", 1)
    assert sorted(p.name for p in tmp_path.iterdir()) == [task.name]         # no runs/ folder


def test_cell_check_of_a_task_for_the_real_cell_that_names_its_devices_passes(tmp_path, capsys):
    from simcell import variant
    task = variant(tmp_path, Path(HINGE), {"cell.backend": "hw", "cell.arm.host": "127.0.0.1",
                                           "cell.pan_tilt.port": "/dev/ttyUSB0"})
    assert main(["check", str(task)]) == 0                        # nothing is contacted by a check
    assert "cell         backend hw" in capsys.readouterr().out


def test_a_reader_that_goes_away_ends_the_command_quietly():
    """`cell check TASK | head`: the pipe closed before the command writes is exit 141 (SIGPIPE's,
    as a shell reports it) and no traceback."""
    import os
    import subprocess
    import sys
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run([sys.executable, "-m", "cell", "check", "tasks/hinge.yaml"], stdout=write,
                              stderr=subprocess.PIPE, text=True, timeout=300, cwd=Path(__file__).resolve().parents[1])
    finally:
        os.close(write)
    assert done.returncode == 141 and "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr


def test_of_several_tasks_one_whose_camera_the_arm_cannot_take_is_named_and_the_others_are_planned(tmp_path, capsys):
    """`cell plan A B` with B's fixed camera under the table (beyond the arm): A's plan is written and
    printed, B named with that cause and no folder, exit 1; --json gives B's verdict."""
    from simcell import variant
    under = variant(tmp_path, HINGE, {"camera.view_direction": [0.0, 0.0, -1.0]})
    assert main(["plan", HINGE, str(under), "--out", str(tmp_path / "plans")]) == 1
    out, err = capsys.readouterr()
    assert (tmp_path / "plans" / "hinge" / "plan.json").is_file()
    assert sorted(p.name for p in (tmp_path / "plans").iterdir()) == ["hinge"]
    assert "Aluminium hinge, leaf surface: feasible" in out
    refused = [line for line in out.splitlines() if "INFEASIBLE, not planned" in line]
    assert len(refused) == 1 and "where the arm cannot take it" in refused[0]
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"cell plan: infeasible: {under}: ") and "where the arm cannot take it" in last
    assert HINGE not in last                                # the feasible task is not named as a failure
    # --json's entry for it: plan.json's verdict keys
    from cell.cli.plan import plan_one, refused_json
    from cell.core.progress import Progress
    from cell.planning.parallel import SERIAL
    from cell.task.loader import load_task
    task = load_task(under)
    document = refused_json(task, plan_one(task, Progress.silent(), SERIAL))
    assert document["feasible"] is False and document["binding"] == "camera_reach"
    assert document["task"] == task.name and "where the arm cannot take it" in document["hint"]
