"""The BRDF fitter (`cell fit-brdf`, sec. 3.3): it recovers parameters it generated, says when a
term is absent instead of fitting noise, writes a material the loader reads back, and turns every
broken CSV into one line with exit code 2."""
import dataclasses
import json
import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import assume, given, settings, strategies as st

from cell import cli

from cell.physics import brdf_fit
from cell.task.loader import load_material
from cell.physics.brdf import reflectance

ROOT = Path(__file__).resolve().parents[1]
NOISE = 0.01                       # 1 % multiplicative noise on every reading

# Synthetic goniometer: lamp s and camera v fixed at +-alpha/2 from the vertical, the sample's
# normal tilted by beta towards azimuth psi, as a goniometer that tilts the sample does. At
# beta = 0 the camera sits in the mirror direction, and <v,r> ~ cos(2 beta): a spike of
# exponent m2 is ~sqrt(ln 2 / (2 m2)) wide in beta (0.5 deg at m2 = 5000), so tilts are spaced
# geometrically from 0.05 deg (10 tilts inside 1 deg resolve it) up to 60 deg (the diffuse
# background and the lobe's tail); eight azimuths sample in and out of the plane.
TILTS = np.radians(np.concatenate([[0.0], np.geomspace(0.05, 60.0, 24)]))
AZIMUTHS = np.radians(np.arange(0.0, 360.0, 45.0))


def goniometer(params, phase_deg, seed=0, noise=NOISE):
    """Measurements of eq. (7) with `params` at one phase angle, readings times (1 + noise N(0,1))."""
    half = np.radians(phase_deg) / 2
    s, v = np.array([np.sin(half), 0, np.cos(half)]), np.array([-np.sin(half), 0, np.cos(half)])
    beta, psi = (a.ravel() for a in np.meshgrid(TILTS[1:], AZIMUTHS))
    n = np.vstack([[0, 0, 1], np.column_stack([np.sin(beta) * np.cos(psi), np.sin(beta) * np.sin(psi),
                                               np.cos(beta)])])
    angle = lambda u: np.degrees(np.arctan2(np.linalg.norm(np.cross(n, u), axis=1), n @ u))  # noqa: E731
    ti, te = angle(s), angle(v)
    front = (ti < 89.0) & (te < 89.0)
    ti, te = ti[front], te[front]
    r = reflectance(np.cos(np.radians(ti)), np.cos(np.radians(te)), np.cos(2 * half), *params)
    r *= 1.0 + noise * np.random.default_rng(seed).standard_normal(r.shape)
    return brdf_fit.Measurements(float(phase_deg), ti, te, r)


def write_csv(path, groups, header="theta_i_deg,theta_e_deg,phase_deg,reflectance"):
    lines = [header] + [",".join(repr(float(x)) for x in (ti, te, g.phase_deg, r)) for g in groups
                        for ti, te, r in zip(g.theta_i_deg, g.theta_e_deg, g.reflectance)]
    path.write_text("\n".join(lines) + "\n")
    return path


ALUMINIUM = (0.03, 4.0, 6.0, 30.0, 400.0)      # tasks/materials/milled_aluminium.yaml
POLISHED = (0.1, 2.0, 10.0, 20.0, 5000.0)      # a spike in the thousands
NO_SPIKE = (0.05, 3.0, 20.0, 0.0, 100.0)


def three_phases():
    """Goniometer data at three phase angles, the spike gone at 60 deg."""
    return [goniometer(ALUMINIUM, 0, 1), goniometer(POLISHED, 20, 2), goniometer(NO_SPIKE, 60, 3)]


@pytest.fixture
def fitted(tmp_path, capsys):
    """`cell fit-brdf` on three_phases(); returns (exit code, stdout, stderr, material path)."""
    data, out = write_csv(tmp_path / "alu.csv", three_phases()), tmp_path / "alu.yaml"
    rc = cli.main(["fit-brdf", str(data), "--out", str(out)])
    return (rc, *capsys.readouterr(), out)


