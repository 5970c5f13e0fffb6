"""`gray_band: any` (issue 25): a feature with declared defects where only their contrast
matters. The loader takes the sensor's range for the band (cell.task.loader.any_band) and refuses
`any` on a feature without defects; the exposure rises to that range's top, where no smaller
exposure of the same lights shows the defect better."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from cell.cli import check
from cell.core.errors import TaskError
from cell.planning import defects, evaluate, one_shot
from cell.task.loader import load_task

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_defects import SCRATCH, problem_at, task_file  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
TASKS = ROOT / "tasks"


def any_task(tmp_path, defects_yaml=(SCRATCH,), sensor=None, name="task.yaml"):
    """The hinge task with these defects, `gray_band: any` and these camera.sensor keys."""
    path = task_file(tmp_path, list(defects_yaml), name=name)
    doc = yaml.safe_load(path.read_text())
    doc["requirements"]["gray_band"] = "any"
    if not defects_yaml:
        del doc["feature"]["defects"]
    doc["camera"]["sensor"].update(sensor or {})
    path.write_text(yaml.safe_dump(doc))
    return path


def test_any_loads_as_the_sensor_s_range_from_its_datasheet_keys(tmp_path):
    task = load_task(any_task(tmp_path, sensor={"system_gain_dn_per_e": 0.05, "dark_noise_e": 6.0,
                                                "black_level": 4.0}))
    req = task.requirements
    assert req.gray_any and req.gray_band == pytest.approx((4.0 + 3 * 0.05 * 6.0, 2**8 - 2))
    assert "requirements gray any (4.9..254, the sensor range)" in check.summarize(task)
    plain = load_task(task_file(tmp_path, [SCRATCH], name="plain.yaml")).requirements
    assert not plain.gray_any and plain.gray_band == (100.0, 125.0)


def test_any_without_defects_is_refused_naming_the_key_in_one_line(tmp_path):
    path = any_task(tmp_path, defects_yaml=())
    with pytest.raises(TaskError) as err:
        load_task(path)
    assert err.value.key == "requirements.gray_band" and "needs the feature's `defects`" in str(err.value)
    run = subprocess.run([sys.executable, "-m", "cell", "check", str(path)], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 2 and "requirements.gray_band: found any" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr


def test_a_feature_s_own_any_without_defects_names_that_feature_s_key(tmp_path):
    path = task_file(tmp_path, [SCRATCH])
    doc = yaml.safe_load(path.read_text())
    feature = doc.pop("feature")
    bare = {k: v for k, v in feature.items() if k != "defects"}
    doc["features"] = [{"name": "leaf", **feature}, {"name": "bare", **bare, "requirements": {"gray_band": "any"}}]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(TaskError) as err:
        load_task(path)
    assert err.value.key == "features[1].requirements.gray_band"


def test_another_text_is_refused_as_neither_a_band_nor_any(tmp_path):
    path = any_task(tmp_path)
    path.write_text(path.read_text().replace("gray_band: any", "gray_band: all"))
    with pytest.raises(TaskError) as err:
        load_task(path)
    assert err.value.key == "requirements.gray_band" and "an ascending pair of gray levels, or any" in str(err.value)


POSES = [(30.0, 50.0, 0.15), (90.0, 60.0, 0.15), (180.0, 40.0, 0.15), (0.0, 30.0, 0.3)]


@pytest.fixture(scope="module")
def problems(tmp_path_factory):
    folder = tmp_path_factory.mktemp("any")
    band = load_task(task_file(folder, [SCRATCH], name="band.yaml"))
    anything = load_task(any_task(folder, name="any.yaml"))
    return problem_at(band)[0], problem_at(anything)[0]


@pytest.mark.parametrize("pan, tilt, radius", POSES)
def test_at_a_lamp_pose_any_shows_the_defect_at_least_as_well_as_the_band(problems, pan, tilt, radius):
    """The band's exposures are among those `any` allows (its band lies inside the sensor's
    range): `any`'s worst CNR is at least the band's, and no shorter exposure of the same light
    beats it (the brute-force scan of one channel's exposures: CNR grows with the exposure)."""
    band, anything = problems
    joints = (np.radians(pan), np.radians(tilt), radius)
    c_band, _ = one_shot.lighting(band, joints)
    c_any, d_any = one_shot.lighting(anything, joints)
    (cnr_band,), (cnr_any,) = ([j.predicted_cnr for j in defects.judge(p, c)]
                               for p, c in ((band, c_band), (anything, c_any)))
    assert cnr_any >= cnr_band * (1 - 1e-9)
    low, high = anything.band
    assert d_any.feasible and c_any.gray.min() >= low and max(c_any.gray.max(), c_any.moved_gray.max()) <= high + 1e-6
    x = float(c_any.shutter[0] / c_any.kappa[0] ** 2)
    t_hi = anything.task.camera.shutter_range_s[1]
    at_top = max(c_any.gray.max(), c_any.moved_gray.max()) >= high - 0.01
    assert at_top or x >= t_hi / anything.kappa_open**2 * (1 - 1e-9)          # the top, or the longest exposure
    kappa = float(c_any.kappa[0])
    for f in (0.3, 0.6, 0.9, 0.99):
        c = evaluate.at_exposure(anything, c_any.position[0], f * x * kappa**2, kappa, joints=joints,
                                 drive=c_any.drive[0])
        (cnr,) = [j.predicted_cnr for j in defects.judge(anything, c)]
        assert cnr <= cnr_any * (1 + 1e-9)



SEEN = ["shadows", "cone_falloff", "noise", "black_level", "quantization", "defects"]


@pytest.mark.long          # two 15-50 s plans
def test_a_plan_with_any_shows_the_defect_at_least_as_well_as_with_the_band(tmp_path):
    """tasks/hinge-scratch.yaml planned with its 100-125 band and with `any`: the band's feasible
    exposures and poses are a subset of any's (its band inside the sensor's range), so any's
    planned worst CNR is at least the band's; its gray stays in the sensor's range (certified)."""
    from simcell import variant
    from cell.planning.one_shot import plan
    band = plan(load_task(TASKS / "hinge-scratch.yaml"))
    anything = plan(load_task(variant(tmp_path, TASKS / "hinge-scratch.yaml", {"requirements.gray_band": "any"})))
    doc = anything.to_json()
    (d_band,), (d_any,) = band.to_json()["defects"], doc["defects"]
    print("hinge scratch planned CNR: band", d_band["predicted_cnr"], "any", d_any["predicted_cnr"])
    assert anything.feasible and doc["gray_band"] == "any" and "gray_band" not in band.to_json()
    assert d_any["predicted_cnr"] >= d_band["predicted_cnr"] * (1 - 1e-9)
    assert doc["verified"]["holds"] and doc["verified"]["gray_max"] <= 2**8 - 2


@pytest.mark.long          # a 15-50 s plan and its closed loop
def test_a_simulated_run_with_any_converges_with_the_defect_over_min_cnr(tmp_path):
    """hinge-scratch with `any`, noise, black level and the defect simulated: the run converges
    (the good surface above the dark noise and unsaturated, the scratch measured at least its
    min_cnr); report.json says the band is any."""
    from simcell import run_loop, variant
    path = variant(tmp_path, TASKS / "hinge-scratch.yaml", {"requirements.gray_band": "any", "sim.effects": SEEN})
    cell = run_loop(path, tmp_path / "run")
    assert cell.error is None and cell.report["converged"], cell.report["reason"]
    assert cell.report["gray_band"] == "any" and cell.report["plan"]["gray_band"] == "any"
    last = cell.report["iterations"][-1]["measured_gray"]
    assert last["saturated"] == 0
    (d,) = cell.report["defects"]
    print("hinge scratch with any: planned", d["predicted_cnr"], "measured", d["measured_cnr"])
    assert d["measured_cnr"] >= d["min_cnr"]


@pytest.mark.long          # a 15-50 s plan and its closed loop
def test_a_run_with_any_whose_defect_does_not_show_stops_with_cause_contrast(tmp_path):
    """The same with `any` on a world without the defect (noise on, `defects` off): the good
    surface is in the sensor's range, but the scratch measures noise: exit 1, cause `contrast`."""
    from simcell import run_loop, variant
    effects = [e for e in SEEN if e != "defects"]
    path = variant(tmp_path, TASKS / "hinge-scratch.yaml", {"requirements.gray_band": "any", "sim.effects": effects})
    cell = run_loop(path, tmp_path / "run")
    assert cell.error is not None and cell.error.exit_code == 1 and cell.error.cause == "contrast"
    assert cell.report["iterations"][-1]["in_band"] and cell.report["gray_band"] == "any"
    (d,) = cell.report["defects"]
    assert d["measured_cnr"] < d["min_cnr"] <= d["predicted_cnr"]


def test_raised_drives_scale_every_exposure_by_one_factor_up_to_the_first_limit():
    """drives.raised on two channels: u = x w grows by one factor, the largest that keeps the
    brightest signal at top_signal, x at t_hi / kappa_open^2 and each drive at w_max (worked by
    hand here), and a defect's CNR at the new u is at least the old one's (it grows with the factor)."""
    from cell.planning import drives
    v = np.array([[100.0, 50.0, 10.0], [20.0, 40.0, 80.0]]) * 1e3          # gray per (s / kappa^2) at full drive
    d = drives.solve_drives(v, (20.0, 200.0), 0.0, 2.0, (1e-5, 0.02), (2.0, 16.0))
    x = d.shutter_s / d.f_number**2
    u = x * d.drive
    for top, expect in ((250.0, 250.0 / (u @ v).max()),
                        (1e6, min(0.02 / 4.0 / x * np.min(1.0 / d.drive[d.drive > 0]), 1e6 / (u @ v).max()))):
        r = drives.raised(d, v, 0.0, 2.0, (1e-5, 0.02), (2.0, 16.0), np.array([[0.0, 1.0], [0.0, 1.0]]), top)
        u_new = r.shutter_s / r.f_number**2 * r.drive
        assert u_new == pytest.approx(u * expect, rel=1e-9)
        assert np.all(r.drive <= 1.0 + 1e-12) and r.shutter_s <= 0.02 * (1 + 1e-12)
        rows = drives.ContrastRows(difference=np.array([[30.0], [-5.0]]) * 1e3, total=(v[:, :1] * 2),
                                   sign=np.array([1.0]), min_cnr=np.array([5.0]), gain=0.0255, dark_e=10.0)
        assert rows.cnr(u_new)[0] >= rows.cnr(u)[0]