# --- recovery ---

# Tolerances: over 400 random draws from these ranges the worst relative errors were rho 0.8 %,
# sigma1 3.6 %, m1 4.0 %, sigma2 0.9 %, m2 2.3 % (1 % noise, ~190 readings per phase, all within
# 3.7 standard errors); the limits leave margin. m1 is the loosest of the three "few %" because a
# broad lobe (m1 ~ 2) trades off against the diffuse cos ti. Outside these ranges a weak, broad
# spike under a strong lobe (sigma2 < sigma1, m2 ~ 150) is fitted less well (m2 off by 11 %, but
# within 3 of its standard errors of 4 %).
TOLERANCE = np.array([0.02, 0.05, 0.06, 0.05, 0.10])


def log_uniform(low, high):
    return st.floats(np.log(low), np.log(high)).map(np.exp)


@st.composite
def brdf_parameters(draw):
    """Both specular terms clearly present and distinct, as in both shipped materials: the spike
    2-100x the diffuse and at least as tall as the lobe, m2 >= 10 m1."""
    m1, sigma1 = draw(log_uniform(2.0, 50.0)), draw(log_uniform(0.5, 10.0))
    return np.array([draw(st.floats(0.02, 0.5)), sigma1, m1, draw(log_uniform(max(2.0, sigma1), 100.0)),
                     draw(log_uniform(max(10 * m1, 100.0), 1e4))])


@settings(max_examples=25, deadline=None, derandomize=True)
@given(params=brdf_parameters(), phase=st.sampled_from([0.0, 10.0, 30.0, 60.0, 80.0]),
       seed=st.integers(0, 2**32 - 1))
def test_fitter_recovers_the_parameters_it_generated(params, phase, seed):
    result = brdf_fit.fit_phase(goniometer(params, phase, seed))
    assert result.absent == ()
    assert np.all(np.abs(result.params / params - 1) < TOLERANCE), (result.params, params)
    assert np.all(np.abs(result.params - params) < 6 * result.stderr)   # the stderr is honest
    assert result.rms_residual < 3 * NOISE * np.max(result.params[0] * (1 + params[1] + params[3]))


@pytest.mark.parametrize("phase", [0.0, 28.9])
def test_spike_in_the_thousands_is_resolved_when_sampled_near_the_mirror_direction(phase):
    result = brdf_fit.fit_phase(goniometer(POLISHED, phase, seed=7))
    assert abs(result.params[4] / 5000.0 - 1) < 0.10
    assert result.stderr[4] < 0.05 * 5000.0


def test_absent_spike_is_reported_unidentifiable_not_fitted_to_noise():
    result = brdf_fit.fit_phase(goniometer(NO_SPIKE, 30.0, seed=5))
    assert result.absent == ("spike",) and result.p_values[1] > brdf_fit.SIGNIFICANCE
    assert result.params[3] == 0.0 and np.isinf(result.stderr[3:]).all()
    assert np.all(np.abs(result.params[:3] / NO_SPIKE[:3] - 1) < TOLERANCE[:3])


def test_a_purely_diffuse_surface_has_neither_lobe_nor_spike():
    result = brdf_fit.fit_phase(goniometer((0.2, 0.0, 1.0, 0.0, 2.0), 30.0, seed=6))
    assert result.absent == ("lobe", "spike")
    assert abs(result.params[0] / 0.2 - 1) < 0.01 and np.isinf(result.stderr[1:]).all()


def test_exponents_of_an_absent_spike_follow_the_neighbouring_phase_and_stay_above_m1():
    fits = brdf_fit.fit_material([goniometer(ALUMINIUM, 0, 1), goniometer(NO_SPIKE, 40, 2)])
    assert fits[1].params[3] == 0.0
    assert fits[1].params[4] == fits[0].params[4] > fits[1].params[2]


def in_plane(phase_deg, betas_deg):
    """Readings of a goniometer stepping the half-angle tilt beta in the plane of incidence."""
    beta = np.asarray(betas_deg, float)
    return brdf_fit.Measurements(float(phase_deg), np.abs(beta + phase_deg / 2), np.abs(beta - phase_deg / 2),
                                 np.ones(len(beta)))


@pytest.mark.parametrize("betas, step", [
    (np.arange(-30, 31, 2.0), 2.0),                         # the mirror pose and a 2 deg step
    (np.arange(-31, 32, 2.0), 2.0),                         # from 1 deg: the mirror between two poses
    ([-30, -10, -6, 6, 10, 30], 12.0),                      # the mirror unmeasured: twice the nearest tilt
    (np.concatenate([[0.0], np.arange(3.0, 40.0, 3.0)]), 3.0),
])
def test_the_data_s_step_about_the_mirror_direction(betas, step):
    for phase in (0.0, 20.0, 60.0):
        assert np.degrees(brdf_fit.sampling_step([in_plane(phase, betas)])) == pytest.approx(step, abs=1e-9)
    assert brdf_fit.mirror_tilt(in_plane(20.0, [0.0]))[0] == 0.0               # exactly, not sqrt(rounding)
    coarse = np.degrees(brdf_fit.sampling_step([in_plane(20.0, np.arange(-30, 31, 2.0)),
                                                in_plane(40.0, np.arange(-30, 31, 5.0))]))
    assert coarse == pytest.approx(5.0)                                         # the coarsest phase's


def test_a_spike_narrower_than_the_data_s_step_is_unresolved_by_fit_brdf_too(tmp_path, capsys):
    """The rule of cell measure-brdf: at a 2 deg step M = ln 2 / (2 step^2) = 284, so m2 = 400
    (the aluminium's) falls between the readings: sigma2 0, m2 = M, standard errors inf."""
    params = (0.03, 4.0, 6.0, 30.0, 400.0)
    beta = np.arange(-40, 41, 2.0)
    m = in_plane(40.0, beta)
    r = reflectance(np.cos(np.radians(m.theta_i_deg)), np.cos(np.radians(m.theta_e_deg)), np.cos(np.radians(40.0)),
                    *params)
    data = write_csv(tmp_path / "d.csv", [dataclasses.replace(m, reflectance=r)])
    assert cli.main(["fit-brdf", str(data), "--out", str(tmp_path / "m.yaml")]) == 0
    out, err = capsys.readouterr()
    doc = yaml.safe_load((tmp_path / "m.yaml").read_text())
    m_max = np.log(2) / (2 * np.radians(2.0) ** 2)
    assert doc["unresolved"] == {"terms": {"spike": [40.0]}, "step_deg": 2.0,
                                 "resolvable_m_max": pytest.approx(m_max, rel=1e-5)}
    assert doc["sigma2"] == [0.0] and doc["m2"] == [pytest.approx(m_max, rel=1e-5)]
    assert np.isinf(doc["m2_stderr"][0]) and doc["m1"][0] == pytest.approx(6.0, rel=0.01)
    assert "spike unresolved at phase 40 deg: the data's step of 2 deg" in err
    assert load_material(tmp_path / "m.yaml").unresolved.terms == {"spike": (np.radians(40.0),)}


@settings(max_examples=30, deadline=None, derandomize=True)
@given(readings=st.lists(st.floats(0.0, brdf_fit.REFLECTANCE_MAX), min_size=brdf_fit.MIN_ROWS, max_size=brdf_fit.MIN_ROWS),
       phase=st.sampled_from([0.0, 30.0, 80.0]))
def test_any_valid_data_give_finite_parameters_and_a_loadable_material(tmp_path_factory, readings, phase):
    """Valid: what read_goniometer accepts; the fit warns of nothing (a warning is an error here)."""
    assume(max(readings) >= brdf_fit.BRIGHTEST_MIN)
    data = goniometer(ALUMINIUM, phase)
    groups = [brdf_fit.Measurements(phase, data.theta_i_deg[:6], data.theta_e_deg[:6], np.array(readings))]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fits = brdf_fit.fit_material(groups)
    assert np.isfinite(fits[0].params).all() and not np.isnan(fits[0].stderr).any()
    path = tmp_path_factory.mktemp("m") / "m.yaml"
    path.write_text(yaml.safe_dump(brdf_fit.material_document(fits, "x", "y")))
    load_material(path)


@st.composite
def any_goniometer(draw):
    """Measurements read_goniometer accepts: one phase angle, lamp and camera in front, the
    spherical triangle closed, readings anywhere in [0, REFLECTANCE_MAX] (no structure at all)."""
    phase = draw(st.floats(0.0, 179.0))
    front = 89.999
    rows = []
    for _ in range(draw(st.integers(brdf_fit.MIN_ROWS, 40))):
        ti = draw(st.floats(max(0.0, phase - front), front))
        rows.append((ti, draw(st.floats(abs(phase - ti), min(phase + ti, front)))))
    readings = draw(st.lists(st.one_of(st.just(0.0), log_uniform(brdf_fit.BRIGHTEST_MIN, brdf_fit.REFLECTANCE_MAX),
                                       st.floats(0.0, 1.0)), min_size=len(rows), max_size=len(rows)))
    assume(max(readings) >= brdf_fit.BRIGHTEST_MIN)
    ti, te = np.array(rows).T
    return brdf_fit.Measurements(phase, ti, te, np.array(readings))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(data=any_goniometer())
def test_any_geometry_and_readings_fit_without_a_warning(data):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        f = brdf_fit.fit_material([data])[0]
    assert np.isfinite(f.params).all() and f.params[0] > 0 and f.params[[1, 3]].max() <= brdf_fit.SIGMA_MAX
    assert np.isfinite(f.rms_residual) and not np.isnan(f.stderr).any()


@pytest.mark.parametrize("scale", [1e-90, 1e90])
def test_the_fit_is_the_same_at_any_scale_of_the_readings(scale):
    data = goniometer(ALUMINIUM, 20.0, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scaled = brdf_fit.fit_phase(dataclasses.replace(data, reflectance=data.reflectance * scale))
    unit = brdf_fit.fit_phase(data)
    per_unit = np.array([scale, 1, 1, 1, 1])
    np.testing.assert_allclose(scaled.params / per_unit, unit.params, rtol=1e-6)
    np.testing.assert_allclose(scaled.stderr / per_unit, unit.stderr, rtol=1e-6)
    assert scaled.rms_residual / scale == pytest.approx(unit.rms_residual, rel=1e-6)


# --- the command ---

def test_cell_fit_brdf_writes_a_material_that_loads_and_reproduces_the_readings(fitted):
    rc, out, err, path = fitted
    assert rc == 0 and f"wrote {path}" in out
    assert "phase 60 deg: no spike in the data" in err and "m2 unidentifiable" in err
    material = load_material(path)
    assert material.source.startswith("fit of ") and "by cell fit-brdf on " in material.source
    assert material.extra["unidentifiable"] == {"spike": [60.0]}
    assert material.extra["m2_stderr"][2] == np.inf and np.isfinite(material.extra["m2_stderr"][:2]).all()
    assert set(material.extra) >= {f"{p}_stderr" for p in brdf_fit.PARAMETERS} | {"rms_residual"}
    for f, truth in zip(brdf_fit.fit_material(three_phases()), (ALUMINIUM, POLISHED, NO_SPIKE)):
        g = goniometer(truth, f.phase_deg, noise=0.0)
        cosines = [np.cos(np.radians(a)) for a in (g.theta_i_deg, g.theta_e_deg, f.phase_deg)]
        p = material.at(np.radians(f.phase_deg))
        loaded = reflectance(*cosines, p.rho, p.sigma1, p.m1, p.sigma2, p.m2)
        np.testing.assert_allclose(loaded, reflectance(*cosines, *f.params), rtol=1e-4)   # 6 digits
        np.testing.assert_allclose(loaded, g.reflectance, rtol=0.02)                       # the truth


def test_cell_fit_brdf_json_runs_as_a_program(tmp_path):
    data = write_csv(tmp_path / "d.csv", [goniometer(NO_SPIKE, 10, 4)])
    done = subprocess.run([sys.executable, "-m", "cell", "fit-brdf", str(data), "--json", "--name", "iron"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)          # strict JSON: an infinite stderr is null
    assert doc["name"] == "iron" and doc["phase_deg"] == [10.0]
    assert doc["m2_stderr"] == [None] and doc["unidentifiable"] == {"spike": [10.0]}
    assert abs(doc["m1"][0] / NO_SPIKE[2] - 1) < 0.06
    assert "m2 unidentifiable" in done.stderr


# --- broken input: (CSV text or None for no file, key the message names, text it contains) ---

GOOD = "theta_i_deg,theta_e_deg,phase_deg,reflectance\n" + "".join(
    f"{10 + i},{12 + i},20,0.{i + 1}\n" for i in range(6))
LINE_MAX = 400                     # an error line quotes short prefixes of values, never a whole file


def refused(capsys, *argv):
    """`cell fit-brdf ARGV` as bad input: exit 2, one short line on stderr, nothing on stdout, no
    traceback and no warning (every warning is an error here); returns that line."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cli.main(["fit-brdf", *map(str, argv)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "Traceback" not in err and len(err) < LINE_MAX, err
    assert err.startswith("cell fit-brdf: ") and "found" in err and "expected" in err
    return err


@pytest.fixture
def no_hang():
    """A test that would block (reading a FIFO) fails after 20 s instead."""
    def timeout(signum, frame):
        raise TimeoutError("cell fit-brdf blocked")
    previous = signal.signal(signal.SIGALRM, timeout)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


BROKEN = [
    pytest.param(None, "", "unreadable file", id="missing-file"),
    pytest.param(b"\xff\xfe\x00bad", "line 1", "not UTF-8", id="binary"),
    pytest.param(GOOD.encode().replace(b"0.2", b"0.\xb2"), "line 3", "not UTF-8 text (0xb2)", id="latin-1"),
    pytest.param("", "", "empty file", id="empty"),
    pytest.param("\n \n,,,\n", "", "empty file", id="blank-lines"),
    pytest.param("theta_i_deg,theta_e_deg,phase_deg,reflectance\n", "", "no data rows", id="header-only"),
    pytest.param(GOOD.replace("reflectance", "R", 1), "line 1 (header)", "missing reflectance",
                 id="missing-column"),
    pytest.param(GOOD.replace("phase_deg,reflectance", "phase_deg,reflectance,reflectance", 1)
                 .replace(",20,0.", ",20,0.5,0."), "line 1 (header)",
                 "the column 'reflectance' in fields 4, 5", id="duplicate-column"),
    pytest.param(GOOD.replace("0.3", "bright"), "line 4, reflectance", "'bright'", id="not-a-number"),
    pytest.param(GOOD.replace("0.3", "nan"), "line 4, reflectance", "a finite number", id="nan"),
    pytest.param(GOOD.replace("0.3", "-inf"), "line 4, reflectance", "a finite number", id="inf"),
    pytest.param(GOOD.replace("12,14", "nan,14"), "line 4, theta_i_deg", "a finite number", id="nan-angle"),
    pytest.param(GOOD.replace("0.3", "-0.3"), "line 4, reflectance", "in [0, 1e+100]", id="negative"),
    pytest.param(GOOD.replace("0.3", "1e300"), "line 4, reflectance",
                 "found '1e300', expected a reflectance in [0, 1e+100]", id="huge"),
    pytest.param(GOOD.replace(",20,0.", ",20,0e"), "phase_deg 20", "found 6 readings, all 0, expected a "
                 "reflectance of at least 1e-100 at each phase angle (nothing to fit)", id="all-zero"),
    pytest.param(GOOD.replace(",20,0.", ",20,1e-10"), "phase_deg 20", "found 6 readings, the largest 1e-101",
                 id="all-dark"),
    pytest.param(GOOD.replace("12,14,20,", "12,14,,"), "line 4, phase_deg", "empty field", id="empty-field"),
    pytest.param(GOOD.replace("12,14,20,0.3", "12,14,20"), "line 4", "3 fields", id="short-row"),
    pytest.param(GOOD.replace("12,14", "95,14"), "line 4, theta_i_deg", "[0, 90)", id="lamp-behind"),
    pytest.param(GOOD.replace("12,14", "-2,14"), "line 4, theta_i_deg",
                 "found '-2', expected an angle in [0, 90)", id="negative-theta-i"),
    pytest.param(GOOD.replace("12,14", "12,-14"), "line 4, theta_e_deg",
                 "found '-14', expected an angle in [0, 90)", id="negative-theta-e"),
    pytest.param(GOOD.replace("12,14,20", "12,14,-20"), "line 4, phase_deg", "[0, 180]", id="negative-phase"),
    pytest.param(GOOD.replace("12,14,20", "12,14,200"), "line 4, phase_deg", "[0, 180]", id="phase-over-180"),
    pytest.param(GOOD.replace("12,14,20", "12,40,20"), "line 4", "spherical triangle",
                 id="triangle-phase-too-small"),
    pytest.param(GOOD.replace("12,14,20", "5,5,20.001"), "line 4", "spherical triangle",
                 id="triangle-phase-too-large"),
    pytest.param(GOOD.replace("15,17,20", "15,17,21"), "phase_deg 20", "5 rows", id="too-few-rows"),
    # a quote never closed: the field runs to the end of the file; the line shows its start
    pytest.param(GOOD + '10,12,20,"0.1\n' + "x" * 80_000 + "\n", "lines 8-9, reflectance",
                 "found '0.1\\nxxx", id="unclosed-quote"),
    pytest.param(GOOD + '10,12,20,"0.1\n' + "x" * 200_000 + "\n", "line 8", "field larger than field limit",
                 id="unclosed-quote-past-the-csv-field-limit"),
    pytest.param('"' + GOOD, "lines 1-7 (header)", "columns 'theta_i_deg,theta_e_deg,",
                 id="unclosed-quote-header"),
]


@pytest.mark.parametrize("content, key, says", BROKEN)
def test_broken_csv_is_one_line_and_exit_2(tmp_path, capsys, content, key, says):
    path = tmp_path / "data.csv"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    err = refused(capsys, path, "--out", tmp_path / "m.yaml")
    assert err.startswith(f"cell fit-brdf: {path}: {key}" if key else f"cell fit-brdf: {path}: found"), err
    assert says in err
    assert not (tmp_path / "m.yaml").exists()


def test_a_long_value_is_shown_as_its_first_80_characters(tmp_path, capsys):
    path = tmp_path / "data.csv"
    path.write_text(GOOD.replace("0.3", "y" * 5000))
    err = refused(capsys, path)
    assert f"found '{'y' * brdf_fit.SHOWN_CHARS}'..., expected a number" in err


def test_a_folder_a_device_or_a_named_pipe_is_refused_before_it_is_opened(tmp_path, capsys, no_hang):
    fifo = tmp_path / "pipe.csv"
    os.mkfifo(fifo)
    assert "found a named pipe (FIFO), expected a regular goniometer CSV file" in refused(capsys, fifo)
    assert "found a device, expected a regular goniometer CSV file" in refused(capsys, "/dev/zero")
    assert "found a folder, expected a regular goniometer CSV file" in refused(capsys, tmp_path)
    link = tmp_path / "zero.csv"
    link.symlink_to("/dev/zero")
    assert "found a device" in refused(capsys, link)


def test_a_csv_over_the_size_limit_is_refused_unread(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("CELL_MAX_CSV_MB", str(0.5 * len(GOOD) / 2**20))
    path = tmp_path / "data.csv"
    path.write_text(GOOD)
    assert (f"{path}: found {len(GOOD) / 2**20:.3g} MB, expected a goniometer CSV file of at most "
            f"{0.5 * len(GOOD) / 2**20:.3g} MB (CELL_MAX_CSV_MB sets the limit)") in refused(capsys, path)


def test_too_many_rows_or_phase_angles_are_refused_before_the_fit(tmp_path, capsys, monkeypatch):
    path = tmp_path / "data.csv"
    path.write_text(GOOD + GOOD.split("\n", 1)[1].replace(",20,", ",21,"))
    monkeypatch.setattr(brdf_fit, "PHASES_MAX", 1)
    assert f"{path}: phase_deg: found 2 phase angles, expected at most 1 (cell.physics.brdf_fit.PHASES_MAX" \
        in refused(capsys, path)
    monkeypatch.setattr(brdf_fit, "ROWS_MAX", 11)
    assert f"{path}: line 13: found more than 11 data rows, expected at most 11 (cell.physics.brdf_fit.ROWS_MAX" \
        in refused(capsys, path)


@pytest.fixture
def no_fit(monkeypatch):
    """`--out` is checked before the fit: fitting is an error here."""
    def fit_goniometer(groups, name, source):
        raise AssertionError("fitted before refusing --out")
    monkeypatch.setattr("cell.cli.fit_brdf.fit_goniometer", fit_goniometer)


@pytest.mark.parametrize("out, says", [
    ("{tmp}", "{tmp} (a folder), expected a material file to write"),
    ("/proc/m.yaml", "/proc/m.yaml (no file can be created in /proc: "),
    ("{tmp}/no/m.yaml", "{tmp}/no/m.yaml (no folder {tmp}/no)"),
    ("{tmp}/data.csv/m.yaml", "(Not a directory)"),
    ("/dev/null", "/dev/null (not a regular file)"),
], ids=["folder", "proc", "no-folder", "under-a-file", "device"])
def test_an_unwritable_out_is_refused_before_the_fit(tmp_path, capsys, no_fit, out, says):
    data = tmp_path / "data.csv"
    data.write_text(GOOD)
    out, says = (x.replace("{tmp}", str(tmp_path)) for x in (out, says))
    err = refused(capsys, data, "--out", out)
    assert err.startswith("cell fit-brdf: command line: --out: found ") and says in err


@pytest.mark.parametrize("alias", ["same", "dotdot", "symlink", "hardlink"])
def test_out_is_never_the_csv_itself(tmp_path, capsys, no_fit, alias):
    data = tmp_path / "data.csv"
    data.write_text(GOOD)
    out = {"same": data, "dotdot": tmp_path / "." / ".." / tmp_path.name / "data.csv",
           "symlink": tmp_path / "m.yaml", "hardlink": tmp_path / "m.yaml"}[alias]
    if alias == "symlink":
        out.symlink_to(data)
    elif alias == "hardlink":
        os.link(data, out)
    err = refused(capsys, data, "--out", out)
    assert f"--out: found {out} (the goniometer CSV itself), expected a material file other than the data" \
        in err
    assert data.read_text() == GOOD


def test_the_good_csv_of_the_broken_cases_fits(tmp_path, capsys):
    path = tmp_path / "ok.csv"
    path.write_text(GOOD)
    assert cli.main(["fit-brdf", str(path)]) == 0
    assert "phase" in capsys.readouterr().out


def test_trailing_empty_columns_and_a_byte_order_mark_are_fine(tmp_path, capsys):
    path = tmp_path / "excel.csv"
    path.write_text("\ufeff" + GOOD.replace("\n", ",,\n"))
    assert cli.main(["fit-brdf", str(path)]) == 0


def test_an_empty_out_is_bad_input_not_no_file(tmp_path, capsys):
    path = tmp_path / "data.csv"
    path.write_text(GOOD)
    assert "--out: found an empty path, expected a material file to write" in refused(capsys, path, "--out", "")
